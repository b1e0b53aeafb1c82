"""Verb ``batch``: train many scenes, one run folder each, on local GPUs / CPU workers or on Ray."""
from __future__ import annotations

import shlex
import sys

from fastneus.cli import threads_override
from fastneus.cli.train import add_config_args


def _run(args) -> int:
    from rich.console import Console

    from fastneus.batch import BatchOptions, run_batch
    from fastneus.batch.plan import split_overrides

    scenes, overrides = split_overrides(list(args.scenes))
    threads_override(args)  # --threads < 1: one line, before anything runs
    opts = BatchOptions(config=args.config, device=args.device, threads=args.threads,
                        overrides=overrides + list(args.overrides or []), gpus=args.gpus, workers=args.workers,
                        ray=args.ray, command=shlex.join(["fastneus", *sys.argv[1:]]))
    return run_batch(scenes, args.out, opts, Console())


def register(sub) -> None:
    p = sub.add_parser(
        "batch", help="train many scenes: one run folder each, local GPUs / CPU workers or a Ray cluster",
        description="Train every scene into OUT/<scene name> with the train verb's defaults, presets and "
                    "overrides; one worker per GPU (or CPU workers), or Ray tasks with --ray. Re-running the "
                    "same command skips finished runs and resumes interrupted ones; a failing scene is "
                    "recorded with its error and the others go on. OUT/summary.json lists every scene.")
    p.add_argument("scenes", nargs="+", metavar="SCENE",
                   help="scene folders, globs ('scans/*') or text files listing scene paths (one a line, "
                        "# comments, relative to the list's folder); key=value overrides may follow")
    p.add_argument("--out", required=True, help="batch folder: one run folder per scene, and summary.json")
    add_config_args(p)
    p.add_argument("--gpus", metavar="IDS", help="GPUs to use, e.g. 0,1 (default: every GPU torch sees); one "
                                                 "worker per GPU, CUDA_VISIBLE_DEVICES set per worker")
    p.add_argument("--workers", type=int, metavar="N",
                   help="runs at once (default: one per GPU; without GPUs cores // threads per run)")
    p.add_argument("--ray", metavar="ADDRESS", help="run each scene as a Ray task on the cluster at ADDRESS "
                                                    "('auto', 'host:port', or 'local' to start one here); "
                                                    'needs pip install "fastneus[ray]"')
    p.set_defaults(func=_run, overrides=[])
