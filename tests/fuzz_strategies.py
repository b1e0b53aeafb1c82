"""Property-based fuzz of every input parser: strategies and the property, shared by
``tests/test_fuzz.py`` (a few hundred examples in CI) and ``scripts/fuzz.py`` (long runs).

Each target starts from a valid small input (built by :func:`build_bases` from a tiny
synthetic scene) and applies random structural mutations: delete or rename a key, replace
a value by another JSON/YAML type, NaN, Infinity, a huge or negative number, a deep list
or odd unicode, duplicate entries, change npz array shapes and dtypes (object arrays
holding a payload that would touch a marker file if it were ever unpickled), truncate or
flip bytes. The property (:func:`check_case`): the loader the verbs call either succeeds
or raises :class:`~fastneus.errors.FastneusError` with a one-line message naming an input
file (or the command line for ``key=value`` overrides); never another exception, never a
hang (:data:`HANG_S`), never a pickle run.

Targets: ``scene`` (scene.json), ``nerf`` (transforms.json), ``activeneus`` and ``neus``
(cameras_sphere.npz), ``opencv`` (calibration YAML/XML through the import-calib builder),
``colmap`` (cameras.txt / images.txt / points3D.txt through the same builder), ``colmap_bin``
(cameras.bin / images.bin / points3D.bin: counts, ids, poses and names overwritten with odd values,
truncation, flipped bytes), ``config``
(a YAML config file) and ``overrides`` (``key=value`` strings).
"""
from __future__ import annotations

import copy
import io
import json
import math
import shutil
import signal
import struct
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
from hypothesis import strategies as st

HANG_S = 20.0  # one example past this is a hang (the hypothesis deadline catches slow ones far earlier)
TARGETS = ("scene", "nerf", "activeneus", "neus", "opencv", "colmap", "colmap_bin", "config", "overrides")


# --------------------------------------------------------------------------- payload
def _touch(path: str) -> None:
    """What an unpickled :class:`Payload` would run: create the marker file."""
    Path(path).write_text("unpickled")


class Payload:
    """An object whose unpickling creates ``marker``: proves a loader never unpickles."""

    def __init__(self, marker: str):
        self.marker = marker

    def __reduce__(self):
        return _touch, (self.marker,)


# --------------------------------------------------------------------------- odd values
WEIRD_FLOATS = [math.nan, math.inf, -math.inf, 1e308, -1e308, 1e-300, -0.0, 5e-324, 1e200, -1.0, 0.0]
WEIRD_INTS = [0, -1, 1, 2, -2 ** 31, 2 ** 31, 2 ** 63, 2 ** 70, 10 ** 30, 100000]
ODD_TEXT = ["", " ", "\x00", "a\x00b", "\u202e", "é", "\U0001f600", "\ud800", "\udcff", "../../../../etc/passwd",
            "/abs/path.png", "a" * 3000, "NaN", "Infinity", "1e999", "\n", "line\nbreak", "C:\\x", "~", "$HOME",
            "%s%n", "null", "true", "[1]", "{}", "*", "cam0", "proj0", ".", "..", "image/000.png"]


def deep_list(depth: int, leaf: Any = 1) -> Any:
    v = leaf
    for _ in range(depth):
        v = [v]
    return v


def weird_values() -> st.SearchStrategy:
    """Values of every JSON type and then some: non-finite, huge, negative, deep, odd text."""
    scalars = st.one_of(st.none(), st.booleans(), st.sampled_from(WEIRD_INTS), st.integers(),
                        st.sampled_from(WEIRD_FLOATS), st.floats(), st.sampled_from(ODD_TEXT), st.text(max_size=12))
    return st.one_of(
        scalars, scalars, scalars,
        st.builds(deep_list, st.sampled_from([2, 10, 200])),
        st.lists(scalars, max_size=5),
        st.lists(st.lists(st.floats(), min_size=4, max_size=4), min_size=0, max_size=5),
        st.dictionaries(st.sampled_from(ODD_TEXT[:10]) | st.text(max_size=4), scalars, max_size=3),
    )


odd_keys = st.one_of(st.sampled_from(ODD_TEXT), st.text(max_size=8))


# --------------------------------------------------------------------------- tree mutations
def _nodes(doc: Any, path: tuple = ()) -> list[tuple]:
    out, stack = [], [(path, doc)]
    while stack:
        p, v = stack.pop()
        out.append(p)
        if len(p) > 40:  # inside a deep list: mutating deeper adds nothing
            continue
        if isinstance(v, dict):
            stack.extend((p + (k,), x) for k, x in v.items())
        elif isinstance(v, list):
            stack.extend((p + (i,), x) for i, x in enumerate(v))
    return out


def _get(doc: Any, path: tuple) -> Any:
    for k in path:
        doc = doc[k]
    return doc


def _set(doc: Any, path: tuple, value: Any) -> Any:
    if not path:
        return value
    _get(doc, path[:-1])[path[-1]] = value
    return doc


def _retype(v: Any) -> Any:
    """The same content as another type: number <-> string, list <-> object."""
    if isinstance(v, bool):
        return int(v)
    if isinstance(v, (int, float)):
        return str(v)
    if isinstance(v, str):
        try:
            return float(v)
        except ValueError:
            return [v]
    if isinstance(v, list):
        return {str(i): x for i, x in enumerate(v)}
    if isinstance(v, dict):
        return list(v.values())
    return {}


# plausible sub-trees a mutation may graft into an object (key, value): they reach the code
# paths the base file does not use (ports, laser projectors, free projectors, ground truth...)
_PORT = {"normal": [0.0, 0.0, 1.0], "distance": 0.05, "thickness": 0.01, "n_air": 1.0, "n_glass": 1.5,
         "n_water": 1.333}
_PLANES = [{"normal": [1.0, 0.0, 0.0], "offset": 0.0, "colour": [1.0, 0.0, 0.0], "width": 0.002, "fan_deg": 60.0}]
GRAFTS = [("port", _PORT), ("port", {**_PORT, "normal": [0.0, 0.0, -1.0]}), ("kind", "laser"), ("planes", _PLANES),
          ("laser0", {"kind": "laser", "proj_to_cam": np.eye(4).tolist(), "planes": _PLANES}),
          ("proj_to_cam", None), ("proj_to_world", np.eye(4).tolist()), ("on", False), ("pattern", None),
          ("gt", {"depth": "gt/000_depth.npy"}), ("gt", {"mesh": "scene.json"}), ("mask", "scene.json"),
          ("illumination", {"i_r": 0.4, "i_b": 0.1, "ambient": 1.0, "known": True}), ("dist", [0.1, 0, 0, 0, 0]),
          ("view", 0), ("camera_model", "OPENCV_FISHEYE"), ("k4", 0.1), ("camera_angle_x", 0.8),
          ("camera_angle_y", 3.5), ("mask_path", "images/000.png"), ("transform_matrix", np.eye(4).tolist()),
          ("projectors", {"proj9": {"pattern": None}}), ("bounds", {"center": [0, 0, 0], "radius": 1e-300}),
          ("units", "mm"), ("meta", {"x": [1]})]


@st.composite
def mutate_tree(draw, base: Any, max_ops: int = 3) -> tuple[Any, list[str]]:
    """A deep copy of ``base`` (parsed JSON/YAML) with 1..max_ops random structural edits."""
    doc = copy.deepcopy(base)
    log = []
    for _ in range(draw(st.integers(1, max_ops))):
        paths = _nodes(doc)
        path = draw(st.sampled_from(sorted(paths, key=lambda p: (len(p), repr(p)))))
        op = draw(st.sampled_from(["delete", "replace", "replace", "replace", "rename", "duplicate", "wrap",
                                   "retype", "numeric", "graft", "graft"]))
        node = _get(doc, path)
        parent = _get(doc, path[:-1]) if path else None
        if op == "graft" and isinstance(node, dict):
            k, v = draw(st.sampled_from(GRAFTS))
            node[k] = copy.deepcopy(v)
            path = path + (k,)
        elif op == "delete" and path:
            del parent[path[-1]]
        elif op == "rename" and isinstance(parent, dict):
            new = draw(odd_keys | st.sampled_from([k for k in parent if isinstance(k, str)] or ["x"]))
            parent[new] = parent.pop(path[-1])
        elif op == "duplicate" and isinstance(parent, list):
            parent.insert(path[-1], copy.deepcopy(node))
        elif op == "duplicate" and isinstance(parent, dict):
            parent[draw(odd_keys)] = copy.deepcopy(node)
        elif op == "wrap":
            doc = _set(doc, path, draw(st.sampled_from([[node], {"x": node}, deep_list(100, node)])))
        elif op == "retype":
            doc = _set(doc, path, _retype(node))
        elif op == "numeric" and isinstance(node, list) and node:
            how = draw(st.sampled_from(["append", "pop", "set"]))
            if how == "append":
                node.append(draw(st.sampled_from(WEIRD_FLOATS + WEIRD_INTS)))
            elif how == "pop":
                node.pop()
            else:
                node[draw(st.integers(0, len(node) - 1))] = draw(st.sampled_from(WEIRD_FLOATS + WEIRD_INTS))
        elif op == "numeric":
            doc = _set(doc, path, draw(st.sampled_from(WEIRD_FLOATS + WEIRD_INTS)))
        else:
            op = "replace"
            doc = _set(doc, path, draw(weird_values()))
        log.append(f"{op} {'.'.join(map(str, path)) or '<root>'}"[:200])
    return doc, log


@st.composite
def mutate_bytes(draw, data: bytes) -> tuple[bytes, str]:
    """Byte-level damage: truncation, flipped or inserted bytes, invalid UTF-8, a BOM, deep nesting."""
    op = draw(st.sampled_from(["truncate", "flip", "insert", "bom", "deep", "nul", "crlf"]))
    n = len(data)
    if op == "truncate":
        i = draw(st.integers(0, max(0, n - 1)))
        return data[:i], f"truncate at {i}"
    if op == "flip" and n:
        i = draw(st.integers(0, n - 1))
        b = draw(st.integers(1, 255))
        return data[:i] + bytes([data[i] ^ b]) + data[i + 1:], f"xor byte {i} with {b}"
    if op == "insert":
        i = draw(st.integers(0, n))
        ins = draw(st.sampled_from([b"\xff\xfe", b"\xc3", b"\x80", b"\xed\xa0\x80", b"\x00", b"\"", b"{", b"]"]))
        return data[:i] + ins + data[i:], f"insert {ins!r} at {i}"
    if op == "bom":
        return b"\xef\xbb\xbf" + data, "UTF-8 BOM"
    if op == "nul":
        return data.replace(b" ", b"\x00", 1), "NUL for the first space"
    if op == "crlf":
        return data.replace(b"\n", b"\r"), "CR line ends"
    depth = draw(st.sampled_from([1000, 100_000]))
    return b"[" * depth + b"]" * depth, f"nested {depth} deep"


@st.composite
def json_bytes(draw, base: dict) -> tuple[bytes, str]:
    """A mutated JSON document (NaN/Infinity allowed, as Python writes them) as bytes."""
    doc, log = draw(mutate_tree(base))
    ascii_only = draw(st.booleans())
    data = json.dumps(doc, ensure_ascii=ascii_only).encode("utf-8", "surrogatepass")
    if draw(st.integers(0, 4)) == 0:
        data, what = draw(mutate_bytes(data))
        log.append(what)
    return data, "; ".join(log)


# --------------------------------------------------------------------------- npz
NPZ_DTYPES = ["int8", "uint8", "int64", "bool", "float16", "float32", "complex128", "U8", "S8", "M8[s]", "m8[s]",
              "struct", "void"]


@st.composite
def weird_array(draw, like: np.ndarray, marker: str) -> tuple[np.ndarray, str]:
    kind = draw(st.sampled_from(["shape", "dtype", "nonfinite", "huge", "scalar", "empty", "object", "zeros",
                                 "transpose", "negate", "many"]))
    a = np.asarray(like)
    if a.dtype.kind != "f":  # an entry an earlier mutation retyped: start again from floats of its shape
        a = np.ones(a.shape if a.dtype != object else (4, 4))
    if kind == "shape":
        shape = tuple(draw(st.lists(st.integers(0, 5), max_size=4)))
        return np.random.default_rng(0).normal(size=shape), f"shape {shape}"
    if kind == "dtype":
        dt = draw(st.sampled_from(NPZ_DTYPES))
        if dt == "struct":
            return np.zeros(a.shape, dtype=[("a", "f8"), ("b", "i4")]), dt
        if dt == "void":
            return np.zeros(a.shape, dtype="V8"), dt
        if dt.startswith(("M8", "m8")):
            return np.zeros(a.shape, dtype=dt), dt
        with np.errstate(all="ignore"):
            return a.astype(dt), dt
    if kind == "nonfinite" and a.size and a.dtype.kind == "f":
        b = a.astype(np.float64).copy()
        b.flat[draw(st.integers(0, a.size - 1))] = draw(st.sampled_from(WEIRD_FLOATS))
        return b, "one entry non-finite/extreme"
    if kind == "huge":
        with np.errstate(all="ignore"):
            return a * draw(st.sampled_from([1e300, -1e300, 1e-300])), "scaled to extreme"
    if kind == "scalar":
        return np.float64(draw(st.floats())), "0-d"
    if kind == "empty":
        return np.zeros((0,)), "empty"
    if kind == "object":
        what = draw(st.sampled_from(["payload0d", "payload", "dict", "list", "none"]))
        if what == "payload0d":
            o = np.empty((), dtype=object)
            o[()] = Payload(marker)
            return o, "0-d object array holding a payload"
        if what == "payload":
            return np.array([Payload(marker), 1.0], dtype=object), "object array holding a payload"
        o = np.empty((), dtype=object)
        o[()] = {"dict": {"ambient": 1.0}, "list": [1.0, 2.0], "none": None}[what]
        return o, f"0-d object array holding a {what}"
    if kind == "zeros":
        return np.zeros_like(a, dtype=np.float64) if a.dtype != object else np.zeros(3), "zeros"
    if kind == "transpose" and a.ndim >= 2:
        return np.swapaxes(a, -1, -2), "transposed"
    if kind == "negate" and a.dtype.kind == "f":
        return -a, "negated"
    n = draw(st.sampled_from([1000, 3])) if a.size <= 64 else 3  # not stacks of stacks (hundreds of MB)
    return np.zeros((n,) + a.shape), "stacked copies"


@st.composite
def weird_illumination(draw, marker: str) -> tuple[np.ndarray, str]:
    """A pickled 0-d object array like the official ``illumination_params``, with odd content."""
    d: Any = {"ambient": 1.0, "diffuse": 0.4, "emissive": 0.1}
    what = draw(st.sampled_from(["value", "delete", "intkey", "payload", "shared", "notdict", "numpy"]))
    if what == "value":
        d[draw(st.sampled_from(sorted(d)))] = draw(weird_values())
    elif what == "delete":
        del d[draw(st.sampled_from(sorted(d)))]
    elif what == "intkey":
        d[1] = 2.0
    elif what == "payload":
        d["diffuse"] = Payload(marker)
    elif what == "shared":  # a memo-shared fan-out: ~1 KB describing fan**depth leaves
        fan, depth = draw(st.sampled_from([(64, 6), (16, 4), (4, 3)]))
        leaf: Any = [1.0]
        for _ in range(depth):
            leaf = [leaf] * fan
        d["ambient"] = leaf
    elif what == "numpy":
        d["ambient"] = draw(st.sampled_from([np.float32(1.0), np.int64(2), np.complex128(1j), np.array([1.0]),
                                             np.bool_(True), np.float64(np.nan)]))
    else:
        d = draw(st.sampled_from([[1.0, 2.0], "ambient", 3.0, None]))
    o = np.empty((), dtype=object)
    o[()] = d
    return o, f"illumination_params: {what}"


@st.composite
def npz_bytes(draw, base: dict[str, np.ndarray], marker: str) -> tuple[bytes, str]:
    """A mutated ``cameras_sphere.npz`` (keys deleted/renamed/added, arrays reshaped/retyped, pickles) as bytes."""
    arrays = dict(base)
    log = []
    for _ in range(draw(st.integers(1, 3))):
        key = draw(st.sampled_from(sorted(arrays) or ["cam_mat_0"]))
        op = draw(st.sampled_from(["delete", "rename", "add", "value", "value", "value"]))
        if key not in arrays:
            op = "add"
        if op == "delete":
            del arrays[key]
        elif op == "rename":
            new = draw(st.sampled_from([key + "0", key.replace("_0", "_-1"), key.upper(), "é" + key, key + "_99",
                                        key.replace("_0", "_1")]))
            arrays[new] = arrays.pop(key)
            key = f"{key} -> {new}"
        elif op == "add":
            key = draw(st.sampled_from(["cam_mat_3", "cam_pose_99", "proj_mat_3", "camera_refraction",
                                        "projector_refraction", "illumination_params", "world_mat_3", "scale_mat_3"]))
            arrays[key] = draw(weird_illumination(marker))[0] if "refraction" in key or "illum" in key \
                else draw(weird_array(np.eye(4), marker))[0]
        elif key == "illumination_params" or arrays[key].dtype == object:
            arrays[key], what = draw(weird_illumination(marker))
            key = f"{key} ({what})"
        else:
            arrays[key], what = draw(weird_array(arrays[key], marker))
            key = f"{key} ({what})"
        log.append(f"{op} {key}")
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    data = buf.getvalue()
    if draw(st.integers(0, 5)) == 0:
        data, what = draw(mutate_bytes(data))
        log.append(what)
    return data, "; ".join(log)


# --------------------------------------------------------------------------- OpenCV FileStorage
# a node: ("mat", rows, cols, dt, [tokens]) | ("scalar", token) | ("seq", [tokens]) | ("map", [(key, node)])
CALIB_KEYS = ["cam_K", "cam_kc", "proj_K", "proj_kc", "R", "T", "M1", "D1", "M2", "D2", "cam_int", "cam_dist",
              "proj_int", "proj_dist", "rotation", "roration", "translation", "cam_width", "cam_height",
              "image_width", "image_height", "cam_size", "image_size", "imageSize", "img_shape", "cam_shape",
              "proj_width", "proj_height", "proj_size", "proj_shape"]
CV_TOKENS = [".Nan", ".Inf", "-.Inf", "1e999", "1e308", "-1e308", "1e-320", "0", "-1", "1", "24", "64", "48",
             "2147483648", "9223372036854775808", "1180591620717411303424", "abc", '"x"', "", "é", "\U0001f600",
             "[", "]", "{", ":", "-", "0x10", "1.5.2", "+", "1e", "nan", "inf", "100000"]


def _tok(x: float) -> str:
    if math.isnan(x):
        return ".Nan"
    if math.isinf(x):
        return ".Inf" if x > 0 else "-.Inf"
    return repr(float(x))


def calib_model(arrays: dict[str, np.ndarray], scalars: dict[str, Any] | None = None) -> list:
    """The (key, node) list a valid calibration file renders from."""
    m = [(k, ("mat", str(a.shape[0]), str(a.shape[1] if a.ndim > 1 else 1), "d", [_tok(v) for v in a.reshape(-1)]))
         for k, a in arrays.items()]
    m += [(k, ("scalar", str(v))) for k, v in (scalars or {}).items()]
    return m


def render_yaml(model: list) -> str:
    def node(n, ind):
        if n[0] == "mat":
            _, r, c, dt, data = n
            return (f" !!opencv-matrix\n{ind}   rows: {r}\n{ind}   cols: {c}\n{ind}   dt: {dt}\n"
                    f"{ind}   data: [ {', '.join(data)} ]\n")
        if n[0] == "scalar":
            return f" {n[1]}\n"
        if n[0] == "seq":
            return f" [ {', '.join(n[1])} ]\n"
        return "\n" + "".join(f"{ind}   {k}:{node(v, ind + '   ')}" for k, v in n[1])
    return "%YAML:1.0\n---\n" + "".join(f"{k}:{node(n, '')}" for k, n in model)


def render_xml(model: list) -> str:
    def node(k, n):
        if n[0] == "mat":
            _, r, c, dt, data = n
            return (f'<{k} type_id="opencv-matrix">\n  <rows>{r}</rows>\n  <cols>{c}</cols>\n  <dt>{dt}</dt>\n'
                    f"  <data>\n    {' '.join(data)}</data></{k}>\n")
        if n[0] == "scalar":
            return f"<{k}>{n[1]}</{k}>\n"
        if n[0] == "seq":
            return f"<{k}>\n  {' '.join(n[1])}</{k}>\n"
        return f"<{k}>\n" + "".join(node(kk, v) for kk, v in n[1]) + f"</{k}>\n"
    return '<?xml version="1.0"?>\n<opencv_storage>\n' + "".join(node(k, n) for k, n in model) + "</opencv_storage>\n"


@st.composite
def weird_cv_node(draw, node=None):
    kind = draw(st.sampled_from(["mat", "scalar", "seq", "map"]))
    tokens = st.sampled_from(CV_TOKENS) | st.floats().map(_tok)
    if kind == "mat":
        r, c = draw(st.sampled_from(["3", "1", "0", "-1", "2", "100000", "x"])), draw(st.sampled_from(["3", "1", "5"]))
        return ("mat", r, c, draw(st.sampled_from(["d", "f", "i", "u", "c", "s", "w", "z", "dd", "3d", "", "<"])),
                draw(st.lists(tokens, max_size=12)))
    if kind == "scalar":
        return ("scalar", draw(tokens))
    if kind == "seq":
        return ("seq", draw(st.lists(tokens, max_size=4)))
    return ("map", [("a", ("scalar", draw(tokens)))] + ([("b", node)] if node is not None else []))


@st.composite
def calib_bytes(draw, model: list) -> tuple[str, bytes, str]:
    """(file suffix, mutated OpenCV YAML/XML calibration, what was done)."""
    model = copy.deepcopy(model)
    log = []
    for _ in range(draw(st.integers(1, 3))):
        i = draw(st.integers(0, max(0, len(model) - 1)))
        op = draw(st.sampled_from(["delete", "rename", "duplicate", "add", "replace", "mat", "mat", "mat"]))
        if not model:
            op = "add"
        if op == "delete":
            k, _ = model.pop(i)
        elif op == "rename":
            k, n = model[i]
            model[i] = (draw(st.sampled_from(CALIB_KEYS + ["x", "_", "a-b", "K" * 300])), n)
        elif op == "duplicate":
            k, _ = model[i]
            model.insert(i, model[i])
        elif op == "add":
            k = draw(st.sampled_from(CALIB_KEYS))
            model.append((k, draw(weird_cv_node())))
        elif op == "replace" or model[i][1][0] != "mat":
            k, n = model[i]
            model[i] = (k, draw(weird_cv_node(n)))
        else:
            k, (_, r, c, dt, data) = model[i]
            part = draw(st.sampled_from(["rows", "cols", "dt", "token", "drop", "extra"]))
            if part == "rows":
                r = draw(st.sampled_from(["0", "-1", "1", "9", "100000", "2147483648", "x", "3.5", ""]))
            elif part == "cols":
                c = draw(st.sampled_from(["0", "-3", "9", "100000", "x"]))
            elif part == "dt":
                dt = draw(st.sampled_from(["f", "i", "u", "c", "s", "w", "z", "dd", "3d", "", "<", "ddd"]))
            elif part == "token" and data:
                data = list(data)
                data[draw(st.integers(0, len(data) - 1))] = draw(st.sampled_from(CV_TOKENS))
            elif part == "drop" and data:
                data = data[:-1]
            else:
                data = list(data) + [draw(st.sampled_from(CV_TOKENS))]
            model[i] = (k, ("mat", r, c, dt, data))
            op = f"mat.{part}"
        log.append(f"{op} {k}"[:80])
    xml = draw(st.booleans())
    data = (render_xml(model) if xml else render_yaml(model)).encode("utf-8", "surrogatepass")
    if draw(st.integers(0, 5)) == 0:
        data, what = draw(mutate_bytes(data))
        if what.startswith("nested"):  # a nested value, as the format allows, rather than a bare bracket run
            depth = int(what.split()[1])
            data = (b'<?xml version="1.0"?>\n<opencv_storage>\n<x>' + b"<_>" * depth + b"1" + b"</_>" * depth
                    + b"</x>\n</opencv_storage>\n") if xml else \
                b"%YAML:1.0\n---\nx: " + b"[" * depth + b"1" + b"]" * depth + b"\n"
        log.append(what)
    return (".xml" if xml else ".yml"), data, "; ".join(log)


# --------------------------------------------------------------------------- COLMAP text
COLMAP_TOKENS = ["nan", "inf", "-inf", "1e200", "-1e200", "1e-320", "1e309", "-1", "0", "1", "1.5", str(2 ** 70),
                 "abc", "é", "PINHOLE", "OPENCV", "SIMPLE_RADIAL", "FISHEYE", "000.png", "../x.png", "#", ""]


@st.composite
def colmap_text(draw, text: str) -> tuple[bytes, str]:
    """A mutated COLMAP text file (token, line and byte edits)."""
    lines = [ln.split(" ") for ln in text.split("\n")]
    log = []
    for _ in range(draw(st.integers(1, 3))):
        i = draw(st.integers(0, len(lines) - 1)) if lines else 0
        op = draw(st.sampled_from(["token", "token", "token", "deltoken", "addtoken", "delline", "dupline",
                                   "swapline", "newline", "comment"]))
        if not lines:
            op = "newline"
        if op in ("token", "deltoken") and lines[i] and lines[i] != [""]:
            j = draw(st.integers(0, len(lines[i]) - 1))
            if op == "token":
                lines[i][j] = draw(st.sampled_from(COLMAP_TOKENS) | st.floats().map(repr))
            else:
                del lines[i][j]
        elif op == "addtoken":
            lines[i].insert(draw(st.integers(0, len(lines[i]))), draw(st.sampled_from(COLMAP_TOKENS)))
        elif op == "delline":
            del lines[i]
        elif op == "dupline":
            lines.insert(i, list(lines[i]))
        elif op == "swapline":
            j = draw(st.integers(0, len(lines) - 1))
            lines[i], lines[j] = lines[j], lines[i]
        elif op == "comment":
            lines.insert(i, ["#", "comment"])
        else:
            lines.insert(i, draw(st.lists(st.sampled_from(COLMAP_TOKENS), max_size=12)))
        log.append(f"{op} line {i}")
    data = "\n".join(" ".join(t) for t in lines).encode("utf-8", "surrogatepass")
    if draw(st.integers(0, 5)) == 0:
        data, what = draw(mutate_bytes(data))
        log.append(what)
    return data, "; ".join(log)


@st.composite
def points3d_text(draw) -> tuple[bytes, str]:
    """A points3D.txt: enough points (>= 10) to set the bounds, some of them odd."""
    n = draw(st.integers(0, 20))
    same = draw(st.booleans())
    pts = []
    for j in range(n):
        xyz = ["0.1", "0.2", "0.3"] if same else [repr(0.1 * j), "0.0", repr(-0.05 * j)]
        if draw(st.integers(0, 3)) == 0:
            xyz[draw(st.integers(0, 2))] = draw(st.sampled_from(COLMAP_TOKENS))
        pts.append(" ".join([str(j + 1), *xyz, "128", "128", "128", "0.5"]))
    return "\n".join(pts).encode("utf-8", "surrogatepass"), f"points3D.txt: {n} points{' all equal' if same else ''}"


# --------------------------------------------------------------------------- COLMAP binary
# COLMAP's model ids (sensor/models.h), written out here so the writer does not lean on the reader's table
COLMAP_MODEL_IDS = {"SIMPLE_PINHOLE": 0, "PINHOLE": 1, "SIMPLE_RADIAL": 2, "RADIAL": 3, "OPENCV": 4,
                    "OPENCV_FISHEYE": 5, "FULL_OPENCV": 6, "FOV": 7, "SIMPLE_RADIAL_FISHEYE": 8, "RADIAL_FISHEYE": 9,
                    "THIN_PRISM_FISHEYE": 10, "RAD_TAN_THIN_PRISM_FISHEYE": 11}


class _Packer:
    """Little-endian bytes with the offset, format and name of every field written (for mutations)."""

    def __init__(self):
        self.data, self.fields = bytearray(), []

    def put(self, fmt: str, label: str, *values) -> None:
        self.fields.append((len(self.data), fmt, label))
        self.data += struct.pack("<" + fmt, *values)


def colmap_binary(cameras, images, points=None) -> tuple[dict[str, bytes], dict[str, list]]:
    """A COLMAP binary model as COLMAP writes it (``Reconstruction::Write*Binary``, little-endian).

    Args:
        cameras: [(camera_id, model_name, width, height, params)].
        images: [(image_id, qvec (w, x, y, z), tvec, camera_id, name, points2d [(x, y, point3D_id)])].
        points: [(point3D_id, xyz, rgb, error, track [(image_id, point2D_idx)])], or None for no points3D.bin.
    Returns:
        ({file name: bytes}, {file name: [(offset, struct format, label)]}).
    """
    out, fields = {}, {}
    c = _Packer()
    c.put("Q", "num_cameras", len(cameras))
    for cid, model, w, h, params in cameras:
        c.put("I", "camera_id", cid)
        c.put("i", "model_id", COLMAP_MODEL_IDS[model])
        c.put("Q", "width", w)
        c.put("Q", "height", h)
        for v in params:
            c.put("d", "param", float(v))
    im = _Packer()
    im.put("Q", "num_reg_images", len(images))
    for iid, q, t, cid, name, pts2d in images:
        im.put("I", "image_id", iid)
        for v in q:
            im.put("d", "qvec", float(v))
        for v in t:
            im.put("d", "tvec", float(v))
        im.put("I", "camera_id", cid)
        im.fields.append((len(im.data), "name", "name"))
        im.data += name.encode("utf-8") + b"\0"
        im.put("Q", "num_points2D", len(pts2d))
        for x, y, pid in pts2d:
            im.put("ddq", "point2D", x, y, pid)
    out["cameras.bin"], fields["cameras.bin"] = bytes(c.data), c.fields
    out["images.bin"], fields["images.bin"] = bytes(im.data), im.fields
    if points is not None:
        pt = _Packer()
        pt.put("Q", "num_points", len(points))
        for pid, xyz, rgb, err, track in points:
            pt.put("Q", "point3D_id", pid)
            for v in xyz:
                pt.put("d", "xyz", float(v))
            pt.put("BBB", "rgb", *rgb)
            pt.put("d", "error", err)
            pt.put("Q", "track_length", len(track))
            for a, b in track:
                pt.put("II", "track", a, b)
        out["points3D.bin"], fields["points3D.bin"] = bytes(pt.data), pt.fields
    return out, fields


ODD_FIELD = {"Q": [0, 1, 2, 3, 2 ** 31, 2 ** 32 + 1, 2 ** 61, 2 ** 63, 2 ** 64 - 1],
             "I": [0, 1, 2 ** 31, 2 ** 32 - 1], "i": [-1, 12, 99, 100, -2 ** 31, 2 ** 31 - 1],
             "d": WEIRD_FLOATS}


@st.composite
def colmap_bin_bytes(draw, files: dict[str, bytes], fields: dict[str, list]) -> tuple[str, bytes, str]:
    """One file of a COLMAP binary model with a field overwritten by an odd value (a count, id,
    model id, pose value, the name's terminator), a byte flipped or the file cut short."""
    name = draw(st.sampled_from(sorted(files)))
    data = bytearray(files[name])
    op = draw(st.sampled_from(["field", "field", "field", "truncate", "flip", "append"]))
    if op == "truncate":
        i = draw(st.integers(0, max(0, len(data) - 1)))
        return name, bytes(data[:i]), f"{name}: truncate at {i}"
    if op == "flip":
        i, b = draw(st.integers(0, len(data) - 1)), draw(st.integers(1, 255))
        data[i] ^= b
        return name, bytes(data), f"{name}: xor byte {i} with {b}"
    if op == "append":
        extra = draw(st.sampled_from([b"\0", b"\xff" * 8, b"\0" * 43]))
        return name, bytes(data) + extra, f"{name}: append {len(extra)} bytes"
    off, fmt, label = draw(st.sampled_from(fields[name]))
    if fmt == "name":
        end = data.index(b"\0", off)
        new = draw(st.sampled_from([b"", b"\xff\xfe", b"x" * 5000, "é/../x.png".encode(), b"001.png"]))
        keep_nul = draw(st.booleans())
        data[off:end + 1] = new + (b"\0" if keep_nul else b"")
        return name, bytes(data), f"{name}: name at {off} -> {new[:20]!r}{'' if keep_nul else ' without NUL'}"
    f0 = fmt[0]
    v = draw(st.sampled_from(ODD_FIELD.get(f0, [0, 255])) if f0 in ODD_FIELD else st.integers(0, 255))
    if f0 in "Ii" or f0 == "Q":
        vals = [v] + [0] * (len(fmt) - 1)
    elif f0 == "d":
        vals = [v] + [0.0] * (len(fmt) - 1) if fmt != "ddq" else [v, 0.0, -1]
    else:
        vals = [v] * len(fmt)
    struct.pack_into("<" + fmt, data, off, *vals)
    return name, bytes(data), f"{name}: {label} at {off} -> {v!r}"


# --------------------------------------------------------------------------- config
YAML_SNIPPETS = ["!!python/object/apply:fuzz_strategies._touch ['{marker}']", "1: 2", "? [1, 2]\n: 3",
                 "steps: &a [*a]", "steps: 0x10", "steps: 1_000", "steps: 1e400", "lr: .nan", "lr: -.inf",
                 "steps: !!binary aGVsbG8=", "steps: !!timestamp 2001-12-14", "steps: !!set {a, b}",
                 "render_frames: [[1, 2], 3]", "render_frames: {a: 1}", "render_frames: [1e400]",
                 "render_frames: [.nan]", "render_frames: [true]", "preset: [1]", "seed: -1", "seed: 1180591620717411303424",
                 "threads: 1e20", "steps: \"many\"", "masks: off", "levels: 2.5", "a" * 300 + ": 1", "null: 1",
                 "<<: {steps: 3}", "steps:\n  - 1\n  - [2]"]


@st.composite
def config_bytes(draw, base: dict, marker: str) -> tuple[bytes, str]:
    import yaml

    doc, log = draw(mutate_tree(base, max_ops=2))
    text = yaml.safe_dump(doc, allow_unicode=draw(st.booleans()))
    if draw(st.booleans()):
        snip = draw(st.sampled_from(YAML_SNIPPETS)).replace("{marker}", marker)
        text = (text if isinstance(doc, dict) else "") + snip + "\n"
        log.append(f"append {snip[:40]!r}")
    data = text.encode("utf-8", "surrogatepass")
    if draw(st.integers(0, 4)) == 0:
        data, what = draw(mutate_bytes(data))
        log.append(what)
    return data, "; ".join(log)


OVERRIDE_VALUES = ["3", "-1", "0", "1e400", ".nan", "-.inf", "1e20", "2.5", "true", "off", "null", "~", "[1, 2]",
                   "[[1]]", "[1e400]", "{a: 1}", "'x'", "\"", "[", "&a [*a]", "!!python/object:os.system", "é",
                   "\U0001f600", "\x00", "", " ", "many", "0x10", str(2 ** 70), "1_000", "!!binary aGk=",
                   "[" * 2000 + "]" * 2000]


@st.composite
def override_list(draw, keys: list[str]) -> tuple[list[str], str]:
    items = []
    for _ in range(draw(st.integers(1, 4))):
        k = draw(st.sampled_from(keys) | odd_keys)
        if draw(st.integers(0, 9)) == 0:
            items.append(k)  # no "="
        else:
            items.append(f"{k}={draw(st.sampled_from(OVERRIDE_VALUES) | st.text(max_size=8))}")
    return items, " ".join(repr(x)[:60] for x in items)


# --------------------------------------------------------------------------- bases
def synth_scene(folder: Path) -> Path:
    """The tests' small scene (conftest ``small_scene``): a sphere, 3 views of 24x24, one projector."""
    from fastneus.synth.render import synthesize

    scene = synthesize(folder, shape="sphere", views=3, size=(24, 24), pattern="crosslaser", illum="normal", seed=0,
                       device="cpu", proj_size=(64, 48), progress=False, contact_sheet=False)
    scene.gt_mesh = None
    scene.save()
    return folder


def build_bases(root: Path, scene_dir: Path) -> dict[str, Path]:
    """Valid inputs of every kind, written under ``root`` from the fastneus scene ``scene_dir``."""
    import cv2
    from scipy.spatial.transform import Rotation

    from fastneus.data import Scene
    from fastneus.formats.activeneus import write_activeneus
    from fastneus.formats.nerf import write_nerf

    root.mkdir(parents=True, exist_ok=True)
    scene = Scene.load(scene_dir)
    b = {"scene": root / "scene", "nerf": root / "nerf", "activeneus": root / "activeneus", "neus": root / "neus",
         "calib": root / "calib.yml", "colmap": root / "colmap", "images": scene_dir / "images"}
    shutil.copytree(scene_dir, b["scene"])
    write_nerf(scene, b["nerf"])
    write_activeneus(scene, b["activeneus"])
    for sub in ("image", "mask"):
        shutil.copytree(b["activeneus"] / sub, b["neus"] / sub)
    K = scene.frame_camera(0).K.copy()
    K[:2, 2] -= 0.5  # NeuS and OpenCV: integer pixel centres
    arrays = {}
    for i in range(len(scene.frames)):
        P = np.eye(4)
        P[:3, :3] = K
        arrays[f"world_mat_{i}"] = P @ scene.world_to_cam(i)
        arrays[f"scale_mat_{i}"] = scene.normalisation()
    np.savez(b["neus"] / "cameras_sphere.npz", **arrays)

    pj = scene.projectors["proj0"]
    Kp = pj.K.copy()
    Kp[:2, 2] -= 0.5
    c2p = np.linalg.inv(pj.proj_to_cam)
    calib = {"cam_K": K, "cam_kc": np.zeros((1, 5)), "proj_K": Kp, "proj_kc": np.zeros((1, 5)),
             "R": c2p[:3, :3], "T": c2p[:3, 3].reshape(3, 1)}
    fs = cv2.FileStorage(str(b["calib"]), cv2.FILE_STORAGE_WRITE)
    for k, v in calib.items():
        fs.write(k, np.ascontiguousarray(v, dtype=np.float64))
    fs.release()
    np.savez(root / "calib_arrays.npz", **calib)
    b["pattern"] = scene_dir / scene.patterns[scene.frames[0].projectors["proj0"].pattern].file
    b["poses"] = scene_dir / "scene.json"

    b["colmap"].mkdir()
    (b["colmap"] / "cameras.txt").write_text(f"1 PINHOLE 24 24 {K[0, 0]} {K[1, 1]} {K[0, 2]} {K[1, 2]}\n")
    lines = []
    for i in range(len(scene.frames)):
        w2c = scene.world_to_cam(i)
        x, y, z, w = Rotation.from_matrix(w2c[:3, :3]).as_quat()
        lines += [f"{i + 1} {w} {x} {y} {z} {' '.join(map(str, w2c[:3, 3]))} 1 {i:03d}.png", ""]
    (b["colmap"] / "images.txt").write_text("\n".join(lines) + "\n")

    # the same model in COLMAP's binary layout, with a few 2D points and a points3D.bin track to skip
    b["colmap_bin"] = root / "colmap_bin"
    b["colmap_bin"].mkdir()
    ims = []
    for i in range(len(scene.frames)):
        w2c = scene.world_to_cam(i)
        x, y, z, w = Rotation.from_matrix(w2c[:3, :3]).as_quat()
        ims.append((i + 1, (w, x, y, z), w2c[:3, 3], 1, f"{i:03d}.png", [(1.5, 2.5, -1), (3.0, 4.0, 1)]))
    pts = [(j + 1, (0.01 * j, 0.0, -0.01 * j), (128, 128, 128), 0.5, [(1, 0), (2, 1)]) for j in range(12)]
    files, fields = colmap_binary([(1, "PINHOLE", 24, 24, [K[0, 0], K[1, 1], K[0, 2], K[1, 2]])], ims, pts)
    for n, data in files.items():
        (b["colmap_bin"] / n).write_bytes(data)
    (root / "colmap_bin_fields.json").write_text(json.dumps(fields))  # where each field lies, for mutations
    return b


# --------------------------------------------------------------------------- targets
@dataclass
class Case:
    """One mutated input: files (relative name -> bytes) written into the target's folder, or argv items."""

    target: str
    files: dict[str, bytes] = field(default_factory=dict)
    items: list[str] = field(default_factory=list)
    what: str = ""

    def __repr__(self) -> str:  # short: hypothesis prints failing cases
        files = ", ".join(f"{n} ({len(b)} bytes)" for n, b in self.files.items())
        return f"Case({self.target}: {files or self.items!r:.300}; {self.what[:300]})"


class Hang(BaseException):
    """An example ran past :data:`HANG_S` (a BaseException, so no ``except Exception`` swallows it)."""


@contextmanager
def hang_guard(seconds: float = HANG_S):
    """Interrupt the body after ``seconds`` (SIGALRM; main thread only, else no guard)."""
    def on_alarm(signum, frame):
        raise Hang(f"no result after {seconds:g} s")

    try:
        old = signal.signal(signal.SIGALRM, on_alarm)
    except (ValueError, AttributeError):  # not the main thread, or no SIGALRM
        yield
        return
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


# the files a target's cases replace, restored from the base before each case
BASE_FILES = {"scene": ["scene.json"], "nerf": ["transforms.json"], "activeneus": ["cameras_sphere.npz"],
              "neus": ["cameras_sphere.npz"], "colmap": ["cameras.txt", "images.txt"],
              "colmap_bin": ["cameras.bin", "images.bin", "points3D.bin"]}


class Fuzz:
    """Bases, scratch folders and per-target strategies/loaders for one fuzz session.

    Args:
        bases: :func:`build_bases`' result.
        work: a scratch folder (each target gets a copy of its base there).
    """

    def __init__(self, bases: dict[str, Path], work: Path):
        import yaml
        from importlib import resources

        from fastneus.config import Config
        from dataclasses import fields

        self.b, self.work = bases, Path(work)
        self.work.mkdir(parents=True, exist_ok=True)
        self.marker = self.work / "UNPICKLED"
        for kind in ("scene", "nerf", "activeneus", "neus", "colmap", "colmap_bin"):
            if not (self.work / kind).exists():
                shutil.copytree(bases[kind], self.work / kind)
        self.scene_json = json.loads((bases["scene"] / "scene.json").read_text())
        self.transforms = json.loads((bases["nerf"] / "transforms.json").read_text())
        with np.load(bases["activeneus"] / "cameras_sphere.npz", allow_pickle=True) as z:  # our own file: trusted
            self.an_arrays = {k: z[k] for k in z.files}
        with np.load(bases["neus"] / "cameras_sphere.npz") as z:
            self.neus_arrays = {k: z[k] for k in z.files}
        with np.load(bases["calib"].parent / "calib_arrays.npz") as z:
            self.calib_model = calib_model({k: z[k] for k in z.files})
        self.colmap_files = {n: (bases["colmap"] / n).read_text() for n in ("cameras.txt", "images.txt")}
        self.colmap_bin = {n: (bases["colmap_bin"] / n).read_bytes() for n in BASE_FILES["colmap_bin"]}
        self.colmap_bin_fields = json.loads((bases["colmap_bin"].parent / "colmap_bin_fields.json").read_text())
        self.config = yaml.safe_load((resources.files("fastneus.configs") / "cpu-quick.yaml").read_text())
        self.config_keys = [f.name for f in fields(Config)]

    # ------------------------------------------------------------------ strategies
    def strategy(self, target: str) -> st.SearchStrategy:
        """Cases for ``target`` (one of :data:`TARGETS`)."""
        m = str(self.marker)
        if target == "scene":
            return json_bytes(self.scene_json).map(lambda x: Case("scene", {"scene.json": x[0]}, what=x[1]))
        if target == "nerf":
            return json_bytes(self.transforms).map(lambda x: Case("nerf", {"transforms.json": x[0]}, what=x[1]))
        if target in ("activeneus", "neus"):
            base = self.an_arrays if target == "activeneus" else self.neus_arrays
            return npz_bytes(base, m).map(lambda x: Case(target, {"cameras_sphere.npz": x[0]}, what=x[1]))
        if target == "opencv":
            return calib_bytes(self.calib_model).map(lambda x: Case("opencv", {"calib" + x[0]: x[1]}, what=x[2]))
        if target == "colmap":
            one = st.sampled_from(["images.txt", "images.txt", "cameras.txt", "points3D.txt"]).flatmap(
                lambda n: (points3d_text() if n == "points3D.txt" else colmap_text(self.colmap_files[n])).map(
                    lambda x: Case("colmap", {n: x[0]}, what=f"{n}: {x[1]}")))
            return one
        if target == "colmap_bin":
            return colmap_bin_bytes(self.colmap_bin, self.colmap_bin_fields).map(
                lambda x: Case("colmap_bin", {x[0]: x[1]}, what=x[2]))
        if target == "config":
            return config_bytes(self.config, m).map(lambda x: Case("config", {"config.yaml": x[0]}, what=x[1]))
        if target == "overrides":
            return override_list(self.config_keys).map(lambda x: Case("overrides", items=x[0], what=x[1]))
        raise ValueError(f"unknown target {target!r}; one of {TARGETS}")

    # ------------------------------------------------------------------ writing and loading
    def folder(self, target: str) -> Path:
        return self.work / {"opencv": "calib", "config": "config", "overrides": "config"}.get(target, target)

    def write(self, case: Case) -> list[Path]:
        """Reset the target's folder to its base, write the case's files; returns their paths."""
        d = self.folder(case.target)
        for n in BASE_FILES.get(case.target, ()):
            shutil.copyfile(self.b[case.target] / n, d / n)
        if case.target == "colmap":
            (d / "points3D.txt").unlink(missing_ok=True)
        d.mkdir(parents=True, exist_ok=True)
        for p in list(d.glob("calib.*")) if case.target == "opencv" else []:
            p.unlink()
        out = []
        for name, data in case.files.items():
            (d / name).write_bytes(data)
            out.append(d / name)
        return out

    def load(self, case: Case, files: list[Path]):
        """Call the loader the verbs call for this target."""
        t = case.target
        if t in ("scene", "nerf", "activeneus", "neus"):
            from fastneus.formats.detect import load_scene

            return load_scene(self.folder(t))
        if t in ("opencv", "colmap", "colmap_bin"):
            from fastneus.formats.opencv_calib import make_scene_from_calibration

            out = self.work / "out"
            shutil.rmtree(out, ignore_errors=True)
            images = sorted(self.b["images"].iterdir())
            calib = files[0] if t == "opencv" else self.b["calib"]
            poses = self.b["poses"] if t == "opencv" else self.folder(t)
            return make_scene_from_calibration(calib, images, [self.b["pattern"]], poses, out, units="m")
        from fastneus.config import load_config

        if t == "config":
            return load_config(str(files[0]))
        return load_config("cpu-quick", case.items)

    def inputs(self, case: Case, files: list[Path]) -> list[Path]:
        """Every path an error may rightly name for this case (the files and folders given)."""
        t = case.target
        if t in ("scene", "nerf", "activeneus", "neus", "colmap", "colmap_bin"):
            colmap = t in ("colmap", "colmap_bin")
            return [self.folder(t)] + ([self.b["calib"], self.b["images"], self.b["pattern"]] if colmap else [])
        if t == "opencv":
            return files + [self.b["images"], self.b["pattern"], self.b["poses"]]
        return files


def _names_input(e, inputs: list[Path], case: Case) -> bool:
    if case.target == "overrides":
        return e.file in (None, "command line") and (e.field is not None or e.file is not None)
    if e.file is None:
        return False
    try:
        f = Path(e.file).resolve()
    except (OSError, ValueError, RuntimeError):
        return False
    for p in inputs:
        p = p.resolve()
        if f == p or p in f.parents:
            return True
    return False


def check_case(fz: Fuzz, case: Case) -> str:
    """Write and load one case; assert the property. Returns 'ok' or the one-line error.

    Raises:
        AssertionError: a FastneusError that does not name an input file or is not one line,
            or a payload was unpickled.
        Hang: the loader ran past :data:`HANG_S`.
        Exception: whatever other exception the loader raised (a bug).
    """
    from fastneus.errors import FastneusError

    files = fz.write(case)
    fz.marker.unlink(missing_ok=True)
    try:
        with hang_guard():
            fz.load(case, files)
        result = "ok"
    except FastneusError as e:
        msg = str(e)
        assert "\n" not in msg and "\r" not in msg, f"error message is not one line: {msg!r}"
        assert _names_input(e, fz.inputs(case, files), case), \
            f"error does not name an input file (file={e.file!r}, field={e.field!r}): {msg}"
        result = msg
    finally:
        assert not fz.marker.exists(), "a pickle from the input ran (marker file created)"
    return result
