"""Projector pattern generators (and Gray-code / phase-shift decoding) + the ``patterns`` verb.

Every generator returns a list of uint8 [H, W, 3] RGB images (a list because Gray code
and phase shift are sequences); the same seed always gives the same images.

Kinds:
    crosslaser  red vertical and green horizontal laser lines (the paper's default)
    graycode    Gray-code bit planes for columns then rows (optionally with inverses)
    grid        white grid lines
    colorline   random vertical stripes of the 8 binary RGB colours (ActiveNeuS sample)
    dots        random white dots
    phaseshift  N-step sinusoidal fringes
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import math
import os
import tempfile
from pathlib import Path

import numpy as np

from fastneus.errors import FastneusError

# the built-in kinds (every registered kind: :func:`pattern_kinds`; see PATTERNS at the end)
KINDS = ("crosslaser", "graycode", "grid", "colorline", "dots", "phaseshift")

# the 8 binary RGB colours (black included, as in the ActiveNeuS sample)
BINARY_COLOURS = np.array([[r, g, b] for r in (0, 255) for g in (0, 255) for b in (0, 255)], dtype=np.uint8)


def line_offset(rng: np.random.Generator, spacing: float, seed: int) -> float:
    """Line phase: centred for seed 0, else a seeded shift within one spacing."""
    return 0.0 if seed == 0 else float(rng.uniform(-0.5, 0.5) * spacing)


def _lines(size: int, count: int, width: int, offset: float) -> np.ndarray:
    """[size] bool: ``count`` evenly spaced lines exactly ``width`` px wide (centres (k+0.5)*size/count)."""
    centres = (np.arange(count) + 0.5) * (size / count) + offset
    on = np.zeros(size, dtype=bool)
    for c in centres:
        start = int(np.floor(c - width / 2.0 + 0.5))
        on[max(0, start):max(0, start + width)] = True
    return on


def crosslaser(width: int, height: int, seed: int = 0, count: int = 8, line_width: int = 3,
               vertical_color=(255, 0, 0), horizontal_color=(0, 255, 0), **_) -> list[np.ndarray]:
    """Red vertical and green horizontal laser lines; colours add where lines cross."""
    rng = np.random.default_rng(seed)
    v = _lines(width, count, line_width, line_offset(rng, width / count, seed))
    h = _lines(height, count, line_width, line_offset(rng, height / count, seed))
    img = np.zeros((height, width, 3), dtype=np.int32)
    img[:, v] += np.asarray(vertical_color, dtype=np.int32)
    img[h, :] += np.asarray(horizontal_color, dtype=np.int32)
    return [np.clip(img, 0, 255).astype(np.uint8)]


def gray_bits(n: int) -> int:
    """Number of Gray-code bits to address ``n`` columns (or rows)."""
    return max(1, math.ceil(math.log2(n)))


def graycode(width: int, height: int, seed: int = 0, inverse: bool = False, **_) -> list[np.ndarray]:
    """Gray-code bit planes, most significant first: columns, then rows.

    Plane b of the columns is white where bit (nbits - 1 - b) of gray(j) is set, with
    gray(j) = j ^ (j >> 1). With ``inverse`` every plane is followed by its inverse.
    """
    out = []
    for axis, n in ((1, width), (0, height)):
        nb = gray_bits(n)
        idx = np.arange(n)
        g = idx ^ (idx >> 1)
        for b in range(nb):
            bit = ((g >> (nb - 1 - b)) & 1).astype(bool)
            plane = np.broadcast_to(bit[None, :] if axis == 1 else bit[:, None], (height, width))
            img = np.repeat((plane * 255).astype(np.uint8)[:, :, None], 3, axis=2)
            out.append(img)
            if inverse:
                out.append(255 - img)
    return out


def decode_graycode(images, width: int, height: int, inverse: bool = False,
                    threshold: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Recover projector column and row indices from captured Gray-code images.

    Args:
        images: the sequence in :func:`graycode` order, each [h, w] or [h, w, 3] (uint8 or float).
        width, height: the projector size the patterns were made for.
        inverse: the sequence holds inverse planes (bit = image > its inverse).
        threshold: without inverses, bit = image > threshold (default: half the max value).

    Returns:
        col, row: int64 [h, w] projector column / row index per pixel.
    """
    ims = [np.asarray(im, dtype=np.float32) for im in images]
    ims = [im.mean(axis=2) if im.ndim == 3 else im for im in ims]
    ncb, nrb = gray_bits(width), gray_bits(height)
    step = 2 if inverse else 1
    if len(ims) != (ncb + nrb) * step:
        raise FastneusError(f"expected {(ncb + nrb) * step} Gray-code images for {width}x{height}"
                            f"{' with inverses' if inverse else ''}, got {len(ims)}", field="images")
    if threshold is None and not inverse:
        threshold = 0.5 * max(float(im.max()) for im in ims)

    def bits(k: int) -> np.ndarray:
        im = ims[k * step]
        return im > ims[k * step + 1] if inverse else im > threshold

    def decode(first: int, nb: int) -> np.ndarray:
        g = np.zeros(ims[0].shape, dtype=np.int64)
        for b in range(nb):
            g = (g << 1) | bits(first + b)
        # gray -> binary: b = g ^ (g >> 1) ^ (g >> 2) ...
        n = g.copy()
        shift = g >> 1
        while np.any(shift):
            n ^= shift
            shift >>= 1
        return n

    return decode(0, ncb), decode(ncb, nrb)


def decode_graycode_captured(images, width: int, height: int, min_contrast: float = 0.06
                             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Decode photographs of a :func:`graycode` sequence (no inverse planes) with a per-pixel threshold.

    A photo of a Gray-code plane is ``D`` where the bit is off and ``D + i_r D + i_b`` where it is on,
    with the surface colour ``D`` varying across the image, so one global threshold fails. Each pixel
    is lit in some planes and dark in others, so its own midpoint ``(min + max) / 2`` over the whole
    sequence separates the two; pixels whose range is below ``min_contrast`` (shadowed, outside the
    projector, background) are invalid.

    Args:
        images: the captured sequence in :func:`graycode` order, each [h, w, 3] or [h, w]
            (uint8 or float in [0, 1]).
        width, height: the projector size the patterns were made for.
        min_contrast: smallest max - min (in [0, 1] units) for a valid pixel.

    Returns:
        col, row: int64 [h, w] projector column / row per pixel (undefined where not valid);
        valid: bool [h, w].
    """
    ncb, nrb = gray_bits(width), gray_bits(height)
    if len(images) != ncb + nrb:
        raise FastneusError(f"expected {ncb + nrb} Gray-code images for {width}x{height}, got {len(images)}",
                            field="images")
    scale = 1.0 / 255.0 if np.asarray(images[0]).dtype == np.uint8 else 1.0
    ims = np.stack([np.asarray(im, dtype=np.float32) * scale for im in images])
    if ims.ndim == 4:
        ims = ims.mean(axis=3)  # [n, h, w]
    lo, hi = ims.min(axis=0), ims.max(axis=0)
    valid = (hi - lo) >= min_contrast
    mid = 0.5 * (lo + hi)
    col, row = decode_graycode(list(ims > mid[None]), width, height, threshold=0.5)
    valid &= (col < width) & (row < height)
    return col, row, valid


def grid(width: int, height: int, seed: int = 0, count: int = 16, line_width: int = 2, **_) -> list[np.ndarray]:
    """White grid: ``count`` lines per axis, ``line_width`` px wide."""
    rng = np.random.default_rng(seed)
    v = _lines(width, count, line_width, line_offset(rng, width / count, seed))
    h = _lines(height, count, line_width, line_offset(rng, height / count, seed))
    on = v[None, :] | h[:, None]
    return [np.repeat((on * 255).astype(np.uint8)[:, :, None], 3, axis=2)]


def colorline(width: int, height: int, seed: int = 0, line_width: int = 4, **_) -> list[np.ndarray]:
    """Vertical stripes ``line_width`` px wide of random binary colours, neighbours differing."""
    rng = np.random.default_rng(seed)
    n = math.ceil(width / line_width)
    idx = np.empty(n, dtype=np.int64)
    idx[0] = rng.integers(8)
    for k in range(1, n):  # draw from the 7 colours that differ from the previous stripe
        idx[k] = (idx[k - 1] + 1 + rng.integers(7)) % 8
    cols = np.repeat(idx, line_width)[:width]
    row = BINARY_COLOURS[cols]
    return [np.ascontiguousarray(np.broadcast_to(row[None], (height, width, 3)))]


def dots(width: int, height: int, seed: int = 0, count: int | None = None, line_width: int = 2,
         **_) -> list[np.ndarray]:
    """``count`` random white square dots of side ``line_width`` (default: ~1 per 64 px^2)."""
    rng = np.random.default_rng(seed)
    count = count if count is not None else max(1, width * height // 64)
    img = np.zeros((height, width), dtype=np.uint8)
    x = rng.integers(0, max(1, width - line_width + 1), count)
    y = rng.integers(0, max(1, height - line_width + 1), count)
    for dy in range(line_width):
        for dx in range(line_width):
            img[y + dy, x + dx] = 255
    return [np.repeat(img[:, :, None], 3, axis=2)]


def phaseshift(width: int, height: int, seed: int = 0, count: int = 4, period: float = 32.0,
               vertical: bool = True, **_) -> list[np.ndarray]:
    """``count``-step sinusoidal fringes: I_k = 0.5 + 0.5 cos(2 pi x / period - 2 pi k / count).

    Fringes are vertical (vary along x) by default; x is the pixel centre coordinate.
    """
    if count < 3:
        raise FastneusError("phase shift needs at least 3 steps", field="count")
    x = (np.arange(width if vertical else height) + 0.5)
    out = []
    for k in range(count):
        v = 0.5 + 0.5 * np.cos(2 * np.pi * x / period - 2 * np.pi * k / count)
        v = np.round(v * 255).astype(np.uint8)
        plane = np.broadcast_to(v[None, :] if vertical else v[:, None], (height, width))
        out.append(np.repeat(plane[:, :, None], 3, axis=2))
    return out


def decode_phaseshift(images) -> np.ndarray:
    """Wrapped phase in [0, 2 pi) from :func:`phaseshift` images ([h, w] float32)."""
    ims = [np.asarray(im, dtype=np.float32) for im in images]
    ims = [im.mean(axis=2) if im.ndim == 3 else im for im in ims]
    n = len(ims)
    s = sum(im * np.sin(2 * np.pi * k / n) for k, im in enumerate(ims))
    c = sum(im * np.cos(2 * np.pi * k / n) for k, im in enumerate(ims))
    return np.mod(np.arctan2(s, c), 2 * np.pi).astype(np.float32)


@dataclass(frozen=True)
class PatternKind:
    """One pattern family: how to draw it and whether a viewpoint shows it as a sequence.

    Attributes:
        name: the id (``fastneus patterns --kind``, ``fastneus synth --pattern``).
        generate: ``(width, height, seed=, **opts) -> list of uint8 [height, width, 3]``.
        sequence: shown as several shots per viewpoint (Gray code, phase shift), one frame per
            image, by one projector; else one image per projector (a one-shot pattern).
        help: one line for users.
    """

    name: str
    generate: Callable[..., list[np.ndarray]]
    sequence: bool = False
    help: str = ""


# name -> kind, in the order shown to users; register_pattern_kind adds one
PATTERNS: dict[str, PatternKind] = {}


def register_pattern_kind(kind: PatternKind) -> None:
    """Make a pattern kind available to ``make_pattern``, the ``patterns`` verb and ``synth``."""
    if not kind.name or not kind.name.replace("_", "").isalnum():
        raise ValueError(f"pattern kind names are words, got {kind.name!r}")
    PATTERNS[kind.name] = kind


def unregister_pattern_kind(name: str) -> None:
    """Remove a registered kind (tests register toy kinds and remove them after)."""
    PATTERNS.pop(name, None)


def pattern_kinds() -> tuple[str, ...]:
    """Every registered kind's name, built-ins first."""
    return tuple(PATTERNS)


def sequence_kinds() -> tuple[str, ...]:
    """The kinds shown as a sequence of shots per viewpoint."""
    return tuple(k for k, v in PATTERNS.items() if v.sequence)


for _k in (PatternKind("crosslaser", crosslaser, help="static red/green cross-laser lines (the paper's rig)"),
           PatternKind("graycode", graycode, sequence=True, help="Gray-code stripes, one image per bit"),
           PatternKind("grid", grid, help="a one-shot grid"),
           PatternKind("colorline", colorline, help="colourful lines (one-shot, the official sample's pattern)"),
           PatternKind("dots", dots, help="random dots (active stereo)"),
           PatternKind("phaseshift", phaseshift, sequence=True, help="sinusoidal phase shifts")):
    register_pattern_kind(_k)


def make_pattern(kind: str, width: int, height: int, seed: int = 0, **opts) -> list[np.ndarray]:
    """Generate pattern ``kind`` at ``width`` x ``height``.

    Args:
        kind: a registered kind (:func:`pattern_kinds`).
        width, height: projector resolution in pixels.
        seed: random seed (same seed, same images).
        **opts: generator options; None values are dropped so CLI defaults apply
            (``count``, ``line_width``, ``inverse``, ``period``, ...).

    Returns:
        list of uint8 [height, width, 3] RGB images.
    """
    if kind not in PATTERNS:
        raise FastneusError(f"unknown pattern kind {kind!r}; use one of {', '.join(PATTERNS)}", field="--kind")
    if width < 1 or height < 1:
        raise FastneusError(f"bad pattern size {width}x{height}", field="--size")
    opts = {k: v for k, v in opts.items() if v is not None}
    for k in ("count", "line_width"):
        if k in opts and int(opts[k]) < 1:
            raise FastneusError(f"{k} must be >= 1", field=f"--{k.replace('_', '-')}")
    return PATTERNS[kind].generate(int(width), int(height), seed=int(seed), **opts)


# --------------------------------------------------------------------------- IO + CLI
def parse_size(text: str, field: str = "--size") -> tuple[int, int]:
    """Parse ``WxH`` into (width, height)."""
    try:
        w, h = (int(v) for v in str(text).lower().split("x"))
    except ValueError:
        raise FastneusError(f"expected WxH (e.g. 1024x768), got {text!r}", field=field) from None
    if w < 1 or h < 1:
        raise FastneusError(f"size must be positive, got {text!r}", field=field)
    return w, h


def write_png(path: str | os.PathLike, rgb: np.ndarray) -> None:
    """Write an RGB (or single-channel) uint8/uint16 image as PNG atomically."""
    import cv2

    path = Path(path)
    img = rgb[:, :, ::-1] if rgb.ndim == 3 else rgb
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img))
    if not ok:
        raise FastneusError("PNG encoding failed", file=path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".tmp", dir=path.parent)
    with os.fdopen(fd, "wb") as f:
        f.write(buf.tobytes())
    os.replace(tmp, path)
