"""fastneus: fast ActiveNeuS reconstruction from structured-light images.

The public API, loaded lazily (``import fastneus`` costs nothing until a name is used)::

    import fastneus

    scene = fastneus.load_scene("my_scene")              # any supported format
    cfg = fastneus.load_config("fewview", ["run.steps=2000"])
    trainer, metrics = fastneus.reconstruct(scene, cfg, out="runs/my_scene")
    mesh = fastneus.extract_mesh(trainer)                 # trimesh.Trimesh, world units
    metrics = fastneus.evaluate("runs/my_scene")          # re-evaluate a run folder

Everything else is internal and may move; docs/ARCHITECTURE.md shows the layers.
"""
from __future__ import annotations

import importlib
import os
from typing import Any

# torch's OpenMP workers (libgomp) spin for 300,000 iterations after each parallel op by
# default, holding the core that the Warp kernels' CPU threads need next: 2 threads made
# only 1.17x the steps of 1. A short spin frees the core and keeps torch's wake-ups cheap
# (docs/perf-notes/2026-11-26-cpu-threads.md). libgomp reads it when torch loads it, so it
# is set here, before any torch import; a user's own setting wins.
if "GOMP_SPINCOUNT" not in os.environ and "OMP_WAIT_POLICY" not in os.environ:
    os.environ["GOMP_SPINCOUNT"] = "30000"

__version__ = "0.1.0"

# public name -> module holding it
_EXPORTS = {
    "FastneusError": "fastneus.errors",
    "Config": "fastneus.config",
    "load_config": "fastneus.config",
    "Scene": "fastneus.data",
    "load_scene": "fastneus.formats.detect",
    "synthesize": "fastneus.synth.render",
    "make_pattern": "fastneus.light.patterns",
    "Trainer": "fastneus.train.trainer",
    "reconstruct": "fastneus.pipeline",
    "extract_mesh": "fastneus.pipeline",
    "evaluate": "fastneus.pipeline",
}
__all__ = sorted(_EXPORTS) + ["__version__"]


def __getattr__(name: str) -> Any:
    mod = _EXPORTS.get(name)
    if mod is None:
        raise AttributeError(f"module 'fastneus' has no attribute {name!r}")
    value = getattr(importlib.import_module(mod), name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
