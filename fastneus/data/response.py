"""Camera response: how 8-bit photo values map to linear light, and back.

A response is written as a string: ``linear``, ``srgb`` (IEC 61966-2-1, what cameras and the web
write into JPEG / PNG) or ``gamma=G`` (value = linear ** (1 / G)). Training decodes photos
through a 256-entry lookup table (:func:`decode_lut`) so the model, i_r and i_b live in linear
light; exported colours are encoded back (:func:`encode`) so they look like the photos.

:func:`resolve_response` is the ``illum.response=auto`` decision: what the scene states,
else what its image files state (PNG ``sRGB`` / ``gAMA`` chunks), else sRGB (the default
meaning of an untagged 8-bit image in both the PNG and JPEG/EXIF conventions).
"""
from __future__ import annotations

import re
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from fastneus.errors import FastneusError

_GAMMA = re.compile(r"^gamma=([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)$")
GAMMA_RANGE = (0.2, 5.0)  # anything outside is not a camera response but a typo
LINEAR_FORMATS = ("activeneus",)  # converted formats whose images are linear (rendered datasets)


@dataclass(frozen=True)
class Response:
    """A parsed response: ``kind`` linear | srgb | gamma, ``gamma`` its exponent (gamma only)."""

    kind: str
    gamma: float = 1.0

    def __str__(self) -> str:
        return f"gamma={self.gamma:g}" if self.kind == "gamma" else self.kind


def parse_response(text, file=None, field: str = "response") -> Response:
    """``"linear"`` | ``"srgb"`` | ``"gamma=G"`` -> :class:`Response`.

    Raises:
        FastneusError: one line naming ``file`` and ``field`` on anything else.
    """
    s = text.strip().lower() if isinstance(text, str) else None
    if s in ("linear", "srgb"):
        return Response(s)
    m = _GAMMA.match(s or "")
    if m:
        g = float(m.group(1))
        if GAMMA_RANGE[0] <= g <= GAMMA_RANGE[1]:
            return Response("linear") if g == 1.0 else Response("gamma", g)
    raise FastneusError(f"expected linear, srgb or gamma=G with G in [{GAMMA_RANGE[0]:g}, {GAMMA_RANGE[1]:g}], "
                        f"got {text!r}", file=file, field=field)


def _as_response(r) -> Response:
    return r if isinstance(r, Response) else parse_response(r)


def _prepared(x, response):
    """(the parsed response, numpy or torch, ``x`` clipped to [0, 1]) for decode/encode."""
    lib = torch if isinstance(x, torch.Tensor) else np
    return _as_response(response), lib, (lib.clip(x, 0.0, 1.0) if lib is np else x.clamp(0.0, 1.0))


def decode(x, response) -> torch.Tensor | np.ndarray:
    """Encoded values in [0, 1] -> linear light (torch or numpy, any shape)."""
    r, lib, x = _prepared(x, response)
    if r.kind == "linear":
        return x
    if r.kind == "gamma":
        return x ** r.gamma
    return lib.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def encode(x, response) -> torch.Tensor | np.ndarray:
    """Linear light -> encoded values in [0, 1] (clipped first, as the camera saturates)."""
    r, lib, x = _prepared(x, response)
    if r.kind == "linear":
        return x
    if r.kind == "gamma":
        return x ** (1.0 / r.gamma)
    return lib.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1.0 / 2.4) - 0.055)


def decode_lut(response) -> np.ndarray:
    """[256] float32: linear value of each 8-bit code (code k -> decode(k / 255))."""
    return decode(np.arange(256, dtype=np.float64) / 255.0, response).astype(np.float32)


def encode_u8(x, response) -> np.ndarray:
    """Linear [..., 3] float -> uint8 photo values in the camera's encoding (rounded)."""
    x = x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x, dtype=np.float64)
    return (encode(x, response) * 255.0 + 0.5).astype(np.uint8)


def png_tags(path) -> dict:
    """The colour chunks of a PNG before its image data: ``{"srgb": True}``, ``{"gamma": 0.45455}``
    (the gAMA chunk's encoding exponent), ``{"iccp": True}``; {} for anything else or no PNG."""
    out: dict = {}
    try:
        with open(path, "rb") as f:
            if f.read(8) != b"\x89PNG\r\n\x1a\n":
                return out
            for _ in range(64):  # colour chunks come before IDAT; never walk a whole file
                head = f.read(8)
                if len(head) < 8:
                    break
                n, typ = struct.unpack(">I4s", head)
                if typ == b"IDAT" or n > 1 << 24:
                    break
                data = f.read(n)
                f.read(4)  # CRC
                if typ == b"sRGB":
                    out["srgb"] = True
                elif typ == b"gAMA" and n == 4:
                    out["gamma"] = struct.unpack(">I", data)[0] / 100000.0
                elif typ == b"iCCP":
                    out["iccp"] = True
    except OSError:
        pass
    return out


def _tagged(p: Path) -> tuple[Response, str] | None:
    """The response image file ``p``'s PNG colour chunks state, None when they state none."""
    tags = png_tags(p)
    if tags.get("srgb"):
        return Response("srgb"), f"{p.name} has a PNG sRGB chunk"
    if tags.get("gamma"):
        g = 1.0 / tags["gamma"] if tags["gamma"] > 0 else 1.0
        if abs(g - 1.0) < 0.05:
            return Response("linear"), f"{p.name} has a PNG gAMA chunk of 1.0"
        if abs(g - 2.2) < 0.05:  # gAMA 0.45455 is how many writers say "sRGB"
            return Response("srgb"), f"{p.name} has a PNG gAMA chunk of 1/2.2"
        if GAMMA_RANGE[0] <= g <= GAMMA_RANGE[1]:
            return Response("gamma", round(g, 3)), f"{p.name} has a PNG gAMA chunk of 1/{g:.3g}"
    return None


def _from_files(paths: list[Path]) -> tuple[Response, str]:
    """The response the image files state, else sRGB; (response, why)."""
    for p in paths:
        tagged = _tagged(Path(p))
        if tagged is not None:
            return tagged
    return Response("srgb"), ("the photos state no encoding; 8-bit camera photos are sRGB unless tagged "
                              "otherwise (set illum.response=linear if yours are raw/linear)")


def deep_file_response(scene) -> tuple[Response, str]:
    """The encoding of a scene's 16-bit photos (:meth:`fastneus.data.Scene.image` decodes them with it):
    what scene.json's ``response`` states, else their PNG colour tags, else linear (a machine-vision
    or raw camera's sensor values); (response, why)."""
    stated = getattr(scene, "response", None)
    if stated is not None:
        return parse_response(stated, field="response"), "scene.json states it"
    tagged = _tagged(Path(scene.path(scene.frames[0].image)))
    return tagged if tagged is not None else (Response("linear"), "no colour tag: a machine-vision or raw "
                                                                  "camera's sensor values")


def deep_to_u8(im: np.ndarray, response, full: int = 65535) -> np.ndarray:
    """A 16-bit photo [H, W, 3] (uint16, in ``response``'s encoding, ``full`` its full-scale value:
    4095 for a 12-bit camera's right-aligned values) as 8-bit sRGB codes: decoded to linear light
    and encoded again. Below 24 % of full scale these codes are finer than 8-bit
    linear ones (the first step is 1/3300 of full scale, not 1/255: the dark room's ambient light
    and noise floor), above it coarser (at full scale 1/112), as a camera's JPEG is."""
    lin = decode(im.astype(np.float64) / float(full), response)
    return encode_u8(lin, Response("srgb"))


def resolve_response(scene, frames: list[int], knob: str) -> tuple[Response, str]:
    """Decide the camera response the photos are decoded with (``illum.response``).

    ``auto``: the scene's ``response`` field; else linear for synthetic scenes and formats of
    rendered data (:data:`LINEAR_FORMATS`); else what the image files state; else sRGB.

    Args:
        scene: the loaded scene; frames: the training frames (their images are inspected);
        knob: ``illum.response`` (validated by the config).
    Returns:
        (response, note): the decision and one line saying why, for the run summary.
    """
    if getattr(scene, "photo_bits", 8) > 8:  # Scene.image gives them as 8-bit sRGB codes
        if knob != "auto":
            raise FastneusError(f"illum.response={knob} is for 8-bit photos; these are 16-bit: state their "
                                "encoding in scene.json's response (linear | srgb | gamma=G)", field="illum.response")
        r, why = deep_file_response(scene)
        full = scene.photo_full_scale()[1] if hasattr(scene, "photo_full_scale") else "16-bit values"
        return Response("srgb"), (f"response: auto -> srgb (16-bit photos, {r}: {why}; {full}; decoded to linear "
                                  "light and kept as 8-bit sRGB codes)")
    if knob != "auto":
        r = parse_response(knob, field="illum.response")
        return r, f"response: {r} (asked for)"
    stated = getattr(scene, "response", None)
    meta = scene.meta or {}
    if stated is not None:
        r, why = parse_response(stated, field="response"), "scene.json states it"
    elif meta.get("generator") == "fastneus synth":
        r, why = Response("linear"), "synthetic scene written before responses were stated: linear"
    elif meta.get("source_format") in LINEAR_FORMATS:
        r, why = Response("linear"), f"converted from {meta['source_format']}, a rendered (linear) dataset"
    else:
        paths = [scene.path(scene.frames[i].image) for i in frames[:3]]
        r, why = _from_files(paths)
    return r, f"response: auto -> {r} ({why})"


def is_identity(response) -> bool:
    """True for the linear response (photos used as they are)."""
    return _as_response(response).kind == "linear"


__all__ = ["Response", "parse_response", "decode", "encode", "decode_lut", "encode_u8", "png_tags",
           "deep_file_response", "deep_to_u8",
           "resolve_response", "is_identity", "GAMMA_RANGE"]
