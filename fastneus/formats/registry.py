"""The scene formats fastneus reads and writes, each registered once (docs/ARCHITECTURE.md).

A :class:`SceneFormat` names its reader and writer as ``"module:function"`` strings, imported
only when used: this module is cheap to import (the CLI builds ``convert --to`` from it at
start-up). :func:`fastneus.formats.detect.load_scene` tries the ``detect`` functions in
registration order; ``fastneus convert --to`` offers every format with a writer.

Adding a format: a module in ``fastneus/formats/`` with a reader (``path -> Scene``) and,
optionally, a writer (``(scene, out, **options) -> ...``), and one :func:`register_format`
call at the bottom of this file.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from fastneus.errors import FastneusError
from fastneus.plugins import registered_in, resolve


@dataclass(frozen=True)
class SceneFormat:
    """One scene format.

    Attributes:
        name: the id used by ``convert --to`` and returned by ``detect_format``.
        help: one line for users.
        detect: ``path -> bool``, whether a folder (or its main file) is in this format; it must
            be cheap and import nothing heavy. It may raise :class:`FastneusError` for a folder
            that is clearly of this format but unreadable.
        reader: ``"module:function"`` (a dotted attribute path after the colon is allowed,
            e.g. ``"fastneus.data.scene:Scene.load"``) taking the path, returning a Scene.
        writer: ``"module:function"`` taking ``(scene, out, **options)``, or None (read only).
        writer_options: the ``convert`` options the writer takes as keywords (e.g. ``downscale``).
    """

    name: str
    help: str
    detect: Callable[[Path], bool]
    reader: str
    writer: str | None = None
    writer_options: tuple[str, ...] = ()

    def read(self, path):
        """The scene at ``path``, read by this format's reader."""
        return resolve(self.reader)(path)

    def write(self, scene, out, **options):
        """Write ``scene`` into ``out`` with this format's writer."""
        if self.writer is None:
            raise FastneusError(f"format {self.name!r} is read only", field="--to")
        return resolve(self.writer)(scene, out, **options)


_FORMATS: dict[str, SceneFormat] = {}




def register_format(fmt: SceneFormat) -> SceneFormat:
    """Add ``fmt`` after the registered formats (detection tries them in order); names are unique."""
    if fmt.name in _FORMATS:
        raise ValueError(f"scene format {fmt.name!r} is already registered")
    if ":" not in fmt.reader or (fmt.writer is not None and ":" not in fmt.writer):
        raise ValueError(f"scene format {fmt.name!r}: reader and writer are 'module:function' strings")
    _FORMATS[fmt.name] = fmt
    return fmt


def unregister_format(name: str) -> None:
    """Remove a registered format (tests register toy formats and remove them after)."""
    del _FORMATS[name]


def registered(fmt: SceneFormat):
    """``with registered(fmt):`` the format is registered inside the block only."""
    return registered_in(register_format, unregister_format, fmt)


def formats() -> list[SceneFormat]:
    """Every registered format, in detection order."""
    return list(_FORMATS.values())


def get_format(name: str) -> SceneFormat:
    try:
        return _FORMATS[name]
    except KeyError:
        raise FastneusError(f"unknown scene format {name!r}; known: {sorted(_FORMATS)}") from None


def writable() -> tuple[str, ...]:
    """Names of the formats that can be written (``convert --to``)."""
    return tuple(f.name for f in _FORMATS.values() if f.writer is not None)


# --------------------------------------------------------------------------- the built-in formats
def _has_file(name: str) -> Callable[[Path], bool]:
    def detect(p: Path) -> bool:
        return p.is_file() and p.name == name or (p / name).is_file()

    return detect


NPZ = "cameras_sphere.npz"


def _npz_kind(p: Path) -> str | None:
    """'activeneus' or 'neus' for a folder with cameras_sphere.npz (by its keys), None without one."""
    npz = p / NPZ
    if not npz.is_file():
        return None
    from fastneus.formats.safe_npz import open_npz  # on use: numpy is not a start-up cost of the CLI

    keys = set(open_npz(npz).files)  # lists keys only; never unpickles
    if "cam_proj_pose_0" in keys or "cam_mat_0" in keys:
        return "activeneus"
    if "world_mat_0" in keys:
        return "neus"
    raise FastneusError("neither ActiveNeuS (cam_mat_0) nor NeuS (world_mat_0) keys found", file=str(npz))


register_format(SceneFormat(
    "fastneus", "a folder with scene.json (docs/FORMAT.md)", _has_file("scene.json"),
    reader="fastneus.data.scene:Scene.load", writer="fastneus.formats.fastneus:write_fastneus"))
register_format(SceneFormat(
    "nerf", "NeRF / nerfstudio transforms.json", _has_file("transforms.json"),
    reader="fastneus.formats.nerf:read_nerf", writer="fastneus.formats.nerf:write_nerf"))
register_format(SceneFormat(
    "activeneus", "ActiveNeuS: cameras_sphere.npz with camera and projector matrices",
    lambda p: _npz_kind(p) == "activeneus",
    reader="fastneus.formats.activeneus:read_activeneus", writer="fastneus.formats.activeneus:write_activeneus",
    writer_options=("downscale",)))
register_format(SceneFormat(
    "neus", "NeuS / DTU: cameras_sphere.npz with world_mat_i (read only)", lambda p: _npz_kind(p) == "neus",
    reader="fastneus.formats.neus:read_neus"))
