"""Open any supported scene folder: fastneus (scene.json), ActiveNeuS, NeuS/DTU, NeRF
(transforms.json), and any format registered in :mod:`fastneus.formats.registry`.

Every verb that takes a scene goes through :func:`load_scene`, so users never need a
conversion step.
"""
from __future__ import annotations

from pathlib import Path

from fastneus.errors import FastneusError
from fastneus.formats.registry import formats, get_format


def detect_format(path: str | Path) -> str:
    """The name of the registered format of a scene folder (or its main file, e.g. scene.json /
    transforms.json): 'fastneus', 'activeneus', 'neus', 'nerf', ...; the first whose ``detect``
    says yes, in registration order."""
    p = Path(path)
    if not p.exists():
        raise FastneusError("scene not found", file=str(p))
    for fmt in formats():
        if fmt.detect(p):
            return fmt.name
    raise FastneusError("not a scene folder: expected scene.json (fastneus), cameras_sphere.npz "
                        "(ActiveNeuS / NeuS) or transforms.json (NeRF / nerfstudio)", file=str(p))


def load_scene(path: str | Path):
    """Load a scene of any supported format as a validated :class:`fastneus.data.Scene`."""
    return get_format(detect_format(path)).read(path)
