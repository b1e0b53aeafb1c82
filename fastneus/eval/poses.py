"""Pose errors of refined against true poses (the real-rig recovery metric)."""
from __future__ import annotations

import numpy as np

from fastneus.geometry.se3 import pose_error


def pose_errors(refined, truth, frames: list[int], anchor: bool = True) -> dict:
    """Mean / max rotation (deg) and translation (mm) errors of refined vs true poses.

    Args:
        refined: scene with the poses to judge (frames in ``frames`` order, as
            :meth:`Rig.refined_scene` returns, or a full scene indexed like ``truth``).
        truth: the scene with the exact poses.
        frames: training frame indices into ``truth``.
    """
    full = len(refined.frames) == len(truth.frames)
    cr, ct = [], []
    first_view = truth.frames[frames[0]].view
    for a, i in enumerate(frames):
        if anchor and truth.frames[i].view == first_view:
            continue
        r, t = pose_error(refined.cam_to_world(i if full else a), truth.cam_to_world(i))
        cr.append(r)
        ct.append(t * 1000)
    pr, pt = [], []
    for pid, pj in truth.projectors.items():
        if pj.proj_to_cam is not None:
            r, t = pose_error(refined.projectors[pid].proj_to_cam, pj.proj_to_cam)
        else:
            i = frames[0]
            r, t = pose_error(refined.proj_to_world(i if full else 0, pid), truth.proj_to_world(i, pid))
        pr.append(r)
        pt.append(t * 1000)
    f = lambda xs, g: float(g(xs)) if xs else 0.0  # noqa: E731
    # what the images feel: pixel shift of points spread over the object (a ball of 0.8x the
    # bounds radius) between the refined and the true camera. A camera turned about the scene
    # centre and moved sideways by distance x angle shifts them far less than either move alone.
    rng = np.random.default_rng(0)
    d = rng.normal(size=(2000, 3))
    pts = truth.bounds.center + 0.8 * truth.bounds.radius * d / np.linalg.norm(d, axis=1, keepdims=True) \
        * rng.uniform(0, 1, (2000, 1)) ** (1 / 3)
    ph = np.c_[pts, np.ones(len(pts))]
    px = []
    for a, i in enumerate(frames):
        if anchor and truth.frames[i].view == first_view:
            continue
        K = truth.frame_camera(i).K
        uv = []
        for T in (refined.cam_to_world(i if full else a), truth.cam_to_world(i)):
            X = (np.linalg.inv(T) @ ph.T)[:3]
            uv.append((K @ X)[:2] / X[2])
        px.append(float(np.linalg.norm(uv[0] - uv[1], axis=0).mean()))
    return {"cam_rot_deg_mean": f(cr, np.mean), "cam_rot_deg_max": f(cr, np.max),
            "cam_trans_mm_mean": f(ct, np.mean), "cam_trans_mm_max": f(ct, np.max),
            "cam_shift_px_mean": f(px, np.mean), "cam_shift_px_max": f(px, np.max),
            "proj_rot_deg_mean": f(pr, np.mean), "proj_rot_deg_max": f(pr, np.max),
            "proj_trans_mm_mean": f(pt, np.mean), "proj_trans_mm_max": f(pt, np.max)}
