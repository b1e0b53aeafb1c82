"""Training configuration: one dataclass holds every default; YAML presets and
``key=value`` overrides layer on top (in that order). The resolved config is saved
with each run, so a run can always be reproduced.
"""
from __future__ import annotations

import dataclasses
import math
import os
import re
from dataclasses import dataclass, field, fields
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from .errors import FastneusError


@dataclass
class Config:
    """All knobs of a fastneus run (defaults = the GPU few-view preset)."""

    # --- run ---
    preset: str = "fewview"            # name of the preset this config came from (informational)
    backend: str = "warp"              # kernel backend: warp | torch (the twins; for comparison)
    pattern_pass: str = "auto"         # fused | split | auto (split on CUDA): sample the patterns per sample
    seed: int = 0
    threads: int = 0                   # CPU threads for the Warp kernels and torch (0 = auto: FASTNEUS_THREADS,
                                       # else every CPU this process may run on); --threads on the CLI
    steps: int = 3000                  # optimisation steps (the run's length when time_budget is 0)
    time_budget: float = 0.0           # seconds of training; when > 0 it is the run's length (steps ignored)
                                       # and every schedule below is a fraction of it
    frames: list[int] | None = None    # frames to train on (None = all)
    log_every: int = 50
    save_every: int = 1000             # checkpoint period (steps); the last step always saves

    # --- rays and samples ---
    target_samples: int = 2 ** 18      # samples per step; the ray count adapts to hit it
    init_rays: int = 2048
    min_rays: int = 256
    max_rays: int = 2 ** 16
    march_step: float = math.sqrt(3) * 2 / 1024   # normalised units
    max_samples_per_ray: int = 1024
    bound: str = "sphere"              # sphere | box
    background: float = 0.0            # background colour behind the object (synthetic data: black)
    min_views: int = 2                 # space seen by fewer distinct viewpoints is never occupied (no
                                       # floaters where nothing can be triangulated); 0 = off
    bg_prior: str = "auto"             # pixels equal to `background` are free space when masks are not
                                       # used: auto (on when >= 5% of pixels are) | on | off
    bg_weight: float = 0.1             # weight of that prior (BCE of opacity toward 0 on those pixels)
    bg_start_frac: float = 0.2         # the prior ramps in from this fraction of the run to twice it:
                                       # from the start it erodes the init sphere before thin parts form
    bg_tolerance: float = 0.008        # per-channel distance to `background` still counted as it (~2/255)
    bright_fraction: float = 0.5       # share of rays drawn in proportion to pixel brightness: sparse
                                       # laser lines in dark scenes are otherwise almost never sampled
    # --- multi-shot (several patterns per viewpoint, e.g. Gray code; fastneus/train/multishot.py) ---
    group_shots: bool = True           # one ray per viewpoint pixel carries its shots (one march and field
                                       # evaluation for all); false = every shot's pixels are separate rays
    shots_per_ray: int = 4             # shots rendered per ray and step, drawn at random (0 = all, in order)
    init_geometry: str = "auto"        # auto | decode | sphere: start the SDF at the decoded surface (Gray code; one-shot sweep)
                                       # when every viewpoint is a Gray-code sequence (fastneus/train/geometry_init.py)
    init_geometry_steps: int = 100     # SDF fit steps of that initialisation (counted in the training time; the
                                       # prior keeps fitting afterwards: H100 10 s, 3 views, 100 beat 300 on Gray
                                       # code, colour and cross lines, by taking 20-30 % more training steps)
    prior_weight: float = 3.0          # after that init, its points stay a prior (SurfacePrior.loss) with this
                                       # weight, fading linearly toward 0 at prior_frac of the run: one view leaves
                                       # depth loosely constrained and the photometric loss alone drifts (GPU, toy,
                                       # 1 view, 10 s: Gray code 4.25 -> 0.11 %, colour lines 5.8 -> 0.42 %)
    prior_frac: float = 2.0            # (fraction of the run; 2 = half the weight is left at the end; 0 < x)

    # --- occupancy grid ---
    occ_resolution: int = 128
    occ_update_every: int = 16
    occ_warmup_frac: float = 0.2       # every cell occupied for this fraction of the run
    occ_threshold: float = 0.01

    # --- hash grid ---
    levels: int = 16
    features: int = 2
    log2_table: int = 19
    base_res: int = 16
    finest_res: int = 2048
    c2f_start_levels: int = 4          # coarse-to-fine: active levels at the start (0 = all)
    c2f_frac: float = 0.4              # ... rising linearly to all levels at this fraction of the run

    # --- networks ---
    sdf_hidden: int = 64
    sdf_layers: int = 1
    geo_features: int = 15
    color_hidden: int = 64
    color_layers: int = 2
    view_dependent: bool = True        # colour network sees the view direction
    init_radius: float = 0.5           # sphere initialisation of the SDF (normalised units)
    variance_init: float = 0.3         # inv_s = exp(10 * v)
    inv_s_floor_end: float = 1000.0    # inv_s >= a floor rising log-linearly from inv_s_floor_start
    inv_s_floor_start: float = 20.0    # to this value over the first inv_s_floor_frac of the run (end 0 = learned only)
    inv_s_floor_frac: float = 0.6
    normal_eps_min: float = 1e-3       # lower bound for the finite-difference step (normalised)
    sdf_grad: str = "analytic"         # SDF gradient (normals, eikonal): analytic = hash features and
                                       # their d/dx from one kernel, MLP d/dinput by autograd (1x the
                                       # points; the curvature prior still uses taps) | fd = 4-tap
                                       # tetrahedron finite differences (hash grid + SDF MLP on 5x the
                                       # points). analytic: 10-18% more steps on GPU, 1.6x on CPU, equal or
                                       # better Chamfer (docs/BENCHMARKS.md "Speed (issue 10)")

    # --- optimisation ---
    lr: float = 1e-2
    lr_variance: float = 5e-3
    lr_illum: float = 3e-2           # on log(i_r), log(i_b)
    adam_eps: float = 1e-15
    warmup_frac: float = 0.03          # linear lr warm-up (fraction of the run)
    color_warmup_frac: float = 0.03    # geometry frozen while the colour net fits the image brightness:
                                       # in dark scenes the init sphere is otherwise deleted, not darkened
    decay_to: float = 0.05             # final lr factor (cosine decay after warm-up)
    eikonal_weight: float = 0.1
    masks: str = "auto"                # auto (on when every training frame has a mask) | on | off
    mask_weight: float = 0.1           # BCE on opacity vs mask, when masks are used
    curvature_weight: float = 0.0      # smoothness prior (oneshot): |sdf(x+e) + sdf(x-e) - 2 sdf(x)|
    cos_anneal_frac: float = 0.15      # NeuS cos-anneal ratio 0 -> 1 over this fraction of the run

    # --- projection / illumination ---
    use_pattern: bool = True           # False = passive NeuS (no projected pattern in the model)
    learn_illum: bool = True
    illum_warmup_frac: float = 0.15    # i_r, i_b frozen for this fraction of the run (illum_init=scene)
    illum_init: str = "scene"          # scene (values from scene.json) | ones (i_r = i_b = 1)

    # --- real rigs (fastneus/train/rig.py, docs/REAL-RIGS.md); every part off by default ---
    pose_refine: bool = False          # learn an SE(3) correction per viewpoint camera and per projector
    pose_anchor: bool = True           # the first training viewpoint's camera stays fixed (world frame)
    pose_fix_scale: bool = True        # with the anchor, hold the rig's global scale (its one free direction)
    lr_pose: float = 2e-4              # on the corrections (radians, normalised units); 1e-3 random-walked the weak modes
    pose_warmup_frac: float = 0.1      # corrections frozen until the geometry has formed
    projector_blur: int = 0            # learned n x n separable blur of each projector's pattern (0 = off; odd n <= 7)
    lr_blur: float = 5e-3              # on the x / y kernel profiles (identity init, each normalised to sum 1)
    blur_warmup_frac: float = 0.1      # kernels frozen for this fraction of the run
    refraction: bool = True            # use the scene's flat ports (underwater housings) for rays and projectors
    medium: str = "auto"               # learned water attenuation + back-scatter: auto (on when the scene has a
                                       # port) | on | off
    lr_medium: float = 1e-2            # on log attenuation / back-scatter coefficients and the veiling light
    medium_far: float = 20.0           # range (world units) of rays that hit nothing, for their back-scatter

    # --- export ---
    mesh_resolution: int = 256
    render_frames: list[int] = field(default_factory=lambda: [0])

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


_CHOICES = {
    "backend": ("warp", "torch"),
    "pattern_pass": ("auto", "fused", "split"),
    "bound": ("sphere", "box"),
    "illum_init": ("scene", "ones"),
    "masks": ("auto", "on", "off"),
    "bg_prior": ("auto", "on", "off"),
    "init_geometry": ("auto", "decode", "sphere"),
    "medium": ("auto", "on", "off"),
    "sdf_grad": ("fd", "analytic"),
}
# fractions of the run: each must lie in [0, 1]
_FRACTIONS = ("occ_warmup_frac", "c2f_frac", "inv_s_floor_frac", "warmup_frac", "color_warmup_frac",
              "cos_anneal_frac", "illum_warmup_frac", "bg_start_frac", "pose_warmup_frac",
              "blur_warmup_frac")
# keys of earlier versions (schedules in steps): converted to fractions of the run when a saved
# config is read back (a run folder from an older fastneus must still open)
_LEGACY_STEPS = {"occ_warmup_steps": "occ_warmup_frac", "warmup_steps": "warmup_frac",
                 "color_warmup_steps": "color_warmup_frac", "cos_anneal_steps": "cos_anneal_frac",
                 "illum_warmup_steps": "illum_warmup_frac"}
_POSITIVE = {"steps", "target_samples", "init_rays", "min_rays", "max_rays", "march_step",
             "max_samples_per_ray", "occ_resolution", "occ_update_every", "levels", "features",
             "log2_table", "base_res", "finest_res", "sdf_hidden", "geo_features", "color_hidden",
             "lr", "adam_eps", "mesh_resolution", "log_every", "save_every", "init_geometry_steps", "lr_pose",
             "lr_blur", "lr_medium", "medium_far", "prior_frac"}


@dataclass(frozen=True)
class _Range:
    """Allowed values of a numeric key: ``lo`` <= v <= ``hi`` (``lo_open``: lo < v); None = unbounded."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    note: str = ""

    def text(self) -> str:
        g = lambda x: f"{x:.4g}" if isinstance(x, float) else str(x)  # noqa: E731
        if self.hi is None:
            return f"must be {'>' if self.lo_open else '>='} {g(self.lo)}"
        return f"must be in {'(' if self.lo_open else '['}{g(self.lo)}, {g(self.hi)}]"


_INT_MAX = 2 ** 31 - 1  # every integer key (but seed) fits int32: kernels, torch and numpy take it as one
# inv_s = exp(10 v) is clamped to [1e-3, 1e6] (field.model.inv_s): outside, the clamp passes no gradient
# and the NeuS variance is stuck there
_VARIANCE = (math.log(1e-3) / 10, math.log(1e6) / 10)
# every bounded key, in one table: validate() checks them all (plus the cross-key checks below it)
_RANGES: dict[str, _Range] = {
    **{k: _Range(0, None, lo_open=True) for k in _POSITIVE},
    **{k: _Range(0.0, 1.0, note="a fraction of the run") for k in _FRACTIONS},
    **{k: _Range(0.0, None, note="0 = off") for k in ("eikonal_weight", "mask_weight", "curvature_weight",
                                                      "bg_weight", "prior_weight", "min_views")},
    **{k: _Range(0.0, None, note="0 = frozen") for k in ("lr_variance", "lr_illum")},
    "seed": _Range(0, 2 ** 32 - 1, note="numpy's seed range"),
    "threads": _Range(0, 4096, note="0 = every CPU"),
    "shots_per_ray": _Range(0, None, note="0 = all shots"),
    "time_budget": _Range(0.0, None, note="seconds; 0 = steps set the length"),
    "levels": _Range(1, 64, note="hash grid levels"),
    "features": _Range(1, 8, note="the hash kernels' limit"),
    "log2_table": _Range(1, 30, note="the hash kernels' limit; 2^30 entries per level"),
    "c2f_start_levels": _Range(0, None, note="0 = all levels from the start"),
    "sdf_layers": _Range(0, 16, note="hidden layers of the SDF network"),
    "color_layers": _Range(0, 16, note="hidden layers of the colour network"),
    "variance_init": _Range(*_VARIANCE, note="inv_s = exp(10 v) must lie in [1e-3, 1e6], where it learns"),
    "inv_s_floor_start": _Range(0.0, 1e6, lo_open=True, note="inv_s is clamped to at most 1e6"),
    "inv_s_floor_end": _Range(0.0, 1e6, note="0 = learned only; inv_s is clamped to at most 1e6"),
    "init_radius": _Range(0.0, 1.0, lo_open=True, note="normalised units: the start sphere inside the bounds"),
    "normal_eps_min": _Range(0.0, None, lo_open=True),
    "background": _Range(0.0, 1.0, note="a colour value"),
    "bg_tolerance": _Range(0.0, None),
    "occ_threshold": _Range(0.0, None),
    "decay_to": _Range(0.0, 1.0, lo_open=True, note="final lr factor"),
    "bright_fraction": _Range(0.0, 1.0, note="a share of the rays"),
    "mesh_resolution": _Range(2, 4096, note="the marching-cubes grid; found only after training otherwise"),
}
# words YAML 1.1 reads as booleans (masks: off -> False): a choice key with on/off takes them back
_YAML_BOOL_CHOICE = {True: "on", False: "off"}


def _shown(v: Any) -> str:
    """A value for a one-line message: huge integers as their magnitude, long reprs cut."""
    if isinstance(v, int) and not isinstance(v, bool) and abs(v) >= 10 ** 15:
        return f"{'-' if v < 0 else ''}2^{abs(v).bit_length() - 1}+"
    r = repr(v)
    return r if len(r) <= 60 else r[:57] + "..."


def preset_names() -> list[str]:
    """Names of the presets shipped in ``configs/``."""
    return sorted(p.name[:-5] for p in resources.files("fastneus.configs").iterdir() if p.name.endswith(".yaml"))


def _flow_depth(text: str) -> int:
    """Deepest nesting of YAML flow brackets ([ {) in ``text`` (an upper bound: quotes are not parsed)."""
    depth = deepest = 0
    for c in re.findall(r"[\[\]{}]", text):
        depth = depth + 1 if c in "[{" else max(0, depth - 1)
        deepest = max(deepest, depth)
    return deepest


def _read_yaml(path: Path | Any, label: str) -> dict[str, Any]:
    try:
        text = path.read_text(encoding="utf-8")
        if _flow_depth(text) > 64:  # PyYAML recurses per level: 100k brackets take seconds to fail
            raise RecursionError
        data = yaml.safe_load(text)
    except (OSError, yaml.YAMLError) as e:
        raise FastneusError(f"cannot read config: {e}".splitlines()[0], file=label) from None
    except UnicodeDecodeError as e:
        raise FastneusError(f"cannot read config: not UTF-8 text (byte {e.start})", file=label) from None
    except ValueError as e:  # e.g. an integer of more digits than Python converts
        raise FastneusError(f"cannot read config: {e}".splitlines()[0][:200], file=label) from None
    except RecursionError:
        raise FastneusError("cannot read config: nested too deeply (a config is a flat mapping)", file=label) from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise FastneusError("a config file must hold a mapping of key: value", file=label)
    return data


def _coerce(name: str, value: Any, default: Any, source: str) -> Any:
    """Convert ``value`` (from YAML or a CLI string) to the type of the field's default."""
    f = {f.name: f for f in fields(Config)}[name]
    typ = str(f.type)
    try:
        if isinstance(value, str) and name != "preset" and not typ.startswith("str"):
            value = yaml.safe_load(value)  # "3", "1e-2", "true", "[0, 4]", "null"
        if typ.startswith("list") or "list[" in typ:
            if value is None:
                return None
            if isinstance(value, int):
                value = [value]
            if not isinstance(value, (list, tuple)):
                raise ValueError("expected a list such as [0, 4, 8]")
            items = [int(v) if isinstance(v, float) and v.is_integer() else v for v in value]
            if any(isinstance(v, bool) or not isinstance(v, int) or abs(v) > _INT_MAX for v in items):
                raise ValueError("expected a list of integers such as [0, 4, 8]")
            return items
        if isinstance(value, bool) and name in _CHOICES and "on" in _CHOICES[name]:
            return _YAML_BOOL_CHOICE[value]  # YAML 1.1: on/off/yes/no are booleans
        if isinstance(default, bool):
            if not isinstance(value, bool):
                raise ValueError("expected true or false")
            return value
        if isinstance(default, int):
            if isinstance(value, float) and value.is_integer():
                value = int(value)
            if not isinstance(value, int) or isinstance(value, bool):
                raise ValueError("expected an integer")
            return value
        if isinstance(default, float):
            if isinstance(value, str):  # YAML 1.1 reads "3e-3" (no dot) as a string
                try:
                    value = float(value)
                except ValueError:
                    pass
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError("expected a number")
            return float(value)
        return str(value)
    except (ValueError, TypeError, OverflowError, RecursionError, yaml.YAMLError) as e:
        raise FastneusError(f"bad value {_shown(value)}: {str(e).splitlines()[0] if str(e) else type(e).__name__}",
                            file=source, field=name) from None


def apply(cfg: Config, updates: dict[str, Any], source: str) -> Config:
    """Return ``cfg`` with ``updates`` applied and validated; unknown keys are errors."""
    known = {f.name for f in fields(cfg)}
    values = cfg.to_dict()
    for k, v in updates.items():
        if not isinstance(k, str):  # a YAML key such as 1: or true:
            raise FastneusError(f"config keys are names, got {type(k).__name__} {k!r}", file=source, field=repr(k))
        if k not in known:
            close = [n for n in known if n.startswith(k[:3])]
            hint = f" (did you mean {', '.join(sorted(close))}?)" if close else ""
            raise FastneusError(f"unknown config key{hint}", file=source,
                                field=k if k.isprintable() else repr(k))  # repr: the message stays one line
        values[k] = _coerce(k, v, getattr(Config(), k), source)
    out = Config(**values)
    validate(out, source)
    return out


def validate(cfg: Config, source: str = "config") -> None:
    for f in fields(cfg):  # .nan / .inf parse as floats; a NaN weight would silently skip every step
        v = getattr(cfg, f.name)
        if isinstance(v, float) and not math.isfinite(v):
            raise FastneusError(f"must be a finite number, got {v!r}", file=source, field=f.name)
    for k, choices in _CHOICES.items():
        if getattr(cfg, k) not in choices:
            raise FastneusError(f"must be one of {', '.join(choices)}, got {getattr(cfg, k)!r}", file=source, field=k)
    for f in fields(cfg):  # the table of ranges, then int32 for every other integer
        v = getattr(cfg, f.name)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            continue
        r = _RANGES.get(f.name, _Range(-_INT_MAX, _INT_MAX) if isinstance(v, int) else None)
        if r is None:
            continue
        if (r.lo is not None and (v <= r.lo if r.lo_open else v < r.lo)) or (r.hi is not None and v > r.hi):
            raise FastneusError(f"{r.text()}{f' ({r.note})' if r.note else ''}, got {_shown(v)}", file=source,
                                field=f.name)
        if isinstance(v, int) and r.hi is None and v > _INT_MAX:
            raise FastneusError(f"must be at most {_INT_MAX}, got {_shown(v)}", file=source, field=f.name)
    if cfg.min_rays > cfg.max_rays:
        raise FastneusError("min_rays must not exceed max_rays", file=source, field="min_rays")
    if cfg.base_res > cfg.finest_res:
        raise FastneusError(f"must not exceed finest_res ({cfg.finest_res}), got {cfg.base_res}", file=source,
                            field="base_res")
    if cfg.projector_blur not in (0, 1, 3, 5, 7):
        raise FastneusError(f"must be 0 (off) or an odd kernel size 1..7, got {cfg.projector_blur}", file=source,
                            field="projector_blur")


def load_config(config: str | None = None, overrides: list[str] | None = None,
                base: dict[str, Any] | None = None) -> Config:
    """Build the run config: defaults <- preset/YAML file <- ``base`` <- ``key=value`` overrides.

    Args:
        config: a preset name (``fewview``, ``oneshot``, ...) or a path to a YAML file.
        overrides: strings ``key=value`` (value parsed as YAML).
        base: extra keys applied after the YAML (used by verbs such as ``oneshot``).
    """
    cfg = Config()
    if config:
        path = Path(config)
        if path.suffix in (".yaml", ".yml") or os.sep in config:
            if not path.is_file():
                raise FastneusError("config file not found", file=config)
            data, label = _read_yaml(path, str(path)), str(path)
        else:
            res = resources.files("fastneus.configs") / f"{config}.yaml"
            if not res.is_file():
                raise FastneusError(f"unknown preset; presets: {', '.join(preset_names())}", field="--config")
            label = f"configs/{config}.yaml"
            data = _read_yaml(res, label)
        data.setdefault("preset", Path(config).stem)
        cfg = apply(cfg, data, label)
    if base:
        cfg = apply(cfg, base, "command line")
    parsed: dict[str, Any] = {}
    for item in overrides or []:
        if "=" not in item:
            raise FastneusError(f"expected key=value, got {item!r}", field="overrides")
        k, v = item.split("=", 1)
        parsed[k.strip()] = v
    return apply(cfg, parsed, "command line")


def save_config(cfg: Config, path: Path) -> None:
    """Write the resolved config as YAML, atomically."""
    from .io import atomic_write_text

    atomic_write_text(path, yaml.safe_dump(cfg.to_dict(), sort_keys=False))


def config_from_dict(d: dict[str, Any], source: str) -> Config:
    """Rebuild a Config from a saved dict (a run's config.yaml or a checkpoint).

    Step-based schedule keys of earlier versions become fractions of that run's ``steps``.
    """
    d = dict(d)

    def num(key: str, default: float) -> float:
        """A finite number the conversion needs; a bad legacy key is named, others are left to apply()."""
        v = d.get(key, default)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or abs(v) > _INT_MAX:
            if key in _LEGACY_STEPS or key == "c2f_steps_per_level":
                raise FastneusError(f"expected a number of steps, got {v!r}"[:120], file=source, field=key)
            return default
        return float(v)

    steps = max(1.0, num("steps", Config.steps))
    for old, new in _LEGACY_STEPS.items():
        if old in d:
            v = num(old, 0)
            d.pop(old)
            d.setdefault(new, min(1.0, max(0.0, v / steps)))
    if "c2f_steps_per_level" in d:
        per = max(1.0, num("c2f_steps_per_level", 1))
        d.pop("c2f_steps_per_level")
        levels, start = num("levels", Config.levels), num("c2f_start_levels", Config.c2f_start_levels)
        d.setdefault("c2f_frac", min(1.0, max(0.0, levels - start) * per / steps))
    return apply(Config(), d, source)
