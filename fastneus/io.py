"""Atomic file writes: write to a temp file in the same folder, then rename.

A crash mid-write never leaves a truncated file in place of an earlier good one.
"""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any, Callable


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
