"""The elements of a scene: cameras, projectors (pattern or laser planes), patterns, frames,
bounds, illumination, flat ports; parsing and serialising the nested ones (ports, planes).

Conventions (docs/INTERNALS.md): OpenCV pinhole axes, poses are 4x4 ``cam_to_world`` /
``proj_to_world`` in world units (metres), ``x_world = radius * x_norm + center``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fastneus.data.validate import as_dict, as_matrix, as_num, field_error, require


@dataclass
class FlatPort:
    """A flat port in front of a device in water (its own frame, world units): the glass's
    inner face is ``normal . X = distance`` (normal unit, pointing into the water), then
    ``thickness`` of glass, then water; refractive indices of air (inside), glass, water."""

    normal: np.ndarray  # [3] unit
    distance: float
    thickness: float = 0.0
    n_air: float = 1.0
    n_glass: float = 1.5
    n_water: float = 1.333

    def row(self) -> list[float]:
        """The kernel's 8-float row (``fastneus.kernels.project.port_row``)."""
        from fastneus.kernels.project import port_row

        return port_row(self.normal, self.distance, self.thickness, self.n_air, self.n_glass, self.n_water)


@dataclass
class Camera:
    """Pinhole camera intrinsics. ``K`` maps camera coords to continuous pixel coords."""

    id: str
    K: np.ndarray  # [3, 3] float64
    width: int
    height: int
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))  # [5] k1 k2 p1 p2 k3
    port: FlatPort | None = None  # underwater housing


@dataclass
class LaserPlane:
    """One light plane of a laser line projector, in the projector's frame (world units).

    Points X with ``normal . X = offset`` are on the plane's centre; the light falls off as a
    Gaussian of the distance to it with full width at half maximum ``width``, and exists only
    inside the fan: the angle between X's in-plane direction and ``axis`` (projected onto the
    plane) is at most ``fan_deg / 2``.
    """

    normal: np.ndarray  # [3] unit
    offset: float
    colour: np.ndarray  # [3] RGB in [0, 1]
    width: float        # FWHM of the sheet thickness (world units)
    fan_deg: float      # full fan angle (degrees)
    axis: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))  # [3] fan centre direction


@dataclass
class Projector:
    """Projector intrinsics; ``proj_to_cam`` [4,4] rigs it to the frame's camera, None = free.

    ``kind`` names its entry in :mod:`fastneus.data.kinds` (default: ``laser`` when ``planes``
    are given, else ``pattern``). A projector of a kind other than ``pattern`` has no image: K
    is the identity and the size 1 x 1 in memory, and its light comes from its kind's light op
    (the laser's from ``planes``; other kinds keep their own fields in ``params``)."""

    id: str
    K: np.ndarray  # [3, 3] float64
    width: int
    height: int
    proj_to_cam: np.ndarray | None = None  # [4, 4] float64 or None (pose given per frame)
    planes: list[LaserPlane] | None = None
    port: FlatPort | None = None  # underwater housing
    kind: str = ""
    params: dict = field(default_factory=dict)  # kind-specific fields of kinds without an attribute here

    def __post_init__(self):
        if not self.kind:
            self.kind = "laser" if self.planes is not None else "pattern"


@dataclass
class Pattern:
    """A pattern image file (path relative to the scene folder)."""

    id: str
    file: str


@dataclass
class FrameProjector:
    """What one projector does in one frame: the pattern shown (None = off), free pose;
    a laser projector has no pattern and is lit when ``on``."""

    pattern: str | None = None
    proj_to_world: np.ndarray | None = None  # [4, 4] float64, only for free projectors
    on: bool = True  # laser projectors only


@dataclass
class Frame:
    """One photograph. Frames sharing ``view`` share a viewpoint (multi-shot sequences)."""

    image: str
    camera: str
    cam_to_world: np.ndarray  # [4, 4] float64
    projectors: dict[str, FrameProjector] = field(default_factory=dict)
    mask: str | None = None
    view: int = 0
    gt: dict[str, str] = field(default_factory=dict)  # optional: depth, normal, clean


@dataclass
class Bounds:
    """Normalisation: ``x_world = radius * x_norm + center``; the unit sphere holds the object."""

    center: np.ndarray  # [3] float64
    radius: float


@dataclass
class Illumination:
    """Pattern-projection parameters; ``known`` marks ground truth (synthetic data)."""

    i_r: float = 0.4
    i_b: float = 0.1
    ambient: float = 1.0
    known: bool = False


def to_list(a: np.ndarray | None):
    return None if a is None else np.asarray(a, dtype=np.float64).tolist()


def parse_planes(value: Any, file, fld: str) -> list[LaserPlane]:
    """Validate a list of plane objects {normal, offset, colour, width, fan_deg[, axis]}.

    The normal is normalised (it must be non-zero); ``offset`` is in the same units as
    ``width`` (world units in scene.json)."""
    if not isinstance(value, list) or not value:
        raise field_error("expected a non-empty list of planes", file, fld)
    out = []
    for j, pl in enumerate(value):
        p = f"{fld}[{j}]"
        pl = as_dict(pl, file, p)
        n = as_matrix(require(pl, "normal", file, p), (3,), file, f"{p}.normal")
        if np.linalg.norm(n) < 1e-9:
            raise field_error("normal must be non-zero", file, f"{p}.normal")
        col = as_matrix(pl.get("colour", pl.get("color", [1.0, 1.0, 1.0])), (3,), file, f"{p}.colour")
        if np.any(col < 0) or np.any(col > 1):
            raise field_error("colour values must be in [0, 1]", file, f"{p}.colour")
        width = as_num(require(pl, "width", file, p), file, f"{p}.width")
        if width <= 0:
            raise field_error("must be > 0", file, f"{p}.width")
        fan = as_num(pl.get("fan_deg", 90.0), file, f"{p}.fan_deg")
        if not 0 < fan <= 180:
            raise field_error("must be in (0, 180] degrees", file, f"{p}.fan_deg")
        axis = as_matrix(pl.get("axis", [0.0, 0.0, 1.0]), (3,), file, f"{p}.axis")
        nn = n / np.linalg.norm(n)
        if np.linalg.norm(axis - nn * (axis @ nn)) < 1e-6:
            raise field_error("axis must not be parallel to the normal (it gives the fan's centre direction in the "
                              "plane)", file, f"{p}.axis")
        out.append(LaserPlane(normal=nn, offset=as_num(pl.get("offset", 0.0), file, f"{p}.offset"), colour=col,
                              width=width, fan_deg=fan, axis=axis / np.linalg.norm(axis)))
    return out


def parse_port(value: Any, file, fld: str) -> FlatPort | None:
    """Validate a flat port {normal, distance, thickness?, n_air?, n_glass?, n_water?} (None = in air)."""
    if value is None:
        return None
    d = as_dict(value, file, fld)
    n = as_matrix(require(d, "normal", file, fld), (3,), file, f"{fld}.normal")
    if np.linalg.norm(n) < 1e-9:
        raise field_error("normal must be non-zero", file, f"{fld}.normal")
    n = n / np.linalg.norm(n)
    if n[2] <= 0.1:
        raise field_error("normal must point forward (z > 0.1 in the device frame: into the water)", file,
                          f"{fld}.normal")
    dist = as_num(require(d, "distance", file, fld), file, f"{fld}.distance")
    thick = as_num(d.get("thickness", 0.0), file, f"{fld}.thickness")
    if dist <= 0 or thick < 0:
        raise field_error("distance must be > 0 and thickness >= 0", file, f"{fld}.distance")
    idx = {k: as_num(d.get(k, v), file, f"{fld}.{k}")
           for k, v in (("n_air", 1.0), ("n_glass", 1.5), ("n_water", 1.333))}
    for k, v in idx.items():
        if v < 1.0:
            raise field_error("refractive indices are >= 1", file, f"{fld}.{k}")
    if idx["n_water"] < idx["n_air"]:
        raise field_error("n_water < n_air: the model needs the denser medium outside", file, f"{fld}.n_water")
    return FlatPort(normal=n, distance=dist, thickness=thick, **idx)


def port_to_dict(p: FlatPort) -> dict:
    return {"normal": to_list(p.normal), "distance": float(p.distance), "thickness": float(p.thickness),
            "n_air": float(p.n_air), "n_glass": float(p.n_glass), "n_water": float(p.n_water)}


def planes_to_list(planes: list[LaserPlane]) -> list[dict]:
    return [{"normal": to_list(p.normal), "offset": float(p.offset), "colour": to_list(p.colour),
             "width": float(p.width),
             "fan_deg": float(p.fan_deg), "axis": to_list(p.axis)} for p in planes]
