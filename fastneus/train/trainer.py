"""The training loop: random rays, occupancy-grid skipping, NeuS + pattern projection,
L1 + eikonal (+ mask BCE, + curvature), Adam with warm-up and cosine decay, illumination
learned after a warm-up, atomic checkpoints, resume, and a NaN/Inf guard.
"""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import torch

from fastneus.config import Config, camera_blur_sigma, config_from_dict, save_config
from fastneus.errors import FastneusError
from fastneus.field.model import SDFField, table_choice
from fastneus.field.renderer import march_samples, march_samples_capped, pattern_pass_split, shade_samples
from fastneus.train.geometry_init import fit_batch, grey_photos_note
from fastneus.io import open_append
from fastneus.kernels.occupancy import OccupancyGrid
from fastneus.train.checkpoint import CKPT_NAME, load_checkpoint, restore, save_checkpoint  # noqa: F401 (re-export)
from fastneus.train.adam import Adam
from fastneus.train import losses
from fastneus.train.guard import finite_flag, finite_step
from fastneus.train.multishot import make_bank
from fastneus.train.precision import matmul_precision, resolve_matmul
from fastneus.train.progress import ProgressWriter
from fastneus.train.rig import Rig
from fastneus.train.rig import load_into as rig_load
from fastneus.train.rig import state_of as rig_state
from fastneus.train.rays import (RayBank, build_projection, core_radius, halo_radius, mask_core, pattern_images, photo_masks,
                                  training_lut)
from fastneus.data.response import decode_lut, is_identity, resolve_response


PLAIN_EVERY_S = 5.0  # seconds between progress lines when stdout is not a terminal
# with CUDA graphs, a ray count this far (a factor) from its target jumps there (Trainer._next_ray_count)
RAY_JUMP = 1.5
# host memory the CPU may spend keeping the pattern images and the blur estimate's blurred stores
# (read and blurred once per run instead of once per candidate and round: ~1 s of a 30-s CPU run)
HOST_PATTERN_CACHE = 64 << 20


def _plain_line(rec: dict, done: int, total: int, timed: bool) -> str:
    """One progress line for logs: where the run is and its latest record (no wrapping, no colour)."""
    where = f"{done / 10:.1f}/{total / 10:.0f} s" if timed else f"step {done}/{total}"
    return (f"train {where} ({100 * done / max(1, total):.0f}%): step {rec['step']} loss {rec['loss']:.4f} "
            f"psnr {rec['psnr']:.2f} i_r {rec['i_r']:.4f} i_b {rec['i_b']:.4f} {rec['it_s']:.1f} it/s")


def resolve_masks(scene, frames: list[int], cfg: Config) -> tuple[bool, str]:
    """Decide whether the mask loss is used: ``masks=auto`` -> on when every training frame has a mask.

    Returns:
        (used, note): the decision and a one-line explanation for the run summary.
    """
    have = sum(scene.frames[i].mask is not None for i in frames)
    n = len(frames)
    if cfg.loss.masks == "on" and have < n:
        raise FastneusError(f"masks=on but only {have} of {n} training frames have a mask", field="masks")
    used = cfg.loss.mask_weight > 0 and (cfg.loss.masks == "on" or (cfg.loss.masks == "auto" and have == n))
    why = {"on": "asked for", "off": "turned off", "auto": f"{have}/{n} training frames have masks"}[cfg.loss.masks]
    if cfg.loss.masks != "off" and cfg.loss.mask_weight <= 0:
        why += "; mask_weight is 0"
    return used, f"masks: {cfg.loss.masks} -> {'on' if used else 'off'} ({why})"


def resolve_bg_prior(cfg: Config, masks_used: bool, bg_fraction: float) -> tuple[bool, str]:
    """Decide whether background-coloured pixels count as free space (``bg_prior``).

    Without masks nothing else tells the model that a black pixel is empty space rather than
    a black surface, and it fills gaps with dark shells. ``auto`` turns the prior on when at
    least 5% of the training pixels have the background colour (a dark room, lasers only,
    synthetic data); a scene with a real backdrop has few such pixels and keeps it off.

    Returns:
        (used, note) for the run summary.
    """
    if masks_used:
        return False, "background prior: off (masks are used)"
    if cfg.loss.bg_prior == "off" or cfg.loss.bg_weight <= 0:
        return False, "background prior: off"
    share = f"{100 * bg_fraction:.0f}% of training pixels are background colour {cfg.rays.background:g}"
    used = cfg.loss.bg_prior == "on" or bg_fraction >= 0.05
    note = f"background prior: {cfg.loss.bg_prior} -> {'on' if used else 'off'} ({share})"
    if used and resolve_fg_prior(cfg, used, bg_fraction):
        note += (f"; with a foreground prior: pixels brighter than the background by {cfg.loss.fg_threshold:g} "
                 "are the object (fg_prior)")
    if used and resolve_bg_lit(cfg, bg_fraction):
        note += "; only where the projectors light the surface (a dark room: bg_lit)"
    return used, note


DARK_ROOM = 0.85  # share of background-colour pixels that makes a scene a dark room (lasers only)


def resolve_fg_prior(cfg: Config, bg_used: bool, bg_fraction: float) -> bool:
    """Whether pixels clearly brighter than the background pull their rays to full opacity
    (``loss.fg_prior``; the mask's other half, read off the photo). auto: with the background
    prior in a dark room, where the thin parts that no laser line crosses are seen only as
    dim, ambient-lit pixels and nothing else makes the model put surface there."""
    if not bg_used or cfg.loss.fg_prior == "off":
        return False
    return cfg.loss.fg_prior == "on" or bg_fraction >= DARK_ROOM


def resolve_bg_lit(cfg: Config, bg_fraction: float) -> bool:
    """Whether the background prior counts a black pixel as empty only where the projected
    light reaches the ray's surface (``loss.bg_lit``; auto: in a dark room, where almost every
    pixel has the background colour and an unlit surface is as black as the backdrop, unless
    the foreground prior marks the object's pixels: then every black pixel is empty space)."""
    if cfg.loss.bg_lit == "auto" and resolve_fg_prior(cfg, True, bg_fraction):
        return False
    return cfg.loss.bg_lit == "on" or (cfg.loss.bg_lit == "auto" and bg_fraction >= DARK_ROOM)


def _configure_threads(requested: int) -> tuple[int, str]:
    """CPU threads for the Warp kernels and torch (``Config.threads``; 0 = auto); (count, note)."""
    from fastneus.kernels import THREADS_ENV, configure_threads

    try:
        return configure_threads(requested)
    except (ValueError, RuntimeError, OverflowError) as e:  # only the automatic count reads the variable
        raise FastneusError(str(e).splitlines()[0] if str(e) else type(e).__name__,
                            field="threads" if requested else THREADS_ENV) from None


def _psnr(mse: float) -> float:
    return -10.0 * math.log10(max(mse, 1e-12))


def lr_warmup(p: float, start: float, frac: float, decay: float) -> float:
    """Learning-rate factor at progress ``p`` of a group that starts learning at ``start``: a
    linear ramp from 0.1 to 1 over the next ``frac`` of the run, then ``decay`` (the run's
    cosine). Before ``start`` the caller holds the group (its rate is 0)."""
    if frac > 0 and p < start + frac:
        return 0.1 + 0.9 * max(0.0, p - start) / frac
    return decay


class BudgetSync:
    """When a time-budgeted CUDA run must wait for the device so its budget ends on time.

    Replayed steps do not wait for the GPU, so between the loop's host syncs (every ``log_every``
    steps) the host may run ahead and ``Trainer.elapsed`` grow by host time only; a sync adds the
    device's lag back. A budget checked on the host alone can end with steps still queued on the
    device (they run before mesh.ply), or, when the crossing falls on a log step, end up to
    ``log_every`` steps past it. This predicts the device's clock from the last sync and the
    seconds per step between the last two, and asks for a sync once the prediction reaches the
    budget; ``elapsed`` is then exact at the step that ends the run. A wrong prediction costs one
    early sync (which re-estimates the rate), never a late end. Today Adam's per-step event wait
    keeps the host's lead short: on an H200 3-s runs ended at 3.00-3.04 s of steps before, 3.001-3.004
    s with this (perf note 34).
    """

    def __init__(self, budget: float):
        self.budget = float(budget)
        self.t_sync, self.s_sync, self.rate = 0.0, 0, None

    def due(self, step: int) -> bool:
        """Whether to sync after ``step`` (steps done so far) so the budget is not overrun."""
        if self.budget <= 0 or self.rate is None:
            return False
        return self.t_sync + (step - self.s_sync) * self.rate >= self.budget

    def synced(self, step: int, elapsed: float) -> None:
        """Record a host sync after ``step`` steps at ``elapsed`` seconds (exact: device caught up)."""
        if step > self.s_sync and elapsed > self.t_sync:
            self.rate = (elapsed - self.t_sync) / (step - self.s_sync)
        self.t_sync, self.s_sync = float(elapsed), int(step)


def view_pixels(scene, frames: list[int]) -> tuple[int, int]:
    """(pixels, viewpoints) of the distinct viewpoints among ``frames`` (a multi-shot sequence's
    patterns count once: they add light codes, not detail)."""
    from fastneus.data.scene import view_frames

    firsts = [fs[0] for fs in view_frames(scene, frames).values()]
    return int(sum(scene.cameras[scene.frames[i].camera].width * scene.cameras[scene.frames[i].camera].height
                   for i in firsts)), len(firsts)


class Trainer:
    """Optimises an :class:`SDFField` on a scene.

    Args:
        scene: loaded :class:`fastneus.data.Scene`.
        cfg: resolved :class:`Config`.
        out: run folder (created).
        device: "cpu" or "cuda".
        console: optional rich Console for the progress bar (None = quiet).
    """

    def __init__(self, scene, cfg: Config, out: Path, device: str, console=None):
        self.scene, self.cfg, self.out, self.console = scene, cfg, Path(out), console
        self.device = torch.device(device)
        self.out.mkdir(parents=True, exist_ok=True)
        self.threads, self.threads_note = _configure_threads(cfg.run.threads)
        # the small networks' float32 GEMMs on tensor cores (TF32) where the GPU has them (precision.py)
        self.matmul = resolve_matmul(cfg.run.matmul, self.device)
        torch.manual_seed(cfg.run.seed)
        np.random.seed(cfg.run.seed)
        n = len(scene.frames)
        self.frames = list(range(n)) if cfg.run.frames is None else list(cfg.run.frames)
        bad = [f for f in self.frames if not 0 <= f < n]
        if bad or not self.frames:
            raise FastneusError(f"frame indices {bad or '[]'} out of range 0..{n - 1}", field="frames")
        self.masks_used, self.masks_note = resolve_masks(scene, self.frames, cfg)
        want_bg = not self.masks_used and cfg.loss.bg_prior != "off" and cfg.loss.bg_weight > 0
        # photos -> linear light through a 256-entry table in the bank: the model, i_r, i_b are linear
        self.response, self.response_note = resolve_response(scene, self.frames, cfg.illum.response)
        # a raw camera's black level taken off and a dim capture scaled up for training (illum.black,
        # illum.level); reports divide the gain back (photo_illumination)
        lut = None if is_identity(self.response) else decode_lut(self.response)
        lut, self.photo_gain, self.photo_black, self.level_note = training_lut(scene, self.frames, lut,
                                                                             cfg.illum.level, cfg.illum.black)
        self.photos_note = grey_photos_note(scene, self.frames)  # None for colour photos
        # multi-shot viewpoints (e.g. Gray code) share one ray per pixel across their shots (fastneus.train.multishot)
        self.bank = make_bank(scene, self.frames, self.device, cfg, load_masks=self.masks_used,
                              brightness_cdf=cfg.rays.bright_fraction > 0,
                              background=cfg.rays.background if want_bg else None, bg_tolerance=cfg.loss.bg_tolerance,
                              bg_noise_k=cfg.loss.bg_noise_k, bg_cap=cfg.loss.fg_threshold, fg_relative=cfg.loss.fg_relative,
                              refraction=cfg.rig.refraction,
                              lut=lut)
        if getattr(self.bank, "empty_masks", None):  # all-zero masks: the object is outside those views (or a wrong file)
            self.masks_note += f"; warning: empty (all-zero) mask {', '.join(self.bank.empty_masks)}"
        # rays end deep inside the object (occupancy.stop_rays): their samples past it carry no weight
        mode = cfg.occupancy.stop_rays
        # with masks: lasers in a dark room or an ambient-lit object (stop_rays and mask_start both ask;
        # read once: it looks at every training pixel)
        room_known = self.masks_used and hasattr(self.bank, "dark_object")
        dark_object = room_known and self.bank.dark_object()
        self.dark_room = bool(dark_object)  # with masks: lasers in a dark room (stop_rays, hull_keep)
        self.stop_used = mode == "on" or (mode == "auto" and dark_object)
        if self.stop_used:
            self.masks_note += (f"; {'dark room: ' if mode == 'auto' else ''}rays end {cfg.occupancy.stop_inside:g} "
                                "grid cells inside the object (stop_rays)")
        # a stronger mask weight early (loss.mask_start): realistic ant, Normal, 3 s on an H200: better on
        # 5 of 6 seeds (median 3.37 against 4.56 mm symmetric); in a dark room it lost the legs on 2 of 3
        # (docs/benchmarks/mask-weight.md)
        ms = cfg.loss.mask_start
        self.mask_start_used = (self.masks_used and cfg.loss.mask_weight_start > cfg.loss.mask_weight
                                and (ms == "on" or (ms == "auto" and room_known and not dark_object)))
        if self.mask_start_used:
            self.masks_note += (f"; {'lit room: ' if ms == 'auto' else ''}mask weight {cfg.loss.mask_weight_start:g} "
                                f"-> {cfg.loss.mask_weight:g} over the first {cfg.loss.mask_start_frac:.0%} (mask_start)")
        if self.masks_used and cfg.loss.mask_loss != "bce":  # the mask term's form (the GPU preset: mixed)
            self.masks_note += (f"; mask pixels' rays must reach a negative SDF (mask_loss={cfg.loss.mask_loss}"
                                f"{'' if cfg.loss.mask_loss == 'sdf' else ', background pixels by opacity'})")
            if cfg.loss.mask_core > 0:  # per-frame or per-viewpoint masks alike ([sum HW] with wh)
                self.bank.mask_core = mask_core(self.bank.mask, self.bank.wh, cfg.loss.mask_core, cfg.loss.mask_thin)
                w, h = (int(v) for v in self.bank.wh[0].tolist())
                self.masks_note += (f"; pixels {core_radius(cfg.loss.mask_core, w, h)} px or more inside the outline"
                                    f"{', and parts thinner than that, ' if cfg.loss.mask_thin else ' '}"
                                    f"by opacity (mask_core {cfg.loss.mask_core:g} of the image)")
        # grid updates query only the cells near the occupied ones on the CPU (occupancy.occ_update_cells)
        cells = cfg.occupancy.occ_update_cells
        self.occ_near = cells == "near" or (cells == "auto" and self.device.type == "cpu")
        self.bg_used, self.bg_note = resolve_bg_prior(cfg, self.masks_used, self.bank.bg_fraction)
        self.fg_used = resolve_fg_prior(cfg, self.bg_used, self.bank.bg_fraction)
        # the noise-floor tolerance (fastneus.train.rays.backdrop_tolerance) decides whether this is a
        # dark room; it flags the pixels the background prior carves only there, where the foreground
        # prior protects the object (elsewhere it carved dim surface: realistic rock Dark 9.0 -> 12.7 mm)
        if not self.fg_used and hasattr(self.bank, "use_floor_background"):
            self.bank.use_floor_background()
        tol = getattr(self.bank, "bg_tolerance", cfg.loss.bg_tolerance)
        if self.bg_used and tol > cfg.loss.bg_tolerance:
            self.bg_note += (f"; background within {tol:.3g} of it ({cfg.loss.bg_noise_k:g} x the photos' noise "
                             f"floor {self.bank.bg_noise:.2g})")
        self.bg_lit = self.bg_used and resolve_bg_lit(cfg, self.bank.bg_fraction)
        # the photo priors' weight: in a lit room the CPU preset trusts them more (thin legs were
        # lost to the photometric term otherwise); in the dark a stronger prior carved dim surface
        # (docs/benchmarks/mask-weight.md)
        self.bg_weight = cfg.loss.bg_weight
        if self.bg_used and cfg.loss.bg_weight_lit > 0 and getattr(self.bank, "lit_room", False):
            self.bg_weight = cfg.loss.bg_weight_lit
            self.bg_note += f"; a lit room: weight {self.bg_weight:g} (bg_weight_lit)"
        # the camera's blur on the projected light (fastneus.train.camblur; blur_via=rays: as rays below);
        # auto: none until it is estimated at blur_at_frac (and again at blur_refine_frac) of the run
        # (decide_camera_blur)
        blur = camera_blur_sigma(cfg.rays.camera_blur)
        fr = cfg.rays.blur_at_frac, cfg.rays.blur_refine_frac
        self._patterns: dict | None = None  # pattern images kept on a GPU (pattern_images)
        self._blurred: dict = {}  # sigma -> blurred PatternStore kept on a GPU (blurred_store)
        self.blur_due: list[float] = ([fr[0]] + ([fr[1]] if fr[1] > fr[0] else [])) if blur is None else []
        # loss.fg_halo waits for this progress (update_fg_halo; the blur's decisions also call it)
        self.fg_halo_due: float | None = cfg.loss.fg_halo_frac if cfg.loss.fg_halo > 0 and cfg.loss.fg_halo_frac > 0 else None
        self.blur_decision: dict = {"mode": "auto", "at_frac": list(self.blur_due), "sigma": None, "rounds": []} \
            if blur is None else {"mode": "set", "sigma": blur}
        self.camera_blur = 0.0 if blur is None else blur  # the blur in use, camera px
        self.pattern_blur = self.camera_blur if cfg.rays.blur_via == "pattern" else 0.0
        self.update_halo()  # a blur given as a number: from the start
        self.proj = build_projection(scene, self.frames, self.device, refraction=cfg.rig.refraction,
                                     camera_blur=self.pattern_blur)
        self.rig = Rig(scene, self.frames, self.bank, self.proj, cfg.rig, self.device,  # real-rig corrections
                       split_patterns=pattern_pass_split(cfg, self.device))
        # the table's size from the photos (hashgrid.pixels_per_entry): 20 views of 200 px fit a 2^17 table
        # better than 2^19 (docs/benchmarks/short-budget-gpu.md, "The hash table's size")
        log2_table, self.table_note = table_choice(cfg.hashgrid, *view_pixels(scene, self.frames))
        self.field = SDFField(cfg.hashgrid, cfg.network, self.device, backend=cfg.run.backend, log2_table=log2_table)
        self.field.init_color_bias(self.bank.mean_rgb())
        self.grid = OccupancyGrid(cfg.occupancy.occ_resolution, self.device)
        self.on_saved = None  # called after each checkpoint write (pipeline.train_scene)
        self.seen = None
        if cfg.occupancy.min_views > 0:
            from fastneus.train.visibility import seen_cells

            self.seen = seen_cells(scene, self.frames, cfg.occupancy.occ_resolution, self.device, cfg.occupancy.min_views)
        self.hull_out = None  # [R^3] float, 1 where the masks say the space is empty (occupancy.hull)
        self.hull_in = None  # [R^3] uint8, 1 inside the hull: kept occupied (occupancy.hull_keep, hull_keep_frac)
        self.hull_note = self._masks_hull()
        if self.seen is not None:
            self.grid.set_allowed(self.seen)
        ill = scene.illumination
        if cfg.illum.illum_init == "ones" or ill is None:
            ir0, ib0 = 1.0, 1.0
        else:
            ir0, ib0 = float(ill.i_r), float(ill.i_b) * self.photo_gain  # i_b is light: in the trained units
        # log-parametrised so i_r, i_b stay positive
        self.log_ir = torch.nn.Parameter(torch.tensor([math.log(max(ir0, 1e-4))], device=self.device))
        self.log_ib = torch.nn.Parameter(torch.tensor([math.log(max(ib0, 1e-4))], device=self.device))
        groups = self.field.param_groups(cfg.optim) + [
            {"params": [self.log_ir, self.log_ib], "lr": cfg.optim.lr_illum, "name": "illum"}] + self.rig.param_groups()
        # per-photo exposure gain (auto-exposure): a log-gain per training frame but the first (gain 1:
        # it fixes the scale that i_r, i_b and the colours share)
        # (auto: the gains exist from the start at 1, learned only once decide_exposure finds the
        # photos' exposures differ; a gain of exactly 1 leaves the run as it is without them)
        self.log_gain = None
        mode = cfg.illum.exposure if len(self.frames) > 1 else "off"
        if mode != "off":
            self.log_gain = torch.nn.Parameter(torch.zeros(len(self.frames) - 1, device=self.device))  # [F-1]
            groups.append({"params": [self.log_gain], "lr": cfg.illum.lr_exposure, "name": "exposure"})
        self.exposure_due = cfg.illum.exposure_at_frac if mode == "auto" else None
        self.exposure_decision: dict = {"mode": mode, "learned": mode == "on"}
        for g in groups:
            g["base_lr"] = g["lr"]
        self.opt = Adam(groups, betas=(0.9, 0.99), eps=cfg.optim.adam_eps)  # torch.optim's would import TorchDynamo (4 s)
        if self.device.type == "cuda":  # one fused pass per tensor for the device-guarded update (the CPU keeps step())
            self.opt.use_fused(cfg.run.backend)
        self.step = 0
        self.n_rays = cfg.rays.init_rays
        self.elapsed = 0.0          # training seconds, kept across resume
        self._skipped = 0           # NaN/Inf steps skipped (CUDA: + the device counter below)
        # on CUDA the NaN guard gates the Adam update on the device: no host sync per step
        self._skipped_dev = torch.zeros((), dtype=torch.int64, device=self.device) if self.device.type == "cuda" else None
        # captured steps whose capped march outgrew its buffers (not applied; graphstep.StepGraphs.capped)
        self._overflow_dev = torch.zeros((), dtype=torch.int64, device=self.device)
        self.empty_steps = 0        # consecutive steps whose rays found no occupied cell
        # rays per training pixel: the camera's defocus as several rays averaged (rays.camera_blur)
        self.blur_sub = cfg.rays.blur_rays if self.camera_blur > 0 and cfg.rays.blur_via == "rays" else 1
        if self.blur_sub > 1 and not isinstance(self.bank, RayBank):
            raise FastneusError("camera_blur needs one ray per shot (set group_shots=false for a multi-shot scene)",
                                field="rays.camera_blur")
        # CUDA: the step after marching replayed as a captured graph (fastneus.train.graphstep)
        self.graphs = None
        self.cos_dev: torch.Tensor | None = None  # [1] cos-anneal ratio on the device (with graphs)
        self.mask_w_dev: torch.Tensor | None = None  # [] the mask loss's weight on the device (with graphs)
        self.bg_w_dev: torch.Tensor | None = None  # [] the background prior's ramped weight on the device (graphs)
        self.prior_w_dev: torch.Tensor | None = None  # [] the surface prior's faded weight on the device (graphs)
        if self.device.type == "cuda" and cfg.run.cuda_graph != "off":
            from fastneus.train.graphstep import StepGraphs

            self.graphs = StepGraphs(self, console)
        self.history: list[dict] = []
        self._grid_open = False     # grid forced fully occupied (warm-up) since the last update
        self.gen = torch.Generator(device=self.device)
        self.gen.manual_seed(cfg.run.seed)
        self.stop_signal: str | None = None  # set by interrupt.stop_on_signal: stop after this step
        self.prior = None  # geometry_init.SurfacePrior kept as a fading prior after a decoded/swept init
        self.clock = None  # fastneus.timing.RunClock of the run (pipeline.train_scene): fit() records its phases

    # ------------------------------------------------------------------ helpers
    @property
    def skipped(self) -> int:
        """Steps skipped by the NaN/Inf guard (a host read of the device counter on CUDA)."""
        return self._skipped + (int(self._skipped_dev) if self._skipped_dev is not None else 0)

    @skipped.setter
    def skipped(self, n: int) -> None:
        self._skipped = int(n)
        if self._skipped_dev is not None:
            self._skipped_dev.zero_()

    def _pixel_min_sdf(self, out: dict) -> tuple[torch.Tensor, torch.Tensor]:
        """Each training pixel's smallest SDF along its rays and whether it has samples ([B], [B]):
        with blur_sub rays per pixel, the pixel enters the object if any of its rays does."""
        m, has = out["min_sdf"], out["has_samples"]
        if self.blur_sub > 1:
            big = torch.finfo(m.dtype).max
            hp = has.view(-1, self.blur_sub).amax(1)
            mp = torch.where(has > 0, m, big).view(-1, self.blur_sub).amin(1)
            return torch.where(hp > 0, mp, torch.zeros_like(hp)), hp
        return m, has

    def photo_priors(self, p: float) -> tuple[bool, bool]:
        """(background prior, foreground prior) acting at progress ``p`` (no masks; each from its
        start fraction). The step's losses and the captured graphs' key both read this."""
        c = self.cfg.loss
        return self.bg_used and p >= c.bg_start_frac, self.fg_used and p >= c.fg_start_frac

    @property
    def blur_pending(self) -> bool:
        """camera_blur=auto has an estimate still to make in this run."""
        return bool(self.blur_due)

    def photo_illumination(self) -> tuple[float, float]:
        """(i_r, i_b) in the photos' own units, for reports: i_b is light and was learned on photos
        scaled by ``photo_gain``; i_r is a ratio of lights and needs no scaling."""
        i_r, i_b = (float(x.detach()) for x in self.illumination())
        return i_r, i_b / self.photo_gain

    def illumination(self) -> tuple[torch.Tensor, torch.Tensor]:
        return self.log_ir.exp(), self.log_ib.exp()

    def progress(self) -> float:
        """Fraction of the run done, in [0, 1]: of ``time_budget`` when set, else of ``steps``.

        Every schedule (warm-ups, coarse-to-fine, cos-anneal, sharpness floor, lr decay) reads
        this, so the same preset works at 5 s and at 10 minutes.
        """
        if self.cfg.run.time_budget > 0:
            p = self.elapsed / self.cfg.run.time_budget
        else:
            p = self.step / max(1, self.cfg.run.steps)
        return min(1.0, p)

    def steps_expected(self) -> float | None:
        """The run's step count: ``steps``, or under a time budget the count expected at the rate
        so far (steps done / share of the budget used; None before the first step)."""
        if self.cfg.run.time_budget > 0:
            p = self.progress()
            return self.step / p if p > 0 and self.step > 0 else None
        return float(self.cfg.run.steps)

    def floor_note(self) -> str:
        """One line on the sharpness floor's end when the run's length sets it (``inv_s_floor_per_step``)."""
        c = self.cfg.network
        if c.inv_s_floor_per_step <= 0 or c.inv_s_floor_end <= 0:
            return ""
        n = self.steps_expected()
        end = self.field.floor_end(n)
        how = f"{c.inv_s_floor_per_step:g} x {n:.0f} steps" if n else "no step yet"
        return f"sharpness floor: ends at inv_s {end:.0f} ({how}, at most inv_s_floor_end {c.inv_s_floor_end:g})"

    def finished(self) -> bool:
        """Whether the run has reached its length (or was asked to stop). A time-budgeted run trains
        at least one step: on a slow or busy machine its setup (a geometry initialisation counts as
        training) can spend a short budget before any step, and a mesh of the untrained field is
        no result."""
        if self.stop_signal is not None:
            return True
        if self.cfg.run.time_budget > 0:
            return self.step > 0 and self.elapsed >= self.cfg.run.time_budget
        return self.step >= self.cfg.run.steps

    def _set_lr(self, p: float) -> None:
        c = self.cfg
        decay = c.optim.decay_to + (1 - c.optim.decay_to) * 0.5 * (1 + math.cos(math.pi * p))
        f = lr_warmup(p, 0.0, c.optim.warmup_frac, decay)
        # the geometry warms up from where it unfreezes: started at the full rate, Adam's first
        # steps (each ~lr on every table entry with a gradient) broke the surface's eikonal up
        # (0.03 -> 0.12) and on a realistic Dark scene the run fell into an empty field when
        # steps happened to come a little faster (perf note 19)
        f_geo = lr_warmup(p, c.optim.color_warmup_frac, c.optim.warmup_frac, decay)
        # from a blind init (1, 1) the pattern term is several times too bright: waiting for the
        # geometry would let it carve the surface away, so fit it with the colours from the start
        # (geometry frozen meanwhile), then keep learning
        start = 0.0 if c.illum.illum_init == "ones" else c.illum.illum_warmup_frac
        learn_illum = c.illum.learn_illum and c.illum.use_pattern and p >= start
        frozen = p < c.optim.color_warmup_frac
        for g in self.opt.param_groups:
            if g["name"] == "illum":
                # decays with the rest: a constant Adam step of lr_illum on log(i) would leave i_r, i_b
                # jittering by ~lr_illum (3%) at the end of the run
                g["lr"] = g["base_lr"] * decay if learn_illum else 0.0
            elif g["name"] == "exposure":  # per-photo gains wait for a surface to compare photos on
                on = self.exposure_decision["learned"] and p >= c.illum.illum_warmup_frac
                g["lr"] = g["base_lr"] * decay if on else 0.0
            elif g["name"].startswith("rig_"):  # own warm-up, then the common decay
                g["lr"] = g["base_lr"] * decay * self.rig.lr_gate(g["name"], p)
            elif g["name"] in ("geometry", "variance"):
                g["lr"] = 0.0 if frozen else g["base_lr"] * f_geo
            else:
                g["lr"] = g["base_lr"] * f

    def cos_anneal(self, p: float | None = None) -> float:
        p = self.progress() if p is None else p
        return 1.0 if self.cfg.loss.cos_anneal_frac <= 0 else min(1.0, p / self.cfg.loss.cos_anneal_frac)

    def fill_step_scalars(self, p: float) -> None:
        """Write progress ``p``'s schedule values into the device scalars a captured step reads."""
        self.cos_dev.fill_(self.cos_anneal(p))
        if self.mask_start_used:  # else it holds mask_weight from its creation (no launch per step)
            self.mask_w_dev.fill_(self.mask_weight_at(p))
        if self.bg_w_dev is not None and self.bg_used:
            self.bg_w_dev.fill_(self.background_weight_at(p))
        if self.prior_w_dev is not None and self.prior is not None:
            self.prior_w_dev.fill_(self.prior_weight_at(p))

    def prior_on(self, p: float) -> bool:
        """Whether the step at progress ``p`` has the surface prior's term (a decoded or swept
        start, ``init.prior_weight`` > 0, before ``init.prior_frac``)."""
        return self.prior is not None and p < self.cfg.init.prior_frac

    def prior_weight_at(self, p: float) -> float:
        """The surface prior's weight at progress ``p`` (:func:`losses.prior_fade`; 0 once it is off)."""
        c = self.cfg.init
        return losses.prior_fade(p, c.prior_weight, c.prior_frac) if self.prior_on(p) else 0.0

    def background_weight_at(self, p: float) -> float:
        """The background prior's weight at progress ``p``: ``bg_weight`` times its ramp-in
        (:func:`losses.background_ramp`; 0 before ``bg_start_frac``, where the term is off)."""
        return max(0.0, losses.background_ramp(p, self.cfg.loss.bg_start_frac)) * self.bg_weight

    def mask_weight_at(self, p: float) -> float:
        """The mask loss's weight at progress ``p``: ``mask_weight_start`` falling linearly to
        ``mask_weight`` at ``mask_start_frac`` where ``loss.mask_start`` chose it, else ``mask_weight``."""
        c = self.cfg.loss
        if not self.mask_start_used or p >= c.mask_start_frac:
            return c.mask_weight
        return c.mask_weight_start + (c.mask_weight - c.mask_weight_start) * (p / c.mask_start_frac)

    def _masks_hull(self) -> str:
        """``occupancy.hull``: with masks, the space outside their visual hull (:func:`fastneus.train.
        visibility.hull_cells`) is empty for sure: ``loss`` (``auto``) pushes the SDF positive there at
        the eikonal term's uniform points, so a start that sits outside the object (the initial sphere
        in a nut's hole) is carved from the first steps instead of by the photos over hundreds;
        ``bound`` also keeps the grid from ever occupying it. The hull is the tightest one whose
        projection covers every mask (:func:`fastneus.train.visibility.consistent_hull`: widened for
        poses that are off, none when they are far off). Returns the printed note."""
        c = self.cfg.occupancy
        if c.hull == "off":
            return "occupancy: hull off"
        mode = "loss" if c.hull == "auto" else c.hull
        # without masks, a dark room's photos are masks of their own: what the backdrop flags do not
        # claim (ant, Dark, no masks, CPU 600 steps, three seeds: ideal 8.05 -> 6.52 mm, realistic 13.01 -> 11.59)
        photo = (c.photo_hull != "off" and not self.masks_used and self.fg_used and isinstance(self.bank, RayBank)
                 and (c.photo_hull == "auto" or not self.bank.lit_room))
        if not self.masks_used and not photo:
            return "occupancy: no masks, no hull"
        if any(self.scene.frame_camera(i).port is not None for i in self.frames):
            return "occupancy: no hull (a camera behind a flat port: its rays bend)"
        from fastneus.train.visibility import consistent_hull, dilate_cells, seen_fraction

        masks = photo_masks(self.bank, self.frames) if photo else None
        what = "the photos' non-background pixels" if photo else "the masks"
        if photo and masks is None:
            return "occupancy: no masks, no hull"
        hull, pad, worst = consistent_hull(self.scene, self.frames, c.occ_resolution, self.device, masks=masks)
        if hull is None and worst > 0:
            return (f"occupancy: no hull ({what} and the poses disagree: {100 * worst:.1f} % of a view's "
                    f"{'non-background pixels' if photo else 'mask'} lies outside the hull even at {pad:g} px of extra pad)")
        if hull is None or not bool(hull.any()):
            return f"occupancy: no hull (no non-empty {'photo masks' if photo else 'masks'})"
        widened = f", widened by {pad:g} px to cover every view's mask" if pad > 0 else ""
        seen = self.seen if self.seen is not None else torch.ones_like(hull)
        # the term's space starts hull_margin cells beyond the hull
        term = dilate_cells(hull, int(c.hull_margin)) if c.hull_margin > 0 else hull
        self.hull_out = (seen & ~term).float()
        if mode == "bound":
            self.seen = seen & hull
        keep = ""
        if c.hull_keep_frac > 0 and (c.hull_keep == "on" or (c.hull_keep == "auto" and self.dark_room)):
            self.hull_in = (seen & hull).to(torch.uint8)
            span = "the whole run" if c.hull_keep_frac >= 1 else f"the first {c.hull_keep_frac:.0%} of the run"
            keep = f"; {'dark room: ' if c.hull_keep == 'auto' else ''}its cells stay occupied for {span} (hull_keep)"
        return (f"occupancy: hull {c.hull}{' -> ' + mode if c.hull == 'auto' else ''}: {what}' visual hull "
                f"({100 * seen_fraction(seen & hull):.1f} % of the unit ball{widened}) "
                f"{'bounds the grid, and ' if mode == 'bound' else ''}the SDF is pushed positive outside it{keep}")

    def update_grid(self, p: float) -> None:
        c = self.cfg
        if p < c.occupancy.occ_warmup_frac:
            if not self._grid_open:
                self.grid.update(self.field.sdf, 0.0, c.rays.march_step, warmup=True)
                self._grid_open = True
            return
        if self.step % c.occupancy.occ_update_every == 0 or self._grid_open:
            self._grid_open = False
            # margin = half a cell diagonal keeps thin shells occupied once s is large
            self.grid.update(self.field.sdf, float(self.field.inv_s().detach()), c.rays.march_step,
                             threshold=c.occupancy.occ_threshold, margin=math.sqrt(3) / self.grid.resolution,
                             backend=c.run.backend,
                             inside=c.occupancy.stop_inside * 2.0 / self.grid.resolution if self.stop_used else 0.0,
                             near=c.occupancy.occ_near_rest if self.occ_near else None)
            if self.hull_in is not None and p < c.occupancy.hull_keep_frac:
                # the masks' hull stays sampled while the field may not have formed a thin part yet: pruned
                # at the first update, a leg got no samples and the masks could not pull it in. A cell deep
                # inside (grid.stop) still ends a ray, so the kept interior costs few samples.
                self.grid.bits |= self.hull_in

    def decide_camera_blur(self) -> dict:
        """``camera_blur=auto``: estimate the blur from the data (:func:`fastneus.train.blurfit.
        estimate_blur_by_render`) and switch the patterns to it; i_r, i_b keep learning from where
        they are (the estimate's own closed-form fit, kept as ``fit_i_r`` / ``fit_i_b``, comes out
        low even on ideal captures: a field that is not yet aligned attenuates it).

        Called at ``blur_at_frac`` and again at ``blur_refine_frac``: a field trained on sharp
        patterns has adapted to them and favours a sharper blur (rock, realistic Normal, true
        0.76 px: 0.57 on the field at 30 % trained sharp, 0.78 on one trained with 0.57), so the
        second estimate, on the field trained with the first, is the one kept; a sharp capture
        stays at 0 both times.

        The blurred patterns are copied into the trainer's pattern buffer in place (same size):
        the rig, the renderer and any captured CUDA graph hold that buffer, so they all see the
        switch without a rebuild. Printed, kept in :attr:`blur_decision` (run.json, checkpoint).

        Returns:
            The decision (``sigma``, ``i_r``, ``i_b``, ``residuals`` per candidate, ``seconds``).
        """
        from fastneus.train.blurfit import estimate_blur_by_render

        p = self.progress()
        while self.blur_due and p >= self.blur_due[0]:  # both fractions passed (e.g. a resume): once
            self.blur_due.pop(0)
        info = dict(estimate_blur_by_render(self), step=self.step)
        d = self.blur_decision
        d["rounds"] = d.get("rounds", []) + [info]
        d.update(sigma=info["sigma"], step=info["step"], sigmas=info["sigmas"], residuals=info["residuals"],
                 seconds=round(sum(r["seconds"] for r in d["rounds"]), 3))
        self.apply_camera_blur(float(info["sigma"]))
        if not self.blur_due:  # the last estimate: its candidates are not needed again
            self._blurred.clear()
            if self.device.type == "cpu":
                self._patterns = None
        if self.console is not None:
            self.console.print(self.blur_note(), soft_wrap=True, highlight=False, markup=False)
        return self.blur_decision

    def decide_exposure(self) -> dict:
        """``exposure=auto``: fit each photo's gain against the current render
        (:func:`fastneus.train.exposure.estimate_exposure`) and learn the gains from now on only when
        they spread by more than :data:`fastneus.train.exposure.SPREAD_ON` (they start at the fit);
        otherwise they stay at 1 and the run goes on as without them. Printed, kept in
        :attr:`exposure_decision` (run.json, checkpoint).

        Returns:
            The decision (``learned``, ``spread``, ``log_gains``, ``step``, ``seconds``).
        """
        from fastneus.train.exposure import SPREAD_ON, estimate_exposure

        self.exposure_due = None
        info = estimate_exposure(self)
        learned = info["spread"] > SPREAD_ON
        if learned:
            with torch.no_grad():
                self.log_gain.copy_(torch.tensor(info["log_gains"][1:], dtype=self.log_gain.dtype, device=self.device))
        self.exposure_decision.update(learned=learned, step=self.step, **info)
        if self.console is not None:
            self.console.print(self.exposure_note(), soft_wrap=True, highlight=False, markup=False)
        return self.exposure_decision

    def exposure_note(self) -> str:
        """One line on the per-photo exposure gains (printed; run.json keeps :attr:`exposure_decision`)."""
        from fastneus.train.exposure import SPLITS, SPREAD_ON

        d = self.exposure_decision
        if d["mode"] != "auto":
            return f"exposure: {d['mode']}"
        if "spread" not in d:
            return "exposure: auto, decided at {:.0f} % of the run".format(100 * self.cfg.illum.exposure_at_frac)
        verdict = "learned per photo" if d["learned"] else "one exposure for all photos"
        return (f"exposure: auto -> {verdict} (the photos' gains against the render spread by "
                f"{100 * d['spread']:.1f} % at step {d['step']}, as {SPLITS} ray batches agree; threshold "
                f"{100 * SPREAD_ON:.0f} %)")

    def pattern_images(self) -> dict:
        """The unblurred pattern images for the blur estimate's candidates and the chosen blur
        (:func:`fastneus.train.rays.pattern_images`): kept after the first call; read
        again on the CPU only when they hold more than :data:`HOST_PATTERN_CACHE` bytes (a large
        Gray-code set is not kept twice in host memory)."""
        if self._patterns is not None:
            return self._patterns
        pats = pattern_images(self.scene, self.frames, self.device)
        if self.device.type != "cpu" or sum(v.nbytes for v in pats.values()) <= HOST_PATTERN_CACHE:
            self._patterns = pats
        return pats

    def blurred_store(self, sigma: float, keep: bool = False):
        """The scene's patterns blurred by ``sigma`` camera px, packed (a :class:`PatternStore`
        like ``self.proj.store``), from :meth:`pattern_images`.

        Args:
            sigma: the blur. keep: keep it for the next call (the blur estimate's candidates: on
                a GPU built by :meth:`prime` before the clock, so each estimate only renders; on
                the CPU built by the first estimate and reused by the second while all kept
                stores hold at most :data:`HOST_PATTERN_CACHE` bytes; uint8, ~2.4 MB per
                1024 x 768 pattern).
        """
        key = round(float(sigma), 6)
        store = self._blurred.get(key)
        if store is None:
            store = build_projection(self.scene, self.frames, self.device, refraction=self.cfg.rig.refraction,
                                     camera_blur=sigma, patterns=self.pattern_images()).store
            kept = sum(int(v.buffer.numel()) for v in self._blurred.values()) + int(store.buffer.numel())
            if keep and (self.device.type != "cpu" or kept <= HOST_PATTERN_CACHE):
                self._blurred[key] = store
        return store

    def apply_camera_blur(self, sigma: float) -> None:
        """Blur the trainer's patterns by ``sigma`` camera px (from the unblurred images), in place,
        and weigh the lens's halo into the background prior (:meth:`update_halo`)."""
        if self.cfg.rays.blur_via == "pattern" and sigma != self.pattern_blur:
            new = self.blurred_store(sigma)
            if new.buffer.shape != self.proj.store.buffer.shape:  # a blur keeps every pattern's size
                raise FastneusError("blurred patterns changed size", field="rays.camera_blur")
            self.proj.store.buffer.copy_(new.buffer)  # in place: the rig and captured CUDA graphs read this buffer
            self.pattern_blur = sigma
        self.camera_blur = sigma
        self.update_halo()

    def update_halo(self) -> None:
        """Without masks in a lit room, the background prior also covers the halo a blurred camera
        spreads around the object (``loss.bg_halo``, :func:`fastneus.train.rays.halo_weights`;
        realistic Normal, no masks, 10 s on an H100: ant 6.71 -> 3.62 mm symmetric, rock 9.92 ->
        8.45; CPU 600 steps: ant 11.7 -> 5.6, rock 11.1 -> 9.3). A sharp capture (blur 0), a dark
        room (the ambient-lit object fails the brightness ratio next to the lines) or masks: the
        plain flags. The band's width goes into :attr:`blur_decision` (``halo_px``)."""
        b = self.bank
        r = 0
        if self.bg_used and self.cfg.loss.bg_halo > 0 and hasattr(b, "set_halo") and b.lit_room:
            r = halo_radius(self.camera_blur)
            b.set_halo(r, self.cfg.loss.bg_halo)
        self.blur_decision["halo_px"] = r
        self.update_fg_halo()

    def update_fg_halo(self) -> None:
        """Without masks in a dark room, once the camera blur is known and from ``loss.fg_halo_frac``
        of the run: the foreground flags without the lens's halo (``loss.fg_halo``,
        :func:`fastneus.train.rays.trim_halo`); the share used goes into :attr:`blur_decision`
        (``fg_halo``, 0 while it waits or does not apply)."""
        c, b = self.cfg.loss, self.bank
        if c.fg_halo <= 0 or not self.fg_used or not hasattr(b, "set_fg_halo") or b.lit_room:
            return
        share = c.fg_halo if self.camera_blur > 0 and self.fg_halo_due is None else 0.0  # (None: due, or no wait)
        b.set_fg_halo(share)  # (the bank keeps its flags when the share is the one in use)
        self.blur_decision["fg_halo"] = share

    def blur_note(self) -> str:
        """One line on the camera blur in use (printed; run.json keeps :attr:`blur_decision`)."""
        d = self.blur_decision
        halo = (f"; its halo ({d['halo_px']} px around the object) counts as background (bg_halo)"
                if d.get("halo_px") else "")
        if d.get("fg_halo"):
            halo += (f"; foreground pixels beside the backdrop under {d['fg_halo']:g} of their brightest neighbour "
                     "are its halo, not the object (fg_halo)")
        if d["mode"] == "set":
            return f"camera blur: {d['sigma']:g} px (set){halo}"
        if d.get("sigma") is None:
            return f"camera blur: auto, estimated at {' and '.join(f'{100 * f:.0f}' for f in d['at_frac'])} % of the run"
        res = ", ".join(f"{s:g}:{r:.4f}" for s, r in zip(d["sigmas"], d["residuals"]))
        before = " -> ".join(f"{r['sigma']:g}" for r in d["rounds"][:-1])
        return (f"camera blur: auto -> {before + ' -> ' if before else ''}{d['sigma']:g} px at step {d.get('step')} "
                f"({d['seconds']:.1f} s in all; residual per sigma {res or 'none: no lit rays'}){halo}")

    # ------------------------------------------------------------------ one step
    def train_step(self) -> dict | None:
        """One optimisation step (:meth:`_train_step`) under the run's matmul precision (``run.matmul``).

        Returns scalars (as tensors) for logging, or None if skipped.
        """
        if self.device.type != "cuda":
            return self._train_step()
        with matmul_precision(self.matmul):
            return self._train_step()

    def matmul_note(self) -> str:
        """The printed line of ``run.matmul``'s decision (CUDA runs)."""
        if self.matmul == "tf32":
            return "matmul: tf32 (the small networks' products on tensor cores; run.matmul=fp32 for full float32)"
        return f"matmul: fp32{' (this GPU has no TF32)' if self.cfg.run.matmul == 'auto' else ''}"

    def _train_step(self) -> dict | None:
        """One optimisation step. Returns scalars (as tensors) for logging, or None if skipped.

        The host part (schedules, occupancy, rays, marching: the step's one host sync) runs here;
        the rest (:meth:`compute`: field, compositing, losses, backward, Adam) runs eagerly, or on
        CUDA replays a captured graph of itself (:mod:`fastneus.train.graphstep`) when nothing in
        it changes from step to step but the inputs.
        """
        c = self.cfg
        p = self.progress()
        if self.exposure_due is not None and p >= self.exposure_due:
            self.decide_exposure()
        if self.blur_due and p >= self.blur_due[0]:
            self.decide_camera_blur()
        if self.fg_halo_due is not None and p >= self.fg_halo_due:
            self.fg_halo_due = None
            self.update_fg_halo()
            if self.blur_decision.get("fg_halo") and self.console is not None:
                self.console.print(f"foreground flags: the lens's halo left out from step {self.step} "
                                   f"(fg_halo {self.blur_decision['fg_halo']:g})", soft_wrap=True, highlight=False,
                                   markup=False)
        self.field.set_progress(p, self.steps_expected())
        self.update_grid(p)
        self._set_lr(p)
        graphs = self.graphs if self.graphs is not None and self.graphs.eligible(self, p) else None
        n = graphs.ray_count(self.n_rays) if graphs is not None else self.n_rays
        if graphs is None and self.split_now(p):
            return self._split_step(n, p)
        # a replayed graph of the draw and the capped march (graphstep.StepGraphs.drawn): no host work
        # for either, as the ray draw's ~30 small ops and the march's launches were ~1.7 ms of a step's
        # 4.4 ms of host time on an H200 (perf note 37)
        capped = graphs.drawn(self, n, p) if graphs is not None else None
        if capped is None:
            batch, xr = self.draw(n, self.gen)
            if graphs is not None:  # into the graphs' fixed input buffers before the march's host sync
                batch, xr = graphs.inputs(batch, xr, drawn=(n, graphs.draw_token(self)))
                # a key planned from the last sample count read back: the march writes into its graph's
                # buffers and the replay follows with no host sync (graphstep.StepGraphs.capped)
                capped = graphs.capped(self, batch, xr, p)
                if capped is not None:
                    march_samples_capped(self.grid.bits, self.grid.resolution, batch["origins"], batch["dirs"], c,
                                         capped[1].capped_buffers(), stop=self.grid.stop)
        if capped is not None:
            s = graphs.samples_estimate(n)
        else:
            # a replayed step's samples go straight into its graph's fixed buffers (graphs.march_out)
            smp = march_samples(self.grid.bits, self.grid.resolution, batch["origins"], batch["dirs"], c,
                                jitter=True, stop=self.grid.stop,
                                out=None if graphs is None else graphs.march_out(self, batch, xr, p))
            s = smp["n_samples"]  # known on the host from marching
        # adapt the ray count to the sample budget
        self.n_rays = self._next_ray_count(n, s)
        if s == 0:
            return self._empty_step()
        self.empty_steps = 0
        if capped is not None:
            rec = graphs.run_capped(self, *capped, p)
        elif graphs is not None:
            rec = graphs.step(self, batch, xr, smp, p)
        else:
            rec = self.compute(batch, xr, smp, p)
        self.rig.fix_gauge()
        self.step += 1
        if rec is None:
            return None
        rec["spr"], rec["samples"] = s / n, s
        return rec

    def split_now(self, p: float) -> bool:
        """Whether the step at progress ``p`` runs as two half batches on two threads (``run.split_step``).

        On the CPU with 2 threads a step's torch ops are too small to split over the cores (16 k
        samples: 1.35x the steps of one thread), while two half batches on two threads, each
        launching unchunked, overlap almost fully (two trainers on two threads: 1.96x the steps of
        one; the split step 1.5x). Off by default: it computes what one thread does, and over 49 fresh
        seeds of two thin-legged ant cells it came out ~0.2 mm worse on average (perf note 40).
        Only where nothing else of the step needs the whole batch: no surface prior (its points come
        from the run's generator), one ray per pixel (no rays-per-pixel blur)."""
        return (self.cfg.run.split_step == "on" and self.device.type == "cpu" and self.blur_sub == 1
                and not self.prior_on(p))

    def _split_step(self, n: int, p: float, threaded: bool = True) -> dict | None:
        """:meth:`_train_step` after the schedules with the batch as two halves (:meth:`split_now`).

        Both halves are drawn and marched on this thread, in order, from the run's generator (the
        same seed gives the same run); each half's field, losses and ``0.5 * loss`` backward run on
        its own thread with unchunked launches; the two gradients add into ``.grad`` (two terms: the
        same sum in either order); then the one guarded Adam update. The total is the mean of the
        halves' losses (the full batch's up to their sample counts). ``threaded=False`` runs the
        halves one after the other on this thread (the reference the tests compare with).
        """
        import threading

        from fastneus.kernels import local_threads

        c = self.cfg
        halves = []
        for _ in range(2):
            batch, xr = self.draw(max(1, n // 2), self.gen, points=max(1, max(256, n // 4) // 2))
            smp = march_samples(self.grid.bits, self.grid.resolution, batch["origins"], batch["dirs"], c,
                                jitter=True, stop=self.grid.stop)
            halves.append((batch, xr, smp))
        s = sum(int(h[2]["n_samples"]) for h in halves)
        self.n_rays = self._next_ray_count(n, s)
        live = [h for h in halves if int(h[2]["n_samples"]) > 0]
        if not live:
            return self._empty_step()
        self.empty_steps = 0
        self.opt.zero_grad(set_to_none=True)
        w = 1.0 / len(live)
        out: list = [None] * len(live)

        def half(k: int) -> None:
            try:
                torch.set_num_threads(1)  # OpenMP's count is per thread: the new one's too
                with local_threads(1):
                    loss, terms = self.step_loss(*live[k], p)
                    (loss * w).backward()
                out[k] = (loss.detach(), terms)
            except BaseException as e:  # noqa: BLE001 - re-raised on the calling thread
                out[k] = e

        other = threading.Thread(target=half, args=(1,), name="fastneus-half") if len(live) > 1 and threaded else None
        # torch's intra-op threads stay off meanwhile: its small ops only lose to two threads each
        # splitting them (51 against 34 ms a step on the 2-core VM)
        torch_threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            if other is not None:
                other.start()
            half(0)
            if other is not None:
                other.join()
            elif len(live) > 1:
                half(1)
        finally:
            torch.set_num_threads(torch_threads)
        for r in out:
            if isinstance(r, BaseException):
                raise r
        loss = sum(r[0] for r in out) * w
        stepped = finite_step(self.opt, loss)  # NaN/Inf guard
        self.rig.fix_gauge()
        self.step += 1
        if not stepped:
            self._skipped += 1
            return None
        terms = {k: sum(r[1][k].detach() for r in out) * w for k in ("rgb", "mse", "eik")}  # the halves' mean
        return {**self._record(loss, terms), "spr": s / n, "samples": s}

    def _empty_step(self) -> None:
        """A step whose march found no sample: an empty grid would stall training for good, so it is
        re-opened after a few of them."""
        self.empty_steps += 1
        if self.empty_steps >= 8:
            self.grid.update(self.field.sdf, 0.0, self.cfg.rays.march_step, warmup=True)
            self.empty_steps = 0
        self.step += 1
        return None

    def draw(self, n: int, generator: torch.Generator | None, points: int | None = None) -> tuple[dict, torch.Tensor]:
        """This step's random rays and the eikonal term's uniform points.

        Args:
            n: ray count (pixels x ``blur_sub`` rays each); generator: the run's (``self.gen``), or
                None for the default one (a recorded draw graph: graphstep.StepGraphs.drawn).
            points: uniform points to draw (default ``max(256, n / 4)``; a half batch of the split
                step takes half of the whole batch's, so the points weigh as much against the samples).
        Returns:
            (batch, xr): :meth:`RayBank.sample`'s dict after the rig's corrections, and [points, 3]
            uniform points in [-1, 1]^3.
        """
        c, sub = self.cfg, self.blur_sub
        batch = self.rig.rays(self.bank.sample(max(1, n // sub), generator, bright_fraction=c.rays.bright_fraction,
                                               blur=self.camera_blur if sub > 1 else 0.0, sub=sub))
        # a few uniform points for the eikonal term so the far field stays an SDF; they go through
        # the field in the same call as the samples (one hash + MLP pass instead of two)
        xr = torch.rand(max(256, n // 4) if points is None else points, 3, device=self.device, generator=generator) * 2 - 1
        return batch, xr

    def _next_ray_count(self, n: int, s: int) -> int:
        """The ray count adapted to the sample budget after a step of ``n`` rays and ``s`` samples:
        a running mean towards ``target_samples / samples per ray`` (the count per ray is noisy).

        With CUDA graphs, a count more than :data:`RAY_JUMP` away from that target goes straight to
        it: after the occupancy grid's first update the mean climbed through three ray buckets in
        ten steps, each one eager step and one capture (~60 ms of a 5-s budget apiece on an H200,
        scripts/budget_timeline.py), replayed a few times and never again."""
        c = self.cfg.rays
        mean_spr = max(1.0, s / max(1, n))
        want = c.target_samples / mean_spr
        if self.graphs is not None and s > 0 and not want / RAY_JUMP <= self.n_rays <= want * RAY_JUMP:
            new = want
        else:
            new = 0.8 * self.n_rays + 0.2 * want
        return int(min(c.max_rays, max(c.min_rays, new)))

    def compute(self, batch: dict, xr: torch.Tensor, smp: dict, p: float, valid: torch.Tensor | None = None,
                device_adam: bool = False, fits: torch.Tensor | None = None) -> dict | None:
        """The step after marching: field, compositing, losses, backward, guarded Adam update.

        Args:
            batch: :meth:`RayBank.sample` dict (after the rig); xr: [E, 3] uniform points.
            smp: :func:`march_samples` dict (its arrays may be padded past the live samples).
            p: progress in [0, 1].
            valid: [S + E] float, 1 for live samples and the uniform points, 0 for padding (a
                captured step's fixed-capacity buffers); None: every sample is live.
            device_adam: the Adam update reads its learning rates from device scalars (prepared
                by ``Adam.prepare_device_step`` before the step; a captured step).
            fits: [1] bool on the device, or None: False skips the update (a capped march's
                samples did not fit its buffers; counted in ``overflowed``).
        Returns:
            {"loss", "l1", "mse", "eik"} as tensors, or None when the host guard skipped the step.
        """
        loss, terms = self.step_loss(batch, xr, smp, p, valid)
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        if self._skipped_dev is not None:  # NaN/Inf guard on the device (no host sync)
            finite = finite_flag(self.opt, loss)
            ok = finite if fits is None else finite & fits.reshape(finite.shape)
            if device_adam:
                self.opt.device_update(ok)
            else:
                self.opt.gated_step(ok)
            self._skipped_dev += (~finite).to(torch.int64)
            if fits is not None:
                self._overflow_dev += (~fits).sum().to(torch.int64)
        elif not finite_step(self.opt, loss):  # NaN/Inf guard
            self._skipped += 1
            return None
        return self._record(loss, terms)

    @staticmethod
    def _record(loss: torch.Tensor, terms: dict) -> dict:
        """A step's scalars for logging (tensors): the total, its L1 and MSE, the eikonal term."""
        return {"loss": loss.detach(), "l1": terms["rgb"].detach(), "mse": terms["mse"], "eik": terms["eik"]}

    def step_loss(self, batch: dict, xr: torch.Tensor, smp: dict, p: float,
                  valid: torch.Tensor | None = None) -> tuple[torch.Tensor, dict]:
        """The step's loss (field, compositing, every loss term) before its backward.

        Arguments as :meth:`compute`. Returns:
            (loss, terms): the scalar total and the terms it sums (``losses.*`` dicts merged).
        """
        c = self.cfg
        i_r, i_b = self.illumination()
        bg_on, fg_on = self.photo_priors(p)  # both off when masks are used
        bg_on = bg_on and "bg" in batch
        # a graph being recorded reads the ratio from the device buffer StepGraphs.step fills before
        # every replay; an eager step passes the value itself
        capturing = self.cos_dev is not None and torch.cuda.is_current_stream_capturing()
        cos = self.cos_dev if capturing else self.cos_anneal(p)
        mask_form = c.loss.mask_loss if self.masks_used and "mask" in batch else None  # None: no mask term
        out = shade_samples(self.field, smp, self.rig.projection(), batch["origins"], batch["dirs"], batch["fidx"], c,
                            i_r=i_r, i_b=i_b, cos_anneal=cos, curvature=c.loss.curvature_weight > 0,
                            extra_points=xr, lit=bg_on and self.bg_lit,
                            min_sdf=mask_form not in (None, "bce"))
        # the camera clips at 1: a rendered value above it is a saturated pixel, not an error
        # (unclipped, bright pattern pixels would pull i_r down on Normal-light scenes)
        # [B, 3], or [B, K, 3] with K shots per ray (multi-shot); + water (fastneus.train.rig)
        pred = self.rig.composite(out["color"], out, c.rays.background)
        if self.log_gain is not None:  # the photo's exposure gain, before the camera clips
            pred = pred * losses.exposure_gain(self.log_gain, batch["fidx"])
        opacity, lit = out["opacity"], out.get("lit")
        if self.blur_sub > 1:  # the lens blurs before the sensor clips: a pixel is the mean of its rays
            pred = pred.view(-1, self.blur_sub, *pred.shape[1:]).mean(1)
            opacity = opacity.view(-1, self.blur_sub).mean(1)
            lit = None if lit is None else lit.view(-1, self.blur_sub).mean(1)
        pred = pred.clamp(max=1.0)
        terms = losses.photometric(pred, batch["rgb"], c.loss.robust, c.loss.robust_eps, batch.get("sat"),
                                   c.loss.saturated)
        # eikonal on the samples plus the uniform points (evaluated with them in shade_samples)
        terms |= losses.eikonal(out["grad_all"], c.loss.eikonal_weight, valid=valid)
        if mask_form is not None:
            mw = self.mask_w_dev if capturing else self.mask_weight_at(p)
            if mask_form == "bce":
                terms |= losses.mask_bce(opacity, batch["mask"], mw)
            else:
                m, has = self._pixel_min_sdf(out)
                terms |= losses.mask_silhouette(m, has, opacity, batch["mask"], mw, self.field.inv_s(), mask_form,
                                                batch.get("core"))
        elif bg_on:
            bw = self.bg_w_dev if capturing else self.background_weight_at(p)  # a replay reads the ramp
            is_bg = batch["bg"]
            if lit is not None:  # dark room: a black pixel is empty space only where a surface would be lit
                is_bg = is_bg * (lit / c.loss.bg_lit_ref).clamp(max=1.0)
            terms |= losses.background_free_space(opacity, is_bg, bw)
        if fg_on:
            # a pixel (any of its shots, any channel) clearly above the backdrop: the object is there
            if "fg" in batch:  # flagged at load (the bank: threshold and the lens's halo left out)
                is_fg = batch["fg"]
            else:
                rgb = batch["rgb"]
                is_fg = ((rgb.reshape(rgb.shape[0], -1).amax(-1) - c.rays.background) > c.loss.fg_threshold).float()
            terms |= losses.foreground_opacity(opacity, is_fg, self.bg_weight)
        if self.prior_on(p):
            # a graph being recorded reads the faded weight from the device and draws its points with
            # the default CUDA generator (torch registers it with every capture; the run's is not)
            w = self.prior_w_dev if capturing else self.prior_weight_at(p)
            gen = None if capturing else self.gen
            terms |= losses.surface_prior(self.prior.loss(self.field, fit_batch(c) // 2, gen, eikonal=False), w)
        if self.hull_out is not None and c.occupancy.hull_weight > 0:
            r = self.grid.resolution
            ijk = ((xr + 1.0) * (r / 2.0)).long().clamp(0, r - 1)
            out_hull = self.hull_out[ijk[:, 0] + ijk[:, 1] * r + ijk[:, 2] * (r * r)]
            terms["hull"] = c.occupancy.hull_weight * (out_hull * torch.relu(-out["sdf_extra"])).mean()
        if "highlight" in out and c.loss.highlight_weight > 0:
            terms |= losses.highlight(out["highlight"], c.loss.highlight_weight)
        if c.loss.curvature_weight > 0 and out["curv"] is not None:
            cv = None if valid is None else valid[: out["curv"].shape[0]]
            terms |= losses.curvature(out["curv"], c.loss.curvature_weight, valid=cv)
        return losses.total(terms), terms

    # ------------------------------------------------------------------ loop
    def fit(self, final_save: bool = True) -> dict:
        """Train until ``steps`` or, when set, ``time_budget``; returns the final log record.

        Args:
            final_save: write the checkpoint at the end (always when stopped by a signal);
                ``pipeline.train_scene`` writes it itself after mesh.ply, off the mesh's critical path.
        """
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

        c = self.cfg
        t_fit = time.perf_counter()
        save_config(c, self.out / "config.yaml")
        kern: dict = {}
        t_kernels = self.prime(report=kern)
        t_save = 0.0
        from fastneus.train.geometry_init import initialise_geometry

        t0 = time.perf_counter()
        note = initialise_geometry(self)  # e.g. from decoded Gray code; its time counts as training
        if self.cfg is not c:  # the init turned coarse-to-fine off: the saved config says what runs
            c = self.cfg
            save_config(c, self.out / "config.yaml")
        if note:
            self.elapsed += time.perf_counter() - t0
            if self.console is not None:
                self.console.print(note)
        logf = open_append(self.out / "log.jsonl")  # never through a symbolic link
        # validation renders (RUN/validation/) and, when installed, TensorBoard (RUN/tensorboard/); their
        # time is kept out of the training clock
        watch = ProgressWriter(self, every_s=c.run.validate_every, every_steps=c.run.validate_every_steps,
                               tensorboard=c.run.tensorboard)
        t_val = 0.0
        last = {}
        samples_total, t_window, steps_window = 0, time.perf_counter(), 0
        timed = c.run.time_budget > 0
        # the bar counts steps, or tenths of a second of training when the run is a time budget
        total = int(round(c.run.time_budget * 10)) if timed else c.run.steps
        done = (lambda: min(total, int(self.elapsed * 10))) if timed else (lambda: self.step)
        unit = "{task.completed}/{task.total} ds" if timed else "{task.completed}/{task.total}"
        columns = [TextColumn("[bold]train"), BarColumn(), TextColumn(unit),
                   TextColumn("{task.fields[info]}"), TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn()]
        # piped output (a cluster job's log): no bar, a plain unwrapped line every few seconds instead
        plain = self.console is not None and not self.console.is_terminal
        progress = Progress(*columns, console=self.console, disable=self.console is None or plain, transient=False)
        next_line = time.perf_counter() + PLAIN_EVERY_S
        with progress:
            task = progress.add_task("train", total=total, completed=done(), info="")
            budget = BudgetSync(c.run.time_budget)
            budget.synced(self.step, self.elapsed)
            while not self.finished():
                t0 = time.perf_counter()
                rec = self.train_step()
                sync = self.device.type == "cuda" and (self.step % c.run.log_every == 0 or budget.due(self.step))
                if sync:
                    torch.cuda.synchronize(self.device)
                self.elapsed += time.perf_counter() - t0
                if sync:
                    budget.synced(self.step, self.elapsed)
                steps_window += 1
                if rec is not None:
                    samples_total += rec["samples"]
                end = self.finished()
                if self.step % c.run.log_every == 0 or end or rec is None and self.step == 1:
                    if rec is not None:
                        now = time.perf_counter()
                        i_r, i_b = self.photo_illumination()
                        last = {"step": self.step, "time": round(self.elapsed, 3), "progress": round(self.progress(), 4),
                                "loss": float(rec["loss"]),
                                "l1": float(rec["l1"]), "psnr": _psnr(float(rec["mse"])), "eik": float(rec["eik"]),
                                "i_r": i_r, "i_b": i_b, "inv_s": float(self.field.inv_s().detach()),
                                "levels": self.field.active_levels,
                                "rays": self.n_rays, "samples_per_ray": round(rec["spr"], 2),
                                "it_s": steps_window / max(1e-9, now - t_window),
                                "samples_s": samples_total / max(1e-9, now - t_window),
                                "occupied": self.grid.occupied_fraction(), "skipped": self.skipped}
                        t_window, steps_window, samples_total = now, 0, 0
                        self.history.append(last)
                        logf.write(json.dumps(last) + "\n")
                        logf.flush()
                        watch.on_log(self.step, last)
                        progress.update(task, info=(f"loss {last['loss']:.4f} psnr {last['psnr']:.1f} "
                                                    f"i_r {i_r:.3f} i_b {i_b:.3f} spr {last['samples_per_ray']:.0f} "
                                                    f"{last['it_s']:.1f} it/s"))
                progress.update(task, completed=done())
                if plain and last and (end or time.perf_counter() >= next_line):
                    next_line = time.perf_counter() + PLAIN_EVERY_S
                    self.console.print(_plain_line(last, done(), total, timed), soft_wrap=True, highlight=False,
                                       markup=False)
                if self.step % c.run.save_every == 0:
                    t_save -= time.perf_counter()
                    self.save()
                    t_save += time.perf_counter()
                if watch.due(self.step, self.elapsed):
                    t_val -= time.perf_counter()
                    watch.maybe_validate(self.step, self.elapsed, force=True)
                    t_val += time.perf_counter()
        logf.close()
        if final_save:
            t_val -= time.perf_counter()
            watch.finish(self.step, self.elapsed)
            t_val += time.perf_counter()
        elif self.stop_signal is not None:  # stopped: no finish_run, so the TensorBoard records are written now
            watch.close()
        else:  # pipeline.finish_run writes the last validation render after mesh.ply (finish_progress)
            self._watch = watch
        if final_save or self.stop_signal is not None:
            t_save -= time.perf_counter()
            self.save()
            t_save += time.perf_counter()
        if self.graphs is not None:  # how much of the run replayed captured steps (printed and saved)
            g = self.graphs.summary()
            g["overflowed"] = int(self._overflow_dev)
            last["cuda_graphs"] = g
            if self.console is not None:
                self.console.print(f"CUDA graphs: {g['replayed']} steps replayed ({g['unsynced']} without a host sync, "
                                   f"{g['overflowed']} of them past their buffers: not applied), {g['captured']} captured, "
                                   f"{g['eager']} eager{'' if self.graphs.enabled else ' (capture failed: off)'}")
            self.graphs.release()
        clock = self.clock
        if clock is not None:
            clock.add("kernels", t_kernels)
            clock.notes["kernels_compiled"] = kern.get("compiled", [])
            clock.add("checkpoint", t_save)
            clock.add("validation", t_val)
            clock.add("train", time.perf_counter() - t_fit - t_kernels - t_save - t_val)
        return last

    def finish_progress(self) -> None:
        """The last validation render and the TensorBoard writer's close, when :meth:`fit` left
        them for after mesh.ply (``final_save=False``: nothing after training delays the mesh)."""
        watch, self._watch = getattr(self, "_watch", None), None
        if watch is not None:
            watch.finish(self.step, self.elapsed)

    def prime(self, report: dict | None = None) -> float:
        """Load (on a machine's first run: compile) every Warp kernel of a step before the clock
        starts, so a time budget is spent on training; no parameter changes. On CUDA this
        includes the marching cubes of the mesh export, so no compile lands after training.

        Args:
            report: optional dict; gets ``compiled``, the modules compiled now (not cached).
        Returns:
            Seconds spent.
        """
        from fastneus.kernels import prepare_kernels

        ops = ("hash_encode", "march_rays", "render_pattern") + self.rig.kernel_ops()
        if self.device.type == "cuda":
            ops += ("marching_cubes", "adam_update")
        seconds = prepare_kernels(self.device, say=self.console.print if self.console is not None else None,
                                  backend=self.cfg.run.backend, ops=ops, report=report)
        if self.device.type == "cuda":
            t = time.perf_counter()
            if self.blur_due:
                # the blur estimate's first convolution set up the GPU's convolution library
                # (~0.2 s), and its first round read the patterns from disk and blurred them by
                # each candidate (~0.1 s more than the second round), all inside the budget: the
                # candidates depend on the scene only, so they are built here, like the kernels
                from fastneus.train.blurfit import AUTO_SIGMAS

                for sigma in AUTO_SIGMAS:
                    self.blurred_store(sigma, keep=True)
            with matmul_precision(self.matmul):  # the step's own GEMM kernels load before the clock
                self.warm_up()
            torch.cuda.synchronize(self.device)
            seconds += time.perf_counter() - t
        return seconds

    def warm_up(self) -> None:
        """The first step's loss and its backward once, on real rays, changing nothing.

        On CUDA the first use of each kernel loads its module (lazy loading) and cuBLAS and
        autograd set themselves up: the first step took 0.33 s against ~10 ms for the next ones
        (rock, H100), a tenth of a 3-s budget. :meth:`prime` runs this before the clock. The
        gradients come back from :func:`torch.autograd.grad` and are dropped; parameters,
        optimizer state, the occupancy grid, the run's generator and torch's global random
        stream are left as they were (tests/test_warm_up.py).
        """
        c = self.cfg
        gen = torch.Generator(device=self.device)
        gen.manual_seed(int(c.run.seed) * 7919 + 29)
        state = self.gen.get_state()  # the surface prior draws from the run's generator
        params = [q for g in self.opt.param_groups for q in g["params"] if q.requires_grad]
        with torch.random.fork_rng(devices=[self.device] if self.device.type == "cuda" else []):
            sub = self.blur_sub
            batch = self.rig.rays(self.bank.sample(max(1, self.n_rays // sub), gen,
                                                   bright_fraction=c.rays.bright_fraction,
                                                   blur=self.camera_blur if sub > 1 else 0.0, sub=sub))
            xr = torch.rand(max(256, self.n_rays // 4), 3, device=self.device, generator=gen) * 2 - 1
            smp = march_samples(self.grid.bits, self.grid.resolution, batch["origins"], batch["dirs"], c)
            if smp["n_samples"] > 0:
                loss, _ = self.step_loss(batch, xr, smp, 0.0)
                if loss.requires_grad:
                    torch.autograd.grad(loss, params, allow_unused=True)
        self.gen.set_state(state)

    # ------------------------------------------------------------------ checkpoints
    def state(self) -> dict:
        return {"step": self.step, "elapsed": self.elapsed, "n_rays": self.n_rays, "skipped": self.skipped,
                "config": self.cfg.to_dict(), "field": self.field.state_dict(), "grid": self.grid.state_dict(),
                "log_ir": self.log_ir.detach().cpu(), "log_ib": self.log_ib.detach().cpu(),
                **({"log_gain": self.log_gain.detach().cpu()} if self.log_gain is not None else {}),
                "optimizer": self.opt.state_dict(), "frames": self.frames, "rig": rig_state(self.rig),
                "gen": self.gen.get_state().cpu(), "camera_blur": dict(self.blur_decision),
                "exposure": dict(self.exposure_decision)}

    def save(self) -> Path:
        """Write the checkpoint atomically (temp file + rename): a crash keeps the previous one."""
        path = save_checkpoint(self.state(), self.out / CKPT_NAME)
        self.rig.write_json(self.out)
        if self.on_saved is not None:  # e.g. drop the previous run that --overwrite kept aside
            self.on_saved()
        return path

    def load_state(self, st: dict, with_optimizer: bool = True) -> None:
        self.field.load_state_dict(st["field"])
        self.grid.load_state_dict(st["grid"])
        with torch.no_grad():
            self.log_ir.copy_(st["log_ir"].to(self.device))
            self.log_ib.copy_(st["log_ib"].to(self.device))
            if self.log_gain is not None and "log_gain" in st:
                self.log_gain.copy_(st["log_gain"].to(self.device))
        rig_load(self.rig, st.get("rig"))
        d = st.get("camera_blur")
        if isinstance(d, dict) and d.get("mode") == "auto" and self.blur_due and d.get("sigma") is not None:
            self.blur_decision = dict(d)  # estimated before the checkpoint: those rounds are not redone
            self.blur_due = self.blur_due[len(d.get("rounds", [])) or 1:]
            self.apply_camera_blur(float(d["sigma"]))
        e = st.get("exposure")  # decided before the checkpoint (a malformed entry: decided again)
        if (isinstance(e, dict) and self.exposure_decision["mode"] == "auto" and isinstance(e.get("learned"), bool)
                and isinstance(e.get("spread"), (int, float)) and isinstance(e.get("step"), int)):
            self.exposure_decision, self.exposure_due = dict(e), None
        self.step, self.elapsed = int(st["step"]), float(st.get("elapsed", 0.0))
        self.n_rays, self.skipped = int(st.get("n_rays", self.n_rays)), int(st.get("skipped", 0))
        self.field.set_progress(self.progress(), self.steps_expected())
        if with_optimizer:
            groups = self.opt.param_groups
            if self.log_gain is not None and "log_gain" not in st:  # saved before per-photo exposure: gains 1
                self.opt.param_groups = [g for g in groups if g["name"] != "exposure"]
            self.opt.load_state_dict(st["optimizer"])
            self.opt.param_groups = groups
            for g in self.opt.param_groups:  # base_lr may differ if the config changed
                g["base_lr"] = {"geometry": self.cfg.optim.lr, "color": self.cfg.optim.lr, "variance": self.cfg.optim.lr_variance,
                                "illum": self.cfg.optim.lr_illum}.get(g["name"], g["base_lr"])
        if "gen" in st and self.device.type == "cpu":
            self.gen.set_state(st["gen"])


def trainer_from_run(scene, run: Path, device: str, cfg: Config | None = None) -> Trainer:
    """Rebuild a trainer (field, grid, illumination) from a run folder's checkpoint."""
    st = load_checkpoint(run, map_location=device)
    cfg = cfg or config_from_dict(st["config"], str(Path(run) / CKPT_NAME))
    tr = Trainer(scene, cfg, Path(run), device)
    restore(tr, st, Path(run) / CKPT_NAME)
    return tr
