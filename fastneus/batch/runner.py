"""A whole batch: plan the runs, run them locally or on Ray, show progress, write summary.json."""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path

from fastneus.batch.board import Board, write_summary
from fastneus.batch.plan import FINAL_STATES, Job, expand_scenes, plan, prepare, train_args
from fastneus.io import check_out_dir, confined, make_out_dir

# exit statuses: every scene finished (or was already), some failed, the batch was stopped
OK, SOME_FAILED, STOPPED = 0, 1, 130


@dataclass
class BatchOptions:
    """What ``fastneus batch`` was asked: the train options for every run and how to schedule them.

    Attributes:
        config, device, threads, overrides: as ``fastneus train`` takes them (``threads``: per run).
        gpus: ``--gpus`` (``0,1``) or None (detect). workers: ``--workers`` or None.
        ray: ``--ray`` address (``auto``, ``local``, ``host:port``) or None for local scheduling.
        command: the command line, recorded in summary.json.
    """

    config: str | None = None
    device: str | None = None
    threads: int | None = None
    overrides: list[str] = field(default_factory=list)
    gpus: str | None = None
    workers: int | None = None
    ray: str | None = None
    command: str = ""


def _config_arg(config: str | None) -> str | None:
    """A config file as an absolute path (a Ray worker runs elsewhere); a preset name as it is."""
    if config and (config.endswith((".yaml", ".yml")) or os.sep in config) and Path(config).is_file():
        return os.path.abspath(config)
    return config


def check_options(opts: BatchOptions) -> None:
    """Fail before any run starts on a bad preset, config file or override (one line, naming it)."""
    from fastneus.config import load_config

    extra = [f"threads={opts.threads}"] if opts.threads else []
    load_config(opts.config or "fewview", list(opts.overrides) + extra)


def run_batch(items: list[str], out: str | os.PathLike, opts: BatchOptions, console) -> int:
    """Train every scene of ``items`` into its own run folder under ``out``.

    Finished runs are skipped, interrupted ones resumed; a scene that fails is recorded with its
    one-line error and the others go on. ``out/summary.json`` is rewritten as each run ends.

    Returns:
        0 when every scene finished, 1 when some failed, 130 when a signal stopped the batch.

    Raises:
        FastneusError: bad options, no scene, a glob that matches nothing, an unusable ``out``.
    """
    from fastneus.train.runfolder import run_lock

    scenes = expand_scenes(items)
    check_options(opts)
    if opts.ray:
        from fastneus.batch.cluster import import_ray

        import_ray()  # without the extra: one line, before anything is written
    out = Path(os.path.abspath(check_out_dir(out)))
    make_out_dir(out)
    config = _config_arg(opts.config)
    with confined(out), run_lock(out):  # one batch at a time in a folder
        jobs = plan(scenes, out)
        todo = [j for j in jobs if j.state in ("new", "resume")]
        n_resume = sum(j.state == "resume" for j in todo)
        console.print(f"[bold]fastneus batch[/bold]: {len(jobs)} scene(s) -> {out}: {len(todo) - n_resume} to train, "
                      f"{n_resume} to resume, {len(jobs) - len(todo)} finished before (skipped)")
        meta = {"out": str(out), "command": opts.command, "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                "scheduler": "ray" if opts.ray else "local", "train_options": {
                    "config": config, "device": opts.device, "overrides": list(opts.overrides)}}
        per_run = opts.threads
        ray = None
        if opts.ray:
            from fastneus.batch.cluster import connect, task_options

            ray, started_ray = connect(opts.ray, console)
            options, per_run, note = task_options(ray, opts.threads)
            meta.update(ray_address=opts.ray, ray_resources=options)
        else:
            from fastneus.batch.local import plan_workers

            pool, per_run, note = plan_workers(opts.gpus, opts.workers, opts.device, opts.threads)
            meta["workers"] = [w.label for w in pool]
        meta["threads_per_run"] = per_run
        meta["decision"] = note
        console.print(note, markup=False, highlight=False)

        def args_of(job: Job) -> list[str]:
            return train_args(job, config, opts.device, per_run, opts.overrides)

        board = Board(jobs, console)

        def changed(job: Job) -> None:
            board.changed(job)
            if job.state in FINAL_STATES:
                write_summary(out, jobs, meta)

        write_summary(out, jobs, meta)
        try:
            if ray is not None:
                stopped = _run_on_ray(ray, todo, options, args_of, out, changed, board)
                if started_ray:
                    ray.shutdown()
            else:
                from fastneus.batch.local import run_local

                stopped = run_local(todo, pool, args_of, lambda j: prepare(j, out), changed, board.tick)
        finally:
            board.close()
            meta["finished"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
            path = write_summary(out, jobs, meta)
        console.print(f"summary: {path}", markup=False, highlight=False)
    if stopped:
        return STOPPED
    return SOME_FAILED if any(j.state in ("failed", "interrupted") for j in jobs) else OK


def _run_on_ray(ray, todo, options, args_of, out, changed, board) -> bool:
    from fastneus.batch.cluster import run_ray
    from fastneus.batch.local import forward_signals

    signals = {"n": 0}

    def on_signal(signum: int) -> None:
        signals["n"] += 1

    with forward_signals(on_signal):
        return run_ray(ray, todo, options, args_of, lambda j: prepare(j, out), changed, board.tick,
                       lambda: signals["n"] > 0)
