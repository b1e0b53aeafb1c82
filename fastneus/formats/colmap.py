"""A small reader for COLMAP models: text (``cameras.txt``, ``images.txt``, ``points3D.txt``)
and binary (``cameras.bin``, ``images.bin``, ``points3D.bin``, COLMAP's default ``sparse/0`` output).

COLMAP stores, per image, ``qvec`` (w, x, y, z) and ``tvec`` of the world->camera
transform (X_c = R(q) X_w + t), OpenCV axes, in the reconstruction's arbitrary units.
Its pixel convention puts the centre of pixel (u, v) at (u + 0.5, v + 0.5), like fastneus.

The binary layout is COLMAP's (``Reconstruction::Write*Binary``, ``scripts/python/read_write_model.py``),
little-endian throughout:

- ``cameras.bin``: ``uint64 n``; per camera ``uint32 camera_id, int32 model_id, uint64 width,
  uint64 height``, then the model's ``double`` parameters (their count follows from the model id,
  :data:`CAMERA_MODELS`).
- ``images.bin``: ``uint64 n``; per image ``uint32 image_id, double qw, qx, qy, qz, tx, ty, tz,
  uint32 camera_id``, the name as NUL-terminated UTF-8, ``uint64 n2d``, then ``n2d`` times
  ``double x, y, int64 point3D_id``.
- ``points3D.bin``: ``uint64 n``; per point ``uint64 point3D_id, double x, y, z, uint8 r, g, b,
  double error, uint64 track_length``, then ``track_length`` times ``uint32 image_id, uint32 point2D_idx``.

A binary model is untrusted input: every count and length is checked against the bytes left in
the file before anything is read or allocated, and damage is refused with one line naming the
file and the field (:class:`~fastneus.errors.FastneusError`). Nothing is unpickled.
"""
from __future__ import annotations

import mmap
import os
import struct
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


# --------------------------------------------------------------------------- binary models
# model id -> (name, parameter count), as COLMAP's sensor/models.h numbers them
CAMERA_MODELS: dict[int, tuple[str, int]] = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5), 4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5), 8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12), 11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
}
MAX_NAME = 4096  # bytes of an image name (COLMAP's are file paths): a longer one is damage, not a name

_CAMERA = struct.Struct("<IiQQ")           # camera_id, model_id, width, height
_IMAGE = struct.Struct("<I4d3dI")          # image_id, qvec, tvec, camera_id
_POINT2D = 24                              # double x, y, int64 point3D_id
_POINT3D = struct.Struct("<Q3d3BdQ")       # point3D_id, xyz, rgb, error, track_length
_TRACK = 8                                 # uint32 image_id, uint32 point2D_idx
_U64 = struct.Struct("<Q")


class _Bin:
    """Bounds-checked little-endian reads from a binary model file (memory-mapped, read-only).

    Args:
        path: the file; must exist.
    """

    def __init__(self, path: Path):
        self.path, self.pos = path, 0
        try:
            with open(path, "rb") as f:
                size = os.fstat(f.fileno()).st_size
                self.data = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) if size else b""
        except (OSError, ValueError) as e:
            raise FastneusError(f"cannot read ({getattr(e, 'strerror', None) or type(e).__name__})", file=path) \
                from None
        self.size = len(self.data)

    def close(self) -> None:
        if isinstance(self.data, mmap.mmap):
            self.data.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def left(self) -> int:
        return self.size - self.pos

    def fail(self, what: str, field: str):
        raise FastneusError(f"{what} (a truncated or damaged COLMAP binary model?)", file=self.path, field=field)

    def unpack(self, st: struct.Struct, field: str) -> tuple:
        if st.size > self.left:
            self.fail(f"file ends at byte {self.size}, inside this {st.size}-byte record", field)
        v = st.unpack_from(self.data, self.pos)
        self.pos += st.size
        return v

    def count(self, field: str, min_bytes: int) -> int:
        """A uint64 count of records of at least ``min_bytes`` each, checked against the bytes left."""
        (n,) = self.unpack(_U64, field)
        if n * min_bytes > self.left:
            self.fail(f"claims {n} entries of at least {min_bytes} bytes each, but only {self.left} bytes follow",
                      field)
        return n

    def skip(self, n_bytes: int, field: str) -> None:
        if n_bytes > self.left:
            self.fail(f"file ends at byte {self.size}, {n_bytes - self.left} bytes short", field)
        self.pos += n_bytes

    def cstring(self, field: str) -> str:
        end = self.data.find(b"\0", self.pos, self.pos + MAX_NAME + 1)
        if end < 0:
            self.fail(f"no NUL-terminated name within {min(self.left, MAX_NAME + 1)} bytes", field)
        raw = bytes(self.data[self.pos:end])
        self.pos = end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            self.fail(f"name {raw[:60]!r} is not UTF-8", field)

    def end(self, n: int, what: str) -> None:
        if self.left:
            self.fail(f"{self.left} bytes after the {n} {what} the header announces", "end of file")


def read_cameras_bin(path: str | os.PathLike) -> dict[int, ColmapCamera]:
    """Cameras by id of a binary ``cameras.bin``.

    Args:
        path: the file.
    Returns:
        {camera_id: ColmapCamera}.
    Raises:
        FastneusError: missing file, unknown camera model, duplicate id, truncation or trailing bytes.
    """
    path = Path(path)
    if not path.is_file():
        raise FastneusError("file not found (expected a COLMAP binary model)", file=path)
    out: dict[int, ColmapCamera] = {}
    with _Bin(path) as b:
        n = b.count("number of cameras", _CAMERA.size + 8 * 3)
        for k in range(n):
            cid, model_id, w, h = b.unpack(_CAMERA, f"camera {k}")
            if model_id not in CAMERA_MODELS:
                b.fail(f"unknown camera model id {model_id} (known: 0..{max(CAMERA_MODELS)})", f"camera {cid}.model_id")
            name, n_params = CAMERA_MODELS[model_id]
            params = np.array(b.unpack(struct.Struct(f"<{n_params}d"), f"camera {cid}.params"), dtype=np.float64)
            if cid in out:
                b.fail(f"duplicate camera id {cid}", f"camera {cid}")
            out[cid] = ColmapCamera(cid, name, int(w), int(h), params)
        b.end(n, "cameras")
    return out


def read_images_bin(path: str | os.PathLike) -> dict[str, ColmapImage]:
    """Image name -> pose of a binary ``images.bin`` (the 2D points are skipped, bounds-checked).

    Args:
        path: the file.
    Returns:
        {name: ColmapImage}.
    Raises:
        FastneusError: missing file, a bad pose or name, duplicate names, no images, truncation or
            trailing bytes.
    """
    path = Path(path)
    if not path.is_file():
        raise FastneusError("file not found (expected a COLMAP binary model)", file=path)
    out: dict[str, ColmapImage] = {}
    with _Bin(path) as b:
        n = b.count("number of images", _IMAGE.size + 1 + 8)
        for k in range(n):
            v = b.unpack(_IMAGE, f"image {k}")
            iid, q, tv, cid = v[0], np.array(v[1:5], dtype=np.float64), np.array(v[5:8], dtype=np.float64), v[8]
            name = b.cstring(f"image {iid}.name")
            n2d = b.count(f"{name or iid}.num_points2D", _POINT2D)
            b.skip(n2d * _POINT2D, f"{name or iid}.points2D")
            if not (np.all(np.isfinite(q)) and np.all(np.isfinite(tv))) or not np.any(q) or not name:
                pose = " ".join(f"{v:.6g}" for v in (*q, *tv))
                b.fail(f"bad pose (qw qx qy qz tx ty tz = {pose})" if name else "empty image name", name or f"image {iid}")
            if name in out:
                b.fail(f"duplicate image {name!r} (image ids {out[name].id} and {iid})", name)
            q = q / np.abs(q).max()  # scaled first, as the text reader: |q| of huge components overflows
            T = np.eye(4)
            T[:3, :3] = qvec_to_rotation(q)
            T[:3, 3] = tv
            out[name] = ColmapImage(iid, name, cid, T)
        b.end(n, "images")
    if not out:
        raise FastneusError("no images in the model", file=path)
    return out


def read_points3d_bin(path: str | os.PathLike) -> np.ndarray | None:
    """[N, 3] point positions of a binary ``points3D.bin``, or None when the file is absent.

    Raises:
        FastneusError: a non-finite point, truncation or trailing bytes.
    """
    path = Path(path)
    if not path.is_file():
        return None
    with _Bin(path) as b:
        n = b.count("number of points", _POINT3D.size)
        pts = np.empty((n, 3), dtype=np.float64)
        for k in range(n):
            v = b.unpack(_POINT3D, f"point {k}")
            pts[k] = v[1:4]
            track = v[8]
            if track * _TRACK > b.left:
                b.fail(f"track of {track} entries needs {track * _TRACK} bytes, only {b.left} follow",
                       f"point {v[0]}.track_length")
            b.pos += track * _TRACK
        b.end(n, "points")
    if not np.all(np.isfinite(pts)):
        k = int(np.flatnonzero(~np.all(np.isfinite(pts), axis=1))[0])
        raise FastneusError(f"non-finite position {pts[k].tolist()}", file=path, field=f"point {k}")
    return pts


# --------------------------------------------------------------------------- either kind
@dataclass(frozen=True)
class ColmapFiles:
    """The files of one COLMAP model (``points3D`` may not exist); errors name these."""

    cameras: Path
    images: Path
    points3D: Path
    binary: bool


def model_files(folder: str | os.PathLike) -> ColmapFiles:
    """The files of the COLMAP model in ``folder`` (or in its ``sparse/0``): text when
    ``images.txt`` exists, else binary when ``images.bin`` does.

    Args:
        folder: a model folder, or a COLMAP project folder holding ``sparse/0``.
    Raises:
        FastneusError: neither kind of model is there.
    """
    folder = Path(folder)
    for base in (folder, folder / "sparse" / "0"):
        for ext in ("txt", "bin"):
            if (base / f"images.{ext}").is_file():
                return ColmapFiles(base / f"cameras.{ext}", base / f"images.{ext}", base / f"points3D.{ext}",
                                   binary=ext == "bin")
    raise FastneusError("no COLMAP model: expected cameras.txt + images.txt (text) or cameras.bin + images.bin "
                        "(binary), here or in sparse/0", file=folder)


def read_colmap_model(folder: str | os.PathLike):
    """(cameras by id, images by name, points [N, 3] or None) of a text or binary model folder.

    Args:
        folder: the model folder (``cameras.*``, ``images.*``, optional ``points3D.*``) or a COLMAP
            project folder with ``sparse/0``; text is read when both kinds are there.
    Raises:
        FastneusError: one line naming the file and field of any damage.
    """
    f = model_files(folder)
    if f.binary:
        return read_cameras_bin(f.cameras), read_images_bin(f.images), read_points3d_bin(f.points3D)
    return read_cameras_txt(f.cameras), read_images_txt(f.images), read_points3d_txt(f.points3D)
