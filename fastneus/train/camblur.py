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

``camera_blur=auto`` (opt-in) estimates it by rendering (:func:`fastneus.train.blurfit.estimate_blur_by_render`):
at ``blur_at_frac`` of the run, and again at ``blur_refine_frac``, one batch of training rays is
rendered through the patterns blurred by each of ``blurfit.AUTO_SIGMAS``, the illumination refit in
closed form per candidate, and the candidate of least residual near the lines is kept (a sharp
capture picks 0 and the run is unchanged). A measure from the photos' line profiles alone was
tried first and failed on textured surfaces (docs/benchmarks/illum-realistic-cpu.md).
"""
from __future__ import annotations

import math

import numpy as np
import torch

from fastneus.data.images import gaussian_blur


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


def blur_pattern(img, sigma: float):
    """[H, W, 3] uint8 pattern blurred by a Gaussian of ``sigma`` pixels (zero outside), uint8.

    A numpy image is blurred by OpenCV; a torch tensor where it lives (:func:`blur_pattern_torch`,
    the same kernel: on a GPU the in-run blur estimate builds six candidates in milliseconds
    instead of ~0.1 s each on the host).
    """
    if sigma <= 0:
        return img
    if not isinstance(img, np.ndarray):
        return blur_pattern_torch(img, sigma)
    import cv2  # noqa: PLC0415 (an image library, only when a blur is on)

    r = int(math.ceil(3 * sigma))
    out = cv2.GaussianBlur(np.asarray(img, dtype=np.float32), (2 * r + 1, 2 * r + 1), sigmaX=sigma, sigmaY=sigma,
                           borderType=cv2.BORDER_CONSTANT)
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


def blur_pattern_torch(img, sigma: float):
    """Torch twin of :func:`blur_pattern`: ``img`` [H, W, 3] uint8 tensor (any device) blurred with
    zeros outside (:func:`fastneus.data.images.gaussian_blur`), rounded to uint8, same device."""
    if sigma <= 0:
        return img
    return gaussian_blur(img.float(), sigma).round().clamp(0, 255).to(torch.uint8).contiguous()
