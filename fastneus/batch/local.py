"""Local scheduling: one worker per GPU (or a few CPU workers), each running one ``fastneus train``
subprocess at a time.

A worker is a slot with its own environment: ``CUDA_VISIBLE_DEVICES`` names its GPU, so the
child's ``cuda`` is that GPU. Children run in their own session, so a Ctrl-C at the terminal
reaches the batch only; the batch forwards SIGINT / SIGTERM to each running child once per
signal it receives (train saves a checkpoint on the first and stops at once on a second), starts
nothing new, waits for the children and returns.
"""
from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Iterator

from fastneus.batch.plan import Job, conclude, open_log, python_command, read_progress
from fastneus.errors import FastneusError

THREADS_PER_RUN = 4  # a CPU run's default share of cores: training scales to a few cores
POLL_S = 0.5


@dataclass
class Worker:
    """A slot that runs one scene at a time: ``label`` for the table, ``env`` added to the child's."""

    label: str
    env: dict = field(default_factory=dict)


def available_cores() -> int:
    """CPUs this process may use (its affinity mask)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def detect_gpus() -> list[str]:
    """The ids of the CUDA GPUs torch sees (as ``CUDA_VISIBLE_DEVICES`` names them); [] without
    torch or CUDA."""
    try:
        import torch  # function-level: the batch verb pays for torch only when it looks for GPUs
    except ImportError:
        return []
    try:
        n = torch.cuda.device_count() if torch.cuda.is_available() else 0
    except RuntimeError:
        return []
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    ids = [v.strip() for v in visible.split(",") if v.strip()] if visible else []
    return ids[:n] if len(ids) >= n else [str(i) for i in range(n)]


def plan_workers(gpus: str | None, workers: int | None, device: str | None,
                 threads: int | None) -> tuple[list[Worker], int | None, str]:
    """The workers of a local batch, the ``--threads`` each run gets, and a line saying why.

    Args:
        gpus: ``--gpus`` (``0,1``), or None to detect (with ``--device cpu``: no GPU).
        workers: ``--workers``: CPU workers, or runs at once spread over the GPUs.
        device: ``--device``. threads: ``--threads`` per run.

    Raises:
        FastneusError: an empty or repeated GPU id, ``--gpus`` with ``--device cpu``, ``--workers`` < 1.
    """
    if workers is not None and workers < 1:
        raise FastneusError(f"must be >= 1, got {workers}", field="--workers")
    if threads is not None and threads < 1:
        raise FastneusError(f"must be >= 1, got {threads}", field="--threads")
    cores = available_cores()
    if gpus is not None:
        if device == "cpu":
            raise FastneusError("--gpus chooses GPUs but --device cpu trains on the CPU; give one", field="--gpus")
        ids = [g.strip() for g in gpus.split(",")]
        if not ids or any(not g or not g.replace("-", "").isalnum() for g in ids) or len(set(ids)) != len(ids):
            raise FastneusError(f"expected distinct GPU ids separated by commas (e.g. 0,1), got {gpus!r}",
                                field="--gpus")
        how = "as --gpus asks"
    else:
        ids = [] if device == "cpu" else detect_gpus()
        how = "detected by torch"
    if ids:
        n = workers or len(ids)
        pool = [Worker(f"gpu {ids[i % len(ids)]}", {"CUDA_VISIBLE_DEVICES": ids[i % len(ids)]}) for i in range(n)]
        per_run = threads or max(1, cores // n)
        note = (f"{len(ids)} GPU(s) {','.join(ids)} {how}: {n} worker(s), one run each at a time "
                f"(CUDA_VISIBLE_DEVICES per worker), {per_run} CPU thread(s) per run")
        return pool, per_run, note
    if str(device or "").startswith("cuda"):
        raise FastneusError("--device cuda, but torch sees no CUDA GPU (give --gpus to name them)", field="--device")
    per_run = threads or min(cores, THREADS_PER_RUN)
    n = workers or max(1, cores // per_run)
    if threads is None:
        per_run = max(1, cores // n)
    pool = [Worker(f"cpu {i}") for i in range(n)]
    note = (f"no GPU: {cores} CPU core(s), {per_run} thread(s) per run -> {n} worker(s)"
            + (" (--workers)" if workers else f" (cores // {threads or THREADS_PER_RUN} threads per run)"))
    return pool, per_run, note


@contextlib.contextmanager
def forward_signals(on_signal: Callable[[int], None]) -> Iterator[None]:
    """Within the block, SIGINT / SIGTERM call ``on_signal(signum)`` instead of stopping the batch
    (main thread only; elsewhere nothing changes)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.signal(s, lambda signum, frame: on_signal(signum)) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def run_local(jobs: list[Job], pool: list[Worker], args_of: Callable[[Job], list[str]], start: Callable[[Job], None],
              changed: Callable[[Job], None], tick: Callable[[], None]) -> bool:
    """Run every job in ``pool``'s workers, each as ``python -m fastneus <args_of(job)>``.

    Args:
        jobs: the jobs to run (state ``new`` or ``resume``), in order.
        pool: the workers.
        args_of: the train arguments of a job.
        start: called before a job's child starts (creates its run folder and log).
        changed: called when a job's state changes (started, ended).
        tick: called every poll (the live table).

    Returns:
        True when a signal stopped the batch (jobs not started stay ``queued``).
    """
    queue = list(jobs)
    for j in queue:
        j.state = "queued"
    running: dict[int, tuple[Job, subprocess.Popen]] = {}
    free = list(range(len(pool)))
    stop = {"signals": 0}

    def on_signal(signum: int) -> None:
        stop["signals"] += 1
        for _, proc in list(running.values()):
            with contextlib.suppress(OSError):
                proc.send_signal(signum)

    with forward_signals(on_signal):
        while queue or running:
            while queue and free and not stop["signals"]:
                job, slot = queue.pop(0), free.pop(0)
                w = pool[slot]
                try:
                    start(job)
                    with open_log(job) as log:
                        proc = subprocess.Popen(python_command(args_of(job)), stdin=subprocess.DEVNULL, stdout=log,
                                                stderr=subprocess.STDOUT, env={**os.environ, **w.env},
                                                start_new_session=True)
                except (FastneusError, OSError) as e:
                    job.state, job.error, job.worker = "failed", str(e), w.label
                    free.append(slot)
                    changed(job)
                    continue
                job.state, job.worker, job.started = "running", w.label, time.monotonic()
                running[slot] = (job, proc)
                if stop["signals"]:  # a signal came while it started
                    with contextlib.suppress(OSError):
                        proc.send_signal(signal.SIGINT)
                changed(job)
            if stop["signals"] and not running:
                break
            time.sleep(POLL_S)
            for slot, (job, proc) in list(running.items()):
                rc = proc.poll()
                if rc is None:
                    read_progress(job)
                    continue
                job.seconds = time.monotonic() - job.started
                conclude(job, rc, bool(stop["signals"]))
                del running[slot]
                free.append(slot)
                free.sort()
                changed(job)
            tick()
    return bool(stop["signals"])
