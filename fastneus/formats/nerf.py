"""NeRF / instant-ngp / nerfstudio ``transforms.json`` scenes, plus a projector block.

Camera part (what those tools write):

- intrinsics at the top level, or per frame (per-frame keys override the shared ones):
  ``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``, ``h`` (nerfstudio / instant-ngp), or only
  ``camera_angle_x`` (optional ``camera_angle_y``; NeRF-Synthetic), with the principal
  point at the image centre and ``w``/``h`` read from the image when absent;
  distortion ``k1 k2 p1 p2 k3`` (``camera_model`` OPENCV or PINHOLE; fisheye models are
  refused);
- ``frames[i].file_path`` relative to the json's folder (an extension-less path, as in
  NeRF-Synthetic, gets ``.png``), ``frames[i].transform_matrix`` = camera->world in
  **OpenGL axes** (x right, y up, z backward), optional ``mask_path``.

fastneus uses OpenCV axes, so ``cam_to_world = transform_matrix @ diag(1, -1, -1, 1)``.
nerfstudio and instant-ngp cast pixel (u, v) through (u + 0.5, v + 0.5) like fastneus, so
``cx``/``cy`` are copied unchanged (NeRF-Synthetic's ``camera_angle_x`` gives ``w/2``, the
image centre in this convention).

Projector extension (fastneus; other tools ignore unknown keys)::

    "projectors": {
      "proj0": {
        "fl_x": 886.8, "fl_y": 886.8, "cx": 512, "cy": 384, "w": 1024, "h": 768,
                                   # or "camera_angle_x" + "w", "h"; pixel centres at +0.5
        "proj_to_cam": [[...4x4...]],  # projector -> camera, OpenCV axes on both sides
                                   # (as cv2.stereoCalibrate's inverse), in the poses' units;
                                   # the projector moves with the camera (a rig), or
        "transform_matrix": [[...]],   # a static projector -> world, OpenGL axes like frames
        "pattern": "patterns/proj0.png"  # shown in every frame (null/absent = off)
      }
    },
    "frames": [{"file_path": ..., "transform_matrix": ...,
                "projectors": {"proj0": "patterns/gray_03.png"}}]   # optional per-frame pattern

a ``"port"`` (underwater housing, the same object as in scene.json: normal, distance,
thickness, n_air, n_glass, n_water; device frame) may sit at the top level or in a frame
(the camera's) and in a projector block; and optionally ``"bounds": {"center": [x, y, z], "radius": r}`` (the region of interest, in
the poses' units; default: the point the cameras look at, radius half the nearest camera
distance). Units are taken as metres (``"units"`` may say otherwise; it is only a label).
"""
from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from fastneus.data.images import image_size
from fastneus.data.model import parse_port, port_to_dict
from fastneus.data.scene import FORMAT, VERSION, Scene
from fastneus.data.validate import MAX_SIDE, load_json
from fastneus.errors import FastneusError
from fastneus.data.kinds import get_projector_kind

NAME = "transforms.json"
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])  # flips y and z: OpenGL camera axes <-> OpenCV
_DIST = ("k1", "k2", "p1", "p2", "k3")
_PINHOLE_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")
_IMG_EXT = (".png", ".jpg", ".jpeg", ".exr", ".bmp")


def _num(d: dict, key: str, file, fld: str) -> float:
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise FastneusError(f"expected a finite number, got {v!r}", file=file, field=fld)
    return float(v)


def _pose(value: Any, file, fld: str) -> np.ndarray:
    """A 4x4 rigid transform; rounding in the json (float32 printing) is re-orthonormalised."""
    try:
        T = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise FastneusError("expected a 4x4 array of numbers", file=file, field=fld) from None
    if T.shape == (3, 4):
        T = np.vstack([T, [0, 0, 0, 1]])
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise FastneusError(f"expected a finite 4x4 matrix, got shape {T.shape}", file=file, field=fld)
    R = T[:3, :3]
    err = float(np.abs(R.T @ R - np.eye(3)).max())
    if err > 1e-2 or np.linalg.det(R) <= 0:
        raise FastneusError(f"not a rotation (max |R^T R - I| = {err:.3g}, det {np.linalg.det(R):.3g}); "
                            "scaled poses are not supported", file=file, field=fld)
    T = T.copy()
    T[3] = (0, 0, 0, 1)
    if err > 1e-9:  # exact rotations are kept bit for bit
        U, _, Vt = np.linalg.svd(R)
        T[:3, :3] = U @ Vt
    return T


def _intrinsics(d: dict, shared: dict, file, fld: str, size_from=None) -> tuple[np.ndarray, int, int, np.ndarray]:
    """(K [3,3], w, h, dist [5]) from a frame/projector dict ``d`` over the ``shared`` keys."""
    m = {**shared, **d}
    model = m.get("camera_model", "OPENCV")
    if model not in _PINHOLE_MODELS:
        raise FastneusError(f"camera model {model!r} is not supported (pinhole + k1 k2 p1 p2 k3 only)",
                            file=file, field=f"{fld}.camera_model" if "camera_model" in d else "camera_model")
    if any(k in m and m[k] for k in ("k4", "k5", "k6")):
        raise FastneusError("distortion beyond k1 k2 p1 p2 k3 is not supported", file=file, field=fld)
    w = m.get("w")
    h = m.get("h")
    if (w is None or h is None) and size_from is not None:
        wh = image_size(size_from)
        if wh is None:
            raise FastneusError(f"cannot read image {size_from}", file=file, field=f"{fld}.file_path")
        w, h = (wh[0] if w is None else w), (wh[1] if h is None else h)
    if w is None or h is None:
        raise FastneusError("missing w/h (image size)", file=file, field=f"{fld}.w")
    for k, v in (("w", w), ("h", h)):
        if (isinstance(v, bool) or not isinstance(v, (int, float)) or not 1 <= v <= MAX_SIDE
                or (isinstance(v, float) and not v.is_integer())):  # NaN and inf fail the range test
            raise FastneusError(f"expected an integer in 1..{MAX_SIDE}, got {v!r}"[:120], file=file,
                                field=f"{fld}.{k}")
    w, h = int(w), int(h)

    def where(k):
        return f"{fld}.{k}" if k in d else k

    if "fl_x" in m:
        fx = _num(m, "fl_x", file, where("fl_x"))
        fy = _num(m, "fl_y", file, where("fl_y")) if "fl_y" in m else fx
    elif "camera_angle_x" in m:
        ax = _num(m, "camera_angle_x", file, where("camera_angle_x"))
        if not 0 < ax < math.pi:
            raise FastneusError(f"must be in (0, pi) radians, got {ax}", file=file, field=where("camera_angle_x"))
        fx = 0.5 * w / math.tan(0.5 * ax)
        if "camera_angle_y" in m:
            ay = _num(m, "camera_angle_y", file, where("camera_angle_y"))
            if not 0 < ay < math.pi:
                raise FastneusError(f"must be in (0, pi) radians, got {ay}", file=file, field=where("camera_angle_y"))
            fy = 0.5 * h / math.tan(0.5 * ay)
        else:
            fy = fx
    else:
        raise FastneusError("no focal length: give fl_x (and fl_y) or camera_angle_x", file=file, field=fld)
    if fx <= 0 or fy <= 0:
        raise FastneusError("focal length must be > 0", file=file, field=where("fl_x"))
    cx = _num(m, "cx", file, where("cx")) if "cx" in m else w / 2.0
    cy = _num(m, "cy", file, where("cy")) if "cy" in m else h / 2.0
    dist = np.array([_num(m, k, file, where(k)) if k in m else 0.0 for k in _DIST])
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return K, w, h, dist


def _image_path(root: Path, rel: Any, file, fld: str) -> str:
    if not isinstance(rel, str) or not rel:
        raise FastneusError(f"expected a non-empty string, got {rel!r}", file=file, field=fld)
    p = root / rel
    if p.is_file():
        return Path(os.path.relpath(p, root)).as_posix()
    if not p.suffix.lower() in _IMG_EXT:  # NeRF-Synthetic writes "./train/r_0"
        for ext in _IMG_EXT:
            if p.with_name(p.name + ext).is_file():
                return Path(os.path.relpath(p.with_name(p.name + ext), root)).as_posix()
    raise FastneusError(f"file not found: {p}", file=file, field=fld)


def _look_point(c2ws: list[np.ndarray]) -> np.ndarray:
    from fastneus.formats.opencv_calib import axes_meeting_point

    return axes_meeting_point(c2ws)


def read_nerf(path: str | os.PathLike) -> Scene:
    """Read a ``transforms.json`` scene (folder or file) into a validated :class:`Scene`.

    Raises:
        FastneusError: naming the file and field of the first problem.
    """
    path = Path(path)
    file = path / NAME if path.is_dir() else path
    if not file.is_file():
        raise FastneusError("transforms.json not found", file=file)
    root = file.parent.resolve()
    d = load_json(file)  # unreadable, not UTF-8, invalid or absurdly nested: one line naming the file
    if not isinstance(d, dict):
        raise FastneusError("expected a JSON object", file=file)
    frames_in = d.get("frames")
    if not isinstance(frames_in, list) or not frames_in:
        raise FastneusError("expected a non-empty list of frames", file=file, field="frames")
    shared = {k: v for k, v in d.items() if k not in ("frames", "projectors")}

    cameras: dict[str, dict] = {}
    cam_key: dict[tuple, str] = {}
    frames, c2ws = [], []
    for i, f in enumerate(frames_in):
        fld = f"frames[{i}]"
        if not isinstance(f, dict):
            raise FastneusError("expected an object", file=file, field=fld)
        if "file_path" not in f:
            raise FastneusError("missing", file=file, field=f"{fld}.file_path")
        if "transform_matrix" not in f:
            raise FastneusError("missing", file=file, field=f"{fld}.transform_matrix")
        img = _image_path(root, f["file_path"], file, f"{fld}.file_path")
        K, w, h, dist = _intrinsics(f, shared, file, fld, size_from=root / img)
        port = f.get("port", shared.get("port"))
        if port is not None:  # validated (and reported with its field) like a scene.json port
            port = port_to_dict(parse_port(port, file, f"{fld}.port" if "port" in f else "port"))
        key = (w, h, *np.round(K.reshape(-1), 9), *np.round(dist, 12), json.dumps(port, sort_keys=True))
        if key not in cam_key:
            cid = f"cam{len(cam_key)}"
            cam_key[key] = cid
            cameras[cid] = {"K": K.tolist(), "width": w, "height": h, "dist": dist.tolist(),
                            **({"port": port} if port is not None else {})}
        c2w = _pose(f["transform_matrix"], file, f"{fld}.transform_matrix") @ GL_TO_CV
        c2ws.append(c2w)
        fr: dict[str, Any] = {"image": img, "camera": cam_key[key], "cam_to_world": c2w.tolist(), "view": i,
                              "projectors": {}}
        if f.get("mask_path") is not None:
            fr["mask"] = _image_path(root, f["mask_path"], file, f"{fld}.mask_path")
        frames.append(fr)

    projectors, patterns = {}, {}
    pat_id: dict[str, str] = {}

    def pattern(rel, fld):
        if rel is None:
            return None
        p = _image_path(root, rel, file, fld)
        if p not in pat_id:
            pat_id[p] = f"q{len(pat_id):03d}"
            patterns[pat_id[p]] = {"file": p}
        return pat_id[p]

    pb = d.get("projectors", {}) or {}
    if not isinstance(pb, dict):
        raise FastneusError("expected an object {id: {...}}", file=file, field="projectors")
    for pid, pr in pb.items():
        fld = f"projectors.{pid}"
        if not isinstance(pr, dict):
            raise FastneusError("expected an object", file=file, field=fld)
        K, w, h, pdist = _intrinsics(pr, {}, file, fld)
        if np.any(pdist):
            raise FastneusError("projector distortion cannot be modelled; undistort the patterns", file=file, field=fld)
        has_rig, has_world = "proj_to_cam" in pr, "transform_matrix" in pr
        if has_rig == has_world:
            raise FastneusError("give exactly one of proj_to_cam (rigged to the camera, OpenCV axes) or "
                                "transform_matrix (static, projector->world, OpenGL axes)", file=file, field=fld)
        p2c = _pose(pr["proj_to_cam"], file, f"{fld}.proj_to_cam") if has_rig else None
        p2w = _pose(pr["transform_matrix"], file, f"{fld}.transform_matrix") @ GL_TO_CV if has_world else None
        projectors[pid] = {"K": K.tolist(), "width": w, "height": h,
                           "proj_to_cam": None if p2c is None else p2c.tolist(),
                           **({"port": pr["port"]} if pr.get("port") is not None else {})}
        default = pattern(pr.get("pattern"), f"{fld}.pattern")
        for i, f in enumerate(frames_in):
            fp = f.get("projectors", {}) or {}
            if not isinstance(fp, dict):
                raise FastneusError("expected an object {projector id: pattern path}", file=file,
                                    field=f"frames[{i}].projectors")
            q = pattern(fp[pid], f"frames[{i}].projectors.{pid}") if pid in fp else default
            e: dict[str, Any] = {"pattern": q}
            if p2w is not None:
                e["proj_to_world"] = p2w.tolist()
            frames[i]["projectors"][pid] = e
    for i, f in enumerate(frames_in):
        unknown = set((f.get("projectors") or {}).keys()) - set(projectors)
        if unknown:
            raise FastneusError(f"unknown projector id {sorted(unknown)[0]!r}; known: {sorted(projectors)}",
                                file=file, field=f"frames[{i}].projectors")

    b = d.get("bounds")
    if b is not None:
        if not isinstance(b, dict) or "center" not in b or "radius" not in b:
            raise FastneusError("expected {center: [x, y, z], radius: r}", file=file, field="bounds")
        center, radius = b["center"], b["radius"]  # as given: Scene.from_dict checks them, naming this file
    else:
        center = _look_point(c2ws).tolist()
        radius = 0.5 * min(float(np.linalg.norm(T[:3, 3] - center)) for T in c2ws)
    data = {"format": FORMAT, "version": VERSION, "units": str(d.get("units", "m")), "name": root.name,
            "bounds": {"center": center, "radius": radius},
            "cameras": cameras, "projectors": projectors, "patterns": patterns, "frames": frames,
            "meta": {"source_format": "nerf-transforms", "source": str(file)}}
    return Scene.from_dict(data, root, file=file)


def write_nerf(scene: Scene, out: str | os.PathLike, copy_files: bool = True) -> Path:
    """Write ``scene`` as ``out/transforms.json`` (with the projector block); returns its path.

    Intrinsics are shared at the top level when the scene has one camera, else per frame.
    Files are copied into ``out`` (``images/``, ``masks/``, ``patterns/``) unless
    ``copy_files`` is False, in which case paths point at the scene's own files. Free
    projectors must keep one pose in every frame (a static ``transform_matrix``). Copies are
    named by frame index or pattern id (a safe id), each destination checked to lie inside
    ``out``; built aside and swapped in (:func:`fastneus.io.staged_output`), so files in
    ``out`` that fastneus did not write are never replaced or removed.
    """
    from fastneus.io import staged_output

    out = Path(out)
    with staged_output(out) as stage:
        _write_nerf(scene, stage, out, copy_files)
    return out / NAME


def _write_nerf(scene: Scene, stage: Path, final: Path, copy_files: bool) -> None:
    from fastneus.data.validate import check_id
    from fastneus.io import safe_dest

    out = stage
    sj = Path(scene.root) / "scene.json"

    def put(rel: str, sub: str, name: str, fld: str) -> str:
        src = scene.path(rel)
        dst = f"{sub}/{name}{src.suffix.lower()}"
        if not copy_files or src.resolve() == (final / dst).resolve():  # (already in place: kept, not copied)
            return Path(os.path.relpath(src.resolve(), final.resolve())).as_posix()
        (out / sub).mkdir(exist_ok=True)
        shutil.copyfile(src, safe_dest(out, dst, file=sj, field=fld))
        return dst

    def intr(K, w, h, dist=None) -> dict:
        e = {"fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
             "w": int(w), "h": int(h)}
        if abs(K[0, 1]) > 1e-12:
            raise FastneusError("a skewed K cannot be written as transforms.json", field="cameras.K")
        if dist is not None:
            e.update({k: float(v) for k, v in zip(_DIST, dist)})
        return e

    d: dict[str, Any] = {"camera_model": "OPENCV"}
    one_cam = len(scene.cameras) == 1
    if one_cam:
        c = next(iter(scene.cameras.values()))
        d.update(intr(c.K, c.width, c.height, c.dist))
        if c.port is not None:
            d["port"] = port_to_dict(c.port)
    pat_files = {q.id: put(q.file, "patterns", check_id(q.id, sj, "patterns"), f"patterns.{q.id}.file")
                 for q in scene.patterns.values()}
    proj_block: dict[str, Any] = {}
    for pid, pj in scene.projectors.items():
        kind = get_projector_kind(pj.kind)
        if not kind.images:
            raise FastneusError(f"{kind.noun} projectors cannot be written to transforms.json; keep the fastneus "
                                "format", field=f"projectors.{pid}")
        e = intr(pj.K, pj.width, pj.height)
        if pj.port is not None:
            e["port"] = port_to_dict(pj.port)
        if pj.proj_to_cam is not None:
            e["proj_to_cam"] = pj.proj_to_cam.tolist()
        else:
            poses = [f.projectors[pid].proj_to_world for f in scene.frames
                     if pid in f.projectors and f.projectors[pid].proj_to_world is not None]
            if any(not np.allclose(p, poses[0], atol=1e-9) for p in poses):
                raise FastneusError(f"projector {pid!r} moves between frames; transforms.json holds one static "
                                    "pose per free projector", field=f"projectors.{pid}")
            e["transform_matrix"] = (poses[0] @ GL_TO_CV).tolist()
        proj_block[pid] = e
    frames = []
    for i, f in enumerate(scene.frames):
        fe: dict[str, Any] = {"file_path": put(f.image, "images", f"{i:03d}", f"frames[{i}].image"),
                              "transform_matrix": (f.cam_to_world @ GL_TO_CV).tolist()}
        if not one_cam:
            c = scene.cameras[f.camera]
            fe.update(intr(c.K, c.width, c.height, c.dist))
            if c.port is not None:
                fe["port"] = port_to_dict(c.port)
        if f.mask is not None:
            fe["mask_path"] = put(f.mask, "masks", f"{i:03d}", f"frames[{i}].mask")
        fe["projectors"] = {pid: (pat_files[fp.pattern] if fp.pattern is not None else None)
                            for pid, fp in f.projectors.items()}
        frames.append(fe)
    if proj_block:
        d["projectors"] = proj_block
    d["bounds"] = {"center": np.asarray(scene.bounds.center).tolist(), "radius": float(scene.bounds.radius)}
    d["units"] = scene.units
    d["frames"] = frames
    (out / NAME).write_text(json.dumps(d, indent=1) + "\n")
