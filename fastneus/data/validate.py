"""Validation of scene files: one-line errors naming the file and field, JSON parsing, field
checks (numbers, strings, objects, matrices, ids) and the geometric checks of poses,
intrinsics and bounds. Every check raises :class:`~fastneus.errors.FastneusError`; nothing
is guessed.
"""
from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path
from typing import Any

import numpy as np

from fastneus.errors import FastneusError
from fastneus.geometry.cameras import rigid_inverse

POSE_TOL = 1e-4  # tolerance of the rigidity check R^T R = I
MAX_SIDE = 1 << 16  # image / projector width and height (JPEG's limit; no camera or projector is larger)


def field_error(msg: str, file, fld: str | None = None) -> FastneusError:
    return FastneusError(msg, file=file, field=fld)


def as_matrix(value: Any, shape: tuple[int, ...], file, fld: str) -> np.ndarray:
    """Parse a nested list into a finite float64 array of ``shape``."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise field_error(f"expected a {'x'.join(map(str, shape))} array of numbers", file, fld) from None
    if a.shape != shape:
        raise field_error(f"expected shape {'x'.join(map(str, shape))}, got {'x'.join(map(str, a.shape)) or 'scalar'}",
                          file, fld)
    if not np.all(np.isfinite(a)):
        raise field_error("contains non-finite values (nan/inf)", file, fld)
    return a


def show_value(value: Any) -> str:
    """``repr(value)`` cut to one short line (a 400-digit JSON integer would fill the screen)."""
    r = repr(value)
    return r if len(r) <= 40 and r.isprintable() else ascii(r[:32]) + "..."


def as_int(value: Any, file, fld: str, minimum: int = 1, maximum: int = 2 ** 31 - 1) -> int:
    """An integer in [minimum, maximum] (a float with an integer value is accepted; NaN, inf are not)."""
    if (isinstance(value, bool) or not isinstance(value, (int, float))
            or (isinstance(value, float) and not value.is_integer()) or not minimum <= value <= maximum):
        raise field_error(f"expected an integer in {minimum}..{maximum}, got {show_value(value)}", file, fld)
    return int(value)


def as_num(value: Any, file, fld: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise field_error(f"expected a finite number, got {value!r}", file, fld)
    return float(value)


def as_str(value: Any, file, fld: str) -> str:
    if not isinstance(value, str) or not value:
        raise field_error(f"expected a non-empty string, got {value!r}", file, fld)
    return value


def as_dict(value: Any, file, fld: str) -> dict:
    if not isinstance(value, dict):
        raise field_error(f"expected an object, got {type(value).__name__}", file, fld)
    return value


def require(d: dict, key: str, file, prefix: str) -> Any:
    if key not in d:
        raise field_error("missing", file, f"{prefix}.{key}" if prefix else key)
    return d[key]


def check_pose(T: Any, file, fld: str) -> np.ndarray:
    """Validate a rigid 4x4 transform (finite, R^T R = I within 1e-4, det +1, last row 0001)."""
    T = as_matrix(T, (4, 4), file, fld)
    if not np.allclose(T[3], [0, 0, 0, 1], atol=1e-9):
        raise field_error(f"last row must be 0 0 0 1, got {T[3].tolist()}", file, fld)
    R = T[:3, :3]
    err = np.abs(R.T @ R - np.eye(3)).max()
    if err > POSE_TOL:
        raise field_error(f"rotation is not orthonormal (max |R^T R - I| = {err:.3g} > {POSE_TOL})", file, fld)
    if np.linalg.det(R) < 0:
        raise field_error("rotation has determinant -1 (a reflection, not a rotation)", file, fld)
    return T


def check_intrinsics(K: Any, file, fld: str) -> np.ndarray:
    """Validate a 3x3 pinhole K (finite, fx, fy > 0, last row 0 0 1)."""
    K = as_matrix(K, (3, 3), file, fld)
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]):
        raise field_error("must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0", file, fld)
    return K


def check_principal_point(K: np.ndarray, width: int, height: int, file, fld: str) -> None:
    """Refuse a principal point more than one image size outside the image.

    Lens shift puts it off-centre (projectors: often at or past the bottom edge), but never
    that far: such a K is a typo or another unit, and every ray would miss the scene while
    training "succeeds" (metrics turned infinite).
    """
    cx, cy = float(K[0, 2]), float(K[1, 2])
    if not (-width <= cx <= 2 * width and -height <= cy <= 2 * height):
        raise field_error(f"principal point ({cx:.6g}, {cy:.6g}) lies far outside the {width}x{height} image "
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
        raise field_error(f"bounds radius {r:.4g} is more than {BOUNDS_MAX_RATIO:g}x the farthest camera's distance "
                          f"from the centre ({max(dists):.4g}); are the bounds in other units than the poses?",
                          file, fld)
    # a focal length under 0.005 px per pixel of width (a field of view over 179 degrees) is itself the error,
    # reported by fastneus.pipeline.check_inputs naming K; such views do not vote here
    px = [r * float(min(K[0, 0], K[1, 1])) / d if d > r else math.inf for (_, K, w), d in zip(views, dists)
          if min(K[0, 0], K[1, 1]) >= 0.005 * w]
    if px and max(px) < BOUNDS_MIN_PIXELS:
        raise field_error(f"bounds radius {r:.4g} spans under {BOUNDS_MIN_PIXELS} pixel in every image (at most "
                          f"{max(px):.3g}); are the bounds in other units than the poses?", file, fld)


def check_faces_bounds(dev_to_world: np.ndarray, center, radius: float, what: str, file, fld: str) -> None:
    """Refuse a camera or projector that has the whole region of interest behind it.

    Such a device can see (or light) nothing of the scene: usually a world->device pose given
    where device->world is expected, a projector pose inverted, or wrong bounds.
    """
    x = np.append(np.asarray(center, dtype=np.float64), 1.0)
    z = float((rigid_inverse(dev_to_world) @ x)[2])
    if z <= -radius:
        raise field_error(f"the scene (bounds centre {np.round(x[:3], 4).tolist()}, radius {radius:g}) lies entirely "
                          f"behind this {what} (depth {z:.3g}); is the pose inverted (world->{what} instead of "
                          f"{what}->world), or are the bounds wrong?", file, fld)


MAX_JSON_DEPTH = 64  # scene files nest 5 levels; deeper input would exhaust the recursion of later steps


def load_json(file: str | os.PathLike) -> Any:
    """Parse a JSON input file; every way it can be unreadable is one line naming it.

    Raises:
        FastneusError: unreadable, not UTF-8, invalid JSON, or nested deeper than :data:`MAX_JSON_DEPTH`.
    """
    try:
        data = json.loads(Path(file).read_bytes().decode("utf-8-sig"))
    except OSError as e:
        raise field_error(f"cannot read: {e.strerror or e}", file) from None
    except UnicodeDecodeError as e:
        raise field_error(f"not UTF-8 text (byte {e.start}); JSON files are UTF-8", file) from None
    except json.JSONDecodeError as e:
        raise field_error(f"invalid JSON at line {e.lineno} column {e.colno}: {e.msg}", file) from None
    except RecursionError:
        raise field_error(f"invalid JSON: nested deeper than Python can parse (a scene nests {MAX_JSON_DEPTH} levels "
                          "at most)", file) from None
    stack = [(data, 0)]  # iterative: the check itself must not recurse
    while stack:
        v, depth = stack.pop()
        if depth > MAX_JSON_DEPTH:
            raise field_error(f"nested more than {MAX_JSON_DEPTH} levels deep; not a scene file", file)
        if isinstance(v, dict):
            stack.extend((x, depth + 1) for x in v.values())
        elif isinstance(v, list):
            stack.extend((x, depth + 1) for x in v)
    return data


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
        raise field_error(f"unsafe id {value!r}: ids may use {SAFE_ID_RULE}", file, id_field(prefix, value))
    return value
