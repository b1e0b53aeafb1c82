"""Rays -> packed samples -> field -> NeuS compositing with pattern projection.

The glue between the occupancy grid (marching), the field (torch MLPs over the Warp
hash grid) and the render kernel; used by training, rendering and evaluation alike.
"""
from __future__ import annotations

import functools

import torch

from fastneus.kernels import get_op
from fastneus.data.kinds import get_projector_kind


def _empty(n_rays: int, device, dtype=torch.float32, shots: int = 0) -> dict:
    z = lambda *s: torch.zeros(*s, device=device, dtype=dtype)  # noqa: E731
    return {"color": z(n_rays, shots, 3) if shots else z(n_rays, 3), "opacity": z(n_rays), "depth": z(n_rays), "texture": z(n_rays, 3),
            "normal": z(n_rays, 3), "grad": z(0, 3), "curv": None, "n_samples": 0}


@functools.lru_cache(maxsize=16)
def _identity_blur(n_proj: int, device) -> torch.Tensor:
    """[P, 1] unit taps (plain pattern sampling in ``project_pattern``), made once per device:
    the split pattern pass asks for it every step. Read-only: the op never writes its blur."""
    from fastneus.kernels.project import identity_blur

    return identity_blur(n_proj, device=device)


def pattern_pass_split(cfg, device) -> bool:
    """Whether the projected light is sampled in its own per-sample pass (``project_pattern``)
    rather than inside the render kernel's per-ray loop (``cfg.run.pattern_pass``; ``auto``: on
    CUDA, where a step has few rays of hundreds of samples each and the per-ray loop's chain
    of dependent pattern fetches left most of the GPU idle; on the CPU one thread walks many
    rays either way and the extra pass only adds memory traffic)."""
    mode = cfg.run.pattern_pass
    return mode == "split" or (mode == "auto" and torch.device(device).type == "cuda")


def march_samples(bits: torch.Tensor, grid_res: int, origins: torch.Tensor, dirs: torch.Tensor, cfg, *,
                  jitter: bool = True, stop: torch.Tensor | None = None, out=None) -> dict:
    """Samples of a batch of rays through the occupied cells (the step's one host sync: the
    packed sample count sizes the buffers).

    Args:
        bits: [R^3] uint8 occupancy bits; grid_res: R.
        origins, dirs: [B, 3] float32 normalised rays (dirs unit length).
        cfg: run config (march step, sample cap, bound, backend).
        jitter: random start offset per ray (training) or 0 (rendering).
        stop: None or [R^3] uint8 cells that end a ray (the grid's cells deep inside the surface).
        out: None, or a callable given the sample count that returns buffers to write the samples
            into (``march_rays``'s ``out``: a captured step's fixed buffers).
    Returns:
        dict: offsets [B] int32 (first sample of each ray), counts [B] int32, t0, t1 [S] float32
        (sample interval along the ray), ray_index [S] int32, n_samples S (int).
    """
    n = origins.shape[0]
    device = origins.device
    march = get_op("march_rays", cfg.run.backend)
    jit = torch.rand(n, device=device) if jitter else torch.zeros(n, device=device)
    offsets, counts, t0, t1, ray_index = march(origins, dirs, bits, grid_res, cfg.rays.march_step,
                                               cfg.rays.max_samples_per_ray, jit, cfg.rays.bound, 0.0, stop,
                                               out=out)
    return {"offsets": offsets, "counts": counts, "t0": t0, "t1": t1, "ray_index": ray_index,
            "n_samples": int(t0.shape[0])}


def march_samples_capped(bits: torch.Tensor, grid_res: int, origins: torch.Tensor, dirs: torch.Tensor, cfg,
                         out: tuple, *, stop: torch.Tensor | None = None) -> None:
    """:func:`march_samples` (jittered) into fixed buffers with no host sync (``march_rays_capped``:
    ``out`` = offsets, counts [B] int32, total [1] int32, t0, t1 [C] float32, ray_index [C] int32;
    the samples past the capacity C are dropped and ``total`` says so)."""
    march = get_op("march_rays_capped", cfg.run.backend)
    jit = torch.rand(origins.shape[0], device=origins.device)
    march(origins, dirs, bits, grid_res, cfg.rays.march_step, cfg.rays.max_samples_per_ray, jit, cfg.rays.bound, 0.0,
          stop, out=out)


def render_rays(field, bits: torch.Tensor, grid_res: int, proj, origins: torch.Tensor, dirs: torch.Tensor,
                fidx: torch.Tensor, cfg, *, i_r: torch.Tensor, i_b: torch.Tensor, cos_anneal: float,
                jitter: bool = True, with_normals: bool = False, curvature: bool = False,
                use_pattern: bool | None = None, extra_points: torch.Tensor | None = None) -> dict:
    """Render a batch of rays: :func:`march_samples` then :func:`shade_samples`.

    Args:
        field: :class:`fastneus.field.model.SDFField`.
        bits: [R^3] uint8 occupancy bits; grid_res: R.
        proj: :class:`fastneus.train.rays.Projection` (per-frame projector data).
        origins, dirs: [B, 3] float32 normalised rays (dirs unit length).
        fidx: [B] int32 row of ``proj`` (frame) per ray, or [B, K] for K shots of one viewpoint per ray
            (multi-shot: the samples and field are shared, the pattern term is rendered per shot).
        cfg: run config (march step, sample cap, bound, backend).
        i_r, i_b: [1] illumination (reflectance, bias).
        cos_anneal: NeuS cos-anneal ratio in [0, 1].
        jitter: random start offset per ray (training) or 0 (rendering).
        with_normals: also return per-ray weighted normals.
        curvature: also return the curvature residual per sample.
        use_pattern: override ``cfg.illum.use_pattern`` (False renders without projection).
        extra_points: [E, 3] normalised points whose SDF gradients are wanted too (the eikonal
            term's uniform points): evaluated in the same field call as the samples, so the hash
            grid and the MLP run once per step instead of twice.
    Returns:
        dict with color [B,3] ([B,K,3] for a [B,K] fidx), opacity [B], depth [B] (normalised t), texture [B,3],
        normal [B,3] (if asked), grad [S,3], curv [S] or None, n_samples (int); with
        ``extra_points``: grad_all [S + E, 3] (the samples' gradients, then the extra points'), sdf_extra
        [E] (the extra points' SDF).
    """
    smp = march_samples(bits, grid_res, origins, dirs, cfg, jitter=jitter)
    return shade_samples(field, smp, proj, origins, dirs, fidx, cfg, i_r=i_r, i_b=i_b, cos_anneal=cos_anneal,
                         with_normals=with_normals, curvature=curvature, use_pattern=use_pattern,
                         extra_points=extra_points)


def ray_min(values: torch.Tensor, ray_index: torch.Tensor, offsets: torch.Tensor, counts: torch.Tensor,
            backend: str = "warp") -> tuple[torch.Tensor, torch.Tensor]:
    """Each ray's smallest value over its samples, differentiable (the gradient goes to the
    sample that is the minimum: the first of equal ones). Samples outside every ray's
    ``[offsets, offsets + counts)`` (a captured step's padding, whose ray index is stale) are
    left out, with no host read (the index from the ``ray_argmin`` op, then a gather).

    Args:
        values: [S]; ray_index: [S] int32 ray of each sample; offsets, counts: [R] int32.
    Returns:
        ([R] the minimum, 0 for a ray without samples; [R] float, 1 where the ray has samples).
    """
    arg = get_op("ray_argmin", backend)(values, ray_index, offsets, counts).long()
    has = arg >= 0
    # gather, not values[arg]: the indexing's backward on CUDA sorts the indices and walks the
    # repeats one by one (every empty ray points at sample 0): 1.4 ms of a 5-ms step on an
    # H200 (perf note 32); gather's backward is a scatter-add, whose repeats add zeros
    m = values.gather(0, arg.clamp_min(0)) if values.shape[0] else torch.zeros(arg.shape, device=values.device)
    return torch.where(has, m, torch.zeros_like(m)), has.to(values.dtype)


def shade_samples(field, smp: dict, proj, origins: torch.Tensor, dirs: torch.Tensor, fidx: torch.Tensor, cfg, *,
                  i_r: torch.Tensor, i_b: torch.Tensor, cos_anneal: float, with_normals: bool = False,
                  curvature: bool = False, use_pattern: bool | None = None,
                  extra_points: torch.Tensor | None = None, lit: bool = False,
                  canonical_view: bool = False, min_sdf: bool = False) -> dict:
    """The field at the samples of :func:`march_samples` and their NeuS compositing with the
    projected light (arguments and result as :func:`render_rays`; ``lit``: also ``lit`` [B],
    the projected light (summed over channels and projectors) at each ray's rendered surface,
    weighted like its colour, without gradient; ``min_sdf``: also ``min_sdf`` [B], each ray's smallest
    SDF over its samples, with gradient, and ``has_samples`` [B] float, 0 for a ray with none,
    whose ``min_sdf`` is 0).

    The sample arrays may be longer than the rays use (a captured step's fixed-capacity
    buffers): samples past every ray's ``offsets + counts`` are evaluated but composite into no
    ray, and no host value is read here.
    """
    device = origins.device
    n = origins.shape[0]
    render = get_op("render_pattern", cfg.run.backend)
    offsets, counts, t0, t1, ray_index = smp["offsets"], smp["counts"], smp["t0"], smp["t1"], smp["ray_index"]
    s = int(t0.shape[0])
    if smp["n_samples"] == 0:
        res = _empty(n, device, shots=fidx.shape[1] if fidx.dim() == 2 else 0)
        if extra_points is not None:
            f_extra, _, res["grad_all"], _ = field.sdf_and_grad(extra_points)
            res["sdf_extra"] = f_extra.reshape(-1)
        if min_sdf:
            res["min_sdf"], res["has_samples"] = torch.zeros(n, device=device), torch.zeros(n, device=device)
        return res
    ri = ray_index.long()
    d_s = dirs[ri]
    pos = origins[ri] + d_s * ((t0 + t1) * 0.5)[:, None]
    if extra_points is None:
        sdf, geo, grad, curv = field.sdf_and_grad(pos, with_curvature=curvature)
    else:
        sdf, geo, grad_all, curv = field.sdf_and_grad(torch.cat([pos, extra_points]), with_curvature=curvature)
        sdf_extra = sdf[s:].reshape(-1)
        sdf, geo, grad = sdf[:s], geo[:s], grad_all[:s]
        curv = None if curv is None else curv[:s]
    # canonical_view: every sample's colour as seen along its own normal, the same for every photo
    # (a view-dependent colour network can otherwise stand in for a photo's exposure gain)
    d_col = -torch.nn.functional.normalize(grad, dim=-1) if canonical_view else d_s
    shade = getattr(field, "shade", None)  # D and the highlight e ([S] or None: network.highlight off)
    color, spec = shade(pos, grad, d_col, geo) if shade is not None else (field.color(pos, grad, d_col, geo), None)
    pattern_on = cfg.illum.use_pattern if use_pattern is None else use_pattern
    pat = proj.pattern if pattern_on else torch.full_like(proj.pattern, -1)
    blur, lights = getattr(proj, "blur", None), getattr(proj, "lights", None) or {}
    port, sigma = getattr(proj, "port", None), getattr(proj, "sigma", None)

    has_pattern = pattern_on and getattr(proj, "has_pattern", True)
    split = pattern_pass_split(cfg, device) and has_pattern

    def light(f: torch.Tensor, force: bool = False):
        """Projected light Q for frame rows ``f`` [B] computed apart (one thread per sample) and
        handed to the render kernel, or None: the render kernel samples the patterns itself
        (``force``: computed apart anyway, for :func:`shade_samples`' ``lit``)."""
        if blur is None and not lights and port is None and sigma is None and not split and not force:
            return None
        q_ext, b = None, blur
        if b is not None or port is not None or sigma is not None or has_pattern:
            if b is None:
                b = _identity_blur(pat.shape[1], device)
            q_ext = get_op("project_pattern", cfg.run.backend)(pos, ray_index, offsets, counts, f, proj.K, proj.W,
                                                           pat, proj.store, b, port=port, sigma=sigma)
        if pattern_on:  # emitter kinds (laser planes, ...): each kind's light op, in registration order
            for name, (on, packed) in lights.items():
                ql = get_projector_kind(name).light_op(cfg.run.backend)(pos, ray_index, offsets, counts, f, proj.W,
                                                                        on, packed)
                q_ext = ql if q_ext is None else q_ext + ql
        return q_ext

    shots = fidx[:, None] if fidx.dim() == 1 else fidx
    colors = []
    for k in range(shots.shape[1]):  # one render per shot over the same samples (weights are shared)
        f = shots[:, k].contiguous()
        q = light(f)
        out = render(sdf, grad, color, pos, t0, t1, ray_index, offsets, counts, dirs, f,
                     proj.K, proj.W, pat, proj.store, field.inv_s(), cos_anneal, i_r, i_b,
                     return_weights=(with_normals or lit or spec is not None) and k == 0, q_ext=q,
                     **({} if spec is None else {"spec": spec}))
        if k == 0:
            res = dict(out)
            if spec is not None:  # [R] each ray's rendered highlight (the weights held: a penalty on e alone)
                res["highlight"] = torch.zeros(n, device=device).index_add_(0, ri, out["weights"].detach() * spec)
            if lit:  # how brightly the projectors light where this ray's surface is (no gradient)
                with torch.no_grad():
                    q = light(f, force=True) if q is None else q.detach()
                    w = out["weights"].detach()
                    res["lit"] = torch.zeros(n, device=device) if q is None else \
                        torch.zeros(n, device=device).index_add_(0, ray_index.long(), w * q.sum(-1))
        colors.append(out["color"])
    if fidx.dim() == 2:
        res["color"] = torch.stack(colors, 1)
    res["grad"], res["curv"], res["n_samples"] = grad, curv, smp["n_samples"]
    if extra_points is not None:
        res["grad_all"], res["sdf_extra"] = grad_all, sdf_extra
    if min_sdf:
        res["min_sdf"], res["has_samples"] = ray_min(sdf.reshape(-1), ray_index, offsets, counts, cfg.run.backend)
    if with_normals:
        w = res["weights"].detach()
        nrm = grad.detach() / grad.detach().norm(dim=-1, keepdim=True).clamp_min(1e-6)
        res["normal"] = torch.zeros(n, 3, device=device).index_add_(0, ri, w[:, None] * nrm)
    return res


@torch.no_grad()
def render_image(field, bits, grid_res, proj, origins, dirs, fidx, cfg, *, i_r, i_b, chunk: int = 8192) -> dict:
    """Render many rays in chunks without gradients (full images for reports/eval).

    Args: as :func:`render_rays`; origins/dirs [N, 3], fidx [N].
    Returns:
        dict of CPU tensors: color [N,3], texture [N,3], opacity [N], depth [N], normal [N,3].
    """
    outs: dict[str, list[torch.Tensor]] = {k: [] for k in ("color", "texture", "opacity", "depth", "normal")}
    for a in range(0, origins.shape[0], chunk):
        sl = slice(a, a + chunk)
        r = render_rays(field, bits, grid_res, proj, origins[sl], dirs[sl], fidx[sl], cfg, i_r=i_r, i_b=i_b,
                        cos_anneal=1.0, jitter=False, with_normals=True)
        for k in outs:
            outs[k].append(r[k].detach().float().cpu())
    return {k: torch.cat(v) for k, v in outs.items()}
