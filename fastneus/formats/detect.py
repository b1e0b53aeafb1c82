"""Open any supported scene folder: fastneus (scene.json), ActiveNeuS, NeuS/DTU, NeRF
(transforms.json).

Every verb that takes a scene goes through :func:`load_scene`, so users never need a
conversion step.
"""
from __future__ import annotations

import importlib
from pathlib import Path

from fastneus.errors import FastneusError


def detect_format(path: str | Path) -> str:
    """'fastneus', 'activeneus', 'neus' or 'nerf' for a scene folder (or its scene.json /
    transforms.json)."""
    p = Path(path)
    if p.is_file() and p.name == "scene.json" or (p / "scene.json").is_file():
        return "fastneus"
    if p.is_file() and p.name == "transforms.json" or (p / "transforms.json").is_file():
        return "nerf"
    if not p.exists():
        raise FastneusError("scene not found", file=str(p))
    npz = p / "cameras_sphere.npz"
    if npz.is_file():
        from fastneus.formats.safe_npz import open_npz

        keys = set(open_npz(npz).files)  # lists keys only; never unpickles
        if "cam_proj_pose_0" in keys or "cam_mat_0" in keys:
            return "activeneus"
        if "world_mat_0" in keys:
            return "neus"
        raise FastneusError("neither ActiveNeuS (cam_mat_0) nor NeuS (world_mat_0) keys found", file=str(npz))
    raise FastneusError("not a scene folder: expected scene.json (fastneus), cameras_sphere.npz "
                        "(ActiveNeuS / NeuS) or transforms.json (NeRF / nerfstudio)", file=str(p))


_READERS = {"activeneus": ("fastneus.formats.activeneus", "read_activeneus"),
            "neus": ("fastneus.formats.neus", "read_neus"),
            "nerf": ("fastneus.formats.nerf", "read_nerf")}


def load_scene(path: str | Path):
    """Load a scene of any supported format as a validated :class:`fastneus.data.Scene`."""
    from fastneus.data import Scene

    fmt = detect_format(path)
    if fmt == "fastneus":
        return Scene.load(path)
    mod, fn = _READERS[fmt]
    return getattr(importlib.import_module(mod), fn)(path)
