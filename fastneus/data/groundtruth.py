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


def mesh_file_problem(path: Path) -> str | None:
    """Why ``path`` cannot be a triangle mesh, from its header alone (None: it looks like one).

    The check before training (``pipeline.check_inputs``) must not import trimesh: that import
    took ~1 s on a GPU host (1.6 s on the 2-core CPU), all of it between the start of the process
    and mesh.ply. This reads the header of a PLY (format, vertex and face counts, and a binary
    body's minimum size), STL (binary size or ASCII ``solid``), OFF (counts) or glTF binary
    (magic); an OBJ or other format trimesh reads must hold a ``v`` and an ``f`` line. The full
    parse happens at evaluation, after mesh.ply (``eval.metrics.geometry_metrics``, one line on
    failure).
    """
    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            head = f.read(65536)
    except OSError as e:
        return f"cannot read it ({e.strerror or type(e).__name__})"
    if size == 0:
        return "the file is empty"
    suffix = path.suffix.lower()
    if suffix == ".ply":
        end = head.find(b"end_header")
        if not head.startswith(b"ply") or end < 0:
            return "not a PLY file (no 'ply' ... 'end_header' header)"
        lines = [ln.split() for ln in head[:end].decode("ascii", "replace").splitlines()]
        fmt = next((ln[1] for ln in lines if len(ln) >= 2 and ln[0] == "format"), None)
        counts = {ln[1]: ln[2] for ln in lines if len(ln) == 3 and ln[0] == "element"}
        try:
            nv, nf = int(counts.get("vertex", 0)), int(counts.get("face", 0))
        except ValueError:
            return "its header's element counts are not integers"
        if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
            return f"unknown PLY format {fmt!r}"
        if nv < 3 or nf < 1:
            return f"it holds no triangles ({nv} vertices, {nf} faces)"
        # a binary body holds at least 3 floats per vertex and a count + 3 indices per face
        if fmt != "ascii" and size - end < nv * 12 + nf * 13:
            return f"the file ends before its {nv} vertices and {nf} faces"
        return None
    if suffix == ".stl":
        if head[:5].lower() == b"solid" and b"facet" in head:
            return None
        n = int.from_bytes(head[80:84], "little") if len(head) >= 84 else 0
        return None if n > 0 and size >= 84 + 50 * n else "not an STL mesh (no facets)"
    if suffix == ".off":
        tok = head.decode("ascii", "replace").split()
        if not tok or not tok[0].endswith("OFF"):
            return "not an OFF file"
        try:
            nv, nf = int(tok[1]), int(tok[2])
        except (IndexError, ValueError):
            return "its counts line is missing"
        return None if nv >= 3 and nf >= 1 else f"it holds no triangles ({nv} vertices, {nf} faces)"
    if suffix == ".glb":
        return None if head[:4] == b"glTF" else "not a binary glTF file"
    # OBJ and other text formats: vertex and face records somewhere in the file
    try:
        text = path.read_bytes() if size <= 1 << 28 else head
    except OSError as e:
        return f"cannot read it ({e.strerror or type(e).__name__})"
    import re

    if re.search(rb"(?m)^v\s", text) and re.search(rb"(?m)^f\s", text):
        return None
    return "no vertex and face records (an OBJ needs 'v' and 'f' lines)"
