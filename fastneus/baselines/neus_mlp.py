"""Paper-faithful ActiveNeuS reference in plain torch (the speed comparison's baseline).

What the paper (Ichimaru et al., 3DV 2024) builds on NeuS (Wang et al., NeurIPS 2021):

- SDF MLP: 8 hidden layers x 256, positional encoding of x (6 frequencies, input included),
  skip connection (input concatenated, / sqrt 2) at layer 4, geometric (sphere) init,
  Softplus(beta=100), weight normalisation, output sdf + a 256-d feature.
- Colour MLP D: 4 hidden layers x 256 on [x, PE_4(view dir), normal, feature], ReLU, sigmoid.
- NeuS variance: learned v (init 0.3), inv_s = exp(10 v).
- Normals by autograd (create_graph=True, so the eikonal loss trains through them).
- Sampler: 64 stratified samples in [near, far] of the unit sphere plus 64 hierarchical ones
  (NeuS up-sampling, 4 steps of 16 with inv_s = 64 * 2^i), 512 rays per batch.
- Adam lr 5e-4, linear warm-up over 5000 steps then cosine decay to 0.05x at 200k steps;
  eikonal weight 0.1; cos-anneal over 50k steps; i_r, i_b learned after 5000 steps.

The pattern-projection colour formula, NeuS alpha and compositing are *literally* fastneus's:
the 128 samples per ray are packed into the packed-sample layout (offsets / counts /
ray_index / t0 / t1) and fed to :func:`fastneus.kernels.render.render_pattern_torch`. Rays and
projector data come from :class:`fastneus.train.rays.RayBank` (uniform pixels, as the paper)
and :func:`fastneus.train.rays.build_projection`. Only the model and the sampler differ from
fastneus, so meshing and evaluation (``fastneus.export``) are shared unchanged.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn

from fastneus.config import check, coerce, knob
from fastneus.errors import FastneusError
from fastneus.kernels.render import render_pattern_torch
from fastneus.train.rays import RayBank, build_projection
from fastneus.train.guard import finite_step


@dataclass(frozen=True)
class BaselineConfig:
    """Knobs of the reference ActiveNeuS (defaults = the paper / NeuS values), parsed and checked by
    the same code as the run config (:func:`fastneus.config.coerce`, :func:`fastneus.config.check`)."""

    seed: int = knob(0, "random seed", lo=0, hi=2 ** 32 - 1)
    frames: list[int] | None = knob(None, "training frames (null = all)")
    # rays and samples
    n_rays: int = knob(512, "rays per step", lo=1)
    n_samples: int = knob(64, "stratified samples per ray", lo=1)
    n_importance: int = knob(64, "hierarchical samples per ray", lo=0)
    up_sample_steps: int = knob(4, "NeuS up-sampling rounds (n_importance / steps each)", lo=1)
    perturb: bool = knob(True, "jitter the stratified samples")
    bound: str = knob("sphere", "for meshing (the sampler always uses the unit sphere)", choices=("sphere", "box"))
    background: float = knob(0.0, "background colour", lo=0.0, hi=1.0)
    eval_chunk: int = knob(2048, "cap on rays per chunk when rendering images (memory)", lo=1)
    # networks
    multires: int = knob(6, "positional-encoding frequencies of x", lo=0, hi=16)
    multires_view: int = knob(4, "positional-encoding frequencies of the view direction", lo=0, hi=16)
    sdf_hidden: int = knob(256, "SDF MLP width", lo=1)
    sdf_layers: int = knob(8, "SDF MLP layers", lo=1, hi=32)
    skip_in: tuple[int, ...] = knob((4,), "SDF layers that take the input again (skip connections)")
    feature_dim: int = knob(256, "geometry features passed to the colour MLP", lo=1)
    color_hidden: int = knob(256, "colour MLP width", lo=1)
    color_layers: int = knob(4, "colour MLP layers", lo=1, hi=32)
    weight_norm: bool = knob(True, "weight normalisation of the linear layers")
    init_radius: float = knob(0.5, "NeuS geometric-init bias", lo=0.0, hi=1.0, lo_open=True)
    variance_init: float = knob(0.3, "initial NeuS sharpness: inv_s = exp(10 v)", lo=-0.69, hi=1.38)
    # optimisation
    lr: float = knob(5e-4, "learning rate", lo=0.0, lo_open=True)
    warmup_steps: int = knob(5000, "linear lr warm-up steps", lo=0)
    end_steps: int = knob(200_000, "steps of the run", lo=1)
    decay_to: float = knob(0.05, "final lr factor", lo=0.0, hi=1.0, lo_open=True)
    eikonal_weight: float = knob(0.1, "eikonal term weight", lo=0.0)
    cos_anneal_steps: int = knob(50_000, "NeuS cos-anneal steps", lo=0)
    # projection / illumination
    use_pattern: bool = knob(True, "model the projected pattern (false = passive NeuS)")
    learn_illum: bool = knob(True, "learn i_r, i_b")
    illum_warmup_steps: int = knob(5000, "i_r, i_b frozen for these steps", lo=0)
    illum_init: str = knob("scene", "start i_r, i_b at the scene's values | ones", choices=("scene", "ones"))

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def baseline_config(overrides: dict | None = None) -> BaselineConfig:
    """Defaults with ``overrides`` (name -> value, or ``key=value`` strings' parsed values) applied."""
    known = {f.name: f for f in dataclasses.fields(BaselineConfig)}
    values = {}
    for k, v in (overrides or {}).items():
        if k not in known:
            raise FastneusError(f"unknown baseline config key; known: {', '.join(sorted(known))}", field=str(k))
        values[k] = coerce(known[k], v, "baseline config", k)
    cfg = BaselineConfig(**values)
    for f in dataclasses.fields(cfg):
        check(f, getattr(cfg, f.name), "baseline config", f.name)
    if cfg.n_importance % max(1, cfg.up_sample_steps):
        raise FastneusError("n_importance must be a multiple of up_sample_steps", field="n_importance")
    return cfg


def positional_encoding(x: torch.Tensor, n_freq: int) -> torch.Tensor:
    """NeuS/NeRF embedding [x, sin(2^k x), cos(2^k x)] for k < n_freq.

    Args:
        x: [N, 3].
    Returns:
        [N, 3 + 6 n_freq].
    """
    if n_freq <= 0:
        return x
    parts = [x]
    for k in range(n_freq):
        f = 2.0 ** k
        parts += [torch.sin(x * f), torch.cos(x * f)]
    return torch.cat(parts, -1)


class BaselineField(nn.Module):
    """NeuS SDF + colour MLPs (normalised space; the object in the unit sphere).

    Args:
        cfg: :class:`BaselineConfig`.
        device: torch device.
    """

    def __init__(self, cfg: BaselineConfig, device):
        super().__init__()
        self.cfg = cfg
        wn = torch.nn.utils.parametrizations.weight_norm if cfg.weight_norm else (lambda m: m)
        d_in = 3 + 6 * cfg.multires
        dims = [d_in] + [cfg.sdf_hidden] * cfg.sdf_layers + [1 + cfg.feature_dim]
        self.skip_in = set(cfg.skip_in)
        self.n_sdf = len(dims) - 1
        lins = []
        for l in range(self.n_sdf):
            # the layer feeding a skip outputs fewer channels: the input is concatenated after it
            out_dim = dims[l + 1] - d_in if (l + 1) in self.skip_in else dims[l + 1]
            lin = nn.Linear(dims[l], out_dim)
            # NeuS geometric initialisation: f(x) ~= |x| - radius at step 0
            if l == self.n_sdf - 1:
                nn.init.normal_(lin.weight, mean=math.sqrt(math.pi) / math.sqrt(dims[l]), std=1e-4)
                nn.init.constant_(lin.bias, -cfg.init_radius)
            elif l == 0 and cfg.multires > 0:
                nn.init.constant_(lin.bias, 0.0)
                nn.init.constant_(lin.weight[:, 3:], 0.0)
                nn.init.normal_(lin.weight[:, :3], 0.0, math.sqrt(2) / math.sqrt(out_dim))
            elif l in self.skip_in and cfg.multires > 0:
                nn.init.constant_(lin.bias, 0.0)
                nn.init.normal_(lin.weight, 0.0, math.sqrt(2) / math.sqrt(out_dim))
                nn.init.constant_(lin.weight[:, -(d_in - 3):], 0.0)
            else:
                nn.init.constant_(lin.bias, 0.0)
                nn.init.normal_(lin.weight, 0.0, math.sqrt(2) / math.sqrt(out_dim))
            lins.append(wn(lin))
        self.sdf_lins = nn.ModuleList(lins)
        self.softplus = nn.Softplus(beta=100)

        c_in = 3 + (3 + 6 * cfg.multires_view) + 3 + cfg.feature_dim
        cdims = [c_in] + [cfg.color_hidden] * cfg.color_layers + [3]
        self.color_lins = nn.ModuleList([wn(nn.Linear(cdims[i], cdims[i + 1])) for i in range(len(cdims) - 1)])
        self.variance = nn.Parameter(torch.tensor([cfg.variance_init]))
        self.to(device)

    def geometry(self, x: torch.Tensor) -> torch.Tensor:
        """[N, 3] -> [N, 1 + feature_dim]: sdf in column 0, the feature after."""
        inp = positional_encoding(x, self.cfg.multires)
        h = inp
        for l, lin in enumerate(self.sdf_lins):
            if l in self.skip_in:
                h = torch.cat([h, inp], -1) / math.sqrt(2)
            h = lin(h)
            if l < self.n_sdf - 1:
                h = self.softplus(h)
        return h

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        """[N, 3] -> [N] signed distance (normalised units)."""
        return self.geometry(x)[:, 0]

    def sdf_grad_feature(self, x: torch.Tensor, create_graph: bool = True):
        """SDF, autograd gradient and feature.

        Args:
            x: [N, 3] points (need not require grad).
            create_graph: keep the graph of the gradient (training: the eikonal loss and the
                colour net's normal input backpropagate through it).
        Returns:
            sdf [N], grad [N, 3], feature [N, feature_dim].
        """
        with torch.enable_grad():
            x = x.detach().requires_grad_(True)
            out = self.geometry(x)
            sdf = out[:, 0]
            grad, = torch.autograd.grad(sdf, x, torch.ones_like(sdf), create_graph=create_graph)
        return sdf, grad, out[:, 1:]

    def color(self, x: torch.Tensor, dirs: torch.Tensor, normal: torch.Tensor, feature: torch.Tensor) -> torch.Tensor:
        """D: [N, 3] points, [N, 3] unit view dirs, [N, 3] SDF gradients, [N, F] features -> [N, 3] in (0, 1)."""
        h = torch.cat([x, positional_encoding(dirs, self.cfg.multires_view), normal, feature], -1)
        for i, lin in enumerate(self.color_lins):
            h = lin(h)
            if i < len(self.color_lins) - 1:
                h = torch.relu(h)
        return torch.sigmoid(h)

    def inv_s(self) -> torch.Tensor:
        """[1] NeuS sharpness exp(10 v), clipped to [1e-6, 1e6] as NeuS does."""
        return torch.exp(self.variance * 10.0).clamp(1e-6, 1e6)


# ------------------------------------------------------------------------- NeuS sampler
def near_far(origins: torch.Tensor, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """NeuS ``near_far_from_sphere``: [mid - 1, mid + 1] around the ray point nearest the origin.

    Args:
        origins, dirs: [B, 3] (dirs unit length).
    Returns:
        near [B, 1], far [B, 1].
    """
    mid = -(origins * dirs).sum(-1, keepdim=True)
    return mid - 1.0, mid + 1.0


def sample_pdf(bins: torch.Tensor, weights: torch.Tensor, n: int) -> torch.Tensor:
    """Deterministic inverse-CDF sampling of NeuS (``det=True``).

    Args:
        bins: [B, M] interval ends; weights: [B, M - 1].
    Returns:
        [B, n] new sample positions.
    """
    weights = weights + 1e-5
    pdf = weights / weights.sum(-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), torch.cumsum(pdf, -1)], -1)
    u = torch.linspace(0.5 / n, 1.0 - 0.5 / n, n, device=bins.device).expand(cdf.shape[0], n).contiguous()
    inds = torch.searchsorted(cdf, u, right=True)
    below = (inds - 1).clamp_min(0)
    above = inds.clamp_max(cdf.shape[-1] - 1)
    g = torch.stack([below, above], -1)                              # [B, n, 2]
    shape = (cdf.shape[0], n, cdf.shape[-1])
    cdf_g = torch.gather(cdf.unsqueeze(1).expand(shape), 2, g)
    bins_g = torch.gather(bins.unsqueeze(1).expand(shape), 2, g)
    denom = cdf_g[..., 1] - cdf_g[..., 0]
    denom = torch.where(denom < 1e-5, torch.ones_like(denom), denom)
    t = (u - cdf_g[..., 0]) / denom
    return bins_g[..., 0] + t * (bins_g[..., 1] - bins_g[..., 0])


def up_sample(origins, dirs, z: torch.Tensor, sdf: torch.Tensor, n: int, inv_s: float) -> torch.Tensor:
    """One NeuS up-sampling round: weights from a fixed-``inv_s`` SDF-to-alpha, then ``n`` new samples.

    Args:
        origins, dirs: [B, 3]; z: [B, M] sorted sample depths; sdf: [B, M] at those depths.
    Returns:
        [B, n] new depths.
    """
    pts = origins[:, None, :] + dirs[:, None, :] * z[..., None]
    radius = pts.norm(dim=-1)
    inside = (radius[:, :-1] < 1.0) | (radius[:, 1:] < 1.0)
    prev_sdf, next_sdf = sdf[:, :-1], sdf[:, 1:]
    prev_z, next_z = z[:, :-1], z[:, 1:]
    mid_sdf = (prev_sdf + next_sdf) * 0.5
    cos_val = (next_sdf - prev_sdf) / (next_z - prev_z + 1e-5)
    prev_cos = torch.cat([torch.zeros_like(cos_val[:, :1]), cos_val[:, :-1]], -1)
    cos_val = torch.minimum(prev_cos, cos_val).clip(-1e3, 0.0) * inside
    dist = next_z - prev_z
    prev_cdf = torch.sigmoid((mid_sdf - cos_val * dist * 0.5) * inv_s)
    next_cdf = torch.sigmoid((mid_sdf + cos_val * dist * 0.5) * inv_s)
    alpha = (prev_cdf - next_cdf + 1e-5) / (prev_cdf + 1e-5)
    T = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1.0 - alpha + 1e-7], -1), -1)[:, :-1]
    return sample_pdf(z, alpha * T, n)


class BaselineTrainer:
    """Trains the reference ActiveNeuS with the interface of :class:`fastneus.train.trainer.Trainer`
    that the speed comparison and ``fastneus.export`` use.

    Args:
        scene: a loaded :class:`fastneus.data.Scene`.
        out: run folder (created; nothing is written by training itself).
        device: "cpu" or "cuda".
        **overrides: :class:`BaselineConfig` fields (e.g. ``n_rays=256``).
    """

    def __init__(self, scene, out: str | Path | None = None, device: str = "cpu", **overrides):
        self.cfg = baseline_config(overrides)
        c = self.cfg
        self.scene, self.device = scene, torch.device(device)
        self.out = Path(out) if out is not None else None
        if self.out is not None:
            self.out.mkdir(parents=True, exist_ok=True)
        torch.manual_seed(c.seed)
        np.random.seed(c.seed)
        n = len(scene.frames)
        self.frames = list(range(n)) if c.frames is None else list(c.frames)
        if not self.frames or any(not 0 <= f < n for f in self.frames):
            raise FastneusError(f"frame indices out of range 0..{n - 1}", field="frames")
        # uniform rays (bright_fraction = 0), as the paper
        self.bank = RayBank(scene, self.frames, self.device, brightness_cdf=False)
        self.proj = build_projection(scene, self.frames, self.device)
        self.field = BaselineField(c, self.device)
        ill = scene.illumination
        ir0, ib0 = (1.0, 1.0) if c.illum_init == "ones" or ill is None else (float(ill.i_r), float(ill.i_b))
        # same positive (log) parametrisation of i_r, i_b as fastneus
        self.log_ir = nn.Parameter(torch.tensor([math.log(max(ir0, 1e-4))], device=self.device))
        self.log_ib = nn.Parameter(torch.tensor([math.log(max(ib0, 1e-4))], device=self.device))
        self.opt = torch.optim.Adam([
            {"params": list(self.field.parameters()), "lr": c.lr, "name": "field"},
            {"params": [self.log_ir, self.log_ib], "lr": c.lr, "name": "illum"}])
        self.step = 0
        self.elapsed = 0.0
        self.skipped = 0
        self.gen = torch.Generator(device=self.device)
        self.gen.manual_seed(c.seed)

    # ------------------------------------------------------------------ helpers
    def illumination(self) -> tuple[torch.Tensor, torch.Tensor]:
        return self.log_ir.exp(), self.log_ib.exp()

    def cos_anneal(self) -> float:
        return 1.0 if self.cfg.cos_anneal_steps <= 0 else min(1.0, self.step / self.cfg.cos_anneal_steps)

    def _set_lr(self) -> None:
        """NeuS schedule: linear warm-up from 0, then cosine to ``decay_to`` at ``end_steps``."""
        c = self.cfg
        if self.step < c.warmup_steps:
            f = self.step / c.warmup_steps
        else:
            p = min(1.0, (self.step - c.warmup_steps) / max(1, c.end_steps - c.warmup_steps))
            f = (math.cos(math.pi * p) + 1.0) * 0.5 * (1 - c.decay_to) + c.decay_to
        learn_illum = c.learn_illum and c.use_pattern and self.step >= c.illum_warmup_steps
        for g in self.opt.param_groups:
            g["lr"] = (c.lr * f if learn_illum else 0.0) if g["name"] == "illum" else c.lr * f

    @torch.no_grad()
    def sample_depths(self, origins: torch.Tensor, dirs: torch.Tensor, perturb: bool) -> torch.Tensor:
        """NeuS sampler: stratified + hierarchical depths.

        Args:
            origins, dirs: [B, 3] normalised rays.
            perturb: one random shift per ray (training).
        Returns:
            [B, n_samples + n_importance] sorted depths.
        """
        c = self.cfg
        B = origins.shape[0]
        near, far = near_far(origins, dirs)
        z = near + (far - near) * torch.linspace(0.0, 1.0, c.n_samples, device=origins.device)[None]
        if perturb:
            z = z + (torch.rand(B, 1, device=origins.device, generator=self.gen) - 0.5) * 2.0 / c.n_samples
        if c.n_importance <= 0:
            return z
        pts = origins[:, None, :] + dirs[:, None, :] * z[..., None]
        sdf = self.field.sdf(pts.reshape(-1, 3)).reshape(B, -1)
        k = c.n_importance // c.up_sample_steps
        for i in range(c.up_sample_steps):
            new_z = up_sample(origins, dirs, z, sdf, k, 64.0 * 2 ** i)
            z, order = torch.sort(torch.cat([z, new_z], -1), -1)
            if i + 1 < c.up_sample_steps:
                p = origins[:, None, :] + dirs[:, None, :] * new_z[..., None]
                new_sdf = self.field.sdf(p.reshape(-1, 3)).reshape(B, k)
                sdf = torch.gather(torch.cat([sdf, new_sdf], -1), 1, order)
        return z

    def render_rays(self, origins: torch.Tensor, dirs: torch.Tensor, fidx: torch.Tensor, *, proj=None,
                    perturb: bool = True, create_graph: bool = True, cos_anneal: float | None = None,
                    with_normals: bool = False) -> dict:
        """NeuS sampling + field + fastneus's pattern-projection compositing (torch twin).

        Args:
            origins, dirs: [B, 3] normalised rays; fidx: [B] int32 row of ``proj``.
            proj: :class:`fastneus.train.rays.Projection` (default: the training frames').
        Returns:
            dict: color, texture [B, 3], opacity, depth [B], grad [S, 3], pos [S, 3], n_samples,
            and normal [B, 3] if ``with_normals``.
        """
        c = self.cfg
        proj = self.proj if proj is None else proj
        B = origins.shape[0]
        z = self.sample_depths(origins, dirs, perturb)                       # [B, M]
        M = z.shape[1]
        dists = torch.cat([z[:, 1:] - z[:, :-1], torch.full_like(z[:, :1], 2.0 / c.n_samples)], -1)
        mid = z + dists * 0.5
        pos = (origins[:, None, :] + dirs[:, None, :] * mid[..., None]).reshape(-1, 3)
        d_s = dirs[:, None, :].expand(B, M, 3).reshape(-1, 3)
        sdf, grad, feat = self.field.sdf_grad_feature(pos, create_graph=create_graph)
        color = self.field.color(pos, d_s, grad, feat)
        # the packed layout of fastneus (every ray holds M samples), so compositing is shared
        dev = origins.device
        counts = torch.full((B,), M, dtype=torch.int32, device=dev)
        offsets = torch.arange(B, dtype=torch.int32, device=dev) * M
        ray_index = torch.arange(B, dtype=torch.int32, device=dev).repeat_interleave(M)
        pat = proj.pattern if c.use_pattern else torch.full_like(proj.pattern, -1)
        i_r, i_b = self.illumination()
        ca = self.cos_anneal() if cos_anneal is None else cos_anneal
        out = render_pattern_torch(sdf, grad, color, pos, z.reshape(-1), (z + dists).reshape(-1), ray_index,
                                   offsets, counts, dirs, fidx.to(torch.int32), proj.K, proj.W, pat, proj.store,
                                   self.field.inv_s(), float(ca), i_r, i_b, return_weights=with_normals)
        res = dict(out)
        res.update(grad=grad, pos=pos, n_samples=B * M)
        if with_normals:
            w = out["weights"].detach()
            nrm = grad.detach() / grad.detach().norm(dim=-1, keepdim=True).clamp_min(1e-6)
            res["normal"] = (w[:, None] * nrm).reshape(B, M, 3).sum(1)
        return res

    # ------------------------------------------------------------------ one step
    def train_step(self) -> dict | None:
        """One optimisation step (NeuS losses). Returns detached scalars, or None if skipped."""
        c = self.cfg
        self._set_lr()
        batch = self.bank.sample(c.n_rays, self.gen, bright_fraction=0.0)
        out = self.render_rays(batch["origins"], batch["dirs"], batch["fidx"], perturb=c.perturb)
        pred = out["color"] + c.background * (1.0 - out["opacity"])[:, None]
        err = pred - batch["rgb"]
        # NeuS: L1 summed over channels, averaged over rays
        loss_rgb = err.abs().sum() / err.shape[0]
        relax = (out["pos"].norm(dim=-1) < 1.2).float()
        loss_eik = (((out["grad"].norm(dim=-1) - 1.0) ** 2) * relax).sum() / (relax.sum() + 1e-5)
        loss = loss_rgb + c.eikonal_weight * loss_eik
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        stepped = finite_step(self.opt, loss)  # NaN/Inf guard, shared with fastneus
        self.step += 1
        if not stepped:
            self.skipped += 1
            return None
        return {"loss": loss.detach(), "l1": loss_rgb.detach(), "mse": (err ** 2).mean().detach(),
                "eik": loss_eik.detach(), "spr": out["n_samples"] / c.n_rays, "samples": out["n_samples"]}

    # ------------------------------------------------------------------ rendering for evaluation
    def render_image_rays(self, origins: torch.Tensor, dirs: torch.Tensor, fidx: torch.Tensor, chunk: int = 1024,
                          proj=None) -> dict:
        """Render many rays in chunks (no training graph), like ``fastneus.field.renderer.render_image``.

        Args:
            origins, dirs: [N, 3] normalised rays; fidx: [N] int row of ``proj``.
            chunk: rays per chunk (each ray costs n_samples + n_importance MLP evaluations).
            proj: projector data of the frames ``fidx`` refers to (default: the training frames).
        Returns:
            dict of CPU tensors: color [N,3], texture [N,3], opacity [N], depth [N], normal [N,3].
        """
        keys = ("color", "texture", "opacity", "depth", "normal")
        chunk = max(1, min(chunk, self.cfg.eval_chunk))
        outs: dict[str, list[torch.Tensor]] = {k: [] for k in keys}
        for a in range(0, origins.shape[0], chunk):
            sl = slice(a, a + chunk)
            r = self.render_rays(origins[sl], dirs[sl], fidx[sl], proj=proj, perturb=False, create_graph=False,
                                 cos_anneal=1.0, with_normals=True)
            for k in keys:
                outs[k].append(r[k].detach().float().cpu())
        return {k: torch.cat(v) for k, v in outs.items()}
