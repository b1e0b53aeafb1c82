"""Run configuration: a nested, frozen dataclass with one section per component.

Every knob is declared once, with its default, allowed range and one line of help
(:func:`knob`); ``fastneus config`` lists them and :func:`validate` is generated from the
same declarations. Layers, in order: defaults <- preset / YAML file <- verb defaults <-
``key=value`` overrides. Keys are ``section.name`` (``optim.lr=5e-3``); a bare name is
accepted too since every name is unique across sections (``lr=5e-3``). Saved configs of
earlier versions (flat keys, schedules in steps) still load, translated, with a note.
Components receive only their section (``SDFField(cfg.hashgrid, cfg.network)``).
"""
from __future__ import annotations

import dataclasses
import math
import os
import re
import sys
from dataclasses import dataclass, field, fields
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from fastneus.errors import FastneusError

_NOTED: set[str] = set()


def _note(msg: str) -> None:
    """One stderr line per distinct message (translations of old keys)."""
    if msg not in _NOTED:
        _NOTED.add(msg)
        print(f"note: {msg}", file=sys.stderr)


def knob(default: Any, help: str, *, lo: float | None = None, hi: float | None = None, lo_open: bool = False,
         choices: tuple | None = None, model: bool = False) -> Any:
    """A config field with its metadata.

    Args:
        default: the default value (a list default is copied per instance).
        help: one line shown by ``fastneus config``.
        lo, hi: inclusive bounds (``lo_open``: ``lo`` itself is excluded).
        choices: the allowed values of a string/int knob.
        model: the knob shapes the trained model (``--resume`` refuses to change it).
    """
    meta = {"help": help, "lo": lo, "hi": hi, "lo_open": lo_open, "choices": choices, "model": model}
    if isinstance(default, list):
        return field(default_factory=lambda: list(default), metadata=meta)
    return field(default=default, metadata=meta)


FRAC = {"lo": 0.0, "hi": 1.0}  # a fraction of the run
_INT_MAX = 2 ** 31 - 1  # every integer knob (but seed) fits int32: kernels, torch and numpy take it as one


@dataclass(frozen=True)
class RunSection:
    """What runs, how long, and on what."""

    preset: str = knob("fewview", "name of the preset this config came from (informational)")
    backend: str = knob("warp", "kernel backend: warp, or torch (the pure-torch twins, for comparison)",
                        choices=("warp", "torch"))
    pattern_pass: str = knob("auto", "sample patterns per sample: fused | split | auto (split on CUDA)",
                             choices=("auto", "fused", "split"))
    seed: int = knob(0, "random seed (numpy's range)", lo=0, hi=2 ** 32 - 1)
    threads: int = knob(0, "CPU threads for kernels and torch (0 = FASTNEUS_THREADS, else every CPU); --threads",
                        lo=0, hi=4096)
    steps: int = knob(3000, "optimisation steps (the run's length when time_budget is 0)", lo=1)
    time_budget: float = knob(0.0, "seconds of training; > 0 makes it the run's length (steps ignored)",
                              lo=0.0)
    frames: list[int] | None = knob(None, "frames to train on (null = all)", model=True)
    log_every: int = knob(50, "steps between log.jsonl records", lo=1)
    save_every: int = knob(1000, "checkpoint period in steps (the last step always saves)", lo=1)
    split_step: str = knob("off", "CPU: each step's rays as two half batches, field, losses and backward of each on "
                           "its own thread, one Adam update (where the step allows it: no surface prior, one ray per "
                           "pixel): ~1.5x the steps of one thread instead of ~1.35x on 2 cores; it computes what one "
                           "thread does: over 49 fresh seeds of two thin-legged ant cells it came out better on 18, "
                           "~0.2 mm worse on average (docs/perf-notes/2026-11-30-split-step-cpu.md)", choices=("off", "on"))
    cuda_graph: str = knob("auto", "replay the step after marching as a captured CUDA graph where nothing in it "
                           "changes but the inputs (auto/on: on CUDA; off: always eager)", choices=("auto", "on", "off"))
    matmul: str = knob("auto", "float32 matrix products of the training step (the small networks): tf32 (tensor "
                       "cores, 10-bit mantissa, as tiny-cuda-nn's half-precision networks) | fp32 | auto (tf32 on "
                       "CUDA GPUs that have it, compute capability >= 8; fp32 elsewhere)", choices=("auto", "tf32", "fp32"))
    validate_every: float = knob(60.0, "seconds of training between validation renders of one held frame "
                                 "(photo | render | depth) into RUN/validation/; 0 = off (the last step "
                                 "always writes one)", lo=0.0)
    validate_every_steps: int = knob(0, "steps between validation renders (0 = off; with validate_every, "
                                     "whichever comes first)", lo=0)
    tensorboard: str = knob("auto", "TensorBoard event files in RUN/tensorboard/: auto = when the tensorboard "
                            "package is installed (pip install 'fastneus[tensorboard]')", choices=("auto", "on", "off"))


@dataclass(frozen=True)
class RaysSection:
    """Which pixels become rays each step, and how rays are marched."""

    target_samples: int = knob(2 ** 18, "samples per step; the ray count adapts to hit it", lo=1)
    init_rays: int = knob(2048, "rays of the first step", lo=1)
    min_rays: int = knob(256, "fewest rays per step", lo=1)
    max_rays: int = knob(2 ** 16, "most rays per step", lo=1)
    march_step: float = knob(math.sqrt(3) * 2 / 1024, "ray-marching step (normalised units)", lo=0.0, lo_open=True)
    max_samples_per_ray: int = knob(1024, "cap on samples per ray", lo=1)
    bound: str = knob("sphere", "region of interest in normalised space: sphere | box", choices=("sphere", "box"),
                      model=True)
    background: float = knob(0.0, "background colour behind the object (synthetic data: black)", lo=0.0, hi=1.0)
    camera_blur: str = knob("auto", "camera blur (lens defocus + the pixel's area), Gaussian sigma in pixels, "
                            "applied as blur_via says: auto (estimated from the data at blur_at_frac and "
                            "blur_refine_frac of the run, fastneus.train.blurfit; a sharp capture keeps 0), or a "
                            "number in [0, 10] (0 = one ray per pixel through its centre, the patterns as they are)")
    blur_at_frac: float = knob(0.3, "camera_blur=auto: fraction of the run at which the blur is estimated "
                               "(the geometry and colours must be roughly fit by then)", **FRAC)
    blur_refine_frac: float = knob(0.5, "camera_blur=auto: fraction of the run at which it is estimated again, "
                                   "on the field trained with the first estimate (a field trained on sharp "
                                   "patterns favours a sharper blur); 0 or <= blur_at_frac = once", **FRAC)
    blur_via: str = knob("pattern", "how camera_blur enters the model: pattern = the projected light only, each "
                         "pattern image blurred once by it in projector pixels (no cost per step); rays = each "
                         "training pixel is blur_rays rays spread by it, their colours averaged",
                         choices=("pattern", "rays"))
    blur_rays: int = knob(4, "rays per training pixel when camera_blur > 0 and blur_via=rays", lo=2, hi=16)
    bright_fraction: float = knob(0.5, "share of rays drawn in proportion to pixel brightness (sparse laser lines)",
                                  **FRAC)
    group_shots: bool = knob(True, "multi-shot: one ray per viewpoint pixel carries its shots (false = separate)")
    shots_per_ray: int = knob(4, "multi-shot: shots rendered per ray and step, drawn at random (0 = all)",
                              lo=0)


@dataclass(frozen=True)
class OccupancySection:
    """The occupancy grid that skips empty space."""

    occ_resolution: int = knob(128, "cells per side", lo=1, hi=1024, model=True)
    occ_update_every: int = knob(16, "steps between grid updates", lo=1)
    occ_update_cells: str = knob("auto", "cells whose SDF a grid update queries: all | near (the occupied cells, "
                                 "their neighbours and a random occ_near_rest of the others) | auto (near on the "
                                 "CPU, where a full update was 23 % of a 1-thread step; all on a GPU, where it "
                                 "is ~1 %)", choices=("auto", "all", "near"))
    occ_near_rest: float = knob(0.25, "occ_update_cells=near: share of the cells away from the occupied ones "
                                "queried at each update", **FRAC)
    stop_rays: str = knob("auto", "training rays end at the first cell deep inside the object (SDF below "
                          "-stop_inside cells at the last grid update: nothing behind it is seen), so a step's samples "
                          "go to more rays: auto (with masks in a dark room: H100 rock 5 s 7.53 -> 7.08 mm; lit "
                          "rooms were 1-5 % worse, no masks mixed) | on | off", choices=("auto", "on", "off"))
    stop_inside: float = knob(3.0, "depth below the surface, in grid cells, of the cells that end a ray (stop_rays)",
                              lo=0.0, lo_open=True)
    occ_warmup_frac: float = knob(0.2, "every cell occupied for this fraction of the run", **FRAC)
    occ_threshold: float = knob(0.01, "opacity above which a cell is occupied", lo=0.0)
    min_views: int = knob(2, "space seen by fewer distinct viewpoints is never occupied (0 = off)", lo=0)
    hull: str = knob("auto", "space outside the masks' visual hull is empty: loss (the SDF is pushed positive there "
                     "at the uniform points) | bound (loss, and the grid never occupies it) | off; auto = loss with "
                     "masks (H200, Dark, masks, 3 s: a nut whose hole holds the initial sphere 23.0 -> 8.1 mm, other "
                     "shapes within +-4 %; bound: rock 5 s 7.19 -> 6.14 but the nut and toy worse, CPU worse)",
                     choices=("auto", "loss", "bound", "off"))
    hull_weight: float = knob(1.0, "weight of the hull's free-space term (mean over the uniform points)", lo=0.0)
    photo_hull: str = knob("off", "without masks, with the foreground prior on (frames >= 85 % backdrop), the hull of "
                           "the photos' non-background pixels (specks of noise left out) stands in for the masks' in `hull`: "
                           "auto (cpu-quick's choice: ant, Dark, no masks, 600 steps, 3 seeds: ideal 8.05 -> 6.52 mm symmetric, "
                           "realistic 13.01 -> 11.59; a lit room's ideal ant mixed, 5.22 / 6.38 -> 5.99 / 5.94 on seeds 0 / 1) | "
                           "dark = only where the object is dim beside the laser lines (not `lit_room`; fewview's choice: H200, "
                           "10 s, ideal ant, seeds 0-1, 2.76 -> 2.70 mm; on the realistic 200-px ant the views disagree "
                           "and it is dropped) | off; dropped, with its reason printed, where the "
                           "views disagree (a noisy backdrop)", choices=("auto", "dark", "off"))
    hull_keep: str = knob("off", "with masks: the hull's cells stay occupied in the grid (for hull_keep_frac of the "
                          "run), so a thin part the field has not formed when the grid first prunes is still sampled "
                          "and the masks can pull it in; cells deep inside (stop_rays) still end rays. auto = in a "
                          "dark room (cpu-quick's choice: realistic ant, Dark, masks, 600 steps, 3 seeds 7.73 -> 3.87 "
                          "mm symmetric, its legs no longer lost; lit rooms 2-6 % worse); on | off; off on the GPU (H200, "
                          "10 s: the ant's legs form in time there; masked rock realistic 8.05 -> 8.34 mm, again 6.24 -> "
                          "6.77 on three seeds at 2928f64)",
                          choices=("auto", "on", "off"))
    hull_keep_frac: float = knob(1.0, "hull_keep: the fraction of the run it lasts (0.5 kept the legs on 2 of 5 seeds, "
                                 "1.0 on 4 of 5)", **FRAC)
    hull_margin: int = knob(0, "the free-space term acts only this many grid cells beyond the hull (coarse hash "
                            "levels are shared across a few cells: a thin part next to the pushed space is pushed too)",
                            lo=0, hi=16)


@dataclass(frozen=True)
class HashGridSection:
    """The multiresolution hash encoding of the SDF."""

    levels: int = knob(16, "resolution levels", lo=1, hi=64, model=True)
    features: int = knob(2, "features per level (the hash kernels' limit: 8)", lo=1, hi=8, model=True)
    log2_table: int = knob(19, "log2 of the table entries per level (the kernels' limit: 30)", lo=1, hi=30, model=True)
    pixels_per_entry: float = knob(0.0, "if > 0: the table's entries per level follow the photos, one per this many "
                                   "pixels of the distinct viewpoints (a power of two, from 2^17 up to 2^log2_table); "
                                   "0 = 2^log2_table. Printed and saved (run.json hash_table)", lo=0.0, hi=1e6,
                                   model=True)
    base_res: int = knob(16, "resolution of the coarsest level", lo=1, model=True)
    finest_res: int = knob(2048, "resolution of the finest level", lo=1, model=True)
    c2f_start_levels: int = knob(4, "coarse-to-fine: active levels at the start (0 = all)", lo=0)
    c2f_frac: float = knob(0.4, "... rising linearly to all levels at this fraction of the run", **FRAC)


@dataclass(frozen=True)
class NetworkSection:
    """The SDF and colour MLPs and the NeuS sharpness."""

    sdf_hidden: int = knob(64, "SDF MLP width", lo=1, model=True)
    sdf_layers: int = knob(1, "SDF MLP hidden layers", lo=0, hi=16, model=True)
    geo_features: int = knob(15, "geometry features passed from the SDF to the colour MLP", lo=1, hi=4096,
                             model=True)
    color_hidden: int = knob(64, "colour MLP width", lo=1, model=True)
    color_layers: int = knob(2, "colour MLP hidden layers", lo=0, hi=16, model=True)
    view_dependent: bool = knob(True, "the colour MLP sees the view direction", model=True)
    highlight: bool = knob(False, "the colour MLP also learns the projected light's highlight e >= 0 at each "
                           "sample (c = D + (i_r D + i_b + e) Q): a shiny surface's glint of the lasers, which "
                           "otherwise inflates i_r and bends the surface (loss.highlight_weight keeps it where the photos need "
                           "it). For shiny objects: strong glints (synth's specular 1.5, CPU, masks, three seeds) rock "
                           "10.42 -> 10.00 mm, ant 4.05 -> 3.83. Off by default: on the standard realistic mix "
                           "(specular 0.25) the rock gained and the thin ant lost (H200, 10 s), and it does not settle "
                           "i_r / i_b (docs/benchmarks/illum-realistic-gpu.md)",
                           model=True)
    init_radius: float = knob(0.5, "radius of the initial SDF sphere (normalised units)", lo=0.0, hi=1.0, lo_open=True)
    variance_init: float = knob(0.3, "initial NeuS sharpness: inv_s = exp(10 v), inside its clamp [1e-3, 1e6]",
                                lo=round(math.log(1e-3) / 10, 4), hi=round(math.log(1e6) / 10, 4))
    inv_s_floor_end: float = knob(1000.0, "inv_s floor at the end of its ramp (0 = learned only)", lo=0.0, hi=1e6)
    inv_s_floor_start: float = knob(20.0, "inv_s floor at the start of its ramp", lo=0.0, hi=1e6, lo_open=True)
    inv_s_floor_frac: float = knob(0.6, "the floor rises log-linearly over this fraction of the run", **FRAC)
    inv_s_floor_per_step: float = knob(0.0, "cap the floor's end at this many times the run's step count "
                                       "(under a time budget, the count expected at the rate so far): a short run "
                                       "cannot resolve a surface as sharp as a long one; 0 = off", lo=0.0, hi=1e3)
    normal_eps_min: float = knob(1e-3, "lower bound of the finite-difference step (normalised)", lo=0.0,
                                 lo_open=True)
    sdf_grad: str = knob("analytic", "SDF gradient: analytic (hash d/dx from one kernel) | fd (4-tap tetrahedron)",
                         choices=("analytic", "fd"))


@dataclass(frozen=True)
class OptimSection:
    """Adam and the learning-rate schedule."""

    lr: float = knob(1e-2, "learning rate of the hash grid and MLPs", lo=0.0, lo_open=True)
    lr_variance: float = knob(5e-3, "learning rate of the NeuS variance (0 = frozen)", lo=0.0)
    lr_illum: float = knob(3e-2, "learning rate of log(i_r), log(i_b) (0 = frozen)", lo=0.0)
    adam_eps: float = knob(1e-15, "Adam epsilon", lo=0.0, lo_open=True)
    warmup_frac: float = knob(0.03, "linear lr warm-up (fraction of the run; the geometry's starts when it unfreezes)", **FRAC)
    color_warmup_frac: float = knob(0.03, "geometry frozen while the colour net fits the brightness", **FRAC)
    decay_to: float = knob(0.05, "final lr factor (cosine decay after warm-up)", lo=0.0, hi=1.0, lo_open=True)


@dataclass(frozen=True)
class LossSection:
    """The loss terms and their weights (fastneus/train/losses.py)."""

    eikonal_weight: float = knob(0.1, "eikonal term weight (0 = off)", lo=0.0)
    masks: str = knob("auto", "mask BCE: auto (on when every training frame has a mask) | on | off",
                      choices=("auto", "on", "off"))
    mask_weight: float = knob(0.1, "mask term weight (mask_loss; 0 = off)", lo=0.0)
    mask_loss: str = knob("bce", "how a mask pulls: bce (the rendered opacity against the mask) | sdf (a mask "
                          "pixel's ray must enter the object, a background pixel's must not: the smallest SDF along "
                          "the ray, no pull once on the right side) | mixed (sdf for mask pixels, bce for background "
                          "pixels: the GPU preset's, H200 10 s rock Dark 7.40 -> 5.81 mm, 5 s 7.00 -> 6.39, the "
                          "thin-legged realistic ant 2.70-2.92 -> 2.99-3.02; the CPU preset keeps bce, with which its "
                          "128-px realistic ant keeps its legs)",
                          choices=("bce", "sdf", "mixed"))
    mask_core: float = knob(0.0, "with mask_loss sdf or mixed: mask pixels this far inside the outline (a fraction "
                            "of the image's larger side, at least 1 px) are held by the BCE on the opacity (a ray through "
                            "the body's middle must be opaque), the rim by the SDF (0 = every mask pixel by the SDF; the "
                            "GPU preset: 0.02, 4 px at 200 px, which keeps the lit-room realistic ant from opening a "
                            "pocket inside its body, H200 10 s 3.79 -> 2.72 mm)", lo=0.0, hi=0.25)
    mask_thin: bool = knob(False, "with mask_core: the mask's parts narrower than the core's square (the mask minus "
                           "its opening: legs, antennae) are held by the opacity too, not by the SDF hinge")
    mask_start: str = knob("auto", "a stronger mask weight early in the run (mask_weight_start, falling to "
                           "mask_weight at mask_start_frac): thin parts a blurred photo barely shows are held by the "
                           "masks while the shape forms, the photos have the last word. auto: with masks in a lit "
                           "room (the object's pixels bright, not lasers in the dark, where it lost legs) | on | off",
                           choices=("auto", "on", "off"))
    mask_weight_start: float = knob(0.3, "mask BCE weight at the start of the run (mask_start; used when above "
                                    "mask_weight)", lo=0.0)
    mask_start_frac: float = knob(0.3, "where mask_weight_start has fallen to mask_weight (fraction of the run)",
                                  **FRAC)
    curvature_weight: float = knob(0.0, "smoothness prior |f(x+e) + f(x-e) - 2 f(x)| (oneshot; 0 = off)", lo=0.0)
    cos_anneal_frac: float = knob(0.15, "NeuS cos-anneal ratio 0 -> 1 over this fraction of the run", **FRAC)
    bg_prior: str = knob("auto", "background pixels are free space without masks: auto (>= 5 % of pixels) | on | off",
                         choices=("auto", "on", "off"))
    bg_weight: float = knob(0.1, "weight of the background prior", lo=0.0)
    bg_weight_lit: float = knob(0.0, "weight of the background and foreground priors in a lit room (the object's "
                                "pixels bright and solid, not lasers in the dark); 0 = bg_weight", lo=0.0)
    bg_lit: str = knob("auto", "background prior only where the projectors light the ray's surface (a black pixel "
                       "in a dark room says nothing of an unlit surface): auto (when >= 85 % of pixels are "
                       "background colour) | on | off", choices=("auto", "on", "off"))
    bg_lit_ref: float = knob(0.05, "projected light at a ray's surface that makes its black pixel fully background "
                             "(bg_lit)", lo=0.0, lo_open=True)
    bg_start_frac: float = knob(0.2, "the background prior ramps in from this fraction of the run to twice it", **FRAC)
    fg_prior: str = knob("auto", "without masks, pixels brighter than the background colour by fg_threshold pull "
                         "their ray's opacity to 1 (the mask's other half, read off the photo: keeps thin parts "
                         "that only ambient light shows): auto (with the background prior in a dark room, >= 85 % "
                         "background pixels; the background prior then carves every black pixel) | on | off",
                         choices=("auto", "on", "off"))
    fg_threshold: float = knob(0.02, "linear brightness above the background colour that makes a pixel foreground "
                               "(fg_prior)", lo=0.0, lo_open=True)
    fg_relative: float = knob(0.5, "a foreground pixel must also be this share of the brightest pixel within 2 px "
                              "(the lens's halo around a bright object is not the object); 0 = threshold only",
                              lo=0.0, hi=1.0)
    bg_halo: float = knob(0.5, "without masks in a lit room, once the camera blur is known (> 0): a pixel between "
                          "the object and the backdrop (within 2 x the blur of it, neither flag) at a ratio r < bg_halo "
                          "of the brightest pixel within 2 px is backdrop with weight 1 - r / bg_halo (the lens's "
                          "halo is not the object); 0 = off", lo=0.0, hi=1.0)
    fg_halo: float = knob(0.0, "without masks in a dark room, once the camera blur is known (> 0), from fg_halo_frac "
                          "of the run: a foreground-flagged pixel beside a backdrop pixel (4-neighbour) under fg_halo x "
                          "the brightest flagged pixel within 1 px is the lens's halo, not the object, and loses its "
                          "flag (cpu-quick's choice, 0.7: realistic ant, Dark, no masks, 600 steps, seeds 0-2 9.81 -> "
                          "7.48 mm symmetric; fewview's: H200, 10 s, realistic ant, seeds 0-2, 6.26 -> 5.30 mm; at 5 s one "
                          "seed of two lost leg parts); 0 = off",
                          lo=0.0, hi=2.0)
    fg_halo_frac: float = knob(0.0, "fg_halo acts from this fraction of the run (late: the thin parts have formed; "
                               "from the blur's estimate a leg could be lost)", **FRAC)
    fg_start_frac: float = knob(0.2, "the foreground prior acts from this fraction of the run (from the start it "
                                "grew blobs: ant Dark 14.6 vs 5.3 mm GT->rec)", **FRAC)
    bg_tolerance: float = knob(0.008, "per-channel distance to `background` still counted as it (the floor: see "
                               "bg_noise_k)", lo=0.0)
    bg_noise_k: float = knob(3.0, "widen bg_tolerance to this many times the photos' noise floor (the median pixel's "
                             "distance from `background`, when that pixel is backdrop), at most fg_threshold: a real "
                             "camera's black is not 0 (realistic captures: 0.004); 0 = the fixed tolerance", lo=0.0)
    highlight_weight: float = knob(0.5, "L1 weight on each ray's rendered highlight (network.highlight): the "
                                   "light's share the same everywhere is i_b's, not a highlight's (0.5 against 0.05: "
                                   "better on strong glints, CPU seed 0, and on the mean of three GPU seeds of the "
                                   "realistic ant)", lo=0.0)
    robust: str = knob("l1", "photometric penalty on |rendered - photo|: l1 | charbonnier | huber | cauchy "
                       "(scale robust_eps)", choices=("l1", "charbonnier", "huber", "cauchy"))
    robust_eps: float = knob(0.01, "scale of the charbonnier / huber penalty (linear units)", lo=0.0, lo_open=True)
    saturated: str = knob("onesided", "photo channels >= 254: onesided (rendering brighter is no error) | mask "
                          "(pixel left out) | off", choices=("onesided", "mask", "off"))


@dataclass(frozen=True)
class IllumSection:
    """The projected-light model: whether it is used and how i_r, i_b are learned."""

    use_pattern: bool = knob(True, "false = passive NeuS (no projected pattern in the model)", model=True)
    learn_illum: bool = knob(True, "learn i_r (reflectance) and i_b (bias)")
    illum_warmup_frac: float = knob(0.15, "i_r, i_b frozen for this fraction of the run", **FRAC)
    illum_init: str = knob("scene", "start i_r, i_b at the scene's values | ones", choices=("scene", "ones"))
    response: str = knob("auto", "camera response the photos are decoded with: auto (scene.json, else the "
                         "files' tags, else srgb) | linear | srgb | gamma=G")
    level: str = knob("auto", "auto: photos whose brightest 0.1 % of pixels are below 0.12 (linear) are scaled for "
                      "training up to 0.12-0.18 (at most 16x; the priors' thresholds were set on captures that "
                      "bright: a 4x underexposed dark room without masks came out empty); i_b, textures and colours "
                      "are reported in the photos' own units | off", choices=("auto", "off"))
    black: str = knob("auto", "auto: a camera's black level (the photos' most common value when it is a dark floor "
                      "under 0.08 linear that a quarter of the pixels sit on and almost none below: a raw sensor's "
                      "pedestal) is subtracted before training, so the background prior finds the backdrop at 0 | off",
                      choices=("auto", "off"))
    exposure: str = knob("auto", "learn a gain per photo (auto-exposure; the first training frame's is 1): auto "
                         "(at exposure_at_frac of the run, each photo's gain is fit against a render seen along each "
                         "surface's normal, on four ray batches; learned from then on when the batches agree on a "
                         "spread > 6 %: on fixed-exposure captures learning them cost accuracy) | on | off",
                         choices=("auto", "on", "off"), model=True)
    exposure_at_frac: float = knob(0.2, "exposure=auto: fraction of the run at which it is decided", **FRAC)
    lr_exposure: float = knob(1e-2, "learning rate of the per-photo log-gains", lo=0.0)


@dataclass(frozen=True)
class InitSection:
    """Geometry initialisation from decoded / swept surfaces, and its prior."""

    init_geometry: str = knob("auto", "auto | decode | sphere: start the SDF at a decoded or swept surface",
                              choices=("auto", "decode", "sphere"))
    init_geometry_steps: int = knob(100, "SDF fit steps of that initialisation (counted in the training time)",
                                    lo=1)
    prior_weight: float = knob(3.0, "weight of the decoded points as a prior afterwards (0 = off)", lo=0.0)
    prior_frac: float = knob(2.0, "the prior fades linearly toward 0 at this fraction of the run (2 = half left)",
                             lo=0.0, lo_open=True)


@dataclass(frozen=True)
class RigSection:
    """Learned corrections of a real rig (docs/REAL-RIGS.md); every part off by default."""

    pose_refine: bool = knob(False, "learn an SE(3) correction per viewpoint camera and per projector", model=True)
    pose_anchor: bool = knob(True, "the first training viewpoint's camera stays fixed (world frame)", model=True)
    pose_fix_scale: bool = knob(True, "with the anchor, hold the rig's global scale")
    lr_pose: float = knob(2e-4, "learning rate of the pose corrections (radians, normalised units)", lo=0.0, lo_open=True)
    pose_warmup_frac: float = knob(0.1, "corrections frozen for this fraction of the run", **FRAC)
    projector_blur: int = knob(0, "learned n x n blur of each projector's pattern (0 = off; odd n <= 7)",
                               choices=(0, 1, 3, 5, 7), model=True)
    lr_blur: float = knob(5e-3, "learning rate of the blur kernels", lo=0.0, lo_open=True)
    blur_warmup_frac: float = knob(0.1, "blur kernels frozen for this fraction of the run", **FRAC)
    refraction: bool = knob(True, "use the scene's flat ports (underwater housings)", model=True)
    medium: str = knob("auto", "learned water attenuation + back-scatter: auto (on with a port) | on | off",
                       choices=("auto", "on", "off"), model=True)
    lr_medium: float = knob(1e-2, "learning rate of the medium coefficients", lo=0.0, lo_open=True)
    medium_far: float = knob(20.0, "range (world units) of rays that hit nothing", lo=0.0, lo_open=True)


@dataclass(frozen=True)
class ExportSection:
    """What is written after training."""

    mesh_resolution: int = knob(256, "marching-cubes grid resolution (checked before training)", lo=2, hi=4096)


SECTIONS: dict[str, type] = {
    "run": RunSection, "rays": RaysSection, "occupancy": OccupancySection, "hashgrid": HashGridSection,
    "network": NetworkSection, "optim": OptimSection, "loss": LossSection, "illum": IllumSection, "init": InitSection,
    "rig": RigSection, "export": ExportSection,
}


@dataclass(frozen=True)
class Config:
    """All knobs of a fastneus run (defaults = the GPU few-view preset), one section per component."""

    run: RunSection = field(default_factory=RunSection)
    rays: RaysSection = field(default_factory=RaysSection)
    occupancy: OccupancySection = field(default_factory=OccupancySection)
    hashgrid: HashGridSection = field(default_factory=HashGridSection)
    network: NetworkSection = field(default_factory=NetworkSection)
    optim: OptimSection = field(default_factory=OptimSection)
    loss: LossSection = field(default_factory=LossSection)
    illum: IllumSection = field(default_factory=IllumSection)
    init: InitSection = field(default_factory=InitSection)
    rig: RigSection = field(default_factory=RigSection)
    export: ExportSection = field(default_factory=ExportSection)

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """Nested plain dict (section -> name -> value), as saved in config.yaml."""
        return dataclasses.asdict(self)

    def flat(self) -> dict[str, Any]:
        """name -> value over every section (names are unique)."""
        return {k: v for sec in self.to_dict().values() for k, v in sec.items()}

    def replace(self, **updates: Any) -> "Config":
        """A copy with ``name=value`` updates (bare or ``section__name``), validated."""
        return apply(self, {k.replace("__", "."): v for k, v in updates.items()}, "replace()")


# name -> (section, dataclasses.Field), over every section
KEYS: dict[str, tuple[str, dataclasses.Field]] = {f.name: (s, f) for s, cls in SECTIONS.items() for f in fields(cls)}
# keys of earlier versions (schedules in steps): converted to fractions of the run when a saved
# config is read back (a run folder from an older fastneus must still open)
_LEGACY_STEPS = {"occ_warmup_steps": "occ_warmup_frac", "warmup_steps": "warmup_frac",
                 "color_warmup_steps": "color_warmup_frac", "cos_anneal_steps": "cos_anneal_frac",
                 "illum_warmup_steps": "illum_warmup_frac"}
_DROPPED = {"render_frames": "the report picks its frames (fastneus render --frame I renders others)"}


def model_keys() -> set[str]:
    """Names of the knobs that shape the trained model (``--resume`` cannot change them)."""
    return {k for k, (_, f) in KEYS.items() if f.metadata.get("model")}


def describe() -> list[tuple[str, str, str, str]]:
    """(``section.name``, default, range or choices, help) of every knob, for ``fastneus config``."""
    rows = []
    for k, (s, f) in KEYS.items():
        m = f.metadata
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        if m["choices"]:
            rng = " | ".join(str(c) for c in m["choices"])
        elif m["lo"] is not None or m["hi"] is not None:
            rng = _range_text(m["lo"], m["hi"], m["lo_open"])
        else:
            rng = ""
        rows.append((f"{s}.{k}", _fmt(default), rng, m["help"]))
    return rows


def _range_text(lo: Any, hi: Any, lo_open: bool) -> str:
    """``[0, 1]``, ``(0, 1]``, ``>= 0``, ``> 0``."""
    if hi is None:
        return f"{'>' if lo_open else '>='} {_fmt(lo)}"
    return f"{'(' if lo_open else '['}{_fmt(lo)}, {_fmt(hi)}]"


def _fmt(v: Any) -> str:
    if isinstance(v, bool) or v is None:
        return yaml.safe_dump(v).split("\n")[0]
    if isinstance(v, float):
        return f"{v:g}"
    return str(v)


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
    except UnicodeDecodeError as e:
        raise FastneusError(f"cannot read config: not UTF-8 text (byte {e.start})", file=label) from None
    except ValueError as e:  # e.g. an integer of more digits than Python converts
        raise FastneusError(f"cannot read config: {e}".splitlines()[0][:200], file=label) from None
    except RecursionError:
        raise FastneusError("cannot read config: nested too deeply (a config is a mapping of sections)",
                            file=label) from None
    except (OSError, yaml.YAMLError) as e:
        raise FastneusError(f"cannot read config: {e}".splitlines()[0], file=label) from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise FastneusError("a config file must hold a mapping of key: value", file=label)
    return data


def _shown(v: Any) -> str:
    """A value for a one-line message: huge integers as their magnitude, long reprs cut."""
    if isinstance(v, int) and not isinstance(v, bool) and abs(v) >= 10 ** 15:
        return f"{'-' if v < 0 else ''}2^{abs(v).bit_length() - 1}+"
    r = repr(v) if not isinstance(v, float) else _fmt(v)
    return r if len(r) <= 60 else r[:57] + "..."


def _coerce(name: str, value: Any, source: str) -> Any:
    """Convert ``value`` (from YAML or a CLI string) to the type of the knob ``name``."""
    return coerce(KEYS[name][1], value, source, f"{KEYS[name][0]}.{name}")


def coerce(f: dataclasses.Field, value: Any, source: str, where: str) -> Any:
    """Convert ``value`` (from YAML or a CLI string) to the type of dataclass field ``f``.

    The one parser of every config dataclass (the run config's sections, the NeuS-MLP baseline's).

    Raises:
        FastneusError: naming ``source`` and ``where`` (the key as the user writes it).
    """
    name = f.name
    typ = str(f.type)
    default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
    try:
        if isinstance(value, str) and name != "preset" and not typ.startswith("str"):
            value = yaml.safe_load(value)  # "3", "1e-2", "true", "[0, 4]", "null"
        if "list[" in typ:
            if value is None:
                return None
            if isinstance(value, int) and not isinstance(value, bool):
                value = [value]
            if not isinstance(value, (list, tuple)) or not all(isinstance(v, int) and not isinstance(v, bool)
                                                               and 0 <= v <= _INT_MAX for v in value):
                raise ValueError("expected a list of frame indices such as [0, 4, 8]")
            return [int(v) for v in value]
        if "tuple[" in typ:
            value = value if isinstance(value, (list, tuple)) else [value]
            if not all(isinstance(v, int) and not isinstance(v, bool) and abs(v) <= _INT_MAX for v in value):
                raise ValueError("expected a list of integers such as [4]")
            return tuple(value)
        if isinstance(default, bool):
            if isinstance(value, str) and value.lower() in ("on", "off", "yes", "no"):
                value = value.lower() in ("on", "yes")
            if not isinstance(value, bool):
                raise ValueError("expected true or false")
            return value
        if isinstance(default, int):
            if isinstance(value, float) and math.isfinite(value) and value.is_integer():
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
            value = float(value)
            if not math.isfinite(value):
                raise ValueError("expected a finite number")
            return value
        if isinstance(value, bool) and f.metadata.get("choices") and "off" in f.metadata["choices"]:
            return "on" if value else "off"  # YAML 1.1 reads on / off as booleans
        if isinstance(value, str) and f.metadata.get("choices") and "off" in f.metadata["choices"] \
                and value.lower() in ("true", "false", "yes", "no"):
            return "on" if value.lower() in ("true", "yes") else "off"  # a knob that was a boolean before
        if not isinstance(value, (str, int, float)) or isinstance(value, bool):
            raise ValueError("expected a word")
        return str(value)
    except (ValueError, TypeError, OverflowError, RecursionError, yaml.YAMLError) as e:
        raise FastneusError(f"bad value {_shown(value)}: {str(e).splitlines()[0] if str(e) else type(e).__name__}",
                            file=source, field=where) from None


def _key(k: Any, source: str, section: str | None = None) -> str:
    """The knob name of a key (``name``, ``section.name``), or a one-line error."""
    if not isinstance(k, str):  # a YAML key such as 1: or true:
        raise FastneusError(f"config keys are names, got {type(k).__name__} {_shown(k)}", file=source,
                            field=repr(k)[:60])
    sec, _, name = k.rpartition(".")
    sec = sec or section
    if name in _DROPPED:
        return ""
    if name not in KEYS or (sec and KEYS[name][0] != sec):
        close = sorted(f"{KEYS[n][0]}.{n}" for n in KEYS if n.startswith(name[:3]))
        hint = f" (did you mean {', '.join(close)}?)" if close else " (fastneus config lists them)"
        shown = k if k.isprintable() else repr(k)  # repr: the message stays one line
        raise FastneusError(f"unknown config key{hint}", file=source, field=shown[:80])
    return name


def _flatten(updates: dict[Any, Any], source: str) -> dict[str, Any]:
    """name -> value from a nested ({section: {name: v}}), dotted or flat mapping."""
    out: dict[str, Any] = {}
    for k, v in updates.items():
        if isinstance(k, str) and k in SECTIONS:
            if v is None:
                continue
            if not isinstance(v, dict):
                raise FastneusError("a section must hold a mapping of name: value", file=source, field=k)
            for kk, vv in v.items():
                name = _key(kk, source, section=k)
                if name:
                    out[name] = vv
        else:
            name = _key(k, source)
            if name:
                out[name] = v
    return out


def apply(cfg: Config, updates: dict[Any, Any], source: str) -> Config:
    """Return ``cfg`` with ``updates`` (nested, dotted or bare names) applied and validated."""
    values = cfg.flat()
    for name, v in _flatten(updates, source).items():
        values[name] = _coerce(name, v, source)
    out = build(values)
    validate(out, source)
    return out


def build(values: dict[str, Any]) -> Config:
    """A Config from name -> value over all sections (missing names keep their defaults)."""
    return Config(**{s: cls(**{f.name: values[f.name] for f in fields(cls) if f.name in values})
                     for s, cls in SECTIONS.items()})


def check(f: dataclasses.Field, v: Any, source: str, where: str) -> None:
    """Check value ``v`` of field ``f`` against its declared range and choices (:func:`knob`)."""
    m = f.metadata
    if isinstance(v, float) and not math.isfinite(v):
        raise FastneusError(f"must be a finite number, got {v!r}", file=source, field=where)
    if m.get("choices") and v not in m["choices"]:
        raise FastneusError(f"must be one of {', '.join(str(c) for c in m['choices'])}, got {v!r}",
                            file=source, field=where)
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        lo, hi = m.get("lo"), m.get("hi")
        if isinstance(v, int) and hi is None:
            hi = _INT_MAX
        if (lo is not None and (v < lo or (m.get("lo_open") and v == lo))) or (hi is not None and v > hi):
            rng = _range_text(lo, hi, m.get("lo_open", False)) if lo is not None else f"<= {_fmt(hi)}"
            raise FastneusError(f"must be {'in ' if rng[0] in '[(' else ''}{rng}, got {_shown(v)}",
                                file=source, field=where)


def validate(cfg: Config, source: str = "config") -> None:
    """Check every knob against its declared range / choices, then the cross-knob rules."""
    for s, cls in SECTIONS.items():
        sec = getattr(cfg, s)
        for f in fields(cls):
            check(f, getattr(sec, f.name), source, f"{s}.{f.name}")
    if cfg.rays.min_rays > cfg.rays.max_rays:
        raise FastneusError("must not exceed rays.max_rays", file=source, field="rays.min_rays")
    if cfg.hashgrid.base_res > cfg.hashgrid.finest_res:
        raise FastneusError("must not exceed hashgrid.finest_res", file=source, field="hashgrid.base_res")
    cb = cfg.rays.camera_blur
    if camera_blur_sigma(cb) is None and cb != "auto":
        raise FastneusError(f"must be auto or a number in [0, 10], got {cb!r}", file=source, field="rays.camera_blur")
    if cb == "auto" and cfg.rays.blur_via == "rays":
        raise FastneusError("camera_blur=auto puts the blur on the patterns: set blur_via=pattern, or a number",
                            file=source, field="rays.camera_blur")
    r = cfg.illum.response  # the grammar of fastneus.data.response.parse_response (a lower layer may not import it)
    m = re.fullmatch(r"gamma=([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)", r) if isinstance(r, str) else None
    if not (r in ("auto", "linear", "srgb") or (m and 0.2 <= float(m.group(1)) <= 5.0)):
        raise FastneusError(f"must be auto, linear, srgb or gamma=G with G in [0.2, 5], got {r!r}", file=source,
                            field="illum.response")


def camera_blur_sigma(value: Any) -> float | None:
    """``rays.camera_blur`` as a number of pixels, or None for ``auto`` (or a value that is neither).

    Args:
        value: the knob's value (``"auto"``, ``"0.76"``, or a number).
    Returns:
        The blur sigma in camera pixels, finite and in [0, 10], or None.
    """
    if isinstance(value, bool):
        return None
    if isinstance(value, (int, float)):
        v = float(value)
    else:
        try:
            v = float(str(value).strip())
        except ValueError:
            return None
    return v if math.isfinite(v) and 0.0 <= v <= 10.0 else None


def load_config(config: str | None = None, overrides: list[str] | None = None,
                base: dict[str, Any] | None = None) -> Config:
    """Build the run config: defaults <- preset/YAML file <- ``base`` <- ``key=value`` overrides.

    Args:
        config: a preset name (``fewview``, ``oneshot``, ...) or a path to a YAML file.
        overrides: strings ``key=value`` or ``section.key=value`` (value parsed as YAML).
        base: extra keys applied after the YAML (used by verbs such as ``oneshot``).
    """
    cfg = Config()
    notes: list[str] = []
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
        data = _translate(data, label, notes)
        if not (isinstance(data.get("run"), dict) and "preset" in data["run"]) and "preset" not in data:
            data["run.preset"] = Path(config).stem
        cfg = apply(cfg, data, label)
    if base:
        cfg = apply(cfg, base, "command line")
    parsed = parse_overrides(overrides)
    cfg = apply(cfg, parsed, "command line")
    # a step count asked for wins over a time budget the preset or the run set (the oneshot preset
    # is budgeted in time): steps=3000 means 3000 steps
    asked = {k.rsplit(".", 1)[-1] for k in parsed}
    if "steps" in asked and "time_budget" not in asked and cfg.run.time_budget > 0:
        notes.append(f"steps={cfg.run.steps} given: the {cfg.run.time_budget:g}-s time budget is off")
        cfg = apply(cfg, {"run.time_budget": 0.0}, "command line")
    for n in notes:  # only once everything loaded: an error stays one line
        _note(n)
    return cfg


def parse_overrides(overrides: list[str] | None) -> dict[str, str]:
    """``["a=1", "optim.lr=2"]`` -> ``{"a": "1", "optim.lr": "2"}`` (values still strings)."""
    parsed: dict[str, Any] = {}
    for item in overrides or []:
        if "=" not in item:
            raise FastneusError(f"expected key=value, got {item!r}", field="overrides")
        k, v = item.split("=", 1)
        parsed[k.strip()] = v
    return parsed


def save_config(cfg: Config, path: Path) -> None:
    """Write the resolved config as nested YAML, atomically."""
    from fastneus.io import atomic_write_text  # io is a sibling base module; kept lazy for start-up

    atomic_write_text(path, yaml.safe_dump(cfg.to_dict(), sort_keys=False))


def _translate(d: dict[Any, Any], source: str, notes: list[str]) -> dict[Any, Any]:
    """Translate a mapping of an earlier version's step-based schedules into fractions of the run;
    what was translated is appended to ``notes``."""
    d = dict(d)
    # flat keys (an earlier version's saved config) need no translation: bare names are unique
    legacy = [k for k in d if k in _LEGACY_STEPS or k == "c2f_steps_per_level"]
    if legacy:
        steps = d.get("steps", d.get("run", {}).get("steps") if isinstance(d.get("run"), dict) else None)
        try:
            steps = max(1, int(steps if steps is not None else RunSection.steps))
        except (TypeError, ValueError, OverflowError):
            raise FastneusError(f"bad value {steps!r}: expected an integer", file=source, field="run.steps") from None
        for old in legacy:
            v = d.pop(old)
            try:
                v = float(v)
            except (TypeError, ValueError):
                raise FastneusError(f"bad value {v!r}: expected a number", file=source, field=old) from None
            if old == "c2f_steps_per_level":
                levels = int(d.get("levels", HashGridSection.levels) or 1)
                start = int(d.get("c2f_start_levels", HashGridSection.c2f_start_levels) or 0)
                d.setdefault("c2f_frac", min(1.0, max(0, levels - start) * max(1.0, v) / steps))
            else:
                d.setdefault(_LEGACY_STEPS[old], min(1.0, max(0.0, v / steps)))
            new = "c2f_frac" if old == "c2f_steps_per_level" else _LEGACY_STEPS[old]
            notes.append(f"{source}: {old} of an earlier fastneus read as {KEYS[new][0]}.{new}, a fraction of the run")
    return d


def config_from_dict(d: dict[str, Any], source: str) -> Config:
    """Rebuild a Config from a saved dict (a run's config.yaml or a checkpoint), nested or flat.

    What an earlier version's dict needed translated is printed as a note once it loaded.
    """
    if not isinstance(d, dict):
        raise FastneusError("a saved config must be a mapping", file=source)
    notes: list[str] = []
    cfg = apply(Config(), _translate(d, source, notes), source)
    for n in notes:
        _note(n)
    return cfg
