"""A slightly-off calibration: a scene copy with every pose moved by a known random amount
(tests and the real-rig benchmarks recover it with ``pose_refine``)."""
from __future__ import annotations

import copy
import math

import numpy as np
import torch

from fastneus.geometry.se3 import se3_matrix


def perturb_scene(scene, deg: float, metres: float, seed: int = 0, anchor: bool = True,
                  projectors: bool = True):
    """A copy of ``scene`` with every viewpoint's camera (except the first when ``anchor``) and
    every projector's pose moved by a random rotation of ``deg`` degrees about a random axis
    and a random translation of ``metres`` (seeded): a calibration that is slightly off.

    Frames sharing a viewpoint move together; a rigged projector's ``proj_to_cam`` moves once.
    """
    rng = np.random.default_rng(seed)

    def E() -> np.ndarray:
        ax = rng.normal(size=3)
        tr = rng.normal(size=3)
        T = se3_matrix(torch.tensor(np.r_[ax / np.linalg.norm(ax) * math.radians(deg),
                                           tr / np.linalg.norm(tr) * metres][None]), 1.0)[0].numpy()
        return T

    s = copy.deepcopy(scene)
    views = list(dict.fromkeys(f.view for f in s.frames))
    moves = {v: (np.eye(4) if anchor and j == 0 else E()) for j, v in enumerate(views)}
    for f in s.frames:
        f.cam_to_world = f.cam_to_world @ moves[f.view]
    if projectors:
        for pid, pj in s.projectors.items():
            Ep = E()
            if pj.proj_to_cam is not None:
                pj.proj_to_cam = pj.proj_to_cam @ Ep
            else:
                for f in s.frames:
                    fp = f.projectors.get(pid)
                    if fp is not None and fp.proj_to_world is not None:
                        fp.proj_to_world = fp.proj_to_world @ Ep
    return s
