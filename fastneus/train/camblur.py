"""The camera's blur (``rays.camera_blur``): estimated from the data, applied to the projected light.

A real camera records each pixel as the lens's blur of the scene integrated over the pixel's
area. The model renders one ray through the pixel centre; a projected line thinner than a pixel
then comes out as a sharp spike where the photo has a wider, lower bump, and the learned i_r,
i_b explain the lower peak by coming out low (docs/benchmarks/illum-realistic-cpu.md).

The blur is applied where it matters and costs nothing per step: to the projected light, by
blurring each pattern image once with the same blur in projector pixels
(``sigma * f_projector / f_camera * d_camera / d_projector``, the scale between the two images of
the scene for a projector mounted by the camera). ``blur_via=rays`` instead spreads ``blur_rays``
rays per pixel (every colour blurred, ``blur_rays`` times the rays per pixel).

``camera_blur=auto`` (the default) estimates it by rendering (:func:`fastneus.train.blurfit.estimate_blur_by_render`):
at ``blur_at_frac`` of the run, and again at ``blur_refine_frac``, one batch of training rays is
rendered through the patterns blurred by each of ``blurfit.AUTO_SIGMAS``, the illumination refit in
closed form per candidate, and the candidate of least residual near the lines is kept (a sharp
capture picks 0 and the run is unchanged). The line-profile measure below
(:func:`estimate_camera_blur`, second moments across the photos' thin ridges) recovers a known
blur on untextured lines but not on textured photos, where the texture's own ridges dominate; it
is kept as a tool, not used by training.
"""
from __future__ import annotations

import math

import numpy as np

AUTO_MIN = 0.5  # px: the line-profile measure below this is a sharp camera (the pixel box alone is 0.29 px)
_HALF = 3  # profile half-window (px); the baseline is the line through the values at +-(_HALF + 1)


def ridge_moments(img: np.ndarray, min_excess: float = 0.02, rel: float = 0.25) -> np.ndarray:
    """Second moments across the thin bright ridges of an image (projected lines), in px^2.

    A ridge pixel is a maximum along x (or y) standing ``min_excess`` (and ``rel`` times the
    image's 95th-percentile ridge height) above the straight baseline through the values
    ``_HALF + 1`` px to either side. Its profile over +-``_HALF`` px, baseline removed, gives the
    second moment about its centroid; the centroids one row (column) before and after give the
    line's slope s, and the moment across the line is ``m2 / (1 + s^2)`` (ridges with |s| > 1
    are measured by the other axis).

    Args:
        img: [H, W] float, linear intensity (e.g. the sum of the three channels).
        min_excess: least ridge height above the baseline (linear units).
        rel: least ridge height relative to the image's 95th-percentile ridge height.
    Returns:
        [N] float64: the moments of every ridge pixel found (both axes).
    """
    out = []
    for a in (np.asarray(img, dtype=np.float64), np.asarray(img, dtype=np.float64).T):
        h, w = a.shape
        r = _HALF + 1
        if w < 2 * r + 1 or h < 3:
            continue
        k = np.arange(-_HALF, _HALF + 1, dtype=np.float64)
        cols = np.arange(r, w - r)
        # [H, C, 2*HALF+1] windows about every candidate column, baseline through +-r removed
        win = np.stack([a[:, cols + int(d)] for d in k], axis=-1)
        lo, hi = a[:, cols - r], a[:, cols + r]
        base = lo[..., None] + (hi - lo)[..., None] * (k + r) / (2 * r)
        y = win - base
        c = a[:, cols]
        peak = (c > a[:, cols - 1]) & (c >= a[:, cols + 1])
        exc = y[..., _HALF]
        cand = peak & (exc > min_excess)
        if not cand.any():
            continue
        thr = max(min_excess, rel * float(np.percentile(exc[cand], 95)))
        sel = cand & (exc > thr)
        sel[0], sel[-1] = False, False  # need the rows above and below
        tot = y.sum(-1)
        mu = (y * k).sum(-1) / np.where(np.abs(tot) > 1e-12, tot, np.inf)
        rr, cc = np.nonzero(sel & (tot > 0))
        if rr.size == 0:
            continue
        m2 = (y[rr, cc] * (k - mu[rr, cc, None]) ** 2).sum(-1) / tot[rr, cc]
        # the same window one row above / below: where the line's centroid moved
        s = (mu[rr + 1, cc] - mu[rr - 1, cc]) / 2.0
        ok = (tot[rr + 1, cc] > 0) & (tot[rr - 1, cc] > 0) & (np.abs(s) <= 1.0) & (m2 > 0)
        out.append((m2 / (1.0 + s ** 2))[ok])
    return np.concatenate(out) if out else np.zeros(0)


def pattern_line_moment(pattern: np.ndarray) -> float | None:
    """Second moment (projector px^2) across the lines of a pattern image as the renderer samples
    it (bilinear: + 1/6), or None where it has no thin lines (a flood, Gray-code stripes)."""
    m = ridge_moments(np.asarray(pattern, dtype=np.float64).sum(-1) / (3 * 255.0), min_excess=0.1)
    return None if m.size < 20 else float(np.median(m)) + 1.0 / 6.0


def projector_scale(scene, frames: list[int], pid: str) -> float:
    """Projector pixels per camera pixel on the scene (mean over ``frames``):
    ``f_projector / f_camera * d_camera / d_projector``, d = distance to the bounds' centre."""
    centre = np.asarray(scene.bounds.center, dtype=np.float64)
    p = scene.projectors[pid]
    fp = 0.5 * (float(p.K[0, 0]) + float(p.K[1, 1]))
    vals = []
    for i in frames:
        cam = scene.frame_camera(i)
        fc = 0.5 * (float(cam.K[0, 0]) + float(cam.K[1, 1]))
        c2w = np.asarray(scene.cam_to_world(i), dtype=np.float64)
        w2p = np.asarray(scene.world_to_proj(i, pid), dtype=np.float64)
        pc = np.linalg.inv(w2p)[:3, 3]
        dc = np.linalg.norm(c2w[:3, 3] - centre)
        dp = np.linalg.norm(pc - centre)
        if dp > 0 and fc > 0:
            vals.append(fp / fc * dc / dp)
    return float(np.mean(vals)) if vals else 1.0


def image_projectors(scene, frames: list[int]) -> dict[str, set[str]]:
    """{projector id: the pattern ids it shows in ``frames``} for image projectors that are lit."""
    out: dict[str, set[str]] = {}
    for i in frames:
        for pid, fp in scene.frames[i].projectors.items():
            if fp is not None and fp.on and fp.pattern is not None and scene.projectors[pid].kind == "pattern":
                out.setdefault(pid, set()).add(fp.pattern)
    return out


def estimate_camera_blur(photos, scene, frames: list[int]) -> tuple[float, dict]:
    """The camera blur the model lacks, in camera pixels, from the photos' line profiles.

    Args:
        photos: iterable of [H, W, 3] float linear photos (the training frames').
        scene: the loaded scene (patterns, projector and camera intrinsics, poses).
        frames: the training frame indices (into ``scene.frames``).
    Returns:
        (sigma, info): sigma >= 0 (0 when no line was found); info holds ``m2_photo``,
        ``m2_line`` (px^2, camera pixels), ``ridges`` (how many profiles were measured).
    """
    m = [ridge_moments(np.asarray(ph, dtype=np.float64).sum(-1)) for ph in photos]
    m = np.concatenate(m) if m else np.zeros(0)
    info = {"ridges": int(m.size)}
    if m.size < 50:
        return 0.0, info
    m2_photo = float(np.median(m))
    lines = []
    for pid, pats in image_projectors(scene, frames).items():
        scale = projector_scale(scene, frames, pid)
        for q in pats:
            mq = pattern_line_moment(scene.pattern_image(q))
            if mq is not None:
                lines.append(mq / scale ** 2)
    m2_line = float(np.median(lines)) if lines else 0.0
    info.update(m2_photo=round(m2_photo, 4), m2_line=round(m2_line, 4))
    return math.sqrt(max(0.0, m2_photo - m2_line)), info


def blur_pattern(img: np.ndarray, sigma: float) -> np.ndarray:
    """[H, W, 3] uint8 pattern blurred by a Gaussian of ``sigma`` pixels (zero outside), uint8."""
    import cv2  # noqa: PLC0415 (an image library, only when a blur is on)

    if sigma <= 0:
        return img
    r = int(math.ceil(3 * sigma))
    out = cv2.GaussianBlur(np.asarray(img, dtype=np.float32), (2 * r + 1, 2 * r + 1), sigmaX=sigma, sigmaY=sigma,
                           borderType=cv2.BORDER_CONSTANT)
    return np.clip(np.round(out), 0, 255).astype(np.uint8)
