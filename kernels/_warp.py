"""Shared Warp plumbing: one-time init, torch<->warp device mapping, stream sharing, and
the CPU thread pool that splits large launches over every core.

Warp runs a CPU launch on the calling thread only, but its ctypes call releases the GIL
(measured: docs/PERF-NOTES.md, entry 6), so the ops here split a large CPU launch into
chunks of the launch dimension and run them on a small pool of Python threads. The
number of threads is :func:`set_threads` (default: the CPUs this process may run on).

Warp is imported only inside ``fastneus.kernels`` (this folder).
"""
from __future__ import annotations

import contextlib
import math
import os
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Sequence

import torch
import warp as wp

from . import THREADS_ENV

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
            # keep Warp's compile logs out of users' terminals
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


_DUMMIES: dict = {}


def dummy(shape: tuple, ref: torch.Tensor | torch.device, site: str, dtype=torch.float32) -> torch.Tensor:
    """A small zeroed tensor for a kernel argument that is not used: an input the kernel does not
    read (its flag off) or an output nobody reads (a gradient not asked for). Cached per call
    ``site``, shape, dtype and device, so a step does not launch a fill for each (~2 us each, 10-20
    a step on the GPU; perf note 39). Each site has its own tensor: one site's unread writes never
    reach another site's unread input. Not cached while a CUDA graph is being captured (the
    tensor would live in the graph's memory pool).
    """
    dev = ref.device if isinstance(ref, torch.Tensor) else torch.device(ref)
    key = (site, tuple(shape), dtype, dev)
    t = _DUMMIES.get(key)
    if t is None:
        t = torch.zeros(shape, dtype=dtype, device=dev)
        if not (dev.type == "cuda" and torch.cuda.is_current_stream_capturing()):
            _DUMMIES[key] = t
    return t


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


# ----------------------------------------------------------------------------- CPU threads
# Chunks per thread of a split launch: a few more chunks than threads let an idle thread
# take over work from one that the OS has descheduled (the CPU is often shared).
CHUNKS_PER_THREAD = 2

_threads: int | None = None  # resolved thread count (None = not resolved yet)
_pool: ThreadPoolExecutor | None = None
_pool_size = 0
_pool_lock = threading.Lock()
_min_chunk_scale = 1.0  # tests shrink the minimum chunk sizes to force splits of tiny launches
_warm: set = set()  # kernels launched once (their module is loaded; later launches may run in parallel)


def available_cpus() -> int:
    """CPUs this process may run on (its affinity mask; ``os.cpu_count()`` where unknown)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def default_threads() -> tuple[int, str]:
    """The automatic thread count and where it came from.

    ``FASTNEUS_THREADS`` when set to a positive integer, else :func:`available_cpus`.

    Returns:
        (threads, source) with source ``"env FASTNEUS_THREADS"`` or ``"auto"``.
    """
    env = os.environ.get(THREADS_ENV, "").strip()
    if env:
        try:
            n = int(env)
        except ValueError:
            raise ValueError(f"{THREADS_ENV} must be a positive integer, got {env!r}") from None
        if n < 1:
            raise ValueError(f"{THREADS_ENV} must be a positive integer, got {env!r}")
        return n, f"env {THREADS_ENV}"
    return available_cpus(), "auto"


def set_threads(n: int | None) -> int:
    """Set the number of CPU threads the Warp ops use; returns the resolved count.

    Args:
        n: threads (>= 1), or None / 0 for :func:`default_threads`.
    """
    global _threads
    if n is None or n == 0:
        n = default_threads()[0]
    if n < 1:
        raise ValueError(f"threads must be >= 1, got {n}")
    _threads = int(n)
    return _threads


_local = threading.local()  # a calling thread's own count (local_threads)


def get_threads() -> int:
    """The number of CPU threads the Warp ops use (resolved on first use); a thread inside
    :func:`local_threads` gets its own count."""
    own = getattr(_local, "threads", None)
    if own is not None:
        return own
    return _threads if _threads is not None else set_threads(None)


@contextlib.contextmanager
def local_threads(n: int):
    """Launches from the calling thread use ``n`` threads in this block (the others keep theirs):
    a step split over threads (one half batch each, fastneus.train.trainer) launches without chunks."""
    saved = getattr(_local, "threads", None)
    _local.threads = max(1, int(n))
    try:
        yield
    finally:
        _local.threads = saved


@contextlib.contextmanager
def threads(n: int | None, min_chunk_scale: float | None = None):
    """Temporarily use ``n`` threads (and, for tests, scaled minimum chunk sizes).

    Args:
        n: threads for the block (None / 0 = default).
        min_chunk_scale: multiplies every op's minimum chunk size; 0 splits even a
            one-element launch into as many chunks as it has elements.
    """
    global _threads, _min_chunk_scale
    saved = (_threads, _min_chunk_scale)
    set_threads(n)
    if min_chunk_scale is not None:
        _min_chunk_scale = float(min_chunk_scale)
    try:
        yield get_threads()
    finally:
        _threads, _min_chunk_scale = saved


def _get_pool(workers: int) -> ThreadPoolExecutor:
    global _pool, _pool_size
    with _pool_lock:
        if _pool is None or _pool_size < workers:
            if _pool is not None:
                _pool.shutdown(wait=True)
            _pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="fastneus-warp")
            _pool_size = workers
        return _pool


def n_chunks(n: int, ref: torch.Tensor, min_chunk: int) -> int:
    """How many chunks to split a launch over ``n`` elements into.

    1 on CUDA, with one thread, or when ``n`` is below two minimum chunks; else up to
    ``CHUNKS_PER_THREAD`` per thread, each of at least ``min_chunk`` elements.

    Args:
        n: size of the split dimension.
        ref: a tensor on the launch's device.
        min_chunk: smallest worthwhile chunk (amortises the ~50 us per extra launch).
    """
    t = get_threads()
    if ref.device.type != "cpu" or t <= 1 or n <= 1:
        return 1
    m = max(1, int(math.ceil(min_chunk * _min_chunk_scale)))
    return int(max(1, min(t * CHUNKS_PER_THREAD, n // m)))


def split(n: int, parts: int) -> list[tuple[int, int]]:
    """``parts`` contiguous ranges covering ``range(n)`` with sizes differing by at most one
    (empty ranges dropped)."""
    parts = max(1, min(parts, n)) if n > 0 else 1
    q, r = divmod(n, parts)
    out, a = [], 0
    for i in range(parts):
        b = a + q + (1 if i < r else 0)
        if b > a:
            out.append((a, b))
        a = b
    return out


def split_by_weight(cum_start: torch.Tensor, total: int, parts: int) -> list[tuple[int, int]]:
    """Ranges of items whose weights are balanced, from each item's exclusive prefix sum.

    Args:
        cum_start: [R] int CPU tensor, non-decreasing start of each item (e.g. a ray's
            first sample ``offsets``).
        total: sum of all weights (e.g. the sample count).
        parts: wanted number of ranges.

    Returns:
        Contiguous non-empty ranges covering ``range(R)``; any cut points give a valid
        partition, so unsorted input only costs balance.
    """
    R = int(cum_start.shape[0])
    if parts <= 1 or R <= 1:
        return [(0, R)] if R > 0 else []
    targets = torch.tensor([total * k / parts for k in range(1, parts)], dtype=torch.float64)
    cuts = torch.searchsorted(cum_start.to(torch.float64).contiguous(), targets).tolist()
    bounds = sorted({0, R, *(min(max(int(c), 0), R) for c in cuts)})
    return [(a, b) for a, b in zip(bounds, bounds[1:]) if b > a]


def run_tasks(tasks: Sequence[Callable[[], None]], key=None) -> None:
    """Run ``tasks`` on the thread pool (and the calling thread); returns when all are done.

    Tasks are taken in order by whichever thread is free, so their writes must not overlap.
    The first exception is re-raised after every task has finished.

    Args:
        tasks: zero-argument callables, typically one Warp launch each.
        key: identity of the kernel launched; its first run is serial, so that Warp loads
            (or compiles) the module on one thread.
    """
    t = get_threads()
    if len(tasks) <= 1 or t <= 1 or (key is not None and key not in _warm):
        for fn in tasks:
            fn()
        if key is not None:
            _warm.add(key)
        return
    it = iter(tasks)
    lock = threading.Lock()
    errors: list[BaseException] = []

    def drain() -> None:
        while True:
            with lock:
                fn = next(it, None)
            if fn is None:
                return
            try:
                fn()
            except BaseException as e:  # noqa: BLE001 - re-raised on the calling thread
                errors.append(e)

    workers = min(t, len(tasks)) - 1
    pool = _get_pool(workers)
    futs = [pool.submit(drain) for _ in range(workers)]
    drain()
    for f in futs:
        f.result()
    if errors:
        raise errors[0]


def launch_chunked(kernel, inputs: list, outputs: list, ref: torch.Tensor, ranges: Sequence[tuple[int, int]],
                   sliced_in: dict | None = None, sliced_out: dict | None = None, shared: dict | None = None,
                   first_arg: int | None = None) -> None:
    """Launch ``kernel`` once per range ``(a, b)`` of its 1-D launch dimension, on the CPU threads.

    Thread ``i`` of the chunk ``(a, b)`` does the work of thread ``a + i`` of one launch over
    all ranges: its per-item arrays are cut to rows ``a:b`` (``sliced_in``/``sliced_out``),
    or the kernel is told ``a`` (``first_arg``).

    Args:
        kernel: Warp kernel.
        inputs, outputs: launch arguments for the whole range (Warp arrays, descriptors or scalars).
        ref: a tensor on the launch's device.
        ranges: contiguous ``(a, b)`` ranges covering the launch dimension in order (from
            :func:`item_ranges` or :func:`ray_ranges`).
        sliced_in, sliced_out: ``{argument index: (tensor, Warp dtype or None)}``: per-item
            tensors (rows = the launch dimension) passed as rows ``a:b``.
        shared: ``{output index: tensor}``: outputs that threads of every chunk add to with
            atomics (shared parameters). The first chunk writes the tensor itself, every other
            chunk a zeroed private copy, added to it in chunk order afterwards (deterministic
            for a given chunking; atomics are not atomic across CPU threads).
        first_arg: index in ``inputs`` of an int set to ``a`` (kernels whose results depend
            on the global item index).
    """
    if not ranges:
        return
    sliced_in, sliced_out, shared = sliced_in or {}, sliced_out or {}, shared or {}
    copies = [{j: torch.zeros_like(t) for j, t in shared.items()} for _ in ranges[1:]]

    whole = len(ranges) == 1  # one range covering everything: the arguments as given

    def task(c: int, a: int, b: int):
        inp, outp = list(inputs), list(outputs)
        if not whole:
            for j, (t, dt) in sliced_in.items():
                inp[j] = to_wp(t[a:b], dtype=dt, ctype=True)
            for j, (t, dt) in sliced_out.items():
                outp[j] = to_wp(t[a:b], dtype=dt, ctype=True)
        if first_arg is not None:
            inp[first_arg] = a
        if c > 0:
            for j, t in copies[c - 1].items():
                outp[j] = to_wp(t, ctype=True)
        return lambda: launch(kernel, b - a, inp, ref, outputs=outp)

    run_tasks([task(c, a, b) for c, (a, b) in enumerate(ranges)], key=kernel)
    for cp in copies:
        for j, t in cp.items():
            shared[j].add_(t)


def item_ranges(n: int, ref: torch.Tensor, min_chunk: int) -> list[tuple[int, int]]:
    """Equal ranges over ``n`` items for :func:`launch_chunked` (one range off the CPU)."""
    return split(n, n_chunks(n, ref, min_chunk)) if n > 0 else []


def ray_ranges(offsets: torch.Tensor, n_samples: int, ref: torch.Tensor, min_chunk_samples: int) -> list[tuple[int, int]]:
    """Ranges over rays balanced by their sample counts, for one-thread-per-ray kernels.

    Args:
        offsets: [R] int32 first sample of each ray (samples packed by ray).
        n_samples: total samples S.
        ref: a tensor on the launch's device.
        min_chunk_samples: samples per chunk at least.
    """
    R = int(offsets.shape[0])
    parts = min(n_chunks(max(n_samples, 1), ref, min_chunk_samples), R)
    if parts <= 1:
        return [(0, R)] if R > 0 else []
    return split_by_weight(offsets, n_samples, parts)
