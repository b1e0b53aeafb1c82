"""The fastneus scene format (a folder with scene.json; docs/FORMAT.md): writing a copy.

Reading is :meth:`fastneus.data.Scene.load`.
"""
from __future__ import annotations

import copy
import os
import shutil
from pathlib import Path

from fastneus.data import Scene
from fastneus.data.validate import check_id
from fastneus.errors import FastneusError
from fastneus.io import safe_dest, staged_output


def write_fastneus(scene, out: str | os.PathLike):
    """Copy a scene's files into ``out`` (image/, mask/, pattern/, gt/) and save ``scene.json``.

    Files are copied byte for byte (no re-encoding, so nothing is lost); camera
    distortion stays in the scene. Copies are named by frame index, or by pattern id (a
    safe id, :data:`fastneus.data.validate.SAFE_ID`), and every destination is checked to lie
    inside ``out``. Built aside and swapped in (:func:`fastneus.io.staged_output`): files in
    ``out`` that fastneus did not write are never replaced or removed.
    Returns the saved, re-loaded :class:`Scene`.
    """
    out = Path(out)
    if out.resolve() == Path(scene.root).resolve():
        raise FastneusError("output folder is the input folder; choose another --out", file=out)
    with staged_output(out) as stage:
        _write_into(scene, stage)
    return Scene.load(out)


def _write_into(scene, out: Path) -> None:
    sj = Path(scene.root) / "scene.json"
    s = copy.deepcopy(scene)
    copied: dict[str, str] = {}

    def put(rel: str, sub: str, name: str, fld: str) -> str:
        src = scene.path(rel)
        key = str(src.resolve())
        if key not in copied:
            dst = f"{sub}/{name}{src.suffix.lower()}"
            (out / sub).mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, safe_dest(out, dst, file=sj, field=fld))
            copied[key] = dst
        return copied[key]

    for i, f in enumerate(s.frames):
        f.image = put(f.image, "image", f"{i:03d}", f"frames[{i}].image")
        if f.mask is not None:
            f.mask = put(f.mask, "mask", f"{i:03d}", f"frames[{i}].mask")
        f.gt = {k: put(v, "gt", f"{i:03d}_{k}", f"frames[{i}].gt.{k}") for k, v in f.gt.items()}
    for q in s.patterns.values():
        q.file = put(q.file, "pattern", check_id(q.id, sj, "patterns"), f"patterns.{q.id}.file")
    if s.gt_mesh is not None:
        s.gt_mesh = put(s.gt_mesh, "gt", "mesh", "gt.mesh")
    s.root = out
    s.save(out)
