"""Warp kernels of fastneus and their pure-torch twins (installed as ``fastneus.kernels``).

Every op ``name`` has a twin ``name_torch`` with the same signature and maths.
``get_op(name, backend)`` picks one, so the pipeline runs on either backend.
See docs/INTERNALS.md for the contracts.
"""
from __future__ import annotations

import importlib

# op name -> module holding ``name`` and ``name_torch``
_OPS = {
    "hash_encode": "hashgrid",
    "hash_encode_jac": "hashgrid",
    "grad_from_jac": "hashgrid",
    "march_rays": "occupancy",
    "march_rays_capped": "occupancy",
    "occupancy_alpha": "occupancy",
    "render_pattern": "render",
    "ray_argmin": "render",
    "project_pattern": "project",
    "laser_light": "project",
    "raycast_mesh": "raycast",
    "marching_cubes": "mesh",
    "adam_update": "adam",
    "adam_nonfinite": "adam",
    "adam_update_multi": "adam",
    "adam_nonfinite_multi": "adam",
}

BACKENDS = ("warp", "torch")
THREADS_ENV = "FASTNEUS_THREADS"  # the automatic thread count's override (kernels/_warp.py reads it)


def get_op(name: str, backend: str = "warp"):
    """Return the Warp op ``name`` or its torch twin.

    Args:
        name: one of the keys of ``_OPS``.
        backend: "warp" or "torch".
    """
    if name not in _OPS:
        raise KeyError(f"unknown kernel op {name!r}; known: {sorted(_OPS)}")
    if backend not in BACKENDS:
        raise ValueError(f"unknown kernel backend {backend!r}; use one of {BACKENDS}")
    mod = importlib.import_module(f"{__name__}.{_OPS[name]}")
    return getattr(mod, name if backend == "warp" else f"{name}_torch")


def prepare_kernels(device, say=None, backend: str = "warp", ops=("hash_encode", "march_rays", "render_pattern"),
                    report: dict | None = None) -> float:
    """Load every Warp module a training step uses on ``device`` before timing starts.

    On a machine's first run (or after a kernel change) this compiles them and, when ``say``
    is given, prints that it does. The torch backend needs nothing. A module of ``ops`` that
    launches kernels defined elsewhere (e.g. Warp's own marching cubes) names them in a
    ``warp_modules()`` function. ``report``, if given, receives ``compiled``: the modules that
    were not in the kernel cache. Returns seconds spent.
    """
    if backend != "warp":
        return 0.0
    from ._warp import load_modules

    mods = []
    for o in ops:
        m = importlib.import_module(f"{__name__}.{_OPS[o]}")
        mods += m.warp_modules() if hasattr(m, "warp_modules") else [m]
    return load_modules(list(dict.fromkeys(mods)), str(device), say=say, report=report)


def configure_threads(requested: int | None = 0, torch_threads: bool = True) -> tuple[int, str]:
    """Set the CPU threads of the Warp ops (and torch's intra-op threads) for this process.

    Args:
        requested: threads (>= 1), or 0 / None for the automatic choice: the environment
            variable ``FASTNEUS_THREADS`` when set, else every CPU in this process's
            affinity mask (``os.sched_getaffinity``).
        torch_threads: also ``torch.set_num_threads`` to the same count.

    Returns:
        (threads, note): the resolved count and a one-line explanation for the run header.
    """
    from . import _warp

    if requested:
        n, why = int(requested), "asked for"
    else:
        n, why = _warp.default_threads()
        why = f"from {why[4:]}" if why.startswith("env ") else f"all {_warp.available_cpus()} CPUs this process may use"
    _warp.set_threads(n)
    if torch_threads:
        import torch

        torch.set_num_threads(n)
    return n, f"threads: {n} ({why}; Warp kernels{' and torch' if torch_threads else ''})"


def run_on_threads(tasks) -> None:
    """Run zero-argument callables on the CPU thread pool the split Warp launches use.

    Returns when all are done (the first exception is re-raised). ``scripts/split_overhead.py``
    times the pool's hand-off with no-op tasks.
    """
    from ._warp import run_tasks

    run_tasks(list(tasks))


def local_threads(n: int):
    """Context manager: Warp launches from the calling thread use ``n`` CPU threads inside it (the
    other threads keep the process's count). A training step split into half batches on two threads
    runs each half's launches unchunked (``fastneus.train.trainer.Trainer``, ``run.split_step``)."""
    from ._warp import local_threads as _local

    return _local(n)
