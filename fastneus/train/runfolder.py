"""Run folders: what a training run writes, and when starting one there is allowed.

A folder that holds a run (a checkpoint or metrics) is never overwritten silently:
training into it needs ``--resume`` (continue) or ``--overwrite`` (start again). The check
runs before anything is written; the previous run's files are removed only once the new
run's inputs have been validated, so bad input never costs an earlier result.
"""
from __future__ import annotations

import shutil
from pathlib import Path

from fastneus.errors import FastneusError
from fastneus.io import check_out_dir
from fastneus.train.checkpoint import CKPT_NAME

# everything a run writes into its folder (pipeline.train_scene / finish_run, Trainer.fit)
RUN_FILES = (CKPT_NAME, "config.yaml", "run.json", "log.jsonl", "metrics.json", "illumination.json",
             "report.html", "mesh.ply")
RUN_DIRS = ("renders",)


def check_run_folder(out: Path, resume: bool = False, overwrite: bool = False) -> None:
    """Refuse to start a run in ``out`` when that would silently replace another one.

    Args:
        out: the run folder (may not exist yet).
        resume: ``--resume`` was given (continue the run there).
        overwrite: ``--overwrite`` was given (replace whatever run is there).

    Raises:
        FastneusError: one line naming the folder and what to pass instead.
    """
    out = check_out_dir(out)
    if resume and overwrite:
        raise FastneusError("--resume continues the run in the folder, --overwrite replaces it; give one",
                            field="--overwrite")
    if resume or overwrite or not out.is_dir():
        return
    if (out / "metrics.json").is_file():
        raise FastneusError("holds a finished run (metrics.json); pass --overwrite to replace it, --resume to "
                            "train it further, or choose another --out", file=out, field="--out")
    if (out / CKPT_NAME).is_file():
        raise FastneusError(f"holds an unfinished run ({CKPT_NAME}); pass --resume to continue it, --overwrite "
                            "to start again, or choose another --out", file=out, field="--out")
    # hidden files: a crashed atomic write's temp file, OS clutter
    others = sorted(p.name for p in out.iterdir() if p.name not in RUN_FILES + RUN_DIRS and p.name[0] != ".")
    if others:
        raise FastneusError(f"folder is not empty and is not a fastneus run (holds {others[0]!r}); choose "
                            "another --out, or pass --overwrite to write the run into it anyway",
                            file=out, field="--out")


def clear_run_folder(out: Path) -> None:
    """Remove a previous run's files from ``out`` (only the names a run writes, nothing else)."""
    out = Path(out)
    for name in RUN_FILES:
        p = out / name
        if p.is_file() or p.is_symlink():
            p.unlink()
    for name in RUN_DIRS:
        p = out / name
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
