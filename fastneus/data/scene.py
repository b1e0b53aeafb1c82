"""The fastneus scene model: cameras, projectors, patterns, frames, bounds, illumination.

A scene is a folder holding ``scene.json`` (format ``"fastneus-scene"``, version 1) and
the files it names (paths relative to the folder). :meth:`Scene.load` validates
everything and raises :class:`~fastneus.errors.FastneusError` naming the file and field
of the first problem; nothing is guessed.

Conventions (docs/INTERNALS.md): OpenCV pinhole axes, integer pixel (u, v) centred at
(u + 0.5, v + 0.5), poses are 4x4 ``cam_to_world`` / ``proj_to_world`` in world units
(metres), ``x_world = radius * x_norm + center``.
"""
from __future__ import annotations

import copy
import json
import math
import os
import re
import struct
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fastneus.errors import FastneusError
from fastneus.geometry.cameras import look_at, rigid_inverse  # noqa: F401 (public here too)

FORMAT = "fastneus-scene"
VERSION = 1
POSE_TOL = 1e-4  # tolerance of the rigidity check R^T R = I
MAX_SIDE = 1 << 16  # image / projector width and height (JPEG's limit; no camera or projector is larger)
MAX_PIXELS = 1 << 30  # OpenCV's CV_IO_MAX_IMAGE_PIXELS: imread refuses larger images


# --------------------------------------------------------------------------- dataclasses
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

    A laser-plane projector (``planes`` given, ``kind == "laser"``) has no image: K is the
    identity and the size 1 x 1 in memory, and its light is evaluated from the planes."""

    id: str
    K: np.ndarray  # [3, 3] float64
    width: int
    height: int
    proj_to_cam: np.ndarray | None = None  # [4, 4] float64 or None (pose given per frame)
    planes: list[LaserPlane] | None = None
    port: FlatPort | None = None  # underwater housing

    @property
    def kind(self) -> str:
        return "laser" if self.planes is not None else "pattern"


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


GT_KEYS = ("depth", "normal", "clean")


# --------------------------------------------------------------------------- helpers
def _err(msg: str, file, fld: str | None = None) -> FastneusError:
    return FastneusError(msg, file=file, field=fld)


def _matrix(value: Any, shape: tuple[int, ...], file, fld: str) -> np.ndarray:
    """Parse a nested list into a finite float64 array of ``shape``."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise _err(f"expected a {'x'.join(map(str, shape))} array of numbers", file, fld) from None
    if a.shape != shape:
        raise _err(f"expected shape {'x'.join(map(str, shape))}, got {'x'.join(map(str, a.shape)) or 'scalar'}",
                   file, fld)
    if not np.all(np.isfinite(a)):
        raise _err("contains non-finite values (nan/inf)", file, fld)
    return a


def check_pose(T: Any, file, fld: str) -> np.ndarray:
    """Validate a rigid 4x4 transform (finite, R^T R = I within 1e-4, det +1, last row 0001)."""
    T = _matrix(T, (4, 4), file, fld)
    if not np.allclose(T[3], [0, 0, 0, 1], atol=1e-9):
        raise _err(f"last row must be 0 0 0 1, got {T[3].tolist()}", file, fld)
    R = T[:3, :3]
    err = np.abs(R.T @ R - np.eye(3)).max()
    if err > POSE_TOL:
        raise _err(f"rotation is not orthonormal (max |R^T R - I| = {err:.3g} > {POSE_TOL})", file, fld)
    if np.linalg.det(R) < 0:
        raise _err("rotation has determinant -1 (a reflection, not a rotation)", file, fld)
    return T


def check_intrinsics(K: Any, file, fld: str) -> np.ndarray:
    """Validate a 3x3 pinhole K (finite, fx, fy > 0, last row 0 0 1)."""
    K = _matrix(K, (3, 3), file, fld)
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]):
        raise _err("must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0", file, fld)
    return K


def check_principal_point(K: np.ndarray, width: int, height: int, file, fld: str) -> None:
    """Refuse a principal point more than one image size outside the image.

    Lens shift puts it off-centre (projectors: often at or past the bottom edge), but never
    that far: such a K is a typo or another unit, and every ray would miss the scene while
    training "succeeds" (metrics turned infinite).
    """
    cx, cy = float(K[0, 2]), float(K[1, 2])
    if not (-width <= cx <= 2 * width and -height <= cy <= 2 * height):
        raise _err(f"principal point ({cx:.6g}, {cy:.6g}) lies far outside the {width}x{height} image "
                   f"(allowed: cx in [-{width}, {2 * width}], cy in [-{height}, {2 * height}]); is K for "
                   "another image size or in other units?", file, fld)


BOUNDS_MAX_RATIO = 1e3  # bounds radius / farthest camera distance: beyond, the model's resolution is spread thin
BOUNDS_MIN_PIXELS = 0.5  # the region of interest must span at least this many pixels in some image


def check_bounds_scale(center, radius: float, views: list[tuple[np.ndarray, np.ndarray, int]], file,
                       fld: str | None = "bounds.radius") -> None:
    """Refuse bounds far out of scale with the cameras (usually other units than the poses).

    The model lives in the unit sphere of the bounds: a radius 1000x the camera distances spreads its
    resolution over empty space, one that spans under half a pixel in every image leaves nothing to
    reconstruct; either way training would "succeed" on nothing.

    Args:
        views: (cam_to_world [4, 4], K [3, 3], image width) of every frame.
    """
    r = float(radius)
    dists = [float(np.linalg.norm(np.asarray(T)[:3, 3] - np.asarray(center))) for T, _, _ in views]
    if max(dists) > 0 and r > BOUNDS_MAX_RATIO * max(dists):
        raise _err(f"bounds radius {r:.4g} is more than {BOUNDS_MAX_RATIO:g}x the farthest camera's distance from "
                   f"the centre ({max(dists):.4g}); are the bounds in other units than the poses?", file, fld)
    # a focal length under 0.005 px per pixel of width (a field of view over 179 degrees) is itself the error,
    # reported by fastneus.pipeline.check_inputs naming K; such views do not vote here
    px = [r * float(min(K[0, 0], K[1, 1])) / d if d > r else math.inf for (_, K, w), d in zip(views, dists)
          if min(K[0, 0], K[1, 1]) >= 0.005 * w]
    if px and max(px) < BOUNDS_MIN_PIXELS:
        raise _err(f"bounds radius {r:.4g} spans under {BOUNDS_MIN_PIXELS} pixel in every image (at most "
                   f"{max(px):.3g}); are the bounds in other units than the poses?", file, fld)


def check_faces_bounds(dev_to_world: np.ndarray, center, radius: float, what: str, file, fld: str) -> None:
    """Refuse a camera or projector that has the whole region of interest behind it.

    Such a device can see (or light) nothing of the scene: usually a world->device pose given
    where device->world is expected, a projector pose inverted, or wrong bounds.
    """
    x = np.append(np.asarray(center, dtype=np.float64), 1.0)
    z = float((rigid_inverse(dev_to_world) @ x)[2])
    if z <= -radius:
        raise _err(f"the scene (bounds centre {np.round(x[:3], 4).tolist()}, radius {radius:g}) lies entirely "
                   f"behind this {what} (depth {z:.3g}); is the pose inverted (world->{what} instead of "
                   f"{what}->world), or are the bounds wrong?", file, fld)


def _show(value: Any) -> str:
    """``repr(value)`` cut to one short line (a 400-digit JSON integer would fill the screen)."""
    r = repr(value)
    return r if len(r) <= 40 and r.isprintable() else ascii(r[:32]) + "..."


MAX_JSON_DEPTH = 64  # scene files nest 5 levels; deeper input would exhaust the recursion of later steps


def load_json(file: str | os.PathLike) -> Any:
    """Parse a JSON input file; every way it can be unreadable is one line naming it.

    Raises:
        FastneusError: unreadable, not UTF-8, invalid JSON, or nested deeper than :data:`MAX_JSON_DEPTH`.
    """
    try:
        data = json.loads(Path(file).read_bytes().decode("utf-8-sig"))
    except OSError as e:
        raise _err(f"cannot read: {e.strerror or e}", file) from None
    except UnicodeDecodeError as e:
        raise _err(f"not UTF-8 text (byte {e.start}); JSON files are UTF-8", file) from None
    except json.JSONDecodeError as e:
        raise _err(f"invalid JSON at line {e.lineno} column {e.colno}: {e.msg}", file) from None
    except RecursionError:
        raise _err(f"invalid JSON: nested deeper than Python can parse (a scene nests {MAX_JSON_DEPTH} levels "
                   "at most)", file) from None
    stack = [(data, 0)]  # iterative: the check itself must not recurse
    while stack:
        v, depth = stack.pop()
        if depth > MAX_JSON_DEPTH:
            raise _err(f"nested more than {MAX_JSON_DEPTH} levels deep; not a scene file", file)
        if isinstance(v, dict):
            stack.extend((x, depth + 1) for x in v.values())
        elif isinstance(v, list):
            stack.extend((x, depth + 1) for x in v)
    return data


def _int(value: Any, file, fld: str, minimum: int = 1, maximum: int = 2 ** 31 - 1) -> int:
    """An integer in [minimum, maximum] (a float with an integer value is accepted; NaN, inf are not)."""
    if (isinstance(value, bool) or not isinstance(value, (int, float))
            or (isinstance(value, float) and not value.is_integer()) or not minimum <= value <= maximum):
        raise _err(f"expected an integer in {minimum}..{maximum}, got {_show(value)}", file, fld)
    return int(value)


def _num(value: Any, file, fld: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise _err(f"expected a finite number, got {value!r}", file, fld)
    return float(value)


def _str(value: Any, file, fld: str) -> str:
    if not isinstance(value, str) or not value:
        raise _err(f"expected a non-empty string, got {value!r}", file, fld)
    return value


def _dict(value: Any, file, fld: str) -> dict:
    if not isinstance(value, dict):
        raise _err(f"expected an object, got {type(value).__name__}", file, fld)
    return value


# ids of cameras, projectors and patterns name files that writers create (pattern/<id>.png):
# a safe file name, never a path (no "/", no "..", no leading dot or dash)
SAFE_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")
SAFE_ID_RULE = "letters, digits, '.', '_', '-' (1-64 characters, starting with a letter or digit, no '..')"


def id_field(prefix: str, key: Any) -> str:
    """``prefix.key`` for error messages; an unprintable key is quoted so the message stays one line."""
    return f"{prefix}.{key}" if isinstance(key, str) and key.isprintable() else f"{prefix}.{key!r}"


def check_id(value: Any, file, prefix: str) -> str:
    """Validate an id used as a file name (:data:`SAFE_ID`); the error names ``prefix.<id>``."""
    if not isinstance(value, str) or not SAFE_ID.fullmatch(value) or ".." in value:
        raise _err(f"unsafe id {value!r}: ids may use {SAFE_ID_RULE}", file, id_field(prefix, value))
    return value


def _req(d: dict, key: str, file, prefix: str) -> Any:
    if key not in d:
        raise _err("missing", file, f"{prefix}.{key}" if prefix else key)
    return d[key]


# PNG colour type -> channels as decoded (palette images decode to colour)
_PNG_CHANNELS = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}


def image_info(path: str | os.PathLike) -> tuple[int, int, int, int] | None:
    """(width, height, channels, bits per channel) of an image; None if unreadable.

    PNG is read from its header only; other formats are decoded once.
    """
    path = str(path)
    try:
        with open(path, "rb") as f:
            head = f.read(26)
    except OSError:
        return None
    if len(head) >= 26 and head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
        w, h = struct.unpack(">II", head[16:24])
        bits = 8 if head[25] == 3 else int(head[24])  # palette: 8-bit colours whatever the index size
        return int(w), int(h), _PNG_CHANNELS.get(head[25], 0), bits
    import cv2

    try:
        im = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    except cv2.error:  # a header OpenCV refuses (e.g. more pixels than it decodes)
        return None
    if im is None:
        return None
    return int(im.shape[1]), int(im.shape[0]), 1 if im.ndim == 2 else int(im.shape[2]), 8 * im.dtype.itemsize


def image_size(path: str | os.PathLike) -> tuple[int, int] | None:
    """(width, height) of an image, reading only the header for PNG; None if unreadable."""
    info = image_info(path)
    return None if info is None else info[:2]


# what each kind of image may be (channels, bits): photos are 8-bit colour as the model sees them;
# masks use channel 0 (8 or 16 bit); patterns may be grey (white light). Alpha is never dropped silently.
_IMAGE_KINDS = {"image": ((3,), (8,)), "mask": ((1, 3), (8, 16)), "pattern": ((1, 3), (8,))}


def _check_image(root: Path, rel: str, size: tuple[int, int] | None, file, fld: str, kind: str = "image") -> None:
    p = root / rel
    if not p.is_file():
        raise _err(f"file not found: {p}", file, fld)
    info = image_info(p)
    if info is None:
        raise _err(f"cannot read image {p}", file, fld)
    w, h, ch, bits = info
    if size is not None and (w, h) != tuple(size):
        raise _err(f"image {rel} is {w}x{h} but should be {size[0]}x{size[1]}", file, fld)
    channels, depths = _IMAGE_KINDS[kind]
    if ch in (2, 4):
        raise _err(f"{kind} {rel} has an alpha channel, which fastneus would drop; save it without alpha "
                   f"(a transparent background belongs in a mask)", file, fld)
    if ch not in channels:
        raise _err(f"{kind} {rel} has {ch} channel(s); expected {' or '.join(map(str, channels))}"
                   + (" (a colour photo; convert grey images to RGB)" if kind == "image" else ""), file, fld)
    if bits not in depths:
        raise _err(f"{kind} {rel} is {bits}-bit; expected {' or '.join(map(str, depths))}-bit per channel",
                   file, fld)
    if w * h > MAX_PIXELS:  # only a PNG header is read here; OpenCV refuses to decode more
        raise _err(f"{kind} {rel} is {w}x{h}, more than the {MAX_PIXELS} pixels OpenCV decodes", file, fld)
    warn_orientation(p)


def _exif_orientation_tiff(tiff: bytes) -> int | None:
    """The Orientation tag (0x0112) of IFD0 in a TIFF-structured EXIF block, None if absent or malformed."""
    if len(tiff) < 8 or tiff[:2] not in (b"II", b"MM"):
        return None
    e = "<" if tiff[:2] == b"II" else ">"
    ifd = struct.unpack(e + "I", tiff[4:8])[0]
    if ifd + 2 > len(tiff):
        return None
    n = struct.unpack(e + "H", tiff[ifd:ifd + 2])[0]
    for k in range(min(n, 512)):
        at = ifd + 2 + 12 * k
        if at + 12 > len(tiff):
            return None
        tag, typ = struct.unpack(e + "HH", tiff[at:at + 4])
        if tag == 0x0112 and typ == 3:  # SHORT, stored in the first 2 bytes of the value field
            return struct.unpack(e + "H", tiff[at + 8:at + 10])[0]
    return None


def exif_orientation(path: str | os.PathLike) -> int | None:
    """The EXIF Orientation of a JPEG (APP1 ``Exif``) or PNG (``eXIf`` chunk), read from the
    file's first 256 KB without decoding pixels; None when there is none."""
    try:
        with open(path, "rb") as f:
            head = f.read(1 << 18)
    except OSError:
        return None
    try:
        if head[:2] == b"\xff\xd8":  # JPEG: walk the marker segments before the image data
            at = 2
            while at + 4 <= len(head) and head[at] == 0xFF:
                marker, size = head[at + 1], struct.unpack(">H", head[at + 2:at + 4])[0]
                if marker == 0xE1 and head[at + 4:at + 10] == b"Exif\x00\x00":
                    return _exif_orientation_tiff(head[at + 10:at + 2 + size])
                if marker in (0xD9, 0xDA) or size < 2:  # end of image / start of scan
                    return None
                at += 2 + size
        elif head[:8] == b"\x89PNG\r\n\x1a\n":
            at = 8
            while at + 8 <= len(head):
                size, kind = struct.unpack(">I4s", head[at:at + 8])
                if kind == b"eXIf":
                    return _exif_orientation_tiff(head[at + 8:at + 8 + size])
                if kind in (b"IDAT", b"IEND"):
                    return None
                at += 12 + size
    except struct.error:
        return None
    return None


_ORIENTATION_WARNED: set[str] = set()


def warn_orientation(path: str | os.PathLike) -> None:
    """One stderr line (once per file) when an image carries an EXIF rotation/flip that fastneus ignores."""
    import sys

    o = exif_orientation(path)
    if o not in (None, 1) and str(path) not in _ORIENTATION_WARNED:
        _ORIENTATION_WARNED.add(str(path))
        print(f"warning: {path}: EXIF orientation {o} ignored; fastneus uses the pixels as stored, which the "
              "intrinsics and masks must describe (re-save the file without the tag if it is wrong)",
              file=sys.stderr)


def _imread(path: Path, flags: int, file, fld: str) -> np.ndarray:
    """``cv2.imread`` with ``flags`` and the EXIF orientation ignored (pixels as stored, like the
    size check and the masks), one-line errors; None never escapes."""
    import cv2

    if flags != cv2.IMREAD_UNCHANGED:  # IMREAD_UNCHANGED ignores the orientation already (and is -1)
        flags |= cv2.IMREAD_IGNORE_ORIENTATION
    try:
        im = cv2.imread(str(path), flags)
    except cv2.error as e:  # e.g. a header claiming more pixels than OpenCV decodes
        raise _err(f"cannot read image {path}: {str(e).strip().splitlines()[-1][:200]}", file, fld) from None
    if im is None:
        raise _err(f"cannot read image {path}", file, fld)
    return im


def _read_rgb(path: Path, file, fld: str) -> np.ndarray:
    import cv2

    im = _imread(path, cv2.IMREAD_COLOR, file, fld)
    return np.ascontiguousarray(im[:, :, ::-1])


def _read_npy(path: Path, file, fld: str) -> np.ndarray:
    """A numeric ``.npy`` as float32; never unpickles (ground truth files are untrusted too)."""
    try:
        return np.asarray(np.load(path, allow_pickle=False), dtype=np.float32)
    except Exception as e:  # noqa: BLE001 - corrupt, pickled or non-numeric: one line
        raise _err(f"cannot read {path}: {e}".splitlines()[0], file, fld) from None


def _list(a: np.ndarray | None):
    return None if a is None else np.asarray(a, dtype=np.float64).tolist()


# --------------------------------------------------------------------------- scene
@dataclass
class Scene:
    """A validated scene. File paths in ``frames``/``patterns`` are relative to ``root``."""

    root: Path
    cameras: dict[str, Camera]
    projectors: dict[str, Projector]
    patterns: dict[str, Pattern]
    frames: list[Frame]
    bounds: Bounds
    illumination: Illumination = field(default_factory=Illumination)
    gt_mesh: str | None = None
    units: str = "m"
    name: str = ""
    meta: dict = field(default_factory=dict)  # free-form provenance (e.g. how synth made it), kept on save

    # ------------------------------------------------------------------ loading
    @classmethod
    def load(cls, path: str | os.PathLike) -> "Scene":
        """Load and validate a scene folder or its ``scene.json``.

        Raises:
            FastneusError: naming the file and field of the first problem.
        """
        path = Path(path)
        file = path / "scene.json" if path.is_dir() else path
        if not file.is_file():
            raise _err("scene.json not found", file)
        data = load_json(file)
        return cls.from_dict(data, file.parent.resolve(), file=file)

    @classmethod
    def from_dict(cls, data: Any, root: str | os.PathLike, file=None, check_files: bool = True) -> "Scene":
        """Build a scene from the parsed ``scene.json`` content, validating everything.

        Args:
            data: the JSON object.
            root: folder the relative paths are resolved against.
            file: the file named in error messages (default ``root/scene.json``).
            check_files: also check that images/masks/patterns exist and have the right sizes.
        """
        root = Path(root)
        file = file if file is not None else root / "scene.json"
        d = _dict(data, file, None)
        fmt = d.get("format")
        if fmt != FORMAT:
            raise _err(f"unknown format {fmt!r}; expected {FORMAT!r}", file, "format")
        ver = d.get("version")
        if ver != VERSION:
            raise _err(f"unsupported version {ver!r}; this fastneus reads version {VERSION}", file, "version")
        units = _str(d.get("units", "m"), file, "units")
        name = d.get("name", "") or ""
        if not isinstance(name, str):
            raise _err("expected a string", file, "name")

        b = _dict(_req(d, "bounds", file, ""), file, "bounds")
        bounds = Bounds(center=_matrix(_req(b, "center", file, "bounds"), (3,), file, "bounds.center"),
                        radius=_num(_req(b, "radius", file, "bounds"), file, "bounds.radius"))
        if bounds.radius <= 0:
            raise _err("must be > 0", file, "bounds.radius")

        cameras: dict[str, Camera] = {}
        for cid, c in _dict(_req(d, "cameras", file, ""), file, "cameras").items():
            p = f"cameras.{check_id(cid, file, 'cameras')}"
            c = _dict(c, file, p)
            dist = c.get("dist")
            cameras[cid] = Camera(
                id=cid, K=check_intrinsics(_req(c, "K", file, p), file, f"{p}.K"),
                width=_int(_req(c, "width", file, p), file, f"{p}.width", maximum=MAX_SIDE),
                height=_int(_req(c, "height", file, p), file, f"{p}.height", maximum=MAX_SIDE),
                dist=np.zeros(5) if dist is None else _matrix(dist, (5,), file, f"{p}.dist"),
                port=parse_port(c.get("port"), file, f"{p}.port"))
        if not cameras:
            raise _err("no cameras", file, "cameras")
        for cid, cam in cameras.items():
            check_principal_point(cam.K, cam.width, cam.height, file, f"cameras.{cid}.K")

        projectors: dict[str, Projector] = {}
        for pid, pr in _dict(d.get("projectors", {}), file, "projectors").items():
            p = f"projectors.{check_id(pid, file, 'projectors')}"
            pr = _dict(pr, file, p)
            p2c = pr.get("proj_to_cam")
            kind = pr.get("kind", "pattern")
            if kind not in ("pattern", "laser"):
                raise _err(f"unknown projector kind {kind!r}; use pattern or laser", file, f"{p}.kind")
            if kind == "laser":
                if pr.get("port") is not None:
                    raise _err("a laser projector behind a flat port is not modelled (its light sheets bend at the "
                               "port)", file, f"{p}.port")
                projectors[pid] = Projector(
                    id=pid, K=np.eye(3), width=1, height=1,
                    proj_to_cam=None if p2c is None else check_pose(p2c, file, f"{p}.proj_to_cam"),
                    planes=parse_planes(_req(pr, "planes", file, p), file, f"{p}.planes"))
                continue
            projectors[pid] = Projector(
                id=pid, K=check_intrinsics(_req(pr, "K", file, p), file, f"{p}.K"),
                width=_int(_req(pr, "width", file, p), file, f"{p}.width", maximum=MAX_SIDE),
                height=_int(_req(pr, "height", file, p), file, f"{p}.height", maximum=MAX_SIDE),
                proj_to_cam=None if p2c is None else check_pose(p2c, file, f"{p}.proj_to_cam"),
                port=parse_port(pr.get("port"), file, f"{p}.port"))

        for pid, pj in projectors.items():
            if pj.kind == "pattern":
                check_principal_point(pj.K, pj.width, pj.height, file, f"projectors.{pid}.K")
        patterns: dict[str, Pattern] = {}
        pattern_sizes: dict[str, tuple[int, int]] = {}
        for qid, q in _dict(d.get("patterns", {}), file, "patterns").items():
            p = f"patterns.{check_id(qid, file, 'patterns')}"
            q = _dict(q, file, p)
            patterns[qid] = Pattern(id=qid, file=_str(_req(q, "file", file, p), file, f"{p}.file"))
            if check_files:
                _check_image(root, patterns[qid].file, None, file, f"{p}.file", kind="pattern")
                pattern_sizes[qid] = image_size(root / patterns[qid].file)

        fl = _req(d, "frames", file, "")
        if not isinstance(fl, list):
            raise _err("expected a list", file, "frames")
        if not fl:
            raise _err("no frames: a scene needs at least one image", file, "frames")
        frames: list[Frame] = []
        image_of: dict = {}  # path, resolved path, (device, inode) -> first frame using that photo
        for i, f in enumerate(fl):
            p = f"frames[{i}]"
            f = _dict(f, file, p)
            cam = _str(_req(f, "camera", file, p), file, f"{p}.camera")
            if cam not in cameras:
                raise _err(f"unknown camera id {cam!r}; known: {sorted(cameras)}", file, f"{p}.camera")
            image = _str(_req(f, "image", file, p), file, f"{p}.image")
            # the same photo by path, through a symbolic link or a hard link: one photo is one frame
            keys: set = {os.path.normpath(root / image), os.path.realpath(root / image)}
            try:
                st = os.stat(root / image)
                keys.add((st.st_dev, st.st_ino))
            except OSError:  # missing: reported with the file checks
                pass
            hit = next((image_of[k] for k in keys if k in image_of), None)
            if hit is not None:
                raise _err(f"duplicate frame: image {image!r} is the same file as frames[{hit}].image "
                           f"{fl[hit]['image']!r} (each photo is one frame)", file, f"{p}.image")
            image_of.update(dict.fromkeys(keys, i))
            c2w = check_pose(_req(f, "cam_to_world", file, p), file, f"{p}.cam_to_world")
            view = _int(f.get("view", i), file, f"{p}.view", minimum=0)
            mask = f.get("mask")
            if mask is not None:
                mask = _str(mask, file, f"{p}.mask")
            fps: dict[str, FrameProjector] = {}
            for pid, fp in _dict(f.get("projectors", {}), file, f"{p}.projectors").items():
                pp = id_field(f"{p}.projectors", pid)  # an unprintable id is quoted: the error stays one line
                if pid not in projectors:
                    raise _err(f"unknown projector id {pid!r}; known: {sorted(projectors)}", file, pp)
                fp = _dict(fp, file, pp)
                pat = fp.get("pattern")
                on = fp.get("on", True)
                if not isinstance(on, bool):
                    raise _err("expected true or false", file, f"{pp}.on")
                if projectors[pid].kind == "laser" and pat is not None:
                    raise _err(f"projector {pid!r} is a laser (planes); it shows no pattern, use on: true/false",
                               file, f"{pp}.pattern")
                if pat is not None:
                    if not isinstance(pat, str) or pat not in patterns:
                        raise _err(f"unknown pattern id {pat!r}; known: {sorted(patterns)}", file, f"{pp}.pattern")
                    pj = projectors[pid]
                    if check_files and pattern_sizes[pat] != (pj.width, pj.height):
                        w, h = pattern_sizes[pat]
                        raise _err(f"pattern {pat!r} is {w}x{h} but projector {pid!r} is "
                                   f"{pj.width}x{pj.height}", file, f"{pp}.pattern")
                p2w = fp.get("proj_to_world")
                if projectors[pid].proj_to_cam is None:
                    if p2w is None:
                        raise _err(f"projector {pid!r} is free (proj_to_cam null), so each frame needs "
                                   "proj_to_world", file, f"{pp}.proj_to_world")
                    p2w = check_pose(p2w, file, f"{pp}.proj_to_world")
                elif p2w is not None:
                    raise _err(f"projector {pid!r} is rigged to the camera (proj_to_cam); "
                               "a per-frame proj_to_world would contradict it", file, f"{pp}.proj_to_world")
                fps[pid] = FrameProjector(pattern=pat, proj_to_world=p2w, on=on)
            gt = {}
            for k, v in _dict(f.get("gt", {}), file, f"{p}.gt").items():
                if k not in GT_KEYS:
                    raise _err(f"unknown ground-truth key {k!r}; known: {list(GT_KEYS)}", file, id_field(f"{p}.gt", k))
                gt[k] = _str(v, file, f"{p}.gt.{k}")
                if check_files and not (root / gt[k]).is_file():
                    raise _err(f"file not found: {root / gt[k]}", file, f"{p}.gt.{k}")
            if check_files:
                size = (cameras[cam].width, cameras[cam].height)
                _check_image(root, image, size, file, f"{p}.image")
                if mask is not None:
                    _check_image(root, mask, size, file, f"{p}.mask", kind="mask")
            frames.append(Frame(image=image, camera=cam, cam_to_world=c2w, projectors=fps, mask=mask,
                                view=view, gt=gt))
            check_faces_bounds(c2w, bounds.center, bounds.radius, "camera", file, f"{p}.cam_to_world")
            for pid, fp in fps.items():
                if fp.pattern is None:
                    continue
                p2c = projectors[pid].proj_to_cam
                check_faces_bounds(c2w @ p2c if p2c is not None else fp.proj_to_world, bounds.center, bounds.radius,
                                   "projector", file, f"projectors.{pid}.proj_to_cam" if p2c is not None
                                   else f"{p}.projectors.{pid}.proj_to_world")
        check_bounds_scale(bounds.center, bounds.radius,
                           [(f.cam_to_world, cameras[f.camera].K, cameras[f.camera].width) for f in frames], file)

        il = _dict(d.get("illumination", {}), file, "illumination")
        known = il.get("known", False)
        if not isinstance(known, bool):
            raise _err("expected true or false", file, "illumination.known")
        illum = Illumination(**{k: _num(il[k], file, f"illumination.{k}") for k in ("i_r", "i_b", "ambient")
                                if k in il}, known=known)
        for k in ("i_r", "i_b", "ambient"):  # amounts of light: training starts log(i_r), log(i_b) from them
            if getattr(illum, k) < 0:
                raise _err(f"is an amount of light and must be >= 0, got {getattr(illum, k)!r}", file,
                           f"illumination.{k}")
        gt_mesh = _dict(d.get("gt", {}) or {}, file, "gt").get("mesh")
        if gt_mesh is not None:
            gt_mesh = _str(gt_mesh, file, "gt.mesh")
            if check_files and not (root / gt_mesh).is_file():
                raise _err(f"file not found: {root / gt_mesh}", file, "gt.mesh")
        meta = _dict(d.get("meta", {}) or {}, file, "meta")
        return cls(root=root, cameras=cameras, projectors=projectors, patterns=patterns, frames=frames,
                   bounds=bounds, illumination=illum, gt_mesh=gt_mesh, units=units, name=name, meta=meta)

    # ------------------------------------------------------------------ saving
    def to_dict(self, rel_to: str | os.PathLike | None = None) -> dict:
        """The ``scene.json`` content; paths rewritten relative to ``rel_to`` when given."""
        root = Path(self.root).resolve()
        dest = Path(rel_to).resolve() if rel_to is not None else root

        def rp(p: str | None) -> str | None:
            if p is None or dest == root:
                return p
            return Path(os.path.relpath(root / p, dest)).as_posix()

        frames = []
        for f in self.frames:
            fd: dict[str, Any] = {"image": rp(f.image), "camera": f.camera, "cam_to_world": _list(f.cam_to_world),
                                  "view": int(f.view), "projectors": {}}
            for pid, fp in f.projectors.items():
                e: dict[str, Any] = {"on": bool(fp.on)} if self.projectors[pid].kind == "laser" else \
                    {"pattern": fp.pattern}
                if fp.proj_to_world is not None:
                    e["proj_to_world"] = _list(fp.proj_to_world)
                fd["projectors"][pid] = e
            if f.mask is not None:
                fd["mask"] = rp(f.mask)
            if f.gt:
                fd["gt"] = {k: rp(v) for k, v in f.gt.items()}
            frames.append(fd)
        il = self.illumination
        return {
            "format": FORMAT, "version": VERSION, "units": self.units, "name": self.name,
            "bounds": {"center": _list(self.bounds.center), "radius": float(self.bounds.radius)},
            "cameras": {c.id: {"K": _list(c.K), "width": c.width, "height": c.height, "dist": _list(c.dist),
                               **({"port": port_to_dict(c.port)} if c.port is not None else {})}
                        for c in self.cameras.values()},
            "projectors": {p.id: ({"K": _list(p.K), "width": p.width, "height": p.height,
                                   "proj_to_cam": _list(p.proj_to_cam),
                                   **({"port": port_to_dict(p.port)} if p.port is not None else {})}
                                  if p.kind == "pattern" else
                                  {"kind": "laser", "proj_to_cam": _list(p.proj_to_cam),
                                   "planes": planes_to_list(p.planes)}) for p in self.projectors.values()},
            "patterns": {q.id: {"file": rp(q.file)} for q in self.patterns.values()},
            "frames": frames,
            "illumination": {"i_r": float(il.i_r), "i_b": float(il.i_b), "ambient": float(il.ambient),
                             "known": bool(il.known)},
            "gt": {"mesh": rp(self.gt_mesh)},
            "meta": copy.deepcopy(self.meta),
        }

    def save(self, folder: str | os.PathLike | None = None) -> Path:
        """Write ``scene.json`` into ``folder`` (default: the scene's root) atomically.

        Paths are rewritten relative to ``folder`` when it differs from the root, so the
        saved scene refers to the same files. Returns the path written.
        """
        folder = Path(folder if folder is not None else self.root)
        folder.mkdir(parents=True, exist_ok=True)
        text = json.dumps(self.to_dict(rel_to=folder), indent=1)
        out = folder / "scene.json"
        fd, tmp = tempfile.mkstemp(prefix=".scene.", suffix=".json.tmp", dir=folder)
        try:
            with os.fdopen(fd, "w") as fh:
                fh.write(text + "\n")
            os.replace(tmp, out)
        except BaseException:
            if os.path.exists(tmp):
                os.unlink(tmp)
            raise
        return out

    # ------------------------------------------------------------------ accessors
    def path(self, rel: str) -> Path:
        """Absolute path of a file named in the scene."""
        return Path(self.root) / rel

    def __len__(self) -> int:
        return len(self.frames)

    def frame_camera(self, i: int) -> Camera:
        return self.cameras[self.frames[i].camera]

    def cam_to_world(self, i: int) -> np.ndarray:
        """[4, 4] float64 camera->world pose of frame ``i``."""
        return self.frames[i].cam_to_world.copy()

    def world_to_cam(self, i: int) -> np.ndarray:
        return rigid_inverse(self.frames[i].cam_to_world)

    def proj_to_world(self, i: int, proj_id: str) -> np.ndarray:
        """[4, 4] projector->world of ``proj_id`` in frame ``i`` (rig or free pose)."""
        pj = self.projectors[proj_id]
        if pj.proj_to_cam is not None:
            return self.frames[i].cam_to_world @ pj.proj_to_cam
        fp = self.frames[i].projectors.get(proj_id)
        if fp is None or fp.proj_to_world is None:
            raise FastneusError(f"free projector {proj_id!r} has no pose in frame {i}",
                                field=f"frames[{i}].projectors.{proj_id}.proj_to_world")
        return fp.proj_to_world.copy()

    def world_to_proj(self, i: int, proj_id: str) -> np.ndarray:
        """[4, 4] world->projector of ``proj_id`` in frame ``i``."""
        return rigid_inverse(self.proj_to_world(i, proj_id))

    def active_projectors(self, i: int) -> list[tuple[str, str]]:
        """(projector id, pattern id) of every projector showing a pattern in frame ``i``."""
        return [(pid, fp.pattern) for pid, fp in self.frames[i].projectors.items() if fp.pattern is not None]

    def active_lasers(self, i: int) -> list[str]:
        """Ids of the laser-plane projectors lit in frame ``i``."""
        return [pid for pid, fp in self.frames[i].projectors.items()
                if self.projectors[pid].kind == "laser" and fp.on]

    def normalisation(self) -> np.ndarray:
        """[4, 4] float64 S mapping normalised -> world coordinates."""
        S = np.eye(4)
        S[:3, :3] *= self.bounds.radius
        S[:3, 3] = self.bounds.center
        return S

    def views(self) -> dict[int, list[int]]:
        """View id -> frame indices sharing that viewpoint (in frame order)."""
        out: dict[int, list[int]] = {}
        for i, f in enumerate(self.frames):
            out.setdefault(f.view, []).append(i)
        return out

    def image(self, i: int) -> np.ndarray:
        """uint8 [H, W, 3] RGB image of frame ``i`` (undistorted if the camera has distortion)."""
        f = self.frames[i]
        im = _read_rgb(self.path(f.image), self.root / "scene.json", f"frames[{i}].image")
        return self._undistort(i, im)

    def _undistort(self, i: int, im: np.ndarray, nearest: bool = False) -> np.ndarray:
        cam = self.frame_camera(i)
        if not np.any(cam.dist):
            return im
        import cv2

        # cv2 uses the pixel-corner convention for integer coords; shift K by half a pixel
        K = cam.K.copy()
        K[0, 2] -= 0.5
        K[1, 2] -= 0.5
        if nearest:
            m1, m2 = cv2.initUndistortRectifyMap(K, cam.dist, None, K, (im.shape[1], im.shape[0]), cv2.CV_32FC1)
            return cv2.remap(im, m1, m2, cv2.INTER_NEAREST)
        return cv2.undistort(im, K, cam.dist)

    def mask(self, i: int) -> np.ndarray | None:
        """float32 [H, W] in [0, 1] (soft edges kept) or None when the frame has no mask."""
        f = self.frames[i]
        if f.mask is None:
            return None
        import cv2

        m = _imread(self.path(f.mask), cv2.IMREAD_UNCHANGED, self.root / "scene.json", f"frames[{i}].mask")
        if m.ndim == 3:
            m = m[:, :, 0]
        scale = 65535.0 if m.dtype == np.uint16 else 255.0
        m = m.astype(np.float32) / scale
        return self._undistort(i, m)

    def pattern_image(self, pid: str) -> np.ndarray:
        """uint8 [h, w, 3] RGB pattern ``pid``."""
        return _read_rgb(self.path(self.patterns[pid].file), self.root / "scene.json", f"patterns.{pid}.file")

    def gt_depth(self, i: int) -> np.ndarray | None:
        """float32 [H, W] ground-truth z-depth (world units, 0 = background) or None."""
        rel = self.frames[i].gt.get("depth")
        if rel is None:
            return None
        return _read_npy(self.path(rel), self.root / "scene.json", f"frames[{i}].gt.depth")

    def gt_normal(self, i: int) -> np.ndarray | None:
        """float32 [H, W, 3] ground-truth world normals (zero = background) or None."""
        rel = self.frames[i].gt.get("normal")
        if rel is None:
            return None
        if rel.endswith(".npy"):
            return _read_npy(self.path(rel), self.root / "scene.json", f"frames[{i}].gt.normal")
        im = _read_rgb(self.path(rel), self.root / "scene.json", f"frames[{i}].gt.normal").astype(np.float32)
        n = im / 255.0 * 2.0 - 1.0
        n[np.all(im == 0, axis=-1)] = 0.0  # black = background
        return n

    def gt_clean(self, i: int) -> np.ndarray | None:
        """uint8 [H, W, 3] RGB pattern-free image or None."""
        rel = self.frames[i].gt.get("clean")
        if rel is None:
            return None
        return _read_rgb(self.path(rel), self.root / "scene.json", f"frames[{i}].gt.clean")

    def subset(self, frame_indices) -> "Scene":
        """A scene with only the given frames (same root, cameras, projectors, patterns)."""
        idx = [int(i) for i in frame_indices]
        if not idx:
            raise FastneusError("a subset needs at least one frame", field="frames")
        for i in idx:
            if not 0 <= i < len(self.frames):
                raise FastneusError(f"frame index {i} out of range 0..{len(self.frames) - 1}", field="frames")
        s = copy.copy(self)
        s.frames = [copy.deepcopy(self.frames[i]) for i in idx]
        return s


def parse_planes(value: Any, file, fld: str) -> list[LaserPlane]:
    """Validate a list of plane objects {normal, offset, colour, width, fan_deg[, axis]}.

    The normal is normalised (it must be non-zero); ``offset`` is in the same units as
    ``width`` (world units in scene.json)."""
    if not isinstance(value, list) or not value:
        raise _err("expected a non-empty list of planes", file, fld)
    out = []
    for j, pl in enumerate(value):
        p = f"{fld}[{j}]"
        pl = _dict(pl, file, p)
        n = _matrix(_req(pl, "normal", file, p), (3,), file, f"{p}.normal")
        if np.linalg.norm(n) < 1e-9:
            raise _err("normal must be non-zero", file, f"{p}.normal")
        col = _matrix(pl.get("colour", pl.get("color", [1.0, 1.0, 1.0])), (3,), file, f"{p}.colour")
        if np.any(col < 0) or np.any(col > 1):
            raise _err("colour values must be in [0, 1]", file, f"{p}.colour")
        width = _num(_req(pl, "width", file, p), file, f"{p}.width")
        if width <= 0:
            raise _err("must be > 0", file, f"{p}.width")
        fan = _num(pl.get("fan_deg", 90.0), file, f"{p}.fan_deg")
        if not 0 < fan <= 180:
            raise _err("must be in (0, 180] degrees", file, f"{p}.fan_deg")
        axis = _matrix(pl.get("axis", [0.0, 0.0, 1.0]), (3,), file, f"{p}.axis")
        nn = n / np.linalg.norm(n)
        if np.linalg.norm(axis - nn * (axis @ nn)) < 1e-6:
            raise _err("axis must not be parallel to the normal (it gives the fan's centre direction in the plane)",
                       file, f"{p}.axis")
        out.append(LaserPlane(normal=nn, offset=_num(pl.get("offset", 0.0), file, f"{p}.offset"), colour=col,
                              width=width, fan_deg=fan, axis=axis / np.linalg.norm(axis)))
    return out


def parse_port(value: Any, file, fld: str) -> FlatPort | None:
    """Validate a flat port {normal, distance, thickness?, n_air?, n_glass?, n_water?} (None = in air)."""
    if value is None:
        return None
    d = _dict(value, file, fld)
    n = _matrix(_req(d, "normal", file, fld), (3,), file, f"{fld}.normal")
    if np.linalg.norm(n) < 1e-9:
        raise _err("normal must be non-zero", file, f"{fld}.normal")
    n = n / np.linalg.norm(n)
    if n[2] <= 0.1:
        raise _err("normal must point forward (z > 0.1 in the device frame: into the water)", file, f"{fld}.normal")
    dist = _num(_req(d, "distance", file, fld), file, f"{fld}.distance")
    thick = _num(d.get("thickness", 0.0), file, f"{fld}.thickness")
    if dist <= 0 or thick < 0:
        raise _err("distance must be > 0 and thickness >= 0", file, f"{fld}.distance")
    idx = {k: _num(d.get(k, v), file, f"{fld}.{k}") for k, v in (("n_air", 1.0), ("n_glass", 1.5), ("n_water", 1.333))}
    for k, v in idx.items():
        if v < 1.0:
            raise _err("refractive indices are >= 1", file, f"{fld}.{k}")
    if idx["n_water"] < idx["n_air"]:
        raise _err("n_water < n_air: the model needs the denser medium outside", file, f"{fld}.n_water")
    return FlatPort(normal=n, distance=dist, thickness=thick, **idx)


def port_to_dict(p: FlatPort) -> dict:
    return {"normal": _list(p.normal), "distance": float(p.distance), "thickness": float(p.thickness),
            "n_air": float(p.n_air), "n_glass": float(p.n_glass), "n_water": float(p.n_water)}


def planes_to_list(planes: list[LaserPlane]) -> list[dict]:
    return [{"normal": _list(p.normal), "offset": float(p.offset), "colour": _list(p.colour), "width": float(p.width),
             "fan_deg": float(p.fan_deg), "axis": _list(p.axis)} for p in planes]


def view_frames(scene, frames: list[int]) -> dict[int, list[int]]:
    """Training frames grouped by viewpoint (view id -> frame indices, in order)."""
    out: dict[int, list[int]] = {}
    for i in frames:
        out.setdefault(scene.frames[i].view, []).append(i)
    return out
