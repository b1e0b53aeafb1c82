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

from fastneus.config import Config, config_from_dict, save_config
from fastneus.errors import FastneusError
from fastneus.field.model import SDFField
from fastneus.field.renderer import render_rays
from fastneus.io import atomic_write
from fastneus.kernels.occupancy import OccupancyGrid
from fastneus.train.guard import finite_step
from fastneus.sampling import RayBank, build_projection

CKPT_NAME = "checkpoint.pt"


def _psnr(mse: float) -> float:
    return -10.0 * math.log10(max(mse, 1e-12))


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
        torch.manual_seed(cfg.seed)
        np.random.seed(cfg.seed)
        n = len(scene.frames)
        self.frames = list(range(n)) if cfg.frames is None else list(cfg.frames)
        bad = [f for f in self.frames if not 0 <= f < n]
        if bad or not self.frames:
            raise FastneusError(f"frame indices {bad or '[]'} out of range 0..{n - 1}", field="frames")
        need_masks = cfg.mask_weight > 0
        self.bank = RayBank(scene, self.frames, self.device, load_masks=need_masks,
                            brightness_cdf=cfg.bright_fraction > 0)
        if need_masks and not self.bank.has_masks:
            raise FastneusError("mask_weight > 0 but the scene has no masks for every training frame",
                                field="mask_weight")
        self.proj = build_projection(scene, self.frames, self.device)
        self.field = SDFField(cfg, self.device)
        self.field.init_color_bias(self.bank.rgb.float().mean(0) / 255.0)
        self.grid = OccupancyGrid(cfg.occ_resolution, self.device)
        ill = scene.illumination
        if cfg.illum_init == "ones" or ill is None:
            ir0, ib0 = 1.0, 1.0
        else:
            ir0, ib0 = float(ill.i_r), float(ill.i_b)
        # log-parametrised so i_r, i_b stay positive
        self.log_ir = torch.nn.Parameter(torch.tensor([math.log(max(ir0, 1e-4))], device=self.device))
        self.log_ib = torch.nn.Parameter(torch.tensor([math.log(max(ib0, 1e-4))], device=self.device))
        groups = self.field.param_groups(cfg) + [
            {"params": [self.log_ir, self.log_ib], "lr": cfg.lr_illum, "name": "illum"}]
        for g in groups:
            g["base_lr"] = g["lr"]
        self.opt = torch.optim.Adam(groups, betas=(0.9, 0.99), eps=cfg.adam_eps)
        self.step = 0
        self.n_rays = cfg.init_rays
        self.elapsed = 0.0          # training seconds, kept across resume
        self.skipped = 0            # NaN/Inf steps skipped
        self.empty_steps = 0        # consecutive steps whose rays found no occupied cell
        self.history: list[dict] = []
        self.gen = torch.Generator(device=self.device)
        self.gen.manual_seed(cfg.seed)

    # ------------------------------------------------------------------ helpers
    def illumination(self) -> tuple[torch.Tensor, torch.Tensor]:
        return self.log_ir.exp(), self.log_ib.exp()

    def progress(self) -> float:
        p = self.step / max(1, self.cfg.steps)
        if self.cfg.time_budget > 0:
            p = max(p, self.elapsed / self.cfg.time_budget)
        return min(1.0, p)

    def _set_lr(self) -> None:
        c = self.cfg
        if self.step < c.warmup_steps:
            f = (self.step + 1) / c.warmup_steps
        else:
            f = c.decay_to + (1 - c.decay_to) * 0.5 * (1 + math.cos(math.pi * self.progress()))
        # from a blind init (1, 1) the pattern term is several times too bright: waiting for the
        # geometry would let it carve the surface away, so fit it with the colours from step 0
        # (geometry frozen meanwhile), then keep learning
        start = 0 if c.illum_init == "ones" else c.illum_warmup_steps
        learn_illum = c.learn_illum and c.use_pattern and self.step >= start
        frozen = self.step < c.color_warmup_steps
        for g in self.opt.param_groups:
            if g["name"] == "illum":
                g["lr"] = g["base_lr"] if learn_illum else 0.0
            elif frozen and g["name"] in ("geometry", "variance"):
                g["lr"] = 0.0
            else:
                g["lr"] = g["base_lr"] * f

    def cos_anneal(self) -> float:
        return 1.0 if self.cfg.cos_anneal_steps <= 0 else min(1.0, self.step / self.cfg.cos_anneal_steps)

    def update_grid(self) -> None:
        c = self.cfg
        if self.step < c.occ_warmup_steps:
            if self.step == 0:
                self.grid.update(self.field.sdf, 0.0, c.march_step, warmup=True)
            return
        if self.step % c.occ_update_every == 0:
            # margin = half a cell diagonal keeps thin shells occupied once s is large
            self.grid.update(self.field.sdf, float(self.field.inv_s().detach()), c.march_step,
                             threshold=c.occ_threshold, margin=math.sqrt(3) / self.grid.resolution,
                             backend=c.backend)

    # ------------------------------------------------------------------ one step
    def train_step(self) -> dict | None:
        """One optimisation step. Returns scalars (as tensors) for logging, or None if skipped."""
        c = self.cfg
        self.field.set_progress(self.step, self.progress())
        self.update_grid()
        self._set_lr()
        batch = self.bank.sample(self.n_rays, self.gen, bright_fraction=c.bright_fraction)
        i_r, i_b = self.illumination()
        out = render_rays(self.field, self.grid.bits, self.grid.resolution, self.proj, batch["origins"],
                          batch["dirs"], batch["fidx"], c, i_r=i_r, i_b=i_b, cos_anneal=self.cos_anneal(),
                          jitter=True, curvature=c.curvature_weight > 0)
        s = out["n_samples"]
        # adapt the ray count to the sample budget (s is known on the host from marching)
        mean_spr = max(1.0, s / self.n_rays)
        self.n_rays = int(min(c.max_rays, max(c.min_rays, 0.8 * self.n_rays + 0.2 * c.target_samples / mean_spr)))
        if s == 0:
            # an empty grid would stall training for good: re-open it after a few empty steps
            self.empty_steps += 1
            if self.empty_steps >= 8:
                self.grid.update(self.field.sdf, 0.0, c.march_step, warmup=True)
                self.empty_steps = 0
            self.step += 1
            return None
        self.empty_steps = 0
        pred = out["color"] + c.background * (1.0 - out["opacity"])[:, None]
        err = (pred - batch["rgb"]).abs()
        loss_rgb = err.mean()
        grad = out["grad"]
        # eikonal on the samples plus a few uniform points so the far field stays an SDF
        n_rand = max(256, self.n_rays // 4)
        xr = torch.rand(n_rand, 3, device=self.device, generator=self.gen) * 2 - 1
        _, _, grad_r, _ = self.field.sdf_and_grad(xr)
        g_all = torch.cat([grad, grad_r])
        loss_eik = ((g_all.norm(dim=-1) - 1.0) ** 2).mean()
        loss = loss_rgb + c.eikonal_weight * loss_eik
        if c.mask_weight > 0 and "mask" in batch:
            op = out["opacity"].clamp(1e-3, 1 - 1e-3)
            loss = loss + c.mask_weight * torch.nn.functional.binary_cross_entropy(op, batch["mask"])
        if c.curvature_weight > 0 and out["curv"] is not None:
            loss = loss + c.curvature_weight * out["curv"].abs().mean()
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        stepped = finite_step(self.opt, loss)  # NaN/Inf guard
        self.step += 1
        if not stepped:
            self.skipped += 1
            return None
        return {"loss": loss.detach(), "l1": loss_rgb.detach(), "mse": (err ** 2).mean().detach(),
                "eik": loss_eik.detach(), "spr": s / batch["origins"].shape[0], "samples": s}

    # ------------------------------------------------------------------ loop
    def fit(self) -> dict:
        """Train until ``steps`` or ``time_budget``; returns the final log record."""
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

        c = self.cfg
        save_config(c, self.out / "config.yaml")
        logf = open(self.out / "log.jsonl", "a")
        last = {}
        samples_total, t_window, steps_window = 0, time.perf_counter(), 0
        columns = [TextColumn("[bold]train"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                   TextColumn("{task.fields[info]}"), TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn()]
        progress = Progress(*columns, console=self.console, disable=self.console is None, transient=False)
        with progress:
            task = progress.add_task("train", total=c.steps, completed=self.step, info="")
            while self.step < c.steps and not (c.time_budget > 0 and self.elapsed >= c.time_budget):
                t0 = time.perf_counter()
                rec = self.train_step()
                if self.device.type == "cuda" and (self.step % c.log_every == 0):
                    torch.cuda.synchronize(self.device)
                self.elapsed += time.perf_counter() - t0
                steps_window += 1
                if rec is not None:
                    samples_total += rec["samples"]
                if self.step % c.log_every == 0 or self.step >= c.steps or rec is None and self.step == 1:
                    if rec is not None:
                        now = time.perf_counter()
                        i_r, i_b = (float(x.detach()) for x in self.illumination())
                        last = {"step": self.step, "time": round(self.elapsed, 3), "loss": float(rec["loss"]),
                                "l1": float(rec["l1"]), "psnr": _psnr(float(rec["mse"])), "eik": float(rec["eik"]),
                                "i_r": i_r, "i_b": i_b, "inv_s": float(self.field.inv_s().detach()),
                                "rays": self.n_rays, "samples_per_ray": round(rec["spr"], 2),
                                "it_s": steps_window / max(1e-9, now - t_window),
                                "samples_s": samples_total / max(1e-9, now - t_window),
                                "occupied": self.grid.occupied_fraction(), "skipped": self.skipped}
                        t_window, steps_window, samples_total = now, 0, 0
                        self.history.append(last)
                        logf.write(json.dumps(last) + "\n")
                        logf.flush()
                        progress.update(task, info=(f"loss {last['loss']:.4f} psnr {last['psnr']:.1f} "
                                                    f"i_r {i_r:.3f} i_b {i_b:.3f} spr {last['samples_per_ray']:.0f} "
                                                    f"{last['it_s']:.1f} it/s"))
                progress.update(task, completed=self.step)
                if self.step % c.save_every == 0:
                    self.save()
        logf.close()
        self.save()
        return last

    # ------------------------------------------------------------------ checkpoints
    def state(self) -> dict:
        return {"step": self.step, "elapsed": self.elapsed, "n_rays": self.n_rays, "skipped": self.skipped,
                "config": self.cfg.to_dict(), "field": self.field.state_dict(), "grid": self.grid.state_dict(),
                "log_ir": self.log_ir.detach().cpu(), "log_ib": self.log_ib.detach().cpu(),
                "optimizer": self.opt.state_dict(), "frames": self.frames,
                "gen": self.gen.get_state().cpu()}

    def save(self) -> Path:
        """Write the checkpoint atomically (temp file + rename): a crash keeps the previous one."""
        path = self.out / CKPT_NAME
        atomic_write(path, lambda tmp: torch.save(self.state(), tmp))
        return path

    def load_state(self, st: dict, with_optimizer: bool = True) -> None:
        self.field.load_state_dict(st["field"])
        self.grid.load_state_dict(st["grid"])
        with torch.no_grad():
            self.log_ir.copy_(st["log_ir"].to(self.device))
            self.log_ib.copy_(st["log_ib"].to(self.device))
        self.step, self.elapsed = int(st["step"]), float(st.get("elapsed", 0.0))
        self.n_rays, self.skipped = int(st.get("n_rays", self.n_rays)), int(st.get("skipped", 0))
        self.field.set_progress(self.step, self.progress())
        if with_optimizer:
            self.opt.load_state_dict(st["optimizer"])
            for g in self.opt.param_groups:  # base_lr may differ if the config changed
                g["base_lr"] = {"geometry": self.cfg.lr, "color": self.cfg.lr, "variance": self.cfg.lr_variance,
                                "illum": self.cfg.lr_illum}[g["name"]]
        if "gen" in st and self.device.type == "cpu":
            self.gen.set_state(st["gen"])


def load_checkpoint(run: Path, map_location="cpu") -> dict:
    """Read a run's checkpoint; one clear error if it is missing or unreadable."""
    path = Path(run) / CKPT_NAME
    if not path.is_file():
        raise FastneusError("no checkpoint in this run folder (train first)", file=str(path))
    try:
        return torch.load(path, map_location=map_location, weights_only=False)
    except Exception as e:  # noqa: BLE001 - a corrupt file must not become a traceback
        raise FastneusError(f"unreadable checkpoint: {type(e).__name__}: {e}", file=str(path)) from None


def trainer_from_run(scene, run: Path, device: str, cfg: Config | None = None) -> Trainer:
    """Rebuild a trainer (field, grid, illumination) from a run folder's checkpoint."""
    st = load_checkpoint(run, map_location=device)
    cfg = cfg or config_from_dict(st["config"], str(Path(run) / CKPT_NAME))
    tr = Trainer(scene, cfg, Path(run), device)
    tr.load_state(st)
    return tr
