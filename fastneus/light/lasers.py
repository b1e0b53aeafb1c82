"""Laser-plane projectors: planes from a cross-laser layout, the plane calibration file read
by ``import-calib --laser-planes``, and the pattern-image approximation of a laser scene.

A laser line projector is calibrated as light planes (``fastneus.data.model.LaserPlane``):
unit normal n and offset d with n . X = d in the projector's frame, sheet thickness (FWHM,
world units), fan angle and fan axis, colour. fastneus evaluates the light of a point from
its distance to each plane (``fastneus.kernels.project.laser_light``), with no pattern image.

Plane calibration file (YAML or JSON), read by :func:`read_laser_planes`::

    units: mm                  # of offset and width (mm | cm | m; default: import-calib --units)
    lasers:
      laser0:
        proj_to_cam: [[...4x4...]]   # optional: laser frame -> camera (translation in `units`);
                                     # default identity = planes given in camera coordinates,
                                     # as laser-triangulation calibrations usually are
        planes:
          - {normal: [0.99, 0.0, -0.12], offset: 0.0, colour: [1, 0, 0], width: 1.0, fan_deg: 60,
             axis: [0, 0, 1]}       # axis: the fan's centre direction (default +z)
"""
from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np

from fastneus.data.model import LaserPlane, Projector, parse_planes, planes_to_list
from fastneus.data.validate import field_error, require
from fastneus.errors import FastneusError

UNITS = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}


def crosslaser_planes(K: np.ndarray, width: int, height: int, depth: float, seed: int = 0, count: int = 8,
                      line_width: int = 3) -> list[LaserPlane]:
    """The planes of ``fastneus.light.patterns.crosslaser``'s lines (same seed, same line positions):
    red vertical and green horizontal light sheets through the projector centre, sheet
    thickness = ``line_width`` pixels at ``depth`` (world units), fans spanning the image."""
    from fastneus.light.patterns import line_offset

    rng = np.random.default_rng(seed)
    ox = line_offset(rng, width / count, seed)
    oy = line_offset(rng, height / count, seed)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    thick = line_width * depth / fx
    fan_v = math.degrees(2 * math.atan(height / 2 / fy))  # a vertical sheet spans the image height
    fan_h = math.degrees(2 * math.atan(width / 2 / fx))
    planes = []
    for j in range(count):  # _lines: a line of odd width centred at pixel index c covers continuous c + 0.5
        xc = (j + 0.5) * (width / count) + ox + 0.5
        planes.append(LaserPlane(normal=_unit([1.0, 0.0, -(xc - cx) / fx]), offset=0.0, colour=np.array([1.0, 0, 0]),
                                 width=thick, fan_deg=fan_v))
    for j in range(count):
        yc = (j + 0.5) * (height / count) + oy + 0.5
        planes.append(LaserPlane(normal=_unit([0.0, 1.0, -(yc - cy) / fy]), offset=0.0, colour=np.array([0, 1.0, 0]),
                                 width=thick, fan_deg=fan_h))
    return planes


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


# ---------------------------------------------------------------- the laser's projector-kind hooks
# (registered in fastneus.data.kinds; signatures there)
def parse_laser_projector(entry: dict, file, fld: str) -> dict:
    """The planes of a laser projector's scene.json entry (behind a flat port its sheets would bend:
    not modelled)."""
    if entry.get("port") is not None:
        raise field_error("a laser projector behind a flat port is not modelled (its light sheets bend "
                          "at the port)", file, f"{fld}.port")
    return {"planes": parse_planes(require(entry, "planes", file, fld), file, f"{fld}.planes")}


def laser_projector_to_dict(p: Projector) -> dict:
    return {"planes": planes_to_list(p.planes)}


def pack_laser_projectors(projectors: list[Projector | None], device):
    """[P, L, 12] planes for ``laser_light`` (None: a projector of another kind, no planes)."""
    from fastneus.kernels.project import pack_planes  # on use: loading a scene must not pay for torch

    return pack_planes([None if p is None else p.planes for p in projectors], device)


def laser_synth_light(points, world_to_proj: np.ndarray, projector: Projector):
    """[N, 3] light of a laser projector at world points (``fastneus synth``)."""
    return light_at_points(points, world_to_proj, projector.planes)


def light_at_points(points, world_to_proj: np.ndarray, planes: list[LaserPlane]):
    """[N, 3] light of one laser projector at points (its own frame = ``world_to_proj`` of them),
    through the torch twin of the kernel (same maths as training)."""
    import torch  # on use: loading a scene (which parses laser projectors here) must not pay for torch

    from fastneus.kernels.project import laser_light_torch, pack_planes

    n = points.shape[0]
    idx = torch.arange(n, dtype=torch.int32, device=points.device)
    W = torch.as_tensor(np.asarray(world_to_proj)[:3], dtype=points.dtype, device=points.device)[None, None]
    return laser_light_torch(points, idx, idx, torch.ones(n, dtype=torch.int32, device=points.device),
                             torch.zeros(n, dtype=torch.int32, device=points.device), W,
                             torch.ones((1, 1), dtype=torch.int32, device=points.device),
                             pack_planes([planes], points.device).to(points.dtype))


def planes_to_pattern(planes: list[LaserPlane], K: np.ndarray, width: int, height: int, depth: float) -> np.ndarray:
    """uint8 [H, W, 3] pattern image approximating the planes: each pixel shows the light the
    planes put on the point of its ray at ``depth`` (exact there; lines keep their angular width
    at other depths, where a real sheet keeps its metric thickness)."""
    v, u = np.mgrid[0:height, 0:width]
    rays = np.stack([u.ravel() + 0.5, v.ravel() + 0.5, np.ones(u.size)], 1) @ np.linalg.inv(K).T
    import torch  # on use: see light_at_points

    pts = torch.tensor(rays / rays[:, 2:] * depth, dtype=torch.float64)
    q = light_at_points(pts, np.eye(4), planes).numpy().reshape(height, width, 3)
    return np.clip(np.round(q * 255), 0, 255).astype(np.uint8)


def pattern_approximation(scene, out, width: int, height: int, hfov_deg: float, depth: float):
    """A copy of a laser scene whose laser projectors become pattern projectors (pinhole K of
    ``hfov_deg``, ``width`` x ``height``) showing :func:`planes_to_pattern` images: the
    approximation a pattern-only tool must use. Saved in ``out`` (images shared by path).

    Pattern files are named ``patterns/<projector id>_planes.png``; the id must be a safe id
    (:data:`fastneus.data.validate.SAFE_ID`) and each destination is checked to lie inside ``out``.
    """
    from fastneus.data.model import Pattern
    from fastneus.data.scene import Scene
    from fastneus.data.validate import check_id
    from fastneus.io import safe_dest
    from fastneus.light.patterns import write_png
    from fastneus.geometry.cameras import projector_intrinsics

    import os

    out = Path(out)
    sj = Path(scene.root) / "scene.json"
    for pid in scene.projectors:  # before anything is written
        check_id(pid, sj, "projectors")
    (out / "patterns").mkdir(parents=True, exist_ok=True)
    s = copy.deepcopy(scene)
    K = projector_intrinsics(width, height, hfov_deg)
    for pid, pj in scene.projectors.items():
        if pj.kind != "laser":
            continue
        qid = check_id(f"{pid}_planes", sj, "projectors")
        dst = safe_dest(out, f"patterns/{qid}.png", file=sj, field=f"projectors.{pid}")
        write_png(dst, planes_to_pattern(pj.planes, K, width, height, depth))
        s.projectors[pid] = Projector(id=pid, K=K, width=width, height=height, proj_to_cam=pj.proj_to_cam)
        # paths in a scene are relative to its root; save() rewrites them relative to `out`
        s.patterns[qid] = Pattern(id=qid, file=os.path.relpath(dst, Path(s.root).resolve()))
        for f in s.frames:
            fp = f.projectors.get(pid)
            if fp is not None:
                fp.pattern, fp.on = (qid if fp.on else None), True
    s.meta = dict(s.meta, approximation=f"laser planes as pattern images at depth {depth:g}")
    s.save(out)
    return Scene.load(out)


def read_laser_planes(path, units: str = "mm") -> dict[str, Projector]:
    """Laser projectors from a plane calibration file (layout in the module docstring), in metres.

    Raises:
        FastneusError: naming the file and field of the first problem.
    """
    import yaml

    from fastneus.data.validate import check_id, check_pose

    path = Path(path)
    if not path.is_file():
        raise FastneusError("laser plane file not found", file=path)
    try:
        d = yaml.safe_load(path.read_text(encoding="utf-8"))  # YAML is a superset of JSON
    except UnicodeDecodeError as e:
        raise FastneusError(f"cannot read: not UTF-8 text (byte {e.start})", file=path) from None
    except (OSError, ValueError, yaml.YAMLError) as e:
        raise FastneusError(f"cannot read: {str(e).splitlines()[0][:200]}", file=path) from None
    except RecursionError:
        raise FastneusError("cannot read: nested too deeply", file=path) from None
    if not isinstance(d, dict) or not isinstance(d.get("lasers"), dict) or not d["lasers"]:
        raise FastneusError("expected a mapping with a non-empty 'lasers' mapping", file=path, field="lasers")
    u = d.get("units", units)
    if not isinstance(u, str) or u not in UNITS:
        raise FastneusError(f"unknown units {u!r}; use mm, cm or m", file=path, field="units")
    s = UNITS[u]
    out = {}
    for lid, e in d["lasers"].items():
        lid = check_id(str(lid), path, "lasers")  # becomes a projector id (pattern_approximation names files by it)
        fld = f"lasers.{lid}"
        if not isinstance(e, dict):
            raise FastneusError("expected a mapping", file=path, field=fld)
        planes = parse_planes(e.get("planes"), path, f"{fld}.planes")
        for p in planes:
            p.offset *= s
            p.width *= s
        T = np.eye(4)
        if e.get("proj_to_cam") is not None:
            T = check_pose(e["proj_to_cam"], path, f"{fld}.proj_to_cam").copy()
            T[:3, 3] *= s
        out[str(lid)] = Projector(id=str(lid), K=np.eye(3), width=1, height=1, proj_to_cam=T, planes=planes)
    return out
