"""Projector kinds, each registered once (docs/ARCHITECTURE.md, "a projector kind").

A :class:`ProjectorKind` gives everything that differs between kinds of projector: how its
``scene.json`` entry is parsed and written, how it is packed for the light kernel, the light
op itself, and how ``synth`` lights a point with it. Every place that handles projectors
(``data/scene.py``, ``train/rays.py``, ``field/renderer.py``, ``train/rig.py``,
``synth/render.py``, the format writers) asks this registry instead of branching on a name.

Two kinds are built in:

- ``pattern`` (:data:`IMAGE`): an image projector, ``Q = bilinear(pattern, pi(K (R P + t)))``.
  It is the one kind with ``images=True``: frames name the pattern it shows, and the render
  kernel samples the pattern itself (``render_pattern`` / ``project_pattern``, with blur,
  ports and attenuation), so it has no pack or light hook; ``synth`` samples the image.
- ``laser`` (:mod:`fastneus.light.lasers`): light planes, ``fastneus.kernels.project.laser_light``.

Every other kind is an *emitter* like the laser: frames switch it with ``on: true/false``,
its pack hook turns the projectors into one tensor, and its light op adds its light to the
pattern light of each sample (``q_ext`` of the render kernel).

Hooks are callables or ``"module:function"`` strings imported on first use (this module stays
cheap: loading a scene must not pay for torch). Signatures:

- ``parse(entry: dict, file, fld: str) -> dict``: the kind's own fields of its scene.json entry
  (``kind`` and ``proj_to_cam`` are read by the loader) as keyword arguments of
  :class:`fastneus.data.model.Projector` (``K``, ``width``, ``height``, ``port``, ``planes``, or
  anything in ``params``); problems raise a one-line FastneusError naming ``file`` and the field.
- ``serialise(projector) -> dict``: those fields back as JSON values (the inverse of parse).
- ``pack(projectors: list[Projector | None], device) -> Tensor``: per projector of the scene (None
  for projectors of other kinds, which must pack as "no light") a row for the light op.
- ``light``: a kernel op name (``fastneus.kernels.get_op``, Warp op and torch twin) or a
  function, called as ``light(pos, ray_index, offsets, counts, ray_frame, proj_W, on, packed)``
  -> [S, 3] with ``on`` [F, P] int32 (1 where projector k is this kind and lit in frame f) and
  ``proj_W`` [F, P, 3, 4] normalised point -> projector frame (world units).
- ``synth(points [N, 3] torch, world_to_proj [4, 4], projector) -> [N, 3]``: the light at
  world points, used by ``fastneus synth`` (shadows and media are added there).

Adding a kind: a module with the hooks and one :func:`register_projector_kind` call (the
built-ins are registered at the bottom of this file; a plug-in may register from its own
module), its name and fields in ``fastneus/data/scene.schema.json`` and docs/FORMAT.md.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from fastneus.data.model import parse_port, port_to_dict, to_list
from fastneus.data.validate import MAX_SIDE, as_int, check_intrinsics, require
from fastneus.errors import FastneusError
from fastneus.plugins import registered_in, resolve

DEFAULT = "pattern"  # the kind of a scene.json projector entry without "kind"


@dataclass(frozen=True)
class ProjectorKind:
    """One kind of projector (hook signatures in the module docstring).

    Attributes:
        name: the ``kind`` value in scene.json.
        help: one line for users.
        label: how messages name its projectors ("laser-plane projectors cannot be written ...").
        parse, serialise: scene.json entry <-> Projector fields.
        images: shows pattern images (frames say ``pattern``); False: an emitter (frames say ``on``).
        pack, light: the emitter's kernel input and light op (None for the image kind).
        synth: the light at world points for ``fastneus synth`` (None for the image kind:
            synth samples the pattern image itself).
    """

    name: str
    help: str
    parse: str | Callable
    serialise: str | Callable
    label: str = ""
    images: bool = False
    pack: str | Callable | None = None
    light: str | Callable | None = None
    synth: str | Callable | None = None

    @property
    def noun(self) -> str:
        return self.label or self.name

    def call(self, hook: str, *args, **kwargs) -> Any:
        """Call the hook ``hook`` (``"parse"``, ``"serialise"``, ``"pack"``, ``"synth"``)."""
        fn = getattr(self, hook)
        if fn is None:
            raise FastneusError(f"projector kind {self.name!r} has no {hook} hook")
        return resolve(fn)(*args, **kwargs)

    def light_op(self, backend: str = "warp") -> Callable:
        """The light op for ``backend``: a kernel op (Warp or its torch twin) or the given function."""
        if self.light is None:
            raise FastneusError(f"projector kind {self.name!r} has no light op")
        if isinstance(self.light, str) and ":" not in self.light:
            from fastneus.kernels import get_op  # on use: the kernels (torch, Warp) are not a cost of loading scenes

            return get_op(self.light, backend)
        return resolve(self.light)

    def kernel_op(self) -> str | None:
        """The kernel op name of the light (compiled before training's clock starts), or None."""
        return self.light if isinstance(self.light, str) and ":" not in self.light else None


_KINDS: dict[str, ProjectorKind] = {}




def register_projector_kind(kind: ProjectorKind) -> ProjectorKind:
    """Add ``kind``; names are unique."""
    if kind.name in _KINDS:
        raise ValueError(f"projector kind {kind.name!r} is already registered")
    for h in ("parse", "serialise", "pack", "light", "synth"):
        v = getattr(kind, h)
        if isinstance(v, str) and ":" not in v and h != "light":
            raise ValueError(f"projector kind {kind.name!r}: {h} is a callable or a 'module:function' string")
    if not kind.images and (kind.pack is None or kind.light is None):
        raise ValueError(f"projector kind {kind.name!r}: an emitter (images=False) needs pack and light hooks")
    _KINDS[kind.name] = kind
    return kind


def unregister_projector_kind(name: str) -> None:
    """Remove a registered kind (tests register toy kinds and remove them after)."""
    del _KINDS[name]


def registered(kind: ProjectorKind):
    """``with registered(kind):`` the kind is registered inside the block only."""
    return registered_in(register_projector_kind, unregister_projector_kind, kind)


def projector_kinds() -> list[ProjectorKind]:
    """Every registered kind, in registration order (emitters' light is summed in this order)."""
    return list(_KINDS.values())


def get_projector_kind(name: str, file=None, fld: str | None = None) -> ProjectorKind:
    """The kind ``name``; an unknown name raises a FastneusError naming ``file`` and ``fld``."""
    try:
        return _KINDS[name]
    except (KeyError, TypeError):
        raise FastneusError(f"unknown projector kind {name!r}; use {' or '.join(_KINDS)}", file=file,
                            field=fld) from None


def emitters() -> list[ProjectorKind]:
    """The registered kinds that add their light through a light op (all but the image kind)."""
    return [k for k in _KINDS.values() if not k.images]


# --------------------------------------------------------------------------- the image projector
def parse_image_projector(entry: dict, file, fld: str) -> dict:
    """K, width, height and port of a pattern (image) projector."""
    return {"K": check_intrinsics(require(entry, "K", file, fld), file, f"{fld}.K"),
            "width": as_int(require(entry, "width", file, fld), file, f"{fld}.width", maximum=MAX_SIDE),
            "height": as_int(require(entry, "height", file, fld), file, f"{fld}.height", maximum=MAX_SIDE),
            "port": parse_port(entry.get("port"), file, f"{fld}.port")}


def image_projector_to_dict(p) -> dict:
    return {"K": to_list(p.K), "width": p.width, "height": p.height,
            **({"port": port_to_dict(p.port)} if p.port is not None else {})}


IMAGE = register_projector_kind(ProjectorKind(
    "pattern", "an image projector showing pattern images (K, width, height)", parse_image_projector,
    image_projector_to_dict, label="image", images=True))
register_projector_kind(ProjectorKind(
    "laser", "a laser line projector: light planes (planes)", "fastneus.light.lasers:parse_laser_projector",
    "fastneus.light.lasers:laser_projector_to_dict", label="laser-plane",
    pack="fastneus.light.lasers:pack_laser_projectors", light="laser_light",
    synth="fastneus.light.lasers:laser_synth_light"))
