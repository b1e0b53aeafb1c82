"""A batch on a Ray cluster: each scene is one Ray task running ``python -m fastneus train`` on a
worker, into the same run folder layout on a shared filesystem.

Ray does the scheduling: a task asks for one GPU when the cluster has GPUs, else for the CPU
threads of one run. Ray is imported only here, and only when ``--ray`` is given (the extra
``fastneus[ray]``). Ray moves the task's arguments (lists of strings) and its result (a small
dict) with its own serialisation; fastneus never unpickles a file.
"""
from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Callable

from fastneus.batch.plan import Job, conclude, read_progress
from fastneus.errors import FastneusError

POLL_S = 0.5
LOCK_WAIT_S = 300  # after a cancel: how long to wait for a run to save its checkpoint and unlock its folder


def import_ray():
    """The ``ray`` module, or one line saying how to install it.

    Raises:
        FastneusError: ray is not installed.
    """
    try:
        import ray  # function-level: an optional extra, loaded only for --ray
    except ImportError:
        raise FastneusError('needs Ray, which is not installed: pip install "fastneus[ray]"', field="--ray") from None
    return ray


def train_task(args: list[str], log: str) -> dict:
    """The Ray task: run ``python -m fastneus ARGS`` on this worker, output appended to ``log``.

    Ray sets ``CUDA_VISIBLE_DEVICES`` to the task's GPU; the child inherits it. A cancel
    (``ray.cancel``, a KeyboardInterrupt here) is passed to the child as SIGINT: it saves a
    checkpoint and stops.

    Returns:
        ``{"rc", "seconds", "host", "gpus"}``.
    """
    import signal
    import socket
    import subprocess

    from fastneus.batch.plan import python_command
    from fastneus.io import open_append

    t0 = time.monotonic()
    host, gpus = socket.gethostname(), os.environ.get("CUDA_VISIBLE_DEVICES")
    with open_append(log) as f:
        f.write(f"--- ray task on {host}" + (f", CUDA_VISIBLE_DEVICES={gpus}" if gpus else "") + "\n")
        f.flush()
        proc = subprocess.Popen(python_command(args), stdin=subprocess.DEVNULL, stdout=f, stderr=subprocess.STDOUT,
                                start_new_session=True)
        try:
            rc = proc.wait()
        except KeyboardInterrupt:
            proc.send_signal(signal.SIGINT)
            rc = proc.wait()
    return {"rc": rc, "seconds": time.monotonic() - t0, "host": host, "gpus": gpus}


def connect(address: str, console=None):
    """``ray`` connected to ``address`` (``auto``, ``ray://host:port``, ``host:port``, or ``local``
    to start a cluster on this machine); a session already initialised in this process is used as
    it is. Returns (ray, whether this call started the connection)."""
    ray = import_ray()
    if ray.is_initialized():
        return ray, False
    try:
        if address == "local":
            ray.init(include_dashboard=False, log_to_driver=False)
        else:
            ray.init(address=address, log_to_driver=False)
    except Exception as e:  # noqa: BLE001 - Ray raises ConnectionError, RuntimeError, ValueError ...
        msg = (str(e).strip().splitlines() or [type(e).__name__])[0]
        raise FastneusError(f"cannot connect to the Ray cluster at {address!r}: {msg}", field="--ray") from None
    return ray, True


def task_options(ray, threads: int | None) -> tuple[dict, int, str]:
    """Ray resources of one run, the ``--threads`` it gets, and a line saying why."""
    res = ray.cluster_resources()
    cpus, gpus = int(res.get("CPU", 1)), int(res.get("GPU", 0))
    if gpus:
        per_run = threads or max(1, cpus // gpus)
        return ({"num_gpus": 1, "num_cpus": 1}, per_run,
                f"Ray cluster: {gpus} GPU(s), {cpus} CPU(s): one GPU per run, {per_run} CPU thread(s) each")
    per_run = max(1, min(threads or 4, cpus))
    return ({"num_cpus": per_run}, per_run,
            f"Ray cluster without GPUs: {cpus} CPU(s), {per_run} per run -> up to {max(1, cpus // per_run)} at once")


def _message(e: BaseException) -> str:
    cause = getattr(e, "cause", None)
    lines = str(cause if cause is not None else e).strip().splitlines()
    return lines[-1][:500] if lines else type(e).__name__


def _wait_unlocked(job: Job) -> None:
    """Wait until the run's training process has released its folder (it saves first)."""
    end = time.monotonic() + LOCK_WAIT_S
    while (job.run / ".fastneus.lock").exists() and time.monotonic() < end:
        time.sleep(POLL_S)


def run_ray(ray, jobs: list[Job], options: dict, args_of: Callable[[Job], list[str]], start: Callable[[Job], None],
            changed: Callable[[Job], None], tick: Callable[[], None], stop_requested: Callable[[], bool]) -> bool:
    """Submit every job as a Ray task and collect them as they end.

    Args:
        ray: the connected module (:func:`connect`). options: :func:`task_options`'s resources.
        args_of, start, changed, tick: as in :func:`fastneus.batch.local.run_local`.
        stop_requested: polled; once true, every task still pending is cancelled (a running one
            saves its checkpoint first).

    Returns:
        True when stopped.
    """
    remote = ray.remote(train_task).options(max_retries=0, **options)
    refs = {}
    for job in jobs:
        try:
            start(job)
        except (FastneusError, OSError) as e:
            job.state, job.error = "failed", str(e)
            changed(job)
            continue
        job.state, job.worker = "queued", "ray"
        refs[remote.remote(args_of(job), str(job.log))] = job
        changed(job)
    pending, stopping = list(refs), False
    while pending:
        if stop_requested() and not stopping:
            stopping = True
            for ref in pending:
                ray.cancel(ref)
        ready, pending = ray.wait(pending, num_returns=len(pending), timeout=POLL_S)
        for ref in ready:
            job = refs[ref]
            try:
                res = ray.get(ref)
            except Exception as e:  # noqa: BLE001 - a cancelled or crashed task, a lost node
                res = None
                if not stopping:
                    job.state, job.error = "failed", f"ray: {_message(e)}"
                elif job.state == "queued" and _log_size(job) <= job.log_offset:
                    continue  # cancelled before it started: stays queued (not started)
                else:
                    _wait_unlocked(job)
            if res is not None:
                job.seconds = res["seconds"]
                job.worker = f"ray {res['host']}" + (f" gpu {res['gpus']}" if res.get("gpus") else "")
            elif job.started is not None:
                job.seconds = time.monotonic() - job.started
            if job.state != "failed":
                conclude(job, None if res is None else res["rc"], stopping)
            changed(job)
        for ref in pending:
            job = refs[ref]
            if job.state == "queued" and _log_size(job) > job.log_offset:
                job.state, job.started = "running", time.monotonic()
                changed(job)
            elif job.state == "running":
                read_progress(job)
        tick()
    return stopping


def _log_size(job: Job) -> int:
    try:
        return os.stat(Path(job.log)).st_size
    except OSError:
        return 0
