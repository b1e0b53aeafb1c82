"""Ground-truth files of a frame (synthetic scenes): depth, normals, the pattern-free image.

scene.json names them per frame under ``gt`` with the keys :data:`GT_KEYS`."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from fastneus.data.images import read_rgb
from fastneus.data.validate import field_error

GT_KEYS = ("depth", "normal", "clean")


def read_npy(path: Path, file, fld: str) -> np.ndarray:
    """A numeric ``.npy`` as float32; never unpickles (ground truth files are untrusted too)."""
    try:
        return np.asarray(np.load(path, allow_pickle=False), dtype=np.float32)
    except Exception as e:  # noqa: BLE001 - corrupt, pickled or non-numeric: one line
        raise field_error(f"cannot read {path}: {e}".splitlines()[0], file, fld) from None


def read_depth(path: Path, file, fld: str) -> np.ndarray:
    """float32 [H, W] z-depth (world units, 0 = background) from a ``.npy``."""
    return read_npy(path, file, fld)


def read_normal(path: Path, file, fld: str) -> np.ndarray:
    """float32 [H, W, 3] world normals (zero = background) from a ``.npy`` or an RGB image
    (``rgb / 255 * 2 - 1``, black = background)."""
    if str(path).endswith(".npy"):
        return read_npy(path, file, fld)
    im = read_rgb(path, file, fld).astype(np.float32)
    n = im / 255.0 * 2.0 - 1.0
    n[np.all(im == 0, axis=-1)] = 0.0  # black = background
    return n


def read_clean(path: Path, file, fld: str) -> np.ndarray:
    """uint8 [H, W, 3] RGB pattern-free image."""
    return read_rgb(path, file, fld)
