"""Shared Warp plumbing: one-time init, torch<->warp device mapping, stream sharing.

Warp is imported only inside ``fastneus.kernels`` (this folder).
"""
from __future__ import annotations

import contextlib
import os
import sys
import threading
import time

import torch
import warp as wp

_lock = threading.Lock()
_initialised = False


@contextlib.contextmanager
def _quiet_stderr():
    """Silence the process's stderr (file descriptor 2, native writes included)."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def init() -> None:
    """Initialise Warp once, quietly (no banner, kernel cache in the default place)."""
    global _initialised
    if _initialised:
        return
    with _lock:
        if not _initialised:
            wp.config.quiet = True
            if hasattr(wp, "LOG_WARNING"):  # warp 1.19: the banner/module-load lines follow log_level
                wp.config.log_level = wp.LOG_WARNING
            # Warp's CPU path is single-threaded; keep its compile logs out of users' terminals.
            wp.config.verbose = False
            if os.environ.get("FASTNEUS_WARP_DEBUG"):
                wp.config.mode = "debug"
            if torch.cuda.is_available():
                wp.init()
            else:
                # Warp's native CUDA probe prints "Could not find or load the NVIDIA CUDA driver"
                # on every CPU-only run; that is expected here, so keep it out of users' terminals.
                with _quiet_stderr():
                    wp.init()
            _initialised = True


def device_of(t: torch.Tensor) -> str:
    """Warp device string for a torch tensor ("cpu" or "cuda:N")."""
    init()
    if t.device.type == "cuda":
        return f"cuda:{t.device.index if t.device.index is not None else torch.cuda.current_device()}"
    return "cpu"


def stream_of(t: torch.Tensor):
    """Warp stream wrapping torch's current stream for ``t``'s device (None on CPU)."""
    if t.device.type != "cuda":
        return None
    return wp.stream_from_torch(torch.cuda.current_stream(t.device))


def to_wp(t: torch.Tensor, dtype=None, requires_grad: bool = False, ctype: bool = False):
    """Zero-copy view of a contiguous torch tensor as a Warp array.

    Args:
        t: contiguous torch tensor on cpu or cuda.
        dtype: Warp dtype (e.g. ``wp.vec3`` for a [N, 3] float32 tensor); inferred when None.
        requires_grad: kept False: adjoints are passed explicitly as separate arrays so
            that Warp never allocates hidden gradient buffers.
        ctype: return Warp's low-level array descriptor instead of a ``wp.array`` (about 4x
            less host time per argument; only for passing straight to ``launch``).
    """
    if not t.is_contiguous():
        t = t.contiguous()
    if ctype:
        return wp.from_torch(t, dtype=dtype, requires_grad=requires_grad, return_ctype=True)
    return wp.from_torch(t, dtype=dtype, requires_grad=requires_grad)


def launch(kernel, dim, inputs, ref: torch.Tensor, outputs=None, adj_inputs=None, adj_outputs=None,
           adjoint: bool = False) -> None:
    """Launch ``kernel`` on ``ref``'s device and torch's current stream (no host sync)."""
    if (isinstance(dim, int) and dim == 0) or (isinstance(dim, tuple) and 0 in dim):
        return
    wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs or [], adj_inputs=adj_inputs or [],
              adj_outputs=adj_outputs or [], adjoint=adjoint, device=device_of(ref), stream=stream_of(ref))


def _cached(module, device: str) -> bool | None:
    """True if ``module``'s compiled binary for ``device`` is in Warp's kernel cache (None = unknown)."""
    try:
        from warp._src.context import Module, get_module, runtime

        m = module if isinstance(module, Module) else get_module(module.__name__)
        dev = runtime.get_device(device)
        bd = 1 if dev.is_cpu else None  # CPU launches build a block_dim=1 variant (its own hash)
        folder = os.path.join(wp.config.kernel_cache_dir, m.get_module_identifier(bd))
        return os.path.isfile(os.path.join(folder, m._get_compile_output_name(dev, block_dim=bd)))
    except Exception:  # noqa: BLE001 - private API of one Warp version; only used for a message
        return None


def _name(module) -> str:
    """Name of a Python module holding Warp kernels, or of a ``warp.Module``."""
    return getattr(module, "__name__", None) or module.name


def load_modules(modules, device: str, say=None, report: dict | None = None) -> float:
    """Load (compile on a machine's first run) the Warp modules ``modules`` on ``device``.

    Args:
        modules: Python modules holding Warp kernels, or ``warp.Module`` objects.
        device: "cpu" or "cuda[:N]".
        say: optional print function; told when kernels must be compiled first.
        report: optional dict; ``report["compiled"]`` gets the names of the modules that were
            not in the kernel cache (compiled now), appended to what it holds.
    Returns:
        Seconds spent.
    """
    init()
    dev = "cpu" if str(device) == "cpu" else (str(device) if ":" in str(device) else
                                             f"cuda:{torch.cuda.current_device()}")
    t = time.perf_counter()
    missing = [_name(m).rsplit(".", 1)[-1] for m in modules if _cached(m, dev) is False]
    if report is not None:
        report.setdefault("compiled", []).extend(missing)
    if missing and say is not None:
        say(f"compiling Warp kernels for {dev} ({', '.join(missing)}): once per machine and kernel version, "
            f"about 10-30 s; cached in {wp.config.kernel_cache_dir}")
    for m in modules:
        wp.load_module(m, device=dev)
    dt = time.perf_counter() - t
    if missing and say is not None:
        say(f"kernels compiled in {dt:.1f} s")
    return dt


def peak_memory_bytes(device) -> int:
    """High-water mark of Warp's own CUDA memory pool on ``device`` (0 on the CPU, when Warp
    allocated nothing through a pool, or when the query is unsupported).

    fastneus kernels take torch tensors and allocate nothing through Warp; Warp's own
    geometry routines (sparse marching cubes) do.
    """
    if not str(device).startswith("cuda") or not _initialised:
        return 0
    try:
        dev = str(device) if ":" in str(device) else f"cuda:{torch.cuda.current_device()}"
        return int(wp.get_mempool_used_mem_high(dev))
    except Exception:  # noqa: BLE001 - no mempool on this device/driver
        return 0
