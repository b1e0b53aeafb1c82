"""Projector-camera calibration files written by ``cv2.FileStorage`` (YAML or XML).

Layouts recognised (keys):

- Moreno & Taubin "scan3d-capture" (``calibration.yml``): ``cam_K, cam_kc, proj_K,
  proj_kc, R, T`` — from ``cv2.stereoCalibrate`` with the camera as view 1 and the
  projector as view 2.
- OpenCV stereo sample (``intrinsics.yml`` + ``extrinsics.yml``; pass both files or a
  merged one): ``M1, D1, M2, D2, R, T`` — camera = 1, projector = 2.
- kamino410 ``procam-calibration`` (``calibration_result.xml``): ``cam_int, cam_dist,
  proj_int, proj_dist, rotation`` (written misspelt as ``roration``), ``translation``,
  and ``img_shape`` = camera (rows, cols) — also ``stereoCalibrate(cam, proj)``.

In all of them R, T come from ``cv2.stereoCalibrate``, whose R, T map points from view
1 (camera) to view 2 (projector): ``X_p = R X_c + T``. fastneus stores the inverse,
``proj_to_cam``. T is in the calibration target's units (usually mm) and converted to
metres per ``units``.

Pixel convention: OpenCV calibration puts integer pixel centres at integer coordinates
(corner detection, decoded projector columns), fastneus at +0.5; both principal points
are shifted by +0.5. Camera distortion is kept (``Scene`` undistorts at load);
projector distortion cannot be modelled and is dropped with a warning.
"""
from __future__ import annotations

import math
import re
import shutil
import warnings
from pathlib import Path
from typing import Sequence

import numpy as np

from fastneus.data.images import image_size
from fastneus.data.model import Camera, Projector, planes_to_list
from fastneus.data.scene import FORMAT, VERSION, Scene
from fastneus.data.validate import (MAX_SIDE, check_bounds_scale, check_faces_bounds, check_pose, check_principal_point,
                                    load_json)
from fastneus.errors import FastneusError
from fastneus.geometry.cameras import rigid_inverse
from fastneus.io import staged_output

# layout name -> (cam K, cam dist, proj K, proj dist, R candidates, T)
LAYOUTS = {
    "moreno-taubin": ("cam_K", "cam_kc", "proj_K", "proj_kc", ("R",), "T"),
    "opencv-stereo": ("M1", "D1", "M2", "D2", ("R",), "T"),
    "kamino410": ("cam_int", "cam_dist", "proj_int", "proj_dist", ("rotation", "roration"), "translation"),
}
UNITS = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}


MAX_CALIB_BYTES = 16 << 20  # calibration files are a few KB; bounds the work and the nesting
MAX_CALIB_DEPTH = 256  # real files nest 2-3 levels; OpenCV's parser recurses and crashes (SIGSEGV) near 50k


def _nesting_depth(data: bytes) -> int:
    """Upper bound of the YAML flow ([ {) / XML element nesting of a FileStorage file."""
    depth = deepest = 0
    for m in re.finditer(rb"[\[{]|[\]}]|<(/?)[^>?!]*?(/?)>", data):
        tok = m.group(0)
        if tok in (b"[", b"{") or (tok[:1] == b"<" and not m.group(1) and not m.group(2)):
            depth += 1
            deepest = max(deepest, depth)
        elif tok in (b"]", b"}") or m.group(1):
            depth = max(0, depth - 1)
    return deepest


def _cv_msg(e: BaseException) -> str:
    """cv2's multi-line error as one line: keep "file(line): what", drop the C++ source path."""
    lines = [ln.strip() for ln in str(e.__cause__ or e).strip().splitlines() if ln.strip()]
    msg = lines[-1] if lines else type(e).__name__
    if "Parsing error" in msg:  # "... error: (-212:Parsing error) f in function 'calib.yml(4): what'"
        return msg.split(" in function '", 1)[-1].rstrip("'")
    # "OpenCV(x) /path/file.cpp:159: error: (-215:Assertion failed) what in function 'f'"
    return msg.split(" error: ", 1)[-1].split(" in function '", 1)[0]


def _check_matrix_header(node, file: Path, key: str) -> bool:
    """True for an ``opencv-matrix`` whose rows x cols x channels match its data; False for a
    mapping without those fields.

    OpenCV trusts the header when it reads the matrix: a negative ``cols`` corrupts the heap
    (the process aborts later), a non-number allocates a garbage size.
    """
    parts = {k: node.getNode(k) for k in ("rows", "cols", "dt", "data")}
    if all(n.isNone() for n in parts.values()):
        return False
    dt = parts["dt"].string() if parts["dt"].isString() else ""
    form = re.fullmatch(r"([1-4]?)([a-zA-Z])", dt)
    rows, cols = (int(parts[k].real()) if parts[k].isInt() else -1 for k in ("rows", "cols"))
    if form is None or rows < 0 or cols < 0:
        got = ", ".join(f"{k} {int(n.real()) if n.isInt() else n.string() if n.isString() else '?'!r}"
                        for k, n in parts.items() if k != "data")
        raise FastneusError(f"bad matrix header: rows and cols must be integers >= 0 and dt a type such as 'd'; "
                            f"got {got}", file=file, field=key)
    n = parts["data"].size() if parts["data"].isSeq() else 1
    if rows * cols * int(form.group(1) or 1) != n:
        raise FastneusError(f"matrix of {rows}x{cols} holds {n} values", file=file, field=key)
    return True


def _read_nodes(paths: Sequence[Path]) -> dict[str, tuple[Path, object]]:
    """Every top-level key of the FileStorage files -> (file, value: ndarray | float | str)."""
    import cv2

    out: dict[str, tuple[Path, object]] = {}
    for p in paths:
        if not p.is_file():
            raise FastneusError("calibration file not found", file=p)
        try:
            if p.stat().st_size > MAX_CALIB_BYTES:
                raise FastneusError(f"larger than {MAX_CALIB_BYTES >> 20} MB; not a calibration file", file=p)
            depth = _nesting_depth(p.read_bytes())
        except OSError as e:
            raise FastneusError(f"cannot read: {e.strerror}", file=p) from None
        if depth > MAX_CALIB_DEPTH:
            raise FastneusError(f"nested {depth} levels deep; a calibration file nests a few", file=p)
        key = None
        try:
            fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
            if not fs.isOpened():
                raise FastneusError("cannot open as OpenCV YAML/XML", file=p)
            root = fs.root()
            if not root.isMap():
                raise FastneusError("expected a mapping of key: value at the top level", file=p)
            for key in root.keys():
                node = fs.getNode(key)
                if node.isString():
                    val: object = node.string()
                elif node.isReal() or node.isInt():
                    val = node.real()
                elif node.isSeq():
                    val = np.array([node.at(i).real() for i in range(node.size())], dtype=np.float64)
                elif node.isMap() and _check_matrix_header(node, p, key):
                    m = node.mat()
                    val = None if m is None else np.asarray(m, dtype=np.float64)
                else:  # empty, or a mapping that is not a matrix: reported if a needed key
                    val = None
                out[key] = (p, val)
            fs.release()
        except (cv2.error, SystemError) as e:  # some parse errors surface as SystemError (cv2.error as cause)
            raise FastneusError(f"cannot {'read' if key else 'parse'} as OpenCV YAML/XML: {_cv_msg(e)}", file=p,
                                field=key) from None
    return out


def _array(nodes, key: str, shapes: Sequence[tuple[int, ...]]) -> np.ndarray:
    file, v = nodes[key]
    if not isinstance(v, np.ndarray):
        raise FastneusError("expected a matrix", file=file, field=key)
    a = v.reshape(-1) if len(shapes[0]) == 1 else v
    if not any(a.shape == s for s in shapes) and not (len(shapes[0]) == 1 and a.size in [s[0] for s in shapes]):
        raise FastneusError(f"expected shape {' or '.join('x'.join(map(str, s)) for s in shapes)}, "
                            f"got {'x'.join(map(str, v.shape))}", file=file, field=key)
    if not np.all(np.isfinite(a)):
        raise FastneusError("contains non-finite values (nan/inf)", file=file, field=key)
    return a


def _dist5(nodes, key: str) -> np.ndarray:
    """OpenCV distortion (4, 5, 8, 12 or 14 coefficients) -> [5] k1 k2 p1 p2 k3."""
    file = nodes[key][0]
    d = _array(nodes, key, [(4,), (5,), (8,), (12,), (14,)])
    if np.any(d[5:] != 0):
        raise FastneusError("rational/thin-prism/tilt distortion terms (beyond k1 k2 p1 p2 k3) are not "
                            "supported", file=file, field=key)
    out = np.zeros(5)
    out[: min(5, d.size)] = d[:5]
    return out


def _size(nodes, pairs, vecs, rows_cols) -> tuple[int, int] | None:
    def dim(key: str, v) -> int:
        """A size in pixels from the file; NaN, inf, text or absurd values name the file and key."""
        a = np.asarray(v, dtype=object).reshape(-1)
        try:
            x = float(a[0]) if a.size else math.nan
        except (TypeError, ValueError):
            x = math.nan
        if not (math.isfinite(x) and 1 <= round(x) <= MAX_SIDE):
            raise FastneusError(f"expected a size in pixels (1..{MAX_SIDE}), got {str(a[0]) if a.size else repr(v)}"[:120],
                                file=nodes[key][0], field=key)
        return int(round(x))

    for kw, kh in pairs:
        if kw in nodes and kh in nodes:
            return dim(kw, nodes[kw][1]), dim(kh, nodes[kh][1])
    for k in vecs:  # [width, height]
        if k in nodes and isinstance(nodes[k][1], np.ndarray) and nodes[k][1].size == 2:
            w, h = nodes[k][1].reshape(-1)
            return dim(k, w), dim(k, h)
    for k in rows_cols:  # numpy shape order: [rows, cols]
        if k in nodes and isinstance(nodes[k][1], np.ndarray) and nodes[k][1].size in (2, 3):
            h, w = nodes[k][1].reshape(-1)[:2]
            return dim(k, w), dim(k, h)
    return None


def _parse_wh(v, what: str) -> tuple[int, int] | None:
    if v is None:
        return None
    if isinstance(v, str):
        try:
            w, h = (int(x) for x in v.lower().split("x"))
        except ValueError:
            raise FastneusError(f"expected WIDTHxHEIGHT, got {v!r}", field=what) from None
    else:
        try:
            w, h = (int(x) for x in v)
        except (TypeError, ValueError, OverflowError):
            raise FastneusError(f"expected (width, height), got {v!r}"[:120], field=what) from None
    if not (1 <= w <= MAX_SIDE and 1 <= h <= MAX_SIDE):
        raise FastneusError(f"sizes must be in 1..{MAX_SIDE}, got {w}x{h}", field=what)
    return w, h


def read_procam_calibration(path, proj_size=None, units: str = "mm", cam_size=None,
                            require_projector: bool = True) -> tuple[Camera, Projector | None]:
    """Read a projector-camera calibration into a camera and a rig-attached projector.

    Args:
        path: a YAML/XML file written by ``cv2.FileStorage`` (or a list of files whose keys
            are merged, e.g. OpenCV's ``intrinsics.yml`` + ``extrinsics.yml``).
        proj_size: projector (width, height) or ``"WxH"`` when the file lacks it.
        units: unit of T in the file (``mm``, ``cm`` or ``m``); converted to metres.
        cam_size: camera (width, height) when the file lacks it.
        require_projector: False accepts a camera-only file (a laser-plane rig) and then
            returns ``(camera, None)`` when the file has no projector keys.

    Returns:
        (camera ``cam0`` with K [3,3] in fastneus pixel convention and dist [5],
        projector ``proj0`` with ``proj_to_cam`` [4,4] in metres).

    Raises:
        FastneusError: unknown layout, missing key, bad shape, non-finite values,
            non-rotation R, unknown sizes or units.
    """
    paths = [Path(p) for p in (path if isinstance(path, (list, tuple)) else [path])]
    if units not in UNITS:
        raise FastneusError(f"unknown units {units!r}; use one of {sorted(UNITS)}", field="--units")
    nodes = _read_nodes(paths)
    file0 = paths[0]
    layout = None
    for name, (ck, _, pk, _, _, _) in LAYOUTS.items():
        if ck in nodes or pk in nodes:
            layout = name
            break
    if layout is None:
        raise FastneusError("unknown calibration layout: expected cam_K/proj_K (Moreno-Taubin), "
                            "M1/M2 (OpenCV stereo) or cam_int/proj_int (procam-calibration)", file=file0)
    ck, cd, pk, pd, rks, tk = LAYOUTS[layout]
    rk = next((k for k in rks if k in nodes), rks[0])
    camera_only = not require_projector and pk not in nodes
    for key in (ck, cd) if camera_only else (ck, cd, pk, pd, rk, tk):
        if key not in nodes:
            raise FastneusError(f"missing key ({layout} layout)", file=file0, field=key)

    def K_of(key):
        K = _array(nodes, key, [(3, 3)]).copy()
        if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]):
            raise FastneusError("expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]", file=nodes[key][0], field=key)
        K[0, 2] += 0.5  # OpenCV integer pixel centres -> fastneus (+0.5)
        K[1, 2] += 0.5
        return K

    if camera_only:
        cs = _size(nodes, [("cam_width", "cam_height"), ("image_width", "image_height")],
                   ["cam_size", "image_size", "imageSize"], ["img_shape", "cam_shape"]) or _parse_wh(cam_size, "--cam-size")
        if cs is None:
            raise FastneusError("camera image size not in the file; give images", file=file0)
        cam = Camera(id="cam0", K=K_of(ck), width=cs[0], height=cs[1], dist=_dist5(nodes, cd))
        check_principal_point(cam.K, cam.width, cam.height, nodes[ck][0], ck)
        return cam, None
    Kc, Kp = K_of(ck), K_of(pk)
    dc, dp = _dist5(nodes, cd), _dist5(nodes, pd)
    R = _array(nodes, rk, [(3, 3)])
    T = _array(nodes, tk, [(3,)]) * UNITS[units]
    X = np.eye(4)
    X[:3, :3], X[:3, 3] = R, T
    cam_to_proj = check_pose(X, nodes[rk][0], rk)  # X_p = R X_c + T (stereoCalibrate: view 1 -> view 2)
    if np.any(dp):
        warnings.warn(f"{file0}: projector distortion {dp.tolist()} is ignored (fastneus models the "
                      "projector as a pinhole)", stacklevel=2)

    cs = _size(nodes, [("cam_width", "cam_height"), ("image_width", "image_height")],
               ["cam_size", "image_size", "imageSize"], ["img_shape", "cam_shape"]) or _parse_wh(cam_size, "--cam-size")
    ps = _size(nodes, [("proj_width", "proj_height")], ["proj_size"], ["proj_shape"]) or _parse_wh(proj_size, "--proj-size")
    if cs is None:
        raise FastneusError("camera image size not in the file (cam_width/cam_height, image_size or "
                            "img_shape); pass it (cam_size / --cam-size WxH, or give images)", file=file0)
    if ps is None:
        raise FastneusError("projector size not in the file (proj_width/proj_height or proj_size); "
                            "pass --proj-size WxH", file=file0)
    cam = Camera(id="cam0", K=Kc, width=cs[0], height=cs[1], dist=dc)
    proj = Projector(id="proj0", K=Kp, width=ps[0], height=ps[1], proj_to_cam=rigid_inverse(cam_to_proj))
    check_principal_point(cam.K, cam.width, cam.height, nodes[ck][0], ck)  # here, not in the staged scene.json
    check_principal_point(proj.K, proj.width, proj.height, nodes[pk][0], pk)
    return cam, proj


# --------------------------------------------------------------------------- scenes
def axes_meeting_point(c2ws: list[np.ndarray]) -> np.ndarray:
    """[3] least-squares point closest to all optical axes (where the cameras look)."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for T in c2ws:
        d = T[:3, 2] / np.linalg.norm(T[:3, 2])
        M = np.eye(3) - np.outer(d, d)
        A += M
        b += M @ T[:3, 3]
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(b))):
        return np.full(3, np.nan)  # callers refuse non-finite bounds, naming the poses
    try:
        return np.linalg.lstsq(A, b, rcond=None)[0]
    except np.linalg.LinAlgError:
        return np.full(3, np.nan)


def _poses_from_scene_json(path: Path, n: int) -> tuple[list[np.ndarray], dict | None]:
    file = path / "scene.json" if path.is_dir() else path
    d = load_json(file)  # unreadable, not UTF-8, invalid or absurdly nested: one line naming the file
    frames = d.get("frames") if isinstance(d, dict) else None
    if not isinstance(frames, list):
        raise FastneusError("expected a scene.json with a frames list", file=file, field="frames")
    if len(frames) != n:
        raise FastneusError(f"{len(frames)} frames but {n} images were given", file=file, field="frames")
    poses = []
    for i, f in enumerate(frames):
        if not isinstance(f, dict) or "cam_to_world" not in f:
            raise FastneusError("missing", file=file, field=f"frames[{i}].cam_to_world")
        poses.append(check_pose(f["cam_to_world"], file, f"frames[{i}].cam_to_world"))
    return poses, d.get("bounds")


def make_scene_from_calibration(calib, images: Sequence, patterns: Sequence, poses, out, units: str = "mm",
                                proj_size=None, colmap_scale: float = 1.0, bounds=None, lasers=None) -> Scene:
    """Build and save a fastneus scene from a procam calibration, photos, patterns and poses.

    Images and patterns are copied into ``out/image`` and ``out/pattern`` unchanged;
    camera distortion stays in the scene (``Scene.image`` undistorts at load).

    Args:
        calib: a calibration file path (or list of paths) or a ``(Camera, Projector)`` pair.
        images: N photo paths, frame order.
        patterns: the pattern shown in each frame: N paths, or 1 path shown in every frame.
        poses: a ``scene.json`` (its frames' ``cam_to_world`` in order) or a COLMAP model folder,
            text (``cameras.txt``, ``images.txt``) or binary (``cameras.bin``, ``images.bin``), or a
            COLMAP project holding ``sparse/0``; images matched by file name.
        out: destination folder for the new scene.
        units: unit of the calibration's T (``mm`` or ``m``).
        proj_size: projector (width, height) when the calibration lacks it (default: the
            first pattern image's size).
        colmap_scale: metres per COLMAP unit. A COLMAP model has an arbitrary scale, but the
            projector baseline is metric, so the two must agree; set it from a known
            distance (e.g. the camera travel) — 1.0 assumes the model is in metres.
        bounds: ``(center [3], radius)`` in metres; default from the poses file's bounds,
            COLMAP's points3D.txt / .bin (median, 90th percentile distance x 1.2), or the
            point the cameras look at.
        lasers: laser-plane projectors (``fastneus.light.lasers.read_laser_planes``), lit in every
            frame; with lasers the calibration may hold the camera only and ``patterns``
            may be empty (a laser-only rig).

    Returns:
        The saved, validated scene.
    """
    images = [Path(p) for p in images]
    if not images:
        raise FastneusError("no images given", field="--images")
    n = len(images)
    pats = [Path(p) for p in (patterns if isinstance(patterns, (list, tuple)) else [patterns])]
    lasers = dict(lasers or {})
    if not pats and not lasers:
        raise FastneusError("no patterns given (and no laser planes)", field="--patterns")
    if pats and len(pats) not in (1, n):
        raise FastneusError(f"{len(pats)} patterns for {n} images: give one per image or one for all",
                            field="--patterns")
    wh0 = image_size(images[0])
    if wh0 is None:
        raise FastneusError("cannot read image", file=images[0], field="--images")
    for f, what in [(images[0], "--images")] + ([(pats[0], "--patterns")] if pats else []):
        wh = image_size(f) if f.is_file() else None
        if wh is not None and max(wh) > MAX_SIDE:  # a PNG header is read, not the pixels: it may claim anything
            raise FastneusError(f"image is {wh[0]}x{wh[1]}, more than the {MAX_SIDE} pixels a side fastneus reads",
                                file=f, field=what)
    if isinstance(calib, (tuple, list)) and len(calib) == 2 and isinstance(calib[0], Camera):
        cam, proj = calib
    else:
        # the pattern images are the projector's frame buffer: their size is its resolution
        cam, proj = read_procam_calibration(calib, proj_size=proj_size or (image_size(pats[0]) if pats else None),
                                            units=units, cam_size=wh0, require_projector=bool(pats))
    if proj is None and pats:
        raise FastneusError("patterns given but the calibration has no projector", field="--patterns")
    if (cam.width, cam.height) != wh0:
        raise FastneusError(f"image is {wh0[0]}x{wh0[1]} but the calibration's camera is "
                            f"{cam.width}x{cam.height}", file=images[0], field="--images")

    poses_path = Path(poses)
    center = radius = None
    if poses_path.is_dir() and not (poses_path / "scene.json").is_file():
        from fastneus.formats.colmap import model_files, read_colmap_model

        if colmap_scale <= 0:
            raise FastneusError("must be > 0", field="--colmap-scale")
        model = model_files(poses_path)  # text or binary, here or in sparse/0: errors name its files
        _, cimgs, pts = read_colmap_model(poses_path)
        c2ws = []
        for p in images:
            im = cimgs.get(p.name)
            if im is None:
                raise FastneusError(f"image {p.name!r} is not in the COLMAP model", file=model.images)
            T = im.cam_to_world
            T[:3, 3] *= colmap_scale
            c2ws.append(T)
        pose_of = [(model.images, p.name) for p in images]  # (file, field) named in errors
        if pts is not None and len(pts) >= 10:
            pts = pts * colmap_scale
            center = np.median(pts, axis=0)
            radius = 1.2 * float(np.percentile(np.linalg.norm(pts - center, axis=1), 90))
            bounds_of = (model.points3D, None)
    else:
        c2ws, b = _poses_from_scene_json(poses_path, n)
        sj = poses_path / "scene.json" if poses_path.is_dir() else poses_path
        pose_of = [(sj, f"frames[{i}].cam_to_world") for i in range(n)]
        if isinstance(b, dict) and "center" in b and "radius" in b:
            try:
                center, radius = np.asarray(b["center"], np.float64), float(b["radius"])
            except (TypeError, ValueError):
                raise FastneusError("expected {center: [x, y, z], radius: r}", file=sj, field="bounds") from None
            bounds_of = (sj, "bounds")
    if bounds is not None:
        center, radius = np.asarray(bounds[0], np.float64), float(bounds[1])
        bounds_of = (None, "--bounds")
    if center is None:
        center = axes_meeting_point(c2ws)
        radius = 0.5 * min(float(np.linalg.norm(T[:3, 3] - center)) for T in c2ws)
        bounds_of = (pose_of[0][0], None)
    # poses and bounds are checked here, naming the input they came from: the staged scene.json
    # validates them again, but its errors would name a staging file that no longer exists
    center = np.asarray(center, dtype=np.float64)
    if center.shape != (3,) or not np.all(np.isfinite(center)) or not (np.isfinite(radius) and radius > 0):
        derived = "" if bounds_of[1] else " (the region of interest derived from these poses; pass --bounds)"
        raise FastneusError(f"bounds need a finite centre [x, y, z] and radius > 0, got centre "
                            f"{center.tolist()}, radius {radius!r}{derived}", file=bounds_of[0], field=bounds_of[1])
    calib_file = None if isinstance(calib, (tuple, list)) and calib and isinstance(calib[0], Camera) else \
        Path(calib[0] if isinstance(calib, (tuple, list)) else calib)
    check_bounds_scale(center, radius, [(T, cam.K, cam.width) for T in c2ws], bounds_of[0], bounds_of[1])
    for T, (f, fld) in zip(c2ws, pose_of):
        check_faces_bounds(T, center, radius, "camera", f, fld)
        if proj is not None:
            check_faces_bounds(T @ proj.proj_to_cam, center, radius, "projector", calib_file or f,
                               "R, T (camera -> projector)" if calib_file else fld)

    # every input file is checked before anything is copied, naming the file the user gave
    for i, p in enumerate(images):
        wh = image_size(p) if p.is_file() else None
        if wh != (cam.width, cam.height):
            why = "image not found" if not p.is_file() else "cannot read image" if wh is None else \
                f"image is {wh[0]}x{wh[1]} but the calibration's camera is {cam.width}x{cam.height}"
            raise FastneusError(why, file=p, field="--images")
    for q in pats:
        wh = image_size(q) if q.is_file() else None
        if wh != (proj.width, proj.height):
            why = "pattern not found" if not q.is_file() else "cannot read image" if wh is None else \
                f"pattern is {wh[0]}x{wh[1]} but the projector is {proj.width}x{proj.height}"
            raise FastneusError(why, file=q, field="--patterns")

    out = Path(out)
    # built aside and moved in at the end: a failure leaves an earlier scene in ``out`` intact, and
    # files there that fastneus did not write are never replaced or removed (fastneus.io.staged_output)
    with staged_output(out) as stage:
        _write_calibrated_scene(stage, out.resolve().name, cam, proj, images, pats, c2ws, center, radius,
                                poses_path, lasers)
    return Scene.load(out)


def _write_calibrated_scene(out: Path, name: str, cam: Camera, proj: Projector | None, images: list[Path],
                            pats: list[Path], c2ws: list[np.ndarray], center, radius: float,
                            poses_path: Path, lasers: dict) -> None:
    """Copy photos and patterns into ``out`` and write its validated ``scene.json``."""
    (out / "image").mkdir(parents=True, exist_ok=True)
    (out / "pattern").mkdir(parents=True, exist_ok=True)
    frames, pat_ids = [], {}
    for i, p in enumerate(images):
        dst = f"image/{i:03d}{p.suffix.lower()}"
        shutil.copyfile(p, out / dst)
        laser_on = {lid: {"on": True} for lid in lasers}
        if not pats:
            frames.append({"image": dst, "camera": cam.id, "cam_to_world": c2ws[i].tolist(), "view": i,
                           "projectors": laser_on})
            continue
        q = pats[0 if len(pats) == 1 else i]
        key = str(q.resolve())
        if key not in pat_ids:
            pid = f"p{len(pat_ids):03d}"
            shutil.copyfile(q, out / f"pattern/{pid}{q.suffix.lower()}")
            pat_ids[key] = (pid, f"pattern/{pid}{q.suffix.lower()}")
        frames.append({"image": dst, "camera": cam.id, "cam_to_world": c2ws[i].tolist(), "view": i,
                       "projectors": {proj.id: {"pattern": pat_ids[key][0]}, **laser_on}})
    data = {"format": FORMAT, "version": VERSION, "units": "m", "name": name,
            "bounds": {"center": np.asarray(center).tolist(), "radius": float(radius)},
            "cameras": {cam.id: {"K": cam.K.tolist(), "width": cam.width, "height": cam.height,
                                 "dist": np.asarray(cam.dist).tolist()}},
            "projectors": {**({proj.id: {"K": proj.K.tolist(), "width": proj.width, "height": proj.height,
                                         "proj_to_cam": proj.proj_to_cam.tolist()}} if proj is not None else {}),
                           **{lid: {"kind": "laser", "proj_to_cam": np.asarray(lp.proj_to_cam).tolist(),
                                    "planes": planes_to_list(lp.planes)} for lid, lp in lasers.items()}},
            "patterns": {pid: {"file": f} for pid, f in pat_ids.values()},
            "frames": frames,
            "meta": {"source_format": "opencv-calibration", "poses": str(poses_path.resolve())}}
    Scene.from_dict(data, root=out).save(out)
