"""Realistic capture effects applied to synth's linear render (``fastneus synth --realistic``).

The ideal synthetic photo is the linear image model quantised to 8 bits. A real camera adds
what the model does not have, and training must survive it (issue 23). In the order light
meets the camera:

1. speckle: multiplicative noise on the projected light only (laser / projector coherence),
   intensity ~ Gamma(M, 1/M) per pixel and frame, contrast std/mean = ``speckle``;
2. specular highlights: Blinn-Phong ``specular * max(0, n.h)^shininess`` for the ambient light
   (white, times the ambient level) and for every projector's light (times its pattern sample);
3. defocus: a Gaussian blur of ``blur`` pixels over the whole image, formed as a lens and a sensor
   do: the scene is rendered at ``supersample`` x ``supersample`` rays per pixel, blurred on that
   grid, and each pixel's area averaged (the synthetic lasers' lines are thinner than a pixel:
   point-sampled, they would be aliased one-pixel spikes that no camera records);
4. vignetting: ``1 - vignetting * (r / r_corner)^2``;
5. exposure: a per-frame gain, log-uniform within ``1 / (1 + exposure) .. 1 + exposure``;
   frame 0 keeps gain 1 (the reference the learned gains are anchored to);
6. noise: Gaussian with variance ``read_noise^2 + shot_noise * signal``;
7. saturation: clipped at 1 after the gain, so bright laser lines saturate;
8. the camera response ``response`` (linear | srgb | gamma=G), then 8-bit quantisation.

Before all of them, ``interreflection`` > 0 adds one diffuse bounce between surfaces (light that
leaves one part of the object, the ambient's and the projectors', and lights another: a cup's
inside, a nut's hole, a leg beside a body), Monte Carlo at the pixel centres, times that strength
(1 = the physical single bounce of a Lambertian surface). It is not in the ``--realistic`` mix
(its numbers stay comparable); ask for it with ``--interreflection S`` or
``realistic:interreflection=S`` in scripts/quality.py.

Ground truth (i_r, i_b, clean images, depth) stays in linear units, free of these effects; the
true gains are written to ``scene.json``'s ``meta.capture.gains``, the response to ``response``.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

import numpy as np
import torch

from fastneus.data.images import gaussian_blur
from fastneus.data.response import decode, encode, parse_response  # noqa: F401 (decode: tests)
from fastneus.errors import FastneusError


@dataclass(frozen=True)
class Capture:
    """Camera and light effects of a realistic capture (all off = the ideal capture).

    Attributes:
        response: camera response written into the photos (linear | srgb | gamma=G).
        exposure: per-frame auto-exposure spread (0.25 = gains in [0.8, 1.25]); 0 = constant.
        speckle: speckle contrast (std / mean) of the projected light; 0 = none.
        specular: Blinn-Phong strength of the highlights; 0 = Lambertian.
        shininess: Blinn-Phong exponent.
        blur: defocus, Gaussian sigma in camera pixels; 0 = sharp.
        supersample: rays per pixel side when ``blur`` > 0 (the pixel's area integrated, then
            averaged); 1 = the pixel centre only. :func:`make_capture` sets 4 unless given.
        vignetting: relative fall-off at the image corner; 0 = none.
        read_noise: read-noise sigma (linear units).
        shot_noise: shot-noise variance per unit of linear signal.
        interreflection: strength of one diffuse bounce between surfaces (1 = physical); 0 = none.
        bits: bits per channel of the photos written (8, or 16 as a machine-vision camera's PNGs).
        white_balance: per-photo auto white balance: each colour channel's gain log-uniform in
            [1/(1+w), 1+w] per frame on top of the exposure (frame 0: 1); 0 = none. Not in the
            realistic mix.
        mono: 1 = a monochrome camera: each pixel records the mean of the light's three channels
            (:func:`fastneus.light.grey_rgb`'s rule), written as grey PNGs; so is the pattern-free
            ground truth. 0 = colour.
    """

    response: str = "linear"
    exposure: float = 0.0
    speckle: float = 0.0
    specular: float = 0.0
    shininess: float = 40.0
    blur: float = 0.0
    supersample: int = 1
    vignetting: float = 0.0
    read_noise: float = 0.0
    shot_noise: float = 0.0
    interreflection: float = 0.0
    bits: int = 8
    white_balance: float = 0.0
    mono: int = 0

    def to_meta(self, gains: list[float], white: np.ndarray | None = None) -> dict:
        """The settings and the true per-frame gains (and white-balance gains [F, 3] when
        ``white_balance`` is set), for ``scene.json``'s ``meta.capture``."""
        out = {**asdict(self), "gains": [round(float(g), 6) for g in gains]}
        if self.white_balance > 0 and white is not None:
            out["white_balance_gains"] = [[round(float(v), 6) for v in row] for row in white]
        return out


SUPERSAMPLE = 4  # rays per pixel side of a blurred capture (the laser lines are ~0.6 px wide at 128 px)
# the --realistic mix: a consumer camera in auto-exposure, a laser / DLP projector, a glossy object
REALISTIC = dict(response="srgb", exposure=0.25, speckle=0.3, specular=0.25, shininess=40.0, blur=0.7,
                 vignetting=0.25, read_noise=0.002, shot_noise=2e-4)
_LIMITS = {"exposure": (0.0, 4.0), "speckle": (0.0, 1.0), "specular": (0.0, 10.0), "shininess": (1.0, 1e4),
           "blur": (0.0, 5.0), "supersample": (1, 8), "vignetting": (0.0, 0.95), "read_noise": (0.0, 0.5), "shot_noise": (0.0, 0.5),
           "interreflection": (0.0, 4.0), "bits": (8, 16), "mono": (0, 1),
           "white_balance": (0.0, 1.0)}


def make_capture(capture: dict | Capture | None = None, realistic: bool = False) -> Capture | None:
    """The capture settings: ``REALISTIC`` when ``realistic``, updated by ``capture``'s keys.

    Returns:
        None for an ideal capture (nothing set), else a validated :class:`Capture`.
    Raises:
        FastneusError: an unknown key or a value out of range, naming ``capture.<key>``.
    """
    if isinstance(capture, Capture):
        return capture
    vals = dict(REALISTIC) if realistic else {}
    known = {f.name for f in fields(Capture)}
    for k, v in (capture or {}).items():
        if k not in known:
            raise FastneusError(f"unknown capture option; use {', '.join(sorted(known))}", field=f"capture.{k}")
        if v is not None:
            vals[k] = v
    if not vals:
        return None
    vals.setdefault("supersample", SUPERSAMPLE)
    for k, v in vals.items():
        if k == "response":
            vals[k] = str(parse_response(v, field="capture.response"))
            continue
        lo, hi = _LIMITS[k]
        try:
            ok = not isinstance(v, bool) and math.isfinite(float(v)) and lo <= float(v) <= hi
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise FastneusError(f"expected a number in [{lo:g}, {hi:g}], got {v!r}", field=f"capture.{k}")
        vals[k] = int(v) if k in ("supersample", "bits", "mono") else float(v)
        if k in ("supersample", "bits", "mono") and vals[k] != float(v):
            raise FastneusError(f"expected a whole number, got {v!r}", field=f"capture.{k}")
        if k == "bits" and vals[k] not in (8, 16):
            raise FastneusError(f"expected 8 or 16, got {v!r}", field=f"capture.{k}")
    return Capture(**vals)


def frame_gains(n: int, spread: float, seed: int) -> np.ndarray:
    """[n] exposure gains: log-uniform in [1/(1+spread), 1+spread], frame 0 = 1 (the anchor)."""
    g = np.ones(n)
    if spread > 0 and n > 1:
        rng = np.random.default_rng((seed, 11))
        a = math.log1p(spread)
        g[1:] = np.exp(rng.uniform(-a, a, n - 1))
    return g


def channel_gains(n: int, spread: float, seed: int) -> np.ndarray:
    """[n, 3] per-channel white-balance gains: log-uniform in [1/(1+spread), 1+spread] per channel,
    frame 0 = 1 (the anchor)."""
    g = np.ones((n, 3))
    if spread > 0 and n > 1:
        a = math.log1p(spread)
        g[1:] = np.exp(np.random.default_rng((seed, 12)).uniform(-a, a, (n - 1, 3)))
    return g


def apply_speckle(light: torch.Tensor, contrast: float, key: tuple,
                  pixels: tuple[torch.Tensor, int] | None = None) -> torch.Tensor:
    """Projected light [N, 3] times fully developed speckle averaged over M = 1/contrast^2 grains.

    Args:
        light: [N, 3] projected light; contrast: std / mean of the speckle; key: the seed.
        pixels: (index [N] int64, count): the N rays are sub-pixel rays of ``count`` camera pixels,
            ``index`` naming each ray's pixel; the rays of one pixel share its speckle value.
            None: one value per row.
    Returns:
        [N, 3]: ``light * s`` with s ~ Gamma(M, 1/M) per pixel (mean 1, std ``contrast``), one s
        for the three channels.
    """
    if contrast <= 0 or light.shape[0] == 0:
        return light
    m = 1.0 / contrast ** 2
    n = light.shape[0] if pixels is None else int(pixels[1])
    s = torch.from_numpy(np.random.default_rng(key).gamma(m, 1.0 / m, n).astype(np.float32)).to(light.device)
    return light * (s if pixels is None else s[pixels[0]])[:, None]


def blinn_phong(n: torch.Tensor, view: torch.Tensor, to_light: torch.Tensor, shininess: float) -> torch.Tensor:
    """Blinn-Phong lobe max(0, n.h)^shininess (0 where the light is behind the surface).

    Args:
        n: [N, 3] unit normals; view: [N, 3] unit vectors toward the camera;
        to_light: [N, 3] or [3] unit vectors toward the light; shininess: the exponent.
    Returns:
        [N] the lobe.
    """
    to_light = to_light.expand_as(n)
    h = view + to_light
    h = h / h.norm(dim=-1, keepdim=True).clamp_min(1e-9)
    lit = (n * to_light).sum(-1) > 0
    return torch.where(lit, (n * h).sum(-1).clamp_min(0) ** shininess, torch.zeros_like(h[:, 0]))


def vignette(h: int, w: int, strength: float, device) -> torch.Tensor:
    """[H, W, 1] factor 1 - strength * (r / r_corner)^2 about the image centre."""
    yy, xx = torch.meshgrid(torch.arange(h, device=device, dtype=torch.float32) + 0.5,
                            torch.arange(w, device=device, dtype=torch.float32) + 0.5, indexing="ij")
    r2 = ((xx - w / 2) ** 2 + (yy - h / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
    return (1.0 - strength * r2)[..., None]


def sensor_pixels(img: torch.Tensor, sigma: float, sub: int) -> torch.Tensor:
    """A lens and a sensor: [H*sub, W*sub, 3] radiance at sub-pixel centres -> [H, W, 3] pixels.

    The lens's Gaussian (``sigma`` camera pixels) on the fine grid, then each pixel's area averaged
    (``sub`` x ``sub`` box): the pixel value of a continuous image blurred by the lens.
    """
    x = gaussian_blur(img, sigma * sub, "replicate") if sigma > 0 else img
    t = torch.nn.functional.avg_pool2d(x.permute(2, 0, 1)[None], sub)  # [1, 3, H, W]
    return t[0].permute(1, 2, 0).contiguous()


def finish(img: torch.Tensor, cap: Capture, gain, key: tuple, blurred: bool = False) -> torch.Tensor:
    """The camera: linear radiance [H, W, 3] -> encoded values in [0, 1] (before 8-bit rounding).

    Blur (unless ``blurred``: :func:`sensor_pixels` formed the pixels), vignetting, exposure gain,
    read + shot noise, clipping at 1 (saturation), response.
    """
    x = img
    if cap.blur > 0 and not blurred:
        x = gaussian_blur(x, cap.blur, "replicate")
    if cap.vignetting > 0:
        x = x * vignette(x.shape[0], x.shape[1], cap.vignetting, x.device)
    x = x * torch.as_tensor(np.asarray(gain, dtype=np.float32), device=x.device)  # scalar or [3] (white balance)
    if cap.mono:  # one sensor value per pixel: the noise below is drawn once, not per channel
        x = x.mean(dim=-1, keepdim=True)
    if cap.read_noise > 0 or cap.shot_noise > 0:
        var = cap.read_noise ** 2 + cap.shot_noise * x.clamp_min(0)
        z = np.random.default_rng(key).standard_normal(tuple(x.shape)).astype(np.float32)
        x = x + var.sqrt() * torch.from_numpy(z).to(x.device)
    return encode(x.clamp(0.0, 1.0), cap.response).expand(*img.shape)
