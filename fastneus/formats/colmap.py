"""A small reader for COLMAP text models (``cameras.txt``, ``images.txt``, ``points3D.txt``).

COLMAP stores, per image, ``qvec`` (w, x, y, z) and ``tvec`` of the world->camera
transform (X_c = R(q) X_w + t), OpenCV axes, in the reconstruction's arbitrary units.
Its pixel convention puts the centre of pixel (u, v) at (u + 0.5, v + 0.5), like fastneus.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fastneus.errors import FastneusError


@dataclass
class ColmapCamera:
    id: int
    model: str
    width: int
    height: int
    params: np.ndarray  # [k] model parameters


@dataclass
class ColmapImage:
    id: int
    name: str
    camera_id: int
    world_to_cam: np.ndarray  # [4, 4]

    @property
    def cam_to_world(self) -> np.ndarray:
        from fastneus.geometry.cameras import rigid_inverse

        return rigid_inverse(self.world_to_cam)


def _lines(path: Path) -> list[str]:
    if not path.is_file():
        raise FastneusError("file not found (expected a COLMAP text model)", file=path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise FastneusError(f"cannot read as text ({type(e).__name__}); expected a COLMAP text model "
                            "(export with colmap model_converter --output_type TXT)", file=path) from None
    return [ln.rstrip("\n") for ln in text.splitlines() if not ln.startswith("#")]


def qvec_to_rotation(q) -> np.ndarray:
    """[3, 3] rotation of a COLMAP quaternion (w, x, y, z); normalised first."""
    from scipy.spatial.transform import Rotation

    w, x, y, z = (float(v) for v in q)
    return Rotation.from_quat([x, y, z, w]).as_matrix()  # scipy is scalar-last


def read_cameras_txt(path: str | os.PathLike) -> dict[int, ColmapCamera]:
    """``CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]`` per line."""
    path = Path(path)
    out = {}
    for n, ln in enumerate(_lines(path)):
        if not ln.strip():
            continue
        t = ln.split()
        try:
            out[int(t[0])] = ColmapCamera(int(t[0]), t[1], int(t[2]), int(t[3]), np.array(t[4:], dtype=np.float64))
        except (IndexError, ValueError):
            raise FastneusError(f"cannot parse camera line {ln!r}", file=path) from None
    return out


def read_images_txt(path: str | os.PathLike) -> dict[str, ColmapImage]:
    """Image name -> pose. Two lines per image; the second (2D points) may be empty."""
    path = Path(path)
    lines = _lines(path)
    out: dict[str, ColmapImage] = {}
    i = 0
    while i < len(lines):
        ln = lines[i].strip()
        if not ln:
            i += 1
            continue
        t = ln.split()
        try:
            q = np.array(t[1:5], dtype=np.float64)
            tv = np.array(t[5:8], dtype=np.float64)
            iid, cid, name = int(t[0]), int(t[8]), " ".join(t[9:])
        except (IndexError, ValueError):
            raise FastneusError(f"cannot parse image line {ln!r}", file=path) from None
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(tv))) or not np.any(q) or not name:
            raise FastneusError(f"bad pose on image line {ln!r}"[:200], file=path, field=name or str(iid))
        q = q / np.abs(q).max()  # scaled first: |q| of 1e200 components overflows to inf (a NaN rotation)
        if name in out:
            raise FastneusError(f"duplicate image {name!r} (image ids {out[name].id} and {iid})", file=path,
                                field=name)
        T = np.eye(4)
        T[:3, :3] = qvec_to_rotation(q)
        T[:3, 3] = tv
        out[name] = ColmapImage(iid, name, cid, T)
        i += 2  # skip the POINTS2D line
    if not out:
        raise FastneusError("no images in the model", file=path)
    return out


def read_points3d_txt(path: str | os.PathLike) -> np.ndarray | None:
    """[N, 3] point positions, or None when the file is absent."""
    path = Path(path)
    if not path.is_file():
        return None
    pts = []
    for ln in _lines(path):
        t = ln.split()
        if not t:
            continue
        try:
            pts.append([float(v) for v in t[1:4]])
        except ValueError:
            t = []
        if len(t) < 4 or not np.all(np.isfinite(pts[-1])):
            raise FastneusError(f"cannot parse point line {ln[:80]!r}", file=path)
    return np.array(pts, dtype=np.float64).reshape(-1, 3)


def read_colmap_model(folder: str | os.PathLike):
    """(cameras by id, images by name, points [N, 3] or None) of a text model folder."""
    folder = Path(folder)
    if (folder / "sparse" / "0" / "images.txt").is_file():
        folder = folder / "sparse" / "0"
    return (read_cameras_txt(folder / "cameras.txt"), read_images_txt(folder / "images.txt"),
            read_points3d_txt(folder / "points3D.txt"))
