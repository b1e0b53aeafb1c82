"""Open ``.npz`` camera files from untrusted scenes without running code from them.

``np.load(..., allow_pickle=True)`` unpickles object arrays, and unpickling can call any
importable function (a crafted ``__reduce__`` runs shell commands). Scenes are shared and
downloaded, so every npz is opened with ``allow_pickle=False``. The official ActiveNeuS
format does store one pickled value, ``illumination_params`` (a dict {ambient, diffuse,
emissive}); :func:`read_number_dict` decodes that single entry with an unpickler that can
build nothing but the 0-d object array around the dict, the dict itself and numeric numpy
scalars, and refuses every other global with a one-line error.
"""
from __future__ import annotations

import io
import pickle
from pathlib import Path
from typing import Any

import numpy as np

from fastneus.errors import FastneusError

MAX_PICKLE_BYTES = 1 << 20  # a dict of a few numbers is ~200 bytes; refuse anything huge

# the only globals a pickled 0-d object array holding {str: number} needs
# (numpy 1.x writes numpy.core.*, numpy 2.x numpy._core.*)
_MULTIARRAY = ("numpy.core.multiarray", "numpy._core.multiarray")
# numeric dtype codes a numpy scalar in the dict may have; 'O' only for the enclosing array
_NUMERIC = {f"{k}{n}" for k in "iu" for n in (1, 2, 4, 8)} | {"f2", "f4", "f8"}
_OBJECT = {"O4", "O8"}


def open_npz(path: Path):
    """``np.load(path, allow_pickle=False)`` with a one-line error for unreadable files.

    Returns:
        The lazily-read :class:`numpy.lib.npyio.NpzFile`; reading an object array from it
        raises (use :func:`read_number_dict` for ``illumination_params``).
    """
    try:
        with open(path, "rb") as fh:
            magic = fh.read(4)
    except OSError as e:
        raise FastneusError(f"cannot read: {e.strerror}", file=path) from None
    if magic not in (b"PK\x03\x04", b"PK\x05\x06"):  # np.load would try to unpickle a non-zip file
        raise FastneusError("not an npz archive (expected a zip of .npy arrays, as np.savez writes)", file=path)
    try:
        npz = np.load(path, allow_pickle=False)
    except Exception as e:  # noqa: BLE001 - corrupt or foreign file: one line, not a trace
        raise FastneusError(f"unreadable npz: {type(e).__name__}: {e}".splitlines()[0], file=path) from None
    return npz


def npz_array(npz, key: str, file: Path) -> np.ndarray:
    """``npz[key]`` as a plain (non-object) array; one-line errors for missing/corrupt/pickled data."""
    if key not in npz.files:
        raise FastneusError("missing key", file=file, field=key)
    try:
        a = np.asarray(npz[key])
    except ValueError as e:
        if "allow_pickle" in str(e):
            raise FastneusError("holds pickled Python objects, not numbers; fastneus does not unpickle "
                                "scene files", file=file, field=key) from None
        raise FastneusError(f"unreadable array: {e}".splitlines()[0], file=file, field=key) from None
    except Exception as e:  # noqa: BLE001 - truncated member, bad zip entry
        raise FastneusError(f"unreadable array: {type(e).__name__}: {e}".splitlines()[0], file=file,
                            field=key) from None
    if np.iscomplexobj(a):  # a cast to float would drop the imaginary part silently
        raise FastneusError(f"holds complex numbers ({a.dtype}); expected real numbers", file=file, field=key)
    return a


# --------------------------------------------------------------------------- restricted unpickler
class _Refused(Exception):
    """Raised inside the unpickler; turned into a FastneusError by the caller."""


class _Dtype:
    """Stands in for ``numpy.dtype(code, align, copy)``: remembers the code and byte order only."""

    __slots__ = ("code", "order")

    def __init__(self, code: Any, align: Any = False, copy: Any = True):
        if not isinstance(code, str) or code not in _NUMERIC | _OBJECT:
            raise _Refused(f"dtype {code!r} (only numeric scalars are accepted)")
        self.code, self.order = code, "="

    def __setstate__(self, state: Any) -> None:
        order = state[1] if isinstance(state, tuple) and len(state) > 1 else None
        if order not in ("<", ">", "|", "="):
            raise _Refused("malformed dtype state")
        self.order = order


class _Array:
    """Stands in for the 0-d object ndarray ``np.save`` pickles; keeps its state for checking."""

    __slots__ = ("state",)

    def __init__(self):
        self.state = None

    def __setstate__(self, state: Any) -> None:
        self.state = state


_NDARRAY = object()  # what the pickle's reference to numpy.ndarray resolves to


def _reconstruct(cls: Any, shape: Any, typecode: Any) -> _Array:
    if cls is not _NDARRAY:
        raise _Refused("_reconstruct of something other than ndarray")
    return _Array()


def _scalar(dtype: Any, data: Any = None) -> float | int:
    if not isinstance(dtype, _Dtype) or dtype.code not in _NUMERIC or not isinstance(data, bytes):
        raise _Refused("a numpy scalar that is not a plain number")
    dt = np.dtype(dtype.code)
    if len(data) != dt.itemsize:
        raise _Refused("malformed numpy scalar")
    if dtype.order in "<>":
        dt = dt.newbyteorder(dtype.order)
    return np.frombuffer(data, dtype=dt)[0].item()


_ALLOWED = {**{(m, "_reconstruct"): _reconstruct for m in _MULTIARRAY},
            **{(m, "scalar"): _scalar for m in _MULTIARRAY},
            ("numpy", "ndarray"): _NDARRAY, ("numpy", "dtype"): _Dtype}


class _NumberDictUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> Any:
        try:
            return _ALLOWED[(module, name)]
        except KeyError:
            raise _Refused(f"it references {module}.{name}") from None

    def persistent_load(self, pid: Any) -> Any:
        raise _Refused("persistent ids")


def _unwrap_object_array(obj: Any, vector: bool = False) -> Any:
    """The single element of the unpickled 0-d object array stand-in (``vector``: the list of
    elements of a 1-d one)."""
    st = obj.state if isinstance(obj, _Array) else None
    if isinstance(st, tuple) and len(st) == 5:
        st = st[1:]  # (version, shape, dtype, fortran, data) -> drop the version
    if not (isinstance(st, tuple) and len(st) == 4 and isinstance(st[1], _Dtype) and st[1].code in _OBJECT
            and isinstance(st[3], list)):
        raise _Refused("not a pickled object array")
    if st[0] == () and len(st[3]) == 1:
        return st[3][0]
    if vector and isinstance(st[0], tuple) and len(st[0]) == 1 and st[0][0] == len(st[3]):
        return list(st[3])
    raise _Refused("not a single pickled value")


MAX_PICKLE_NODES = 10_000  # values the plain-data walk may visit; the official entries hold a handful


def _check_plain(v: Any, depth: int = 0, budget: list[int] | None = None) -> None:
    """Only numbers, strings and dict/list/tuple of them (what the official format pickles).

    The walk is bounded by node count, not only depth: a pickle's memo lets ~1 KB describe a
    list of 64 references to a list of 64 references ... (64^6 leaves), which a depth limit
    alone would walk for hours.
    """
    if budget is None:
        budget = [MAX_PICKLE_NODES]
    budget[0] -= 1
    if budget[0] < 0:
        raise _Refused(f"more than {MAX_PICKLE_NODES} values (shared references expand too far)")
    if depth > 8:
        raise _Refused("nested too deeply")
    if isinstance(v, dict):
        for k, x in v.items():
            if not isinstance(k, str):
                raise _Refused(f"key {k!r} is not a string")
            _check_plain(x, depth + 1, budget)
    elif isinstance(v, (list, tuple)):
        for x in v:
            _check_plain(x, depth + 1, budget)
    elif not isinstance(v, (int, float, str)) or v is None:
        raise _Refused(f"not plain data: got {'an array' if isinstance(v, _Array) else type(v).__name__}")


def read_pickled_value(npz, key: str, file: Path, want: str, vector: bool = False) -> Any:
    """Decode ``npz[key]``, a pickled 0-d object array (``vector``: or a 1-d one) holding
    plain data: numbers, strings, and dicts / lists / tuples of them.

    Only the globals needed to rebuild such an array are resolvable (to inert stand-ins,
    never to the real numpy functions); a payload that references anything else is refused
    without executing it.

    Args:
        want: what the entry should hold, for the error message.
    Returns:
        The value (a list of the elements for a 1-d array).

    Raises:
        FastneusError: one line naming ``file`` and ``key``.
    """
    member = f"{key}.npy"
    zf = getattr(npz, "zip", None)
    if zf is None or member not in zf.namelist():
        raise FastneusError("missing key", file=file, field=key)
    try:
        with zf.open(member) as fh:
            raw = fh.read(MAX_PICKLE_BYTES + 1)
    except Exception as e:  # noqa: BLE001 - truncated or corrupt zip member
        raise FastneusError(f"unreadable entry: {type(e).__name__}: {e}".splitlines()[0], file=file,
                            field=key) from None
    if len(raw) > MAX_PICKLE_BYTES:
        raise FastneusError(f"entry larger than {MAX_PICKLE_BYTES} bytes; {want}", file=file, field=key)
    f = io.BytesIO(raw)
    try:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(f)
        elif version == (2, 0):
            shape, _, dtype = np.lib.format.read_array_header_2_0(f)
        else:
            raise ValueError(f"unsupported .npy version {version}")
    except Exception as e:  # noqa: BLE001 - not a .npy member
        raise FastneusError(f"unreadable entry: {e}".splitlines()[0], file=file, field=key) from None
    if not dtype.hasobject:
        raise FastneusError(f"{want}, got a {dtype} array of shape {shape}", file=file, field=key)
    if shape != () and not (vector and len(shape) == 1):
        raise FastneusError(f"{want}, got an object array of shape {shape}", file=file, field=key)
    try:
        obj = _unwrap_object_array(_NumberDictUnpickler(f).load(), vector)
        _check_plain(obj)
    except _Refused as e:
        raise FastneusError(f"refused to unpickle: {e}; {want} (fastneus never runs code from scene files)",
                            file=file, field=key) from None
    except Exception as e:  # noqa: BLE001 - truncated or malformed pickle
        raise FastneusError(f"malformed pickled value ({type(e).__name__}); {want}", file=file,
                            field=key) from None
    return obj


def read_number_dict(npz, key: str, file: Path) -> dict[str, float]:
    """Decode ``npz[key]``, a pickled 0-d object array holding a dict of str -> number (see
    :func:`read_pickled_value`).

    Returns:
        The dict with Python float values (finite or not: callers check ranges).
    """
    want = "expected a dict {ambient, diffuse, emissive} of numbers"
    obj = read_pickled_value(npz, key, file, want)
    if not isinstance(obj, dict):
        raise FastneusError(f"{want}, got {type(obj).__name__}", file=file, field=key)
    out: dict[str, float] = {}
    for k, v in obj.items():
        if not isinstance(k, str):
            raise FastneusError(f"{want}; key {k!r} is not a string", file=file, field=key)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            got = "an array" if isinstance(v, _Array) else type(v).__name__
            raise FastneusError(f"expected a number, got {got}", file=file, field=f"{key}.{k}")
        try:
            out[k] = float(v)
        except OverflowError:
            raise FastneusError("number out of range", file=file, field=f"{key}.{k}") from None
    return out
