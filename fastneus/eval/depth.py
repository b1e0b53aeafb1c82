"""Depth error on the visible surface: the one-shot / few-view accuracy metric.

For each training viewpoint with ground-truth depth, the reconstruction's depth map is the
exported mesh ray-cast from that camera (what a user gets; the same maps come out of a
classical decoder, so both are scored alike). Over the pixels where the ground truth has a
surface:

- ``depth_err_mm``: mean |z_rec - z_gt| over pixels where the reconstruction has a surface too;
- ``depth_err_pct``: mean |z_rec - z_gt| / z_gt (percent of depth) over the same pixels;
- ``depth_median_pct``: the median of the same relative error (a few wrong pixels at silhouettes
  move the mean, not this);
- ``depth_within_1pct``: share of *all* ground-truth pixels within 1% (holes count as misses);
- ``depth_coverage``: share of ground-truth pixels where the reconstruction has a surface.

Pixels are pooled over viewpoints. For one-shot frames with a pattern-free ground-truth image the
same numbers are also given on the pattern-lit pixels (``depth_lit_*``: where the photo differs
from the pattern-free image, e.g. the laser curves) and on the rest (``depth_unlit_*``), since a
sparse pattern constrains only the lit part.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from fastneus.data.scene import view_frames

LIT_THRESHOLD = 12  # 8-bit difference between photo and pattern-free image that counts as lit


class DepthPool:
    """Accumulates per-pixel depth errors over several views; :meth:`metrics` pools them."""

    def __init__(self):
        self.abs: list[np.ndarray] = []
        self.rel: list[np.ndarray] = []
        self.n_gt = 0

    def add(self, pred: np.ndarray, gt: np.ndarray, select: np.ndarray | None = None) -> None:
        """Add one view.

        Args:
            pred: [H, W] reconstructed z-depth (world units); NaN, inf or <= 0 = no surface.
            gt: [H, W] ground-truth z-depth; <= 0 = background.
            select: optional [H, W] bool restricting the pixels counted.
        """
        has_gt = gt > 0
        if select is not None:
            has_gt &= select
        ok = has_gt & np.isfinite(pred) & (pred > 0)
        err = np.abs(pred[ok].astype(np.float64) - gt[ok])
        self.abs.append(err)
        self.rel.append(err / gt[ok])
        self.n_gt += int(has_gt.sum())

    def metrics(self, prefix: str = "depth_", unit_mm: float = 1000.0) -> dict:
        """Pooled metrics (keys ``{prefix}err_mm``, ``err_pct``, ``median_pct``, ``within_1pct``,
        ``coverage``, ``pixels``)."""
        a = np.concatenate(self.abs) if self.abs else np.zeros(0)
        r = np.concatenate(self.rel) if self.rel else np.zeros(0)
        n = max(1, self.n_gt)
        return {f"{prefix}err_mm": float(a.mean() * unit_mm) if a.size else math.inf,
                f"{prefix}err_pct": float(r.mean() * 100) if r.size else math.inf,
                f"{prefix}median_pct": float(np.median(r) * 100) if r.size else math.inf,
                f"{prefix}within_1pct": float((r < 0.01).sum() / n),
                f"{prefix}coverage": float(a.size / n),
                f"{prefix}pixels": int(self.n_gt)}


def depth_errors(pred: np.ndarray, gt: np.ndarray, prefix: str = "depth_") -> dict:
    """Depth metrics of one view (see the module docstring); pred, gt: [H, W] z-depth."""
    pool = DepthPool()
    pool.add(pred, gt)
    return pool.metrics(prefix)


def camera_rays(K: np.ndarray, c2w: np.ndarray, width: int, height: int, device="cpu"):
    """World rays through every pixel centre, row-major.

    Returns:
        origins [H*W, 3], unit dirs [H*W, 3] (float32 on ``device``), and cos [H*W] = the
        z-component of each unit direction in camera coordinates (z-depth = t * cos).
    """
    v, u = np.mgrid[0:height, 0:width]
    pix = np.stack([u.ravel() + 0.5, v.ravel() + 0.5, np.ones(width * height)])
    d_cam = np.linalg.inv(np.asarray(K, dtype=np.float64)) @ pix
    d_cam /= np.linalg.norm(d_cam, axis=0, keepdims=True)
    d = (np.asarray(c2w, dtype=np.float64)[:3, :3] @ d_cam).T
    o = np.broadcast_to(np.asarray(c2w, dtype=np.float64)[:3, 3], d.shape)
    f32 = dict(dtype=torch.float32, device=device)
    return torch.tensor(o, **f32).contiguous(), torch.tensor(d, **f32).contiguous(), d_cam[2]


def mesh_depth(vertices: np.ndarray, faces: np.ndarray, K: np.ndarray, c2w: np.ndarray, width: int, height: int,
               device="cpu") -> np.ndarray:
    """[H, W] z-depth of a mesh seen from a camera (NaN where no surface), by Warp BVH ray casting.

    Args:
        vertices: [V, 3], faces: [F, 3] in world units; K: [3, 3]; c2w: [4, 4] OpenCV pose.
    """
    if len(faces) == 0:
        return np.full((height, width), np.nan, dtype=np.float32)
    from fastneus.kernels.raycast import raycast_mesh

    o, d, cos = camera_rays(K, c2w, width, height, device)
    V = torch.as_tensor(np.asarray(vertices), dtype=torch.float32, device=device)
    F = torch.as_tensor(np.asarray(faces), dtype=torch.int32, device=device)
    t, _, _ = raycast_mesh(V, F, o, d, 1e6)
    z = t.cpu().double().numpy() * cos
    z[~np.isfinite(z)] = np.nan
    return z.reshape(height, width).astype(np.float32)


def lit_pixels(photo: np.ndarray, clean: np.ndarray, threshold: int = LIT_THRESHOLD) -> np.ndarray:
    """[H, W] bool: pixels where the projected pattern shows (photo - pattern-free > threshold)."""
    return (photo.astype(np.int16) - clean.astype(np.int16)).max(axis=2) > threshold


def view_depth_metrics(mesh, scene, frames: list[int], device="cpu", unit_mm: float | None = None) -> dict:
    """Depth metrics of ``mesh`` on every training viewpoint of ``frames`` that has GT depth.

    One-shot viewpoints (one frame) with a pattern-free GT image also get ``depth_lit_*`` and
    ``depth_unlit_*``. Empty dict when no viewpoint has GT depth.
    """
    unit_mm = unit_mm if unit_mm is not None else (1000.0 if scene.units == "m" else 1.0)
    pools = {"": DepthPool(), "lit_": DepthPool(), "unlit_": DepthPool()}
    n_views, lit_views = 0, 0
    for _, idx in view_frames(scene, frames).items():
        i = idx[0]
        gt = scene.gt_depth(i)
        if gt is None:
            continue
        cam = scene.frame_camera(i)
        pred = mesh_depth(mesh.vertices, mesh.faces, cam.K, scene.cam_to_world(i), cam.width, cam.height, device)
        pools[""].add(pred, gt)
        n_views += 1
        clean = scene.gt_clean(i) if len(idx) == 1 else None
        if clean is not None:
            lit = lit_pixels(scene.image(i), clean)
            pools["lit_"].add(pred, gt, lit)
            pools["unlit_"].add(pred, gt, ~lit)
            lit_views += 1
    if n_views == 0:
        return {}
    out = pools[""].metrics("depth_", unit_mm)
    out["depth_views"] = n_views
    if lit_views:
        out.update(pools["lit_"].metrics("depth_lit_", unit_mm))
        out.update(pools["unlit_"].metrics("depth_unlit_", unit_mm))
    return out


def error_map(pred: np.ndarray, gt: np.ndarray, max_pct: float = 1.0) -> np.ndarray:
    """uint8 [H, W, 3] picture of |z_rec - z_gt| / z_gt: black = background, 0 .. ``max_pct`` % on
    a colour ramp (turbo), magenta = GT surface the reconstruction misses."""
    import cv2

    has = gt > 0
    ok = has & np.isfinite(pred) & (pred > 0)
    rel = np.zeros(gt.shape, np.float64)
    rel[ok] = np.abs(pred[ok] - gt[ok]) / gt[ok] * 100.0
    g = np.clip(rel / max_pct * 255.0, 0, 255).astype(np.uint8)
    img = cv2.applyColorMap(g, cv2.COLORMAP_TURBO)[:, :, ::-1].copy()
    img[~has] = 0
    img[has & ~ok] = (255, 0, 255)
    return img


def depth_image(z: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """uint8 [H, W, 3] depth picture (near bright, far dark, viridis), black where no surface."""
    import cv2

    ok = np.isfinite(z) & (z > 0)
    g = np.zeros(z.shape, np.uint8)
    g[ok] = np.clip((hi - z[ok]) / max(hi - lo, 1e-9) * 255.0, 0, 255).astype(np.uint8)
    img = cv2.applyColorMap(g, cv2.COLORMAP_VIRIDIS)[:, :, ::-1].copy()
    img[~ok] = 0
    return img


def baseline_depth_metrics(scene, depths: dict[int, np.ndarray]) -> dict:
    """The visible-surface depth metrics of depth maps from a baseline (Gray code, plane sweep).

    Args:
        depths: {frame index: [H, W] depth along the camera z axis, world units}.
    """
    pool = DepthPool()
    for i, z in depths.items():
        gt = scene.gt_depth(i)
        if gt is not None:
            pool.add(z, gt)
    return pool.metrics("depth_", 1000.0 if scene.units == "m" else 1.0)
