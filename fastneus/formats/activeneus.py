"""Read and write the official ActiveNeuS scene format (``cameras_sphere.npz`` + PNG folders).

Layout (see ``FORMAT-activeneus.md``): ``image/NNN.png``, ``mask/NNN.png``,
``pattern/NNN_KK.png`` (frame NNN, projector KK) and ``cameras_sphere.npz`` with, per
frame i, ``cam_mat_i`` [4,4] (K padded), ``cam_pose_i`` [4,4] world->camera,
``scale_mat_i`` [4,4] normalised->world, ``proj_mat_i`` [P,4,4] projector K,
``cam_proj_pose_i`` [P,4,4] camera->projector, plus ``illumination_params`` (a 0-d
object array holding {ambient, diffuse, emissive}), ``aabb``, ``near``, ``far``.

Conventions that differ from fastneus:
- camera pixels: the format puts integer pixel centres at integer coords, fastneus at
  +0.5, so reading shifts the camera principal point by +0.5 (writing by -0.5);
- projector pixels: the official code samples patterns with ``grid_sample(align_corners=
  False)``, i.e. the fastneus convention already, so projector K is copied unchanged;
- flat ports: optional ``camera_refraction`` {normal: [nx, ny], depth, mu} (all cameras) and
  ``projector_refraction`` (one per projector) describe a thin interface whose plane is
  n . X = |n|^2 depth with n = (nx, ny, 1) (camera frame, world units) and index ratio
  mu = n_water / n_air; they become fastneus ports with unit normal n / |n|, distance
  |n| depth, no glass (and are written back from such ports).
"""
from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Any

import numpy as np

from fastneus.data.images import image_size
from fastneus.data.scene import FORMAT, VERSION, Scene
from fastneus.data.validate import check_faces_bounds, check_intrinsics, check_pose
from fastneus.errors import FastneusError
from fastneus.formats.safe_npz import npz_array, open_npz, read_number_dict, read_pickled_value
from fastneus.geometry.cameras import rigid_inverse
from fastneus.data.kinds import get_projector_kind

NPZ = "cameras_sphere.npz"
IMG_EXT = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
SAME_TOL = 1e-6  # per-frame matrices equal within this are treated as one rig


# --------------------------------------------------------------------------- helpers
def image_files(folder: Path) -> list[Path]:
    """Sorted image files of ``folder`` (frame i = i-th file; names are not parsed)."""
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMG_EXT and p.is_file())


def npz_matrix(npz, key: str, shape: tuple[int, ...], file: Path) -> np.ndarray:
    """A finite float64 array ``npz[key]`` of exactly ``shape`` (-1 = any length)."""
    a = npz_array(npz, key, file)
    try:
        a = np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError):
        raise FastneusError(f"expected a numeric array of shape {shape}", file=file, field=key) from None
    if a.ndim != len(shape) or any(s != -1 and s != t for s, t in zip(shape, a.shape)):
        want = "x".join("P" if s == -1 else str(s) for s in shape)
        raise FastneusError(f"expected shape {want}, got {'x'.join(map(str, a.shape)) or 'scalar'}",
                            file=file, field=key)
    if not np.all(np.isfinite(a)):
        raise FastneusError("contains non-finite values (nan/inf)", file=file, field=key)
    return a


def _digest(path: Path) -> str:
    return hashlib.sha1(path.read_bytes()).hexdigest()


def group_equal(mats: list[np.ndarray]) -> list[int]:
    """Index of the first matrix equal (within SAME_TOL) to each one: identical -> one id."""
    out: list[int] = []
    for i, m in enumerate(mats):
        j = next((j for j in range(i) if out[j] == j and np.allclose(mats[j], m, atol=SAME_TOL, rtol=0)), i)
        out.append(j)
    return out


def rel_posix(path: Path, root: Path) -> str:
    return Path(os.path.relpath(path, root)).as_posix()


# --------------------------------------------------------------------------- flat ports
def _port_dict(d: Any, file: Path, fld: str) -> dict:
    """The format's {normal: [nx, ny], depth, mu} -> a fastneus ``port`` object (see module doc)."""
    if not isinstance(d, dict) or not {"normal", "depth", "mu"} <= set(d):
        raise FastneusError("expected {normal: [nx, ny], depth, mu}", file=file, field=fld)
    try:
        nxy = np.asarray(d["normal"], dtype=np.float64).reshape(-1)
        depth, mu = float(d["depth"]), float(d["mu"])
    except (TypeError, ValueError):
        raise FastneusError("expected numbers", file=file, field=fld) from None
    if nxy.shape != (2,) or not np.all(np.isfinite(nxy)) or not np.isfinite(depth) or not np.isfinite(mu):
        raise FastneusError("expected normal [nx, ny] and finite depth, mu", file=file, field=fld)
    n = np.array([nxy[0], nxy[1], 1.0])
    ln = float(np.linalg.norm(n))
    return {"normal": (n / ln).tolist(), "distance": max(depth * ln, 1e-6),  # the official code uses relu(depth)
            "thickness": 0.0, "n_air": 1.0, "n_glass": mu, "n_water": mu}


def _port_in(npz, key: str, file: Path) -> dict | None:
    if key not in npz.files:
        return None
    # a pickled dict in the official format: decoded by the restricted unpickler (never np.load's)
    return _port_dict(read_pickled_value(npz, key, file, "expected {normal: [nx, ny], depth, mu}"), file, key)


def _port_out(port, where: str) -> dict:
    """A thin fastneus port -> the format's {normal: [nx, ny], depth, mu}."""
    if port.thickness != 0 or port.n_air != 1.0:
        raise FastneusError("the ActiveNeuS format holds thin ports in air (thickness 0, n_air 1) only", field=where)
    n = np.asarray(port.normal, dtype=np.float64)
    return {"normal": [float(n[0] / n[2]), float(n[1] / n[2])], "depth": float(port.distance * n[2]),
            "mu": float(port.n_water)}


# --------------------------------------------------------------------------- reading
def open_npz_folder(root: Path):
    """Open ``root/cameras_sphere.npz`` and list ``image/`` and ``mask/`` (shared by the
    ActiveNeuS and NeuS readers).

    Returns:
        (npz path, loaded npz, sorted image paths, sorted mask paths (may be empty)).
    """
    npz_path = root / NPZ
    if not npz_path.is_file():
        raise FastneusError("missing camera file", file=npz_path)
    npz = open_npz(npz_path)  # never unpickles: scenes are untrusted
    images = image_files(root / "image")
    if not images:
        raise FastneusError("no images found (expected image/NNN.png)", file=root / "image")
    masks = image_files(root / "mask")
    if masks and len(masks) != len(images):
        raise FastneusError(f"{len(masks)} masks for {len(images)} images", file=root / "mask")
    return npz_path, npz, images, masks


def read_activeneus(path: str | os.PathLike) -> Scene:
    """Read an ActiveNeuS scene folder into a validated in-memory :class:`Scene`.

    The scene's root is the folder itself (paths are relative to it) and nothing is
    written there, so read-only folders work. Cameras with equal K share one camera;
    projectors whose K and camera->projector pose are the same in every frame become
    rig-attached (``proj_to_cam``), otherwise free projectors with per-frame poses.
    Pattern files identical across frames become one shared pattern.

    Args:
        path: the folder holding ``cameras_sphere.npz``, ``image/``, ``mask/``, ``pattern/``.

    Returns:
        The scene (frame i = i-th sorted file of ``image/``).

    Raises:
        FastneusError: one line naming the file and key of the first problem.
    """
    root = Path(path)
    npz_path, npz, images, masks = open_npz_folder(root)
    n = len(images)

    # patterns: pattern/NNN_KK.png grouped by the part before the last "_"
    pat_files: dict[str, list[Path]] = {}
    for p in image_files(root / "pattern"):
        stem, sep, _ = p.stem.rpartition("_")
        if not sep:
            raise FastneusError("pattern files must be named NNN_KK.png (frame_projector)", file=p)
        pat_files.setdefault(stem, []).append(p)
    pat_groups = [pat_files[k] for k in sorted(pat_files)]

    # per-frame matrices
    Ks, poses, Ss, PKs, CPs = [], [], [], [], []
    for i in range(n):
        Ks.append(check_intrinsics(npz_matrix(npz, f"cam_mat_{i}", (4, 4), npz_path)[:3, :3], npz_path, f"cam_mat_{i}"))
        poses.append(check_pose(npz_matrix(npz, f"cam_pose_{i}", (4, 4), npz_path), npz_path, f"cam_pose_{i}"))
        Ss.append(npz_matrix(npz, f"scale_mat_{i}", (4, 4), npz_path))
        has_proj = f"proj_mat_{i}" in npz.files or f"cam_proj_pose_{i}" in npz.files
        PKs.append(npz_matrix(npz, f"proj_mat_{i}", (-1, 4, 4), npz_path) if has_proj else np.zeros((0, 4, 4)))
        CPs.append(npz_matrix(npz, f"cam_proj_pose_{i}", (-1, 4, 4), npz_path) if has_proj else np.zeros((0, 4, 4)))
        for k in range(len(CPs[i])):
            check_pose(CPs[i][k], npz_path, f"cam_proj_pose_{i}[{k}]")
        for k in range(len(PKs[i])):
            check_intrinsics(PKs[i][k][:3, :3], npz_path, f"proj_mat_{i}[{k}]")
        if len(PKs[i]) != len(CPs[i]):
            raise FastneusError(f"{len(CPs[i])} projector poses but proj_mat_{i} has {len(PKs[i])}",
                                file=npz_path, field=f"cam_proj_pose_{i}")
        if len(PKs[i]) != len(PKs[0]):
            raise FastneusError(f"{len(PKs[i])} projectors but frame 0 has {len(PKs[0])}; every frame "
                                "needs the same projectors", file=npz_path, field=f"proj_mat_{i}")
    P = len(PKs[0])

    S = Ss[0]
    s = S[0, 0]
    if not (s > 0 and np.allclose(S[:3, :3], s * np.eye(3), rtol=1e-6, atol=1e-9)
            and np.allclose(S[3], [0, 0, 0, 1])):
        raise FastneusError("expected [[s I, c], [0, 1]] with s > 0 (isotropic scale + offset)",
                            file=npz_path, field="scale_mat_0")
    for i in range(1, n):
        if not np.allclose(Ss[i], S, rtol=1e-6, atol=1e-9):
            raise FastneusError("differs from scale_mat_0; all frames must share one normalisation",
                                file=npz_path, field=f"scale_mat_{i}")
    # named by npz key here (Scene validation would name scene.json fields)
    for i in range(n):
        c2w = rigid_inverse(poses[i])
        check_faces_bounds(c2w, S[:3, 3], s, "camera", npz_path, f"cam_pose_{i}")
        for k in range(len(CPs[i])):
            check_faces_bounds(c2w @ rigid_inverse(CPs[i][k]), S[:3, 3], s, "projector", npz_path,
                               f"cam_proj_pose_{i}[{k}]")

    # pattern files: frame i uses group i; a single group (or identical groups) is shared
    if P and not pat_groups:
        raise FastneusError(f"missing pattern files: frame 0 has {P} projector(s) but no pattern/000_00.png",
                            file=root / "pattern", field="proj_mat_0")
    for g, files in zip(sorted(pat_files), pat_groups):
        if len(files) != P:
            raise FastneusError(f"frame {g} has {len(files)} pattern file(s) but the npz has {P} projector(s) "
                                f"(pattern counts must match in every frame)", file=root / "pattern",
                                field=f"{g}_KK.png")
    if P and len(pat_groups) not in (1, n):
        stems = [im.stem for im in images]
        missing = [st for st in stems if st not in pat_files]
        if set(pat_files) <= set(stems) and missing:
            raise FastneusError(f"missing pattern file(s) for frame {missing[0]} ({P} projector(s) in the npz)",
                                file=root / "pattern" / f"{missing[0]}_00.png",
                                field=f"proj_mat_{stems.index(missing[0])}")
        raise FastneusError(f"pattern files for {len(pat_groups)} frames but there are {n} images "
                            f"(expected one NNN_KK.png set per frame, or one for all)",
                            file=root / "pattern")
    if P and len(pat_groups) == n:
        shared = all(_digest(pat_groups[i][k]) == _digest(pat_groups[0][k])
                     for i in range(1, n) for k in range(P))
    else:
        shared = True

    # cameras: one per distinct K (pixel centre shift +0.5 to fastneus convention)
    cam_of = group_equal(Ks)
    cameras: dict[str, Any] = {}
    cam_ids: list[str] = []
    for i in range(n):
        cid = "cam0" if cam_of[i] == 0 else f"cam{cam_of[i]:03d}"
        cam_ids.append(cid)
        if cid in cameras:
            continue
        wh = image_size(images[i])
        if wh is None:
            raise FastneusError("cannot read image", file=images[i])
        K = Ks[i].copy()
        K[0, 2] += 0.5
        K[1, 2] += 0.5
        cameras[cid] = {"K": K.tolist(), "width": wh[0], "height": wh[1], "dist": [0.0] * 5}

    # projectors: rig-attached when K and cam->proj pose are constant over frames
    projectors: dict[str, Any] = {}
    rig = [all(np.allclose(PKs[i][k], PKs[0][k], atol=SAME_TOL, rtol=0)
               and np.allclose(CPs[i][k], CPs[0][k], atol=SAME_TOL, rtol=0) for i in range(n)) for k in range(P)]
    proj_id: list[list[str]] = [[] for _ in range(n)]  # [frame][k] -> projector id
    patterns: dict[str, Any] = {}
    for k in range(P):
        files0 = pat_groups[0][k] if P else None
        pw, ph = image_size(files0) or (0, 0)
        if rig[k]:
            pid = f"proj{k}"
            projectors[pid] = {"K": PKs[0][k][:3, :3].tolist(), "width": pw, "height": ph,
                               "proj_to_cam": np.linalg.inv(CPs[0][k]).tolist()}
            for i in range(n):
                proj_id[i].append(pid)
        else:
            kgroup = group_equal([PKs[i][k][:3, :3] for i in range(n)])
            for i in range(n):
                pid = f"proj{k}" if kgroup[i] == 0 else f"proj{k}_{kgroup[i]:03d}"
                projectors.setdefault(pid, {"K": PKs[i][k][:3, :3].tolist(), "width": pw, "height": ph,
                                            "proj_to_cam": None})
                proj_id[i].append(pid)

    frames = []
    for i in range(n):
        w2c = poses[i]
        c2w = np.linalg.inv(w2c)
        fp: dict[str, Any] = {}
        for k in range(P):
            g = pat_groups[0 if shared or len(pat_groups) == 1 else i]
            qid = f"p{k:02d}" if shared or len(pat_groups) == 1 else f"f{i:03d}_p{k:02d}"
            patterns.setdefault(qid, {"file": rel_posix(g[k], root)})
            e: dict[str, Any] = {"pattern": qid}
            if not rig[k]:
                e["proj_to_world"] = (c2w @ np.linalg.inv(CPs[i][k])).tolist()
            fp[proj_id[i][k]] = e
        frames.append({"image": rel_posix(images[i], root), "camera": cam_ids[i], "cam_to_world": c2w.tolist(),
                       "projectors": fp, "view": i, **({"mask": rel_posix(masks[i], root)} if masks else {})})
    # frames with the same pose and camera are one viewpoint (multi-shot sequences)
    for i in range(n):
        for j in range(i):
            if cam_ids[j] == cam_ids[i] and np.allclose(poses[j], poses[i], atol=SAME_TOL, rtol=0):
                frames[i]["view"] = frames[j]["view"]
                break

    illum = {"i_r": 0.4, "i_b": 0.1, "ambient": 1.0, "known": False}
    if "illumination_params" in npz.files:
        # the official format pickles this dict: decoded by a restricted unpickler
        ip = read_number_dict(npz, "illumination_params", npz_path)
        for key, name in (("diffuse", "i_r"), ("emissive", "i_b"), ("ambient", "ambient")):
            if key not in ip:
                raise FastneusError("missing key", file=npz_path, field=f"illumination_params.{key}")
            if not np.isfinite(ip[key]):
                raise FastneusError(f"expected a finite number, got {ip[key]!r}", file=npz_path,
                                    field=f"illumination_params.{key}")
            illum[name] = ip[key]

    cam_port = _port_in(npz, "camera_refraction", npz_path)
    if cam_port is not None:
        for c in cameras.values():
            c["port"] = cam_port
    if "projector_refraction" in npz.files:
        lst = read_pickled_value(npz, "projector_refraction", npz_path,
                                 "expected a list of {normal: [nx, ny], depth, mu}", vector=True)
        if not isinstance(lst, (list, tuple)):
            raise FastneusError("expected a list of {normal: [nx, ny], depth, mu}", file=npz_path,
                                field="projector_refraction")
        if len(lst) != P:
            raise FastneusError(f"{len(lst)} entries for {P} projector(s)", file=npz_path, field="projector_refraction")
        for k in range(P):
            pp = _port_dict(lst[k], npz_path, f"projector_refraction[{k}]")
            for pid, pr in projectors.items():
                if pid == f"proj{k}" or pid.startswith(f"proj{k}_"):
                    pr["port"] = pp

    data = {"format": FORMAT, "version": VERSION, "units": "m", "name": root.resolve().name,
            "bounds": {"center": S[:3, 3].tolist(), "radius": float(s)},
            "cameras": cameras, "projectors": projectors, "patterns": patterns, "frames": frames,
            "illumination": illum, "meta": {"source_format": "activeneus", "source": str(root.resolve())}}
    return Scene.from_dict(data, root=root, file=npz_path)


# --------------------------------------------------------------------------- writing
def write_activeneus(scene: Scene, out: str | os.PathLike, downscale: int = 1) -> Path:
    """Write ``scene`` as an ActiveNeuS folder (``cameras_sphere.npz``, image/, mask/, pattern/).

    Images are written undistorted (``Scene.image`` undistorts), as BGR PNG of their linear light
    (the format's photos are linear: ``auto``'s response decodes any other encoding, 16-bit
    photos included, before they are written). Projectors
    must be rig-attached (the format stores camera->projector per frame and the official
    code uses frame 0's); a projector that is off in a frame gets a black pattern
    (Q = 0, the same image formation). ``illumination_params`` holds the scene's
    ambient / i_r / i_b (our colour network D includes the ambient, so ambient = 1.0
    unless the scene says otherwise).

    Args:
        scene: the scene to write.
        out: destination folder (created; existing files of the same names are replaced).
        downscale: integer factor to shrink camera images, masks and camera K (projectors
            unchanged); 1 = full size. Handy for fast CPU runs.

    Returns:
        The path of the written npz.

    Raises:
        FastneusError: free (non rig-attached) projectors, a bad ``downscale``, or a file in
            ``out`` that fastneus did not write would be replaced (built aside and swapped in by
            :func:`fastneus.io.staged_output`: such files are never touched).
    """
    from fastneus.io import staged_output

    out = Path(out)
    if out.resolve() == Path(scene.root).resolve():
        raise FastneusError("output folder is the input folder; choose another --out", file=out)
    with staged_output(out) as stage:
        _write_activeneus(scene, stage, downscale)
    return out / NPZ


def _write_activeneus(scene: Scene, out: Path, downscale: int) -> None:
    """:func:`write_activeneus` into a fresh (staging) folder ``out``; files are named by index."""
    lights = [p for p, pj in scene.projectors.items() if not get_projector_kind(pj.kind).images]
    if lights:
        noun = get_projector_kind(scene.projectors[lights[0]].kind).noun
        raise FastneusError(f"{noun} projectors ({', '.join(lights)}) have no ActiveNeuS form; keep the "
                            "fastneus format", field=f"projectors.{lights[0]}")
    import cv2

    from fastneus.io import atomic_write, atomic_write_image

    if int(downscale) != downscale or downscale < 1:
        raise FastneusError(f"downscale must be an integer >= 1, got {downscale!r}", field="downscale")
    downscale = int(downscale)
    small = [c for c in scene.cameras.values() if min(c.width, c.height) < downscale]
    if small:  # cv2.resize would fail on a 0-pixel image half-way through the copy
        c = small[0]
        raise FastneusError(f"{downscale} shrinks camera {c.id}'s {c.width}x{c.height} images to nothing (at most "
                            f"{min(c.width, c.height)})", field="downscale")
    free = [p.id for p in scene.projectors.values() if p.proj_to_cam is None]
    if free:
        raise FastneusError(f"the ActiveNeuS format needs projectors rigidly attached to the camera; "
                            f"{free} have per-frame poses (proj_to_cam null)", file=Path(scene.root) / "scene.json",
                            field=f"projectors.{free[0]}.proj_to_cam")
    for sub in ("image", "mask", "pattern"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    pids = list(scene.projectors)
    S = scene.normalisation()
    arrays: dict[str, Any] = {}
    has_mask = any(f.mask is not None for f in scene.frames)
    pattern_cache: dict[str, np.ndarray] = {}
    from fastneus.data.response import decode, encode_u8, is_identity, resolve_response

    # what Scene.image's codes mean (as training decodes them); the format's photos are linear light
    response = resolve_response(scene, list(range(len(scene.frames))), "auto")[0]
    for i, f in enumerate(scene.frames):
        cam = scene.frame_camera(i)
        im = scene.image(i)
        if not is_identity(response):
            im = encode_u8(decode(im / 255.0, response), "linear")
        K = cam.K.copy()
        if downscale > 1:
            h, w = im.shape[:2]
            size = (w // downscale, h // downscale)
            im = cv2.resize(im, size, interpolation=cv2.INTER_AREA)
            # continuous coords (corner origin, fastneus convention) scale exactly by 1/f
            K[:2] /= downscale
        atomic_write_image(out / "image" / f"{i:03d}.png", im)
        if has_mask:
            m = scene.mask(i)
            if m is None:  # the format needs all or none: a missing mask means "all object"
                m = np.ones(im.shape[:2], np.float32)
            elif downscale > 1:
                m = cv2.resize(m, (im.shape[1], im.shape[0]), interpolation=cv2.INTER_AREA)
            atomic_write_image(out / "mask" / f"{i:03d}.png", np.round(np.clip(m, 0, 1) * 255).astype(np.uint8))
        Kf = np.eye(4)
        Kf[:3, :3] = K
        Kf[0, 2] -= 0.5  # fastneus pixel centres (+0.5) -> the format's integer centres
        Kf[1, 2] -= 0.5
        arrays[f"cam_mat_{i}"] = Kf
        arrays[f"cam_pose_{i}"] = scene.world_to_cam(i)
        arrays[f"scale_mat_{i}"] = S
        PK = np.tile(np.eye(4), (len(pids), 1, 1))
        CP = np.tile(np.eye(4), (len(pids), 1, 1))
        for k, pid in enumerate(pids):
            pj = scene.projectors[pid]
            PK[k, :3, :3] = pj.K
            CP[k] = rigid_inverse(pj.proj_to_cam)
            fp = f.projectors.get(pid)
            qid = fp.pattern if fp is not None else None
            if qid is None:
                pat = np.zeros((pj.height, pj.width, 3), np.uint8)
            else:
                if qid not in pattern_cache:
                    pattern_cache[qid] = scene.pattern_image(qid)
                pat = pattern_cache[qid]
            atomic_write_image(out / "pattern" / f"{i:03d}_{k:02d}.png", pat)
        arrays[f"proj_mat_{i}"] = PK
        arrays[f"cam_proj_pose_{i}"] = CP
    ports = {(c.port.row() if c.port is not None else None).__repr__(): c for c in scene.cameras.values()}
    if any(c.port is not None for c in scene.cameras.values()):
        if len(ports) != 1:
            raise FastneusError("the ActiveNeuS format holds one camera port for all cameras", field="cameras.port")
        arrays["camera_refraction"] = np.array(_port_out(next(iter(ports.values())).port, "cameras.port"),
                                               dtype=object)
    if any(scene.projectors[p].port is not None for p in pids):
        if any(scene.projectors[p].port is None for p in pids):
            raise FastneusError("the ActiveNeuS format needs a port on every projector or none",
                                field="projectors.port")
        arrays["projector_refraction"] = np.array([_port_out(scene.projectors[p].port, f"projectors.{p}.port")
                                                   for p in pids], dtype=object)
    il = scene.illumination
    arrays["illumination_params"] = np.array({"ambient": float(il.ambient), "diffuse": float(il.i_r),
                                              "emissive": float(il.i_b)}, dtype=object)
    centres = np.array([scene.cam_to_world(i)[:3, 3] for i in range(len(scene.frames))])
    dist = np.linalg.norm(centres - scene.bounds.center, axis=1)
    r = float(scene.bounds.radius)
    arrays["aabb"] = np.array({"center": np.asarray(scene.bounds.center, np.float64),
                               "extent": np.full(3, 2.0 * r)}, dtype=object)
    # stored for completeness (the official code does not read them): world-unit depth range
    arrays["near"] = np.float32(max(float(dist.min()) - r, 1e-3))
    arrays["far"] = np.float32(float(dist.max()) + r)

    # (a previous, longer scene's extra frames are removed at the swap: they are in its manifest)

    def w(tmp: str) -> None:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
    atomic_write(out / NPZ, w)
