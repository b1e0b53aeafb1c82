"""Run folders: what a training run writes, and when starting one there is allowed.

A folder that holds a run (a checkpoint or metrics) is never overwritten silently:
training into it needs ``--resume`` (continue) or ``--overwrite`` (start again). The check
runs before anything is written. fastneus marks a folder it trains into (:data:`RUN_MARK`)
and only ever replaces its own run files there: a same-named file in a folder that is not
a fastneus run is refused, never replaced. One process at a time writes a run folder
(:func:`run_lock`). ``--overwrite`` moves the previous run aside (:class:`PreviousRun`) and
deletes it only once the new run has saved its first checkpoint; it comes back if the new
run fails before that, also after a kill (:func:`recover`).
"""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import sys
from pathlib import Path
from typing import Iterator

from fastneus.errors import FastneusError
from fastneus.io import atomic_write_json, check_no_link, check_out_dir, make_out_dir
from fastneus.train.checkpoint import CKPT_NAME

# everything a run writes into its folder (pipeline.train_scene / finish_run, Trainer.fit / save)
RUN_FILES = (CKPT_NAME, "config.yaml", "run.json", "log.jsonl", "metrics.json", "illumination.json",
             "report.html", "mesh.ply", "rig.json")
RUN_DIRS = ("renders", "validation", "tensorboard")  # validation/, tensorboard/: fastneus.train.progress
RUN_MARK = ".fastneus-run.json"      # "fastneus wrote the run files here": --overwrite may replace them
LOCK_NAME = ".fastneus.lock"         # flock held by the process writing the run (holds its pid)
ASIDE = ".fastneus-previous"         # the previous run during --overwrite, until the first checkpoint

def _warn(msg: str) -> None:
    print(f"warning: {msg}", file=sys.stderr)


def _is_ours(out: Path) -> bool:
    """``out`` was written by fastneus: it has the run mark, or is a run of a version before the mark
    (run.json as train writes it, next to a checkpoint or metrics)."""
    mark = out / RUN_MARK
    try:
        if not mark.is_symlink() and mark.is_file() and json.loads(mark.read_text()).get("written_by") == "fastneus":
            return True
    except (OSError, ValueError, AttributeError, RecursionError):
        pass
    try:
        meta = out / "run.json"
        d = json.loads(meta.read_text()) if meta.is_file() and not meta.is_symlink() else None
    except (OSError, ValueError, RecursionError):
        d = None
    return (isinstance(d, dict) and {"scene", "device", "preset"} <= set(d)
            and any((out / n).is_file() for n in (CKPT_NAME, "metrics.json")))


def mark_run(out: Path) -> None:
    """Record that fastneus owns the run files in ``out`` (written before any of them)."""
    atomic_write_json(Path(out) / RUN_MARK, {"written_by": "fastneus", "run_files": list(RUN_FILES + RUN_DIRS),
                                            "note": "a fastneus run folder: --overwrite replaces these files only"})


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
    if resume or not out.is_dir():
        return
    if not _is_ours(out):  # a user's folder: never replace their mesh.ply or renders/, even with --overwrite
        for name in RUN_FILES + RUN_DIRS:
            if os.path.lexists(out / name):
                raise FastneusError(f"holds {name!r}, which fastneus did not write (the folder is not a fastneus "
                                    "run), so a run is not written over it; move it away or choose another --out",
                                    file=out, field="--out")
    if overwrite:
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


@contextlib.contextmanager
def run_lock(out: Path) -> Iterator[Path]:
    """Hold an exclusive lock on run folder ``out`` (created if missing) while the body runs.

    ``fcntl.flock`` on :data:`LOCK_NAME`: the kernel releases it when the holder exits, however
    it ends, so a lock file left by a killed process is simply taken over. The file is removed
    on release (a waiter that locked the removed file notices and tries again), and a folder
    this call created is removed again if the body fails before writing anything into it.

    Raises:
        FastneusError: another process holds the lock (one line, with its pid).
    """
    import fcntl

    out = check_out_dir(out)
    created = not out.exists()
    make_out_dir(out)
    path = out / LOCK_NAME
    check_no_link(path)
    for _ in range(100):
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
        except OSError as e:
            raise FastneusError(f"cannot open the run folder's lock file: {e.strerror}", file=path) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            pid = os.read(fd, 32).decode("ascii", "replace").strip()
            os.close(fd)
            raise FastneusError(f"another fastneus process{f' (pid {pid})' if pid.isdigit() else ''} is writing "
                                "this run folder; wait for it to finish or choose another --out", file=out,
                                field="--out") from None
        try:
            same = os.stat(path, follow_symlinks=False).st_ino == os.fstat(fd).st_ino
        except OSError:
            same = False
        if same:
            break
        os.close(fd)  # locked a lock file its holder removed on release: take the current one
    else:
        raise FastneusError("cannot take the run folder's lock (it keeps being replaced)", file=path)
    try:
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        yield out
    finally:
        with contextlib.suppress(OSError):
            path.unlink()
        os.close(fd)  # releases the lock
        if created:
            with contextlib.suppress(OSError):
                out.rmdir()  # only when empty: the body failed before writing anything


def _remove_entry(p: Path) -> None:
    """Remove a run file or folder; a symbolic link is removed itself, never followed."""
    if p.is_symlink() or p.is_file():
        p.unlink()
    elif p.is_dir():
        shutil.rmtree(p)


class PreviousRun:
    """The previous run's files, kept in ``RUN/.fastneus-previous`` while ``--overwrite`` starts again."""

    def __init__(self, out: Path):
        self.out, self.aside = Path(out), Path(out) / ASIDE

    @classmethod
    def set_aside(cls, out: Path) -> "PreviousRun | None":
        """Move the run files of ``out`` aside (None when there are none)."""
        prev = cls(out)
        names = [n for n in RUN_FILES + RUN_DIRS if os.path.lexists(prev.out / n)]
        if not names:
            return None
        check_no_link(prev.aside)
        if os.path.lexists(prev.aside):
            _remove_entry(prev.aside)
        prev.aside.mkdir()
        for n in names:
            os.replace(prev.out / n, prev.aside / n)  # a rename: never follows a link
        return prev

    def drop(self) -> None:
        """The new run has a checkpoint: the previous one goes."""
        if self.aside.is_dir() and not self.aside.is_symlink():
            shutil.rmtree(self.aside)

    def restore(self) -> None:
        """The new run failed before its first checkpoint: its files go, the previous run's come back."""
        if not self.aside.is_dir() or self.aside.is_symlink():
            return
        for n in RUN_FILES + RUN_DIRS:
            if os.path.lexists(self.out / n):
                _remove_entry(self.out / n)
        for p in self.aside.iterdir():
            os.replace(p, self.out / p.name)
        self.aside.rmdir()


def recover(out: Path) -> None:
    """Finish what a killed ``--overwrite`` left: drop the previous run kept aside if the new run
    had saved a checkpoint, else bring it back (with a warning). Call under :func:`run_lock`."""
    prev = PreviousRun(out)
    if not prev.aside.is_dir() or prev.aside.is_symlink():
        return
    if (prev.out / CKPT_NAME).is_file():
        prev.drop()
    else:
        prev.restore()
        _warn(f"{out}: restored the previous run, which an interrupted --overwrite had moved aside into {ASIDE}")


def remove_stale_temps(out: Path) -> None:
    """Delete the temp files of fastneus's own atomic writes (``.<name>.XXXX``) that a kill left behind
    in ``out``, ``out/renders`` and ``out/validation``. Call under :func:`run_lock` (no writer is active)."""
    prefixes = tuple(f".{n}." for n in RUN_FILES + (RUN_MARK,))
    folders = [(Path(out), lambda n: n.startswith(prefixes))]
    for name in ("renders", "validation"):
        sub = Path(out) / name
        if sub.is_dir() and not sub.is_symlink():
            folders.append((sub, lambda n: n.startswith(".") and ".png." in n))
    for folder, ours in folders:
        for e in os.scandir(folder):
            if ours(e.name) and e.is_file(follow_symlinks=False):
                os.unlink(e.path)


def repair_log(out: Path) -> None:
    """Drop a torn last line of ``out/log.jsonl`` (kill -9 or a full disk mid-append), with a warning,
    so that appending to it continues with whole lines."""
    path = Path(out) / "log.jsonl"
    if path.is_symlink() or not path.is_file():
        return
    data = path.read_bytes()
    cut = data.rfind(b"\n", 0, len(data) - 1) + 1 if data else 0
    last = data[cut:]
    try:
        torn = bool(last) and (not last.endswith(b"\n") or not isinstance(json.loads(last), dict))
    except (ValueError, RecursionError):
        torn = True
    if torn:
        fd = os.open(path, os.O_WRONLY | os.O_NOFOLLOW)
        try:
            os.ftruncate(fd, cut)
        finally:
            os.close(fd)
        _warn(f"{path}: dropped a torn last line (a write cut short, e.g. by kill -9 or a full disk)")


def resume_config(out: Path, overrides: list[str]):
    """The config to continue the run in ``out`` with: its saved ``config.yaml`` (else the
    checkpoint's), with ``key=value`` ``overrides`` on top (more steps, a longer time budget,
    another learning rate).

    Raises:
        FastneusError: no saved config, or an override of a key that shapes the trained model
            (:func:`fastneus.config.model_keys`), named.
    """
    import yaml

    from fastneus.config import KEYS, config_from_dict, load_config, model_keys

    out = Path(out)
    path = out / "config.yaml"
    if not (out / CKPT_NAME).is_file():
        raise FastneusError("--resume given but the run folder has no checkpoint", file=out / CKPT_NAME)
    if path.is_file():
        try:
            data = yaml.safe_load(path.read_text())
        except (OSError, UnicodeDecodeError, RecursionError, yaml.YAMLError) as e:
            raise FastneusError(f"cannot read the run's config: {e}".splitlines()[0], file=path) from None
        if not isinstance(data, dict):
            raise FastneusError("a run's config.yaml must hold a mapping of key: value", file=path)
        saved = config_from_dict(data, str(path))
    else:
        from fastneus.train.checkpoint import load_checkpoint

        saved = config_from_dict(load_checkpoint(out)["config"], str(out / CKPT_NAME))
    cfg = load_config(None, overrides, base=saved.to_dict())
    new, old = cfg.flat(), saved.flat()
    for k in sorted(model_keys()):
        if new[k] != old[k]:
            raise FastneusError(f"cannot change {k} of a trained model on --resume (the run has {old[k]!r}, got "
                                f"{new[k]!r}); start a new run (--overwrite or another --out) to change it",
                                field=f"{KEYS[k][0]}.{k}")
    return cfg
