"""Atomic file writes (temp file in the same folder, then rename) and output folders.

A crash mid-write never leaves a truncated file in place of an earlier good one, and a
command that finds bad input half-way through never leaves a half-written output folder
(:func:`staged_output`).
"""
from __future__ import annotations

import contextlib
import json
import math
import os
import re
import shutil
import tempfile
from pathlib import Path
from typing import Any, Callable, Iterator

from fastneus.errors import FastneusError


# --------------------------------------------------------------------------- no writes through symbolic links
# output folders (absolute, as the user named them) below which every write refuses symbolic links
_CONFINED: list[str] = []


@contextlib.contextmanager
def confined(root: str | os.PathLike) -> Iterator[Path]:
    """While active, writes below ``root`` (:func:`atomic_write`, :func:`open_append`) refuse a
    destination that is, or passes through, a symbolic link: a link planted in a run folder
    (``renders`` -> elsewhere, ``log.jsonl`` -> a user's file) can never redirect a write.
    ``root`` itself, the folder the user named, may be a link."""
    r = os.path.abspath(root)
    _CONFINED.append(r)
    try:
        yield Path(root)
    finally:
        _CONFINED.remove(r)


def check_no_link(path: str | os.PathLike) -> None:
    """Refuse ``path`` when it or a folder between a :func:`confined` root and it is a symbolic link.

    Raises:
        FastneusError: one line naming the link.
    """
    p = os.path.abspath(path)
    for root in _CONFINED:
        if p.startswith(root.rstrip(os.sep) + os.sep):
            q = p
            while q != root and len(q) > len(root):
                if os.path.islink(q):
                    raise FastneusError("is a symbolic link; fastneus never writes through a link inside its "
                                        "output folder (remove the link)", file=q)
                q = os.path.dirname(q)


def open_append(path: str | os.PathLike):
    """Open a text file for appending, never through a symbolic link (:func:`check_no_link`, O_NOFOLLOW)."""
    check_no_link(path)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
    except OSError as e:
        if os.path.islink(path):
            raise FastneusError("is a symbolic link; fastneus does not append through links", file=path) from None
        raise FastneusError(f"cannot open for appending: {e.strerror}", file=path) from None
    return os.fdopen(fd, "a")


def _read_umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


_UMASK = _read_umask()


def atomic_write(path: str | os.PathLike, write: Callable[[str], None], suffix: str = "") -> None:
    """Call ``write(tmp_path)`` then rename the temp file onto ``path`` (never through a link, see :func:`confined`)."""
    path = Path(path)
    check_no_link(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix or path.suffix, dir=path.parent)
    os.close(fd)
    try:
        write(tmp)
        # mkstemp makes the file 0600; a report or mesh in a shared lab folder must be readable as any
        # file the user creates there (the umask decides)
        os.chmod(tmp, 0o666 & ~_UMASK)
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


def json_safe(obj: Any) -> Any:
    """``obj`` with every non-finite float (and numpy scalar) replaced by a JSON-able value:
    NaN and +-inf become None, so the text is strict JSON (``Infinity`` is not JSON)."""
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if hasattr(obj, "item") and callable(obj.item) and getattr(obj, "ndim", None) == 0:  # numpy / torch scalar
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def json_text(obj: Any, indent: int = 2) -> str:
    """Strict JSON of ``obj`` (non-finite numbers as null, see :func:`json_safe`)."""
    return json.dumps(json_safe(obj), indent=indent, allow_nan=False)


def atomic_write_json(path: str | os.PathLike, obj: Any) -> None:
    """Write ``obj`` as strict JSON (NaN/inf as null: metrics of a failed evaluation stay readable), atomically."""
    atomic_write_text(path, json_text(obj) + "\n")


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


# --------------------------------------------------------------------------- outputs that hold user files
MANIFEST = ".fastneus-manifest.json"
# a path fastneus writes: "/"-separated plain names (no "..", no leading dot, no odd characters)
_SAFE_PART = re.compile(r"[A-Za-z0-9_][A-Za-z0-9._-]{0,127}")


def _safe_rel(rel: Any) -> bool:
    parts = rel.split("/") if isinstance(rel, str) else []
    return bool(parts) and all(_SAFE_PART.fullmatch(p) and ".." not in p for p in parts)


def safe_dest(root: str | os.PathLike, rel: str, file=None, field: str | None = None) -> Path:
    """``root/rel`` once it is sure to name a file inside ``root``.

    ``rel`` must be "/"-separated plain names (letters, digits, ``._-``; no ``..``, no leading
    dot), no folder on the way may be a symbolic link or a file, and the destination itself
    must not be a symbolic link: a name taken from input data can never write elsewhere.

    Raises:
        FastneusError: naming ``file`` (default ``root``) and ``field``.
    """
    base = Path(root).resolve()
    if not _safe_rel(rel):
        raise FastneusError(f"refusing to write {rel!r}: not a plain file name inside the output folder",
                            file=file if file is not None else root, field=field)
    parts = rel.split("/")
    cur = base
    for part in parts:
        cur = cur / part
        if cur.is_symlink() or (cur != base / rel and cur.exists() and not cur.is_dir()):
            raise FastneusError(f"refusing to write {rel!r}: {cur} is a symbolic link or a file; fastneus writes "
                                "only into real folders inside the output folder", file=file if file is not None
                                else root, field=field)
    dst = base.joinpath(*parts)
    if os.path.commonpath([str(dst.parent.resolve()), str(base)]) != str(base):
        raise FastneusError(f"refusing to write {rel!r}: it lies outside the output folder",
                            file=file if file is not None else root, field=field)
    return dst


def read_manifest(out: str | os.PathLike) -> set[str]:
    """The files fastneus wrote in ``out`` (:data:`MANIFEST`); unreadable or odd entries count as not ours."""
    try:
        d = json.loads((Path(out) / MANIFEST).read_text())
    except (OSError, ValueError, RecursionError):
        return set()
    files = d.get("files") if isinstance(d, dict) else None
    return {f for f in files if _safe_rel(f)} if isinstance(files, list) else set()


def _write_manifest(out: Path, files: set[str]) -> None:
    atomic_write_json(out / MANIFEST, {"written_by": "fastneus", "note": "files fastneus wrote here; a later "
                                       "fastneus output replaces or removes these only", "files": sorted(files)})


def _remove_ours(out: Path, rel: str) -> None:
    """Remove file ``out/rel`` (listed in the manifest) and the folders it leaves empty."""
    try:
        p = safe_dest(out, rel)
    except FastneusError:
        return  # a symlinked folder on the way: never follow it to delete
    if p.is_symlink() or p.is_file():
        p.unlink()
    base = out.resolve()
    for d in p.parents:
        if d == base or base not in d.parents:
            break
        try:
            d.rmdir()  # only when empty: a user's file in there keeps its folder
        except OSError:
            break


@contextlib.contextmanager
def staged_output(out: str | os.PathLike, field: str = "--out",
                  adopt: Callable[[Path], set[str]] | None = None) -> Iterator[Path]:
    """Build an output in a hidden sibling folder, then swap it into ``out`` without losing a file.

    Nothing in ``out`` changes until the body has finished (bad input, an error or Ctrl-C
    half-way leave it as it was, and the staging folder is removed). Then each staged file
    is moved in (index files at the top level last); files of an earlier output that
    fastneus wrote (listed in ``out/.fastneus-manifest.json``) are replaced or removed; a
    file of the same name that fastneus did not write is never touched: the swap is refused
    before anything moves, naming that file.

    Args:
        out: the folder the user named.
        field: the option named in errors.
        adopt: for a folder written before manifests existed: called with ``out`` when it has
            no manifest, returns the relative paths to treat as fastneus's own.

    Yields:
        The staging folder to write into.

    Raises:
        FastneusError: a user's file would be replaced, or a destination is not a plain file
            inside ``out``.
    """
    out = check_out_dir(out, field)
    make_out_dir(out.parent, field)
    stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.staging-", dir=out.parent))
    try:
        yield stage
        new = {p.relative_to(stage).as_posix() for p in stage.rglob("*") if p.is_file() or p.is_symlink()}
        make_out_dir(out, field)
        old = read_manifest(out)
        if not old and adopt is not None and not (out / MANIFEST).exists():
            old = {r for r in adopt(out) if _safe_rel(r)}
        for rel in sorted(new):  # check everything before moving anything
            dst = safe_dest(out, rel, field=field)
            if dst.is_dir() or ((dst.exists() or dst.is_symlink()) and rel not in old):
                raise FastneusError(f"exists and was not written by fastneus, so it is left alone; choose another "
                                    f"{field}", file=dst, field=field)
        _write_manifest(out, old | new)  # first: an interrupted swap still knows every file it moved
        for rel in sorted(new, key=lambda r: ("/" not in r, r)):  # the index (scene.json, npz) arrives last
            dst = out / rel
            dst.parent.mkdir(parents=True, exist_ok=True)
            os.replace(stage / rel, dst)
        for rel in sorted(old - new):  # stale files of fastneus's earlier output
            _remove_ours(out, rel)
        _write_manifest(out, new)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
