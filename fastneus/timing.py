"""Wall-clock phases of a run, measured from process start, and the run's peak memory.

``fastneus.cli`` notes the process start as early as it can (``note_process_start``); the
pipeline then records its phases on a :class:`RunClock` (``clock.phase("mesh")``) and writes
``clock.summary()`` into metrics.json and run.json as ``timing``. Everything here is cheap and
imports nothing heavy: it runs before torch is imported.
"""
from __future__ import annotations

import contextlib
import os
import resource
import sys
import time

# perf_counter() value at process start (from /proc when available, else when cli.py was imported)
_process_start: float | None = None
_pending: "RunClock | None" = None


def process_age() -> float | None:
    """Seconds since this process started (Linux /proc, ~10 ms resolution), or None."""
    try:
        with open("/proc/self/stat") as f:
            stat = f.read()
        start_ticks = int(stat[stat.rindex(")") + 2:].split()[19])   # field 22: starttime (ticks after boot)
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
        age = uptime - start_ticks / os.sysconf("SC_CLK_TCK")
        return age if 0.0 <= age < 3600.0 else None
    except (OSError, ValueError, IndexError):
        return None


def note_process_start() -> float:
    """Remember when this process started (idempotent); returns it as a perf_counter() value."""
    global _process_start
    if _process_start is None:
        now = time.perf_counter()
        age = process_age()
        _process_start = now - (age if age is not None else 0.0)
    return _process_start


class RunClock:
    """Named phases of one run: seconds each, plus marks (seconds since the origin).

    Args:
        origin: perf_counter() value time is measured from (the process start for a CLI run).
        source: what the origin is ("process start" or "run start"), written with the times.
    """

    def __init__(self, origin: float | None = None, source: str = "run start"):
        self.origin = time.perf_counter() if origin is None else origin
        self.source = source
        self.phases: dict[str, float] = {}
        self.marks: dict[str, float] = {}
        self.notes: dict = {}
        self._first: float | None = None

    def now(self) -> float:
        """Seconds since the origin."""
        return time.perf_counter() - self.origin

    @contextlib.contextmanager
    def phase(self, name: str):
        """Time the block as phase ``name`` (accumulates when entered again)."""
        t = time.perf_counter()
        if self._first is None:
            self._first = t
        try:
            yield self
        finally:
            self.add(name, time.perf_counter() - t)

    def add(self, name: str, seconds: float) -> None:
        if self._first is None:
            self._first = time.perf_counter() - seconds
        self.phases[name] = self.phases.get(name, 0.0) + float(seconds)

    def mark(self, name: str) -> float:
        """Record that ``name`` happened now; returns seconds since the origin."""
        self.marks[name] = self.now()
        return self.marks[name]

    def summary(self) -> dict:
        """``{"origin": ..., "startup": s, <phase>: s, ..., "other": s, "total": s, <mark>_at: s, "notes": {...}}``.

        ``startup`` is the time before the first phase (interpreter start, imports, argument
        parsing); ``other`` is what no phase covered; ``total`` runs to now.
        """
        total = self.now()
        start = (self._first - self.origin) if self._first is not None else total
        out = {"origin": self.source, "startup": round(start, 3)}
        out.update({k: round(v, 3) for k, v in self.phases.items()})
        out["other"] = round(max(0.0, total - start - sum(self.phases.values())), 3)
        out["total"] = round(total, 3)
        out.update({f"{k}_at": round(v, 3) for k, v in self.marks.items()})
        if self.notes:
            out["notes"] = dict(self.notes)
        return out


def begin_cli_run(from_process_start: bool = True) -> None:
    """Called by the CLI before a verb runs: the next run measures from the process start
    (or, for ``main(argv)`` called inside a longer-lived process such as a test, from now)."""
    global _pending
    _pending = RunClock(note_process_start(), "process start") if from_process_start else RunClock(None, "cli call")


def take_clock() -> RunClock:
    """The clock the CLI prepared for this run (once), else a new one starting now."""
    global _pending
    clock, _pending = _pending, None
    return clock if clock is not None else RunClock()


def peek_clock() -> RunClock | None:
    """The CLI's pending clock, without taking it (phases before the run starts, e.g. scene load)."""
    return _pending


def peak_memory(device) -> dict:
    """Peak memory of this process so far, in MiB.

    Keys: ``peak_rss_mb`` (host, getrusage maxrss); on CUDA also ``peak_gpu_torch_mb``
    (torch.cuda.max_memory_allocated), ``peak_gpu_warp_mb`` (Warp's memory-pool high-water
    mark: Warp's own allocations, e.g. marching cubes; fastneus kernels allocate through torch)
    and ``peak_gpu_mb``, their sum (an upper bound: the two peaks need not coincide).
    """
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    out = {"peak_rss_mb": round(rss / (2 ** 20 if sys.platform == "darwin" else 1024.0), 1)}
    if str(device).startswith("cuda") and "torch" in sys.modules:
        import torch

        if torch.cuda.is_available():
            dev = torch.device(device)
            torch_b = torch.cuda.max_memory_allocated(dev)
            warp_b = 0
            if "warp" in sys.modules:
                from fastneus.kernels._warp import peak_memory_bytes

                warp_b = peak_memory_bytes(dev)
            out.update(peak_gpu_torch_mb=round(torch_b / 2 ** 20, 1), peak_gpu_warp_mb=round(warp_b / 2 ** 20, 1),
                       peak_gpu_mb=round((torch_b + warp_b) / 2 ** 20, 1))
    return out


PHASE_ORDER = ("startup", "synth", "scene_load", "imports", "cuda_init", "setup", "kernels", "train", "validation",
               "checkpoint", "mesh", "renders", "eval", "report", "other", "total")


def table(summary: dict) -> str:
    """The phases of ``summary`` as a two-column text table (seconds, share of total)."""
    total = max(float(summary.get("total", 0.0)), 1e-9)
    names = [k for k in PHASE_ORDER if k in summary] + sorted(
        k for k, v in summary.items() if k not in PHASE_ORDER and isinstance(v, (int, float)) and not k.endswith("_at"))
    lines = [f"{k:<12s} {summary[k]:8.2f} s {100 * summary[k] / total:5.1f}%" for k in names]
    marks = [f"{k[:-3]} at {v:.2f} s" for k, v in summary.items() if k.endswith("_at")]
    return "\n".join(lines + ([", ".join(marks)] if marks else []))
