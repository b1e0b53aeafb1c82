"""The classical baseline for multi-shot scenes: Gray-code decoding + ray/plane triangulation.

What a structured-light user would run instead of a neural reconstruction: per viewpoint,
decode the projector column and row of every camera pixel from the Gray-code photos
(:func:`fastneus.light.patterns.decode_graycode_captured`, per-pixel threshold), intersect the
camera ray with the plane of the decoded projector column (the column centre; no sub-pixel
refinement, as in OpenCV's ``structured_light`` module), and reject pixels whose triangulated
point does not reproject within ``row_tol`` pixels of the decoded projector row (the epipolar
check that removes decoding errors at shadows and edges). numpy only; one depth map per view.
"""
from __future__ import annotations

import time

import numpy as np

from fastneus.data.scene import view_frames
from fastneus.errors import FastneusError
from fastneus.light.patterns import decode_graycode_captured, gray_bits


def _sequence_projector(scene, frames: list[int]) -> str:
    """The one projector that shows the sequence in every frame of a view."""
    pids = {pid for i in frames for pid, _ in scene.active_projectors(i)}
    if len(pids) != 1:
        raise FastneusError(f"Gray-code decoding needs exactly one active projector per view, found "
                            f"{sorted(pids) or 'none'}", field="projectors")
    return pids.pop()


def triangulate_columns(col: np.ndarray, row: np.ndarray, valid: np.ndarray, K: np.ndarray, c2w: np.ndarray,
                        Kp: np.ndarray, p2w: np.ndarray, row_tol: float = 1.5) -> np.ndarray:
    """Camera z-depth from decoded projector columns (ray / column-plane intersection).

    Args:
        col, row: int64 [H, W] decoded projector column / row per camera pixel.
        valid: bool [H, W] pixels with a decoded code.
        K, c2w: camera intrinsics [3, 3] and pose [4, 4]; Kp, p2w: the projector's.
        row_tol: largest distance (projector pixels) between the triangulated point's projector row
            and the decoded row's centre; farther pixels are rejected (<= 0 turns the check off).

    Returns:
        [H, W] float32 z-depth in world units, NaN where nothing was triangulated.
    """
    H, W = col.shape
    out = np.full((H, W), np.nan, dtype=np.float32)
    v, u = np.nonzero(valid)
    if v.size == 0:
        return out
    d_cam = np.linalg.inv(K) @ np.stack([u + 0.5, v + 0.5, np.ones(u.size)])   # [3, N], z = 1
    d = c2w[:3, :3] @ d_cam
    w2p = np.linalg.inv(p2w)
    R, T = w2p[:3, :3], w2p[:3, 3]
    a = R @ c2w[:3, 3] + T                     # [3] camera centre in projector coords
    b = R @ d                                  # [3, N] ray directions in projector coords
    # column c is the plane (Kp[0] - (c + 0.5) Kp[2]) . X = 0
    n = Kp[0][:, None] - (col[v, u] + 0.5)[None] * Kp[2][:, None]   # [3, N]
    den = (n * b).sum(0)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -(n * a[:, None]).sum(0) / den
    X = a[:, None] + t[None] * b
    ok = np.isfinite(t) & (t > 0) & (np.abs(den) > 1e-12) & (X[2] > 1e-6)
    if row_tol > 0:
        with np.errstate(divide="ignore", invalid="ignore"):
            py = (Kp[1] @ X) / X[2]
        ok &= np.abs(py - (row[v, u] + 0.5)) <= row_tol
    out[v[ok], u[ok]] = t[ok]                  # d_cam has z = 1: t is the camera z-depth
    return out


def graycode_depth(scene, frames: list[int], min_contrast: float = 0.06, row_tol: float = 1.5) -> np.ndarray:
    """Depth map of one viewpoint from its Gray-code frames (in sequence order).

    Args:
        scene: a loaded scene; ``frames``: the frame indices of one viewpoint, one per Gray-code
            plane, in :func:`fastneus.light.patterns.graycode` order (as ``fastneus synth`` writes them).
    Returns:
        [H, W] float32 z-depth (world units), NaN where nothing was triangulated.
    """
    pid = _sequence_projector(scene, frames)
    pj = scene.projectors[pid]
    need = gray_bits(pj.width) + gray_bits(pj.height)
    if len(frames) != need:
        raise FastneusError(f"a {pj.width}x{pj.height} Gray-code sequence has {need} planes, the view has "
                            f"{len(frames)} frames", field="frames")
    col, row, valid = decode_graycode_captured([scene.image(i) for i in frames], pj.width, pj.height,
                                               min_contrast=min_contrast)
    i = frames[0]
    return triangulate_columns(col, row, valid, scene.frame_camera(i).K, scene.cam_to_world(i), pj.K,
                               scene.proj_to_world(i, pid), row_tol=row_tol)


def graycode_baseline(scene, frames: list[int] | None = None, **kw) -> tuple[dict[int, np.ndarray], float]:
    """Decode + triangulate every viewpoint of ``frames`` (default: all frames).

    Returns:
        ({first frame of each view: [H, W] depth}, seconds spent; image reading included).
    """
    frames = list(range(len(scene.frames))) if frames is None else list(frames)
    t = time.perf_counter()
    out = {idx[0]: graycode_depth(scene, idx, **kw) for idx in view_frames(scene, frames).values()}
    return out, time.perf_counter() - t
