"""Atomic file writes (temp file in the same folder, then rename) and output folders.

A crash mid-write never leaves a truncated file in place of an earlier good one, and a
command that finds bad input half-way through never leaves a half-written output folder
(:func:`staged_dir`).
"""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Callable, Iterator

from fastneus.errors import FastneusError


def atomic_write(path: str | os.PathLike, write: Callable[[str], None], suffix: str = "") -> None:
    """Call ``write(tmp_path)`` then rename the temp file onto ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix or path.suffix, dir=path.parent)
    os.close(fd)
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    def w(tmp: str) -> None:
        with open(tmp, "w") as f:
            f.write(text)
    atomic_write(path, w)


def atomic_write_json(path: str | os.PathLike, obj: Any) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2) + "\n")


def atomic_write_image(path: str | os.PathLike, rgb) -> None:
    """Write an RGB uint8 image [H, W, 3] (or gray [H, W]) as PNG, atomically."""
    import cv2
    import numpy as np

    img = np.asarray(rgb)
    if img.ndim == 3:
        img = img[..., ::-1]  # RGB -> BGR for OpenCV

    def w(tmp: str) -> None:
        if not cv2.imwrite(tmp, np.ascontiguousarray(img)):
            raise OSError(f"cannot write image {path}")
    atomic_write(path, w, suffix=Path(path).suffix or ".png")


def check_out_dir(path: str | os.PathLike, field: str = "--out") -> Path:
    """Refuse an output folder that is an existing file, or lies under one (one-line error)."""
    p = Path(path)
    for q in (p, *p.parents):
        if q.exists():
            if not q.is_dir():
                raise FastneusError("exists and is not a folder" if q == p else f"{q} is a file, not a folder",
                                    file=p, field=field)
            break
    return p


def make_out_dir(path: str | os.PathLike, field: str = "--out") -> Path:
    """:func:`check_out_dir`, then create the folder (and parents)."""
    p = check_out_dir(path, field)
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise FastneusError(f"cannot create folder: {e.strerror}", file=p, field=field) from None
    return p


@contextlib.contextmanager
def staged_dir(out: str | os.PathLike, replace: tuple[str, ...] = (), field: str = "--out") -> Iterator[Path]:
    """Build an output folder's content in a hidden sibling folder, then move it into ``out``.

    If the body raises (bad input found half-way), ``out`` is left exactly as it was. On
    success each top-level entry replaces the one of the same name in ``out``; folders, and
    the folders named in ``replace`` even when the new output lacks them, are replaced whole
    so no stale file of an earlier output stays behind. Other files in ``out`` are kept.

    Yields:
        The staging folder to write into.
    """
    out = check_out_dir(out, field)
    make_out_dir(out.parent, field)
    stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.staging-", dir=out.parent))
    try:
        yield stage
        out.mkdir(exist_ok=True)
        names = sorted(e.name for e in stage.iterdir())
        trash = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
        try:
            for name in set(replace) | set(names):
                old = out / name
                if old.is_dir() and not old.is_symlink():
                    os.replace(old, trash / name)
            # folders first: the index file (scene.json, npz) arrives last
            for name in sorted(names, key=lambda n: (stage / n).is_file()):
                os.replace(stage / name, out / name)
        finally:
            shutil.rmtree(trash, ignore_errors=True)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
