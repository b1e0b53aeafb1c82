"""Checkpoints that hold data only: tensors, numbers, strings and plain containers.

A run folder may come from someone else (``--resume``, ``mesh``, ``render``, ``eval``), and
``torch.load(weights_only=False)`` unpickles arbitrary objects, i.e. can run code. So
checkpoints are written from plain data only (:func:`plain` refuses anything else at save
time, so a checkpoint fastneus writes always loads) and read with ``weights_only=True``,
torch's restricted unpickler. Every failure is one line naming the file and entry.
"""
from __future__ import annotations

import errno
import math
import os
import pickle
import re
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import torch

from fastneus.errors import FastneusError
from fastneus.io import atomic_write

CKPT_NAME = "checkpoint.pt"
# entries every checkpoint has (Trainer.state); checked before use so a foreign or truncated
# file is reported by name instead of failing deep inside load_state
REQUIRED = ("step", "config", "field", "grid", "log_ir", "log_ib")


def plain(obj: Any, where: str = "state") -> Any:
    """``obj`` as tensors, Python numbers/strings/None and dict/list/tuple only.

    numpy arrays become tensors and numpy scalars Python numbers; anything else raises.

    Raises:
        TypeError: naming the entry (a programming error: the trainer saved a new kind of object).
    """
    if obj is None or isinstance(obj, (bool, int, float, str, torch.Tensor)):
        return obj
    if isinstance(obj, np.ndarray) and not obj.dtype.hasobject:
        return torch.from_numpy(np.ascontiguousarray(obj))
    if isinstance(obj, np.generic) and isinstance(obj.item(), (bool, int, float)):
        return obj.item()
    if isinstance(obj, dict):
        out = {}
        for k, v in obj.items():
            if isinstance(k, bool) or not isinstance(k, (str, int)):
                raise TypeError(f"checkpoint entry {where} has a key of type {type(k).__name__}")
            out[k] = plain(v, f"{where}.{k}")
        return out
    if isinstance(obj, (list, tuple)):
        items = [plain(v, f"{where}[{i}]") for i, v in enumerate(obj)]
        return tuple(items) if isinstance(obj, tuple) else items  # namedtuples become plain tuples
    raise TypeError(f"checkpoint entry {where} is a {type(obj).__name__}; only tensors, numbers, strings "
                    f"and plain containers are saved")


def save_checkpoint(state: dict, path: Path) -> Path:
    """Write ``plain(state)`` to ``path`` atomically (temp file + rename): a crash keeps the previous one."""
    data = plain(state)

    def write(tmp: str) -> None:
        # through a Python file object: a full disk surfaces as OSError(ENOSPC) naming the file, not
        # as torch's "[enforce fail at inline_container.cc] ... unexpected pos" RuntimeError
        try:
            with open(tmp, "wb") as fh:
                torch.save(data, fh)
                fh.flush()
                os.fsync(fh.fileno())
        except OSError as e:
            raise OSError(e.errno, e.strerror or str(e), str(path)) from None
        except RuntimeError as e:  # torch's writer failing some other way
            if "enforce fail" in str(e) or "write" in str(e):
                full = shutil.disk_usage(os.path.dirname(tmp) or ".").free < (64 << 20)
                raise OSError(errno.ENOSPC if full else errno.EIO, os.strerror(errno.ENOSPC) if full else
                              f"cannot write the checkpoint ({str(e).splitlines()[0][:120]})", str(path)) from None
            raise

    atomic_write(path, write)
    return Path(path)


def load_checkpoint(run: Path, map_location="cpu") -> dict:
    """Read a run's checkpoint with torch's restricted unpickler; one clear error if it is
    missing, unreadable, holds anything but data, or lacks an entry.
    """
    path = Path(run) / CKPT_NAME
    if not path.is_file():
        raise FastneusError("no checkpoint in this run folder (train first)", file=str(path))
    try:
        st = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as e:
        # weights_only refuses globals other than torch's tensor rebuilders; say which, in one line
        what = re.search(r"GLOBAL (\S+)", str(e))
        raise FastneusError("refused to load: it holds Python objects other than tensors, numbers and "
                            "strings, which could run code (fastneus never unpickles them)"
                            + (f"; it references {what.group(1)}" if what else ""), file=str(path)) from None
    except Exception as e:  # noqa: BLE001 - truncated or foreign file: one line, not a trace
        first = (str(e).strip().splitlines() or [""])[0].split(". ")[0]
        raise FastneusError(f"unreadable checkpoint (truncated, or not a torch file): {type(e).__name__}: {first}",
                            file=str(path)) from None
    if not isinstance(st, dict):
        raise FastneusError(f"not a fastneus checkpoint (holds a {type(st).__name__})", file=str(path))
    for key in REQUIRED:
        if key not in st:
            raise FastneusError("missing entry (not a fastneus checkpoint, or a truncated one)",
                                file=str(path), field=key)
    if isinstance(st["step"], bool) or not isinstance(st["step"], int) or st["step"] < 0:
        raise FastneusError(f"expected a step count >= 0, got {st['step']!r}", file=str(path), field="step")
    if not isinstance(st["config"], dict):
        raise FastneusError("expected a mapping of config keys", file=str(path), field="config")
    bad = _first_non_finite(st)
    if bad is not None:  # NaN weights would mesh to nothing and "succeed"
        raise FastneusError("holds non-finite values (NaN/inf): the training that wrote it diverged, or the file "
                            "was altered; resume from an earlier copy or train again", file=str(path), field=bad)
    return st


def _first_non_finite(obj: Any, where: str = "") -> str | None:
    """Dotted name of the first floating-point tensor or number holding NaN/inf in a checkpoint entry."""
    if isinstance(obj, torch.Tensor):
        return where if obj.is_floating_point() and not bool(torch.isfinite(obj).all()) else None
    if isinstance(obj, float):
        return None if math.isfinite(obj) else where
    items = obj.items() if isinstance(obj, dict) else enumerate(obj) if isinstance(obj, (list, tuple)) else ()
    for k, v in items:
        if where == "" and k == "config":  # a config's floats are checked, by key, when it is applied
            continue
        hit = _first_non_finite(v, f"{where}.{k}" if where else str(k))
        if hit is not None:
            return hit
    return None


def restore(trainer, st: dict, path: Path, with_optimizer: bool = True) -> None:
    """``trainer.load_state(st)``, reporting a checkpoint that does not fit the trainer's
    model (other config, other scene) as one line instead of a shape-mismatch trace."""
    try:
        trainer.load_state(st, with_optimizer=with_optimizer)
    except (KeyError, RuntimeError, ValueError, TypeError, AttributeError, IndexError) as e:
        lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()] or [type(e).__name__]
        # torch lists the mismatches after a header line: show the first one
        msg = next((ln for ln in lines if "mismatch" in ln or "key" in ln.lower()), lines[0])
        raise FastneusError(f"does not fit this run's model/config ({type(e).__name__}: {msg[:200]})",
                            file=str(path)) from None
