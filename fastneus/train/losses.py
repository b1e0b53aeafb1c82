"""The training loss, one function per term (DESIGN: L1 colour + lambda eikonal + beta mask BCE,
plus fastneus's priors; the mask term also in a silhouette form, :func:`mask_silhouette`). Each
returns ``{name: weighted scalar}``; :func:`total` sums them in a fixed order. Adding a term: a
function here, its weight as a knob in the config's ``loss`` section, one line in
``Trainer.train_step``.
"""
from __future__ import annotations

import torch

# the order terms are summed in (fixed, so a run is reproducible bit for bit)
TERMS = ("rgb", "eikonal", "mask", "background", "foreground", "prior", "curvature", "hull", "highlight")


def penalty(err: torch.Tensor, robust: str = "l1", eps: float = 0.01) -> torch.Tensor:
    """Per-element photometric penalty of an absolute error (``loss.robust``).

    Args:
        err: absolute differences, any shape; robust: ``l1`` | ``charbonnier`` (sqrt(e^2 + eps^2) - eps:
            L1 with a smooth minimum) | ``huber`` (quadratic below ``eps``, L1 slope above) | ``cauchy``
            (eps log(1 + e / eps): grows only logarithmically, so large residuals the model cannot
            explain (highlights, speckle peaks) pull less); eps: ``loss.robust_eps``.
    Returns:
        Same shape as ``err``, in the units of L1 for errors much larger than ``eps``.
    """
    if robust == "l1":
        return err
    if robust == "charbonnier":
        return torch.sqrt(err * err + eps * eps) - eps
    if robust == "huber":
        return torch.where(err < eps, 0.5 * err * err / eps, err - 0.5 * eps)
    if robust == "cauchy":
        return eps * torch.log1p(err / eps)
    raise ValueError(f"unknown robust penalty {robust!r}")


def photometric(pred: torch.Tensor, target: torch.Tensor, robust: str = "l1", eps: float = 0.01,
                sat: torch.Tensor | None = None, saturated: str = "off") -> dict[str, torch.Tensor]:
    """Photometric error between rendered and photographed colour (L1 by default).

    Args:
        pred: [B, 3] or [B, K, 3] rendered colour (with the pattern, times the frame's exposure
            gain), clipped at 1 like the camera.
        target: same shape, the photo (linear).
        robust: ``loss.robust`` (:func:`penalty`); eps: ``loss.robust_eps``.
        sat: same shape, bool, the photo's channel is saturated (>= 254); None = none.
        saturated: ``loss.saturated``: ``onesided`` (a saturated channel says only "at least this
            bright": rendering brighter is no error), ``mask`` (pixels with a saturated channel are
            left out), ``off``.
    Returns:
        {"rgb": mean penalty} (weight 1: the loss's unit), and "mse" (for the log's PSNR, from the
        same difference, not summed).
    """
    diff = pred - target
    if sat is not None and saturated == "onesided":
        diff = torch.where(sat & (diff > 0), torch.zeros_like(diff), diff)
    err = diff.abs()
    pen = penalty(err, robust, eps)
    if sat is not None and saturated == "mask":
        keep = (~sat.any(-1, keepdim=True)).to(err.dtype).expand_as(err)
        n = keep.sum().clamp_min(1.0)
        return {"rgb": (pen * keep).sum() / n, "mse": ((err.detach() ** 2) * keep).sum() / n}
    return {"rgb": pen.mean(), "mse": (err.detach() ** 2).mean()}


def frame_log_gains(log_gain: torch.Tensor) -> torch.Tensor:
    """[F] log exposure gain of every training frame from the learned [F-1]: the first frame's is 0
    (its gain 1 is the anchor that keeps the colours' scale fixed)."""
    return torch.cat([log_gain.new_zeros(1), log_gain])


def exposure_gain(log_gain: torch.Tensor, fidx: torch.Tensor) -> torch.Tensor:
    """Per-ray exposure gain of each ray's frame, shaped to multiply a colour.

    Args:
        log_gain: [F-1] learned log-gains of the training frames after the first (:func:`frame_log_gains`).
        fidx: [B] or [B, K] int rows of the training frames.
    Returns:
        [B, 1] or [B, K, 1] gains.
    """
    # index_select, not [fidx]: every frame's gain is read by thousands of rays, and the
    # indexing's CUDA backward walks each index's repeats serially (perf note 32)
    g = frame_log_gains(log_gain).exp().index_select(0, fidx.reshape(-1).long())
    return g.view(*fidx.shape, 1)


def _mean(x: torch.Tensor, valid: torch.Tensor | None) -> torch.Tensor:
    """Mean of ``x`` [N], or over the entries where ``valid`` [N] (0/1) is 1 (padded buffers)."""
    return x.mean() if valid is None else (x * valid).sum() / valid.sum().clamp_min(1.0)


def eikonal(grads: torch.Tensor, weight: float, valid: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Eikonal term: the SDF gradient has unit length.

    Args:
        grads: [N, 3] SDF gradients (at the samples and at uniform points).
        weight: ``loss.eikonal_weight``.
        valid: [N] 0/1, the rows that count (a captured step pads its sample buffers); None: all.
    Returns:
        {"eikonal": weight * mean (|g| - 1)^2, "eik": the unweighted mean (for the log, not summed)}.
    """
    r = _mean((grads.norm(dim=-1) - 1.0) ** 2, valid)
    return {"eikonal": weight * r, "eik": r.detach()}


def mask_bce(opacity: torch.Tensor, mask: torch.Tensor, weight: float | torch.Tensor) -> dict[str, torch.Tensor]:
    """Binary cross-entropy of the rendered opacity against the object mask.

    Args:
        opacity: [B] accumulated opacity; mask: [B] in {0, 1}; weight: the scheduled mask weight
            (``Trainer.mask_weight_at``; a 0-d device tensor inside a captured step).
    """
    op = opacity.clamp(1e-3, 1 - 1e-3)
    return {"mask": weight * torch.nn.functional.binary_cross_entropy(op, mask)}


def mask_silhouette(min_sdf: torch.Tensor, has: torch.Tensor, opacity: torch.Tensor, mask: torch.Tensor,
                    weight: float | torch.Tensor, inv_s: torch.Tensor, kind: str,
                    core: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """The mask as a statement about where rays cross the surface, not about their opacity.

    A mask pixel's ray must enter the object somewhere (its smallest SDF along the ray is
    negative), a background pixel's ray must not (positive): ``inv_s * relu(min_sdf)`` and
    ``inv_s * relu(-min_sdf)``, zero once the ray is on the right side. The BCE on the opacity
    asks a grazing ray inside the silhouette for full opacity, which NeuS gives a short chord
    only at infinite sharpness: it pulls the surface outwards there (docs/benchmarks/mask-weight.md,
    "the inner outline"). ``inv_s`` (detached) makes the penalty the asymptote of the BCE on the
    wrong side (-log sigmoid(-s m) ~ s m), so the two pull alike where a part is missing.

    Args:
        min_sdf: [B] the smallest SDF over each ray's samples (0 where ``has`` is 0);
        has: [B] 1 where the ray has samples; opacity: [B]; mask: [B] in {0, 1};
        weight: the scheduled mask weight; inv_s: NeuS's sharpness (0-d);
        kind: ``sdf`` (both sides by the SDF) or ``mixed`` (mask pixels by the SDF, background
            pixels by the BCE on the opacity: nothing semi-transparent outside the silhouette);
        core: [B] in {0, 1}, or None: mask pixels well inside the outline (``loss.mask_core``),
            held by the BCE on the opacity instead (a ray through the middle of the body must be
            opaque: the hinge alone let the GPU preset open a pocket inside the realistic ant).
    """
    s = inv_s.detach().reshape(())
    rim = mask if core is None else mask * (1.0 - core)
    inside = rim * torch.relu(min_sdf) * has
    if kind == "sdf":
        r = (inside + (1.0 - mask) * torch.relu(-min_sdf) * has).mean() * s
    else:  # the background pixels as the no-mask background prior pushes them
        r = inside.mean() * s + background_free_space(opacity, 1.0 - mask, 1.0)["background"]
    if core is not None:
        r = r + foreground_opacity(opacity, mask * core, 1.0)["foreground"]
    return {"mask": weight * r}


def background_free_space(opacity: torch.Tensor, is_bg: torch.Tensor, weight: float) -> dict[str, torch.Tensor]:
    """One-sided prior without masks: background-coloured pixels are pushed to zero opacity,
    the others are free.

    Args:
        opacity: [B]; is_bg: [B] 1 where the photo equals the background colour;
        weight: ``loss.bg_weight`` times the ramp-in factor.
    """
    op = opacity.clamp(max=1 - 1e-3)
    return {"background": -(weight * (is_bg * torch.log1p(-op)).mean())}


def foreground_opacity(opacity: torch.Tensor, is_fg: torch.Tensor, weight: float) -> dict[str, torch.Tensor]:
    """One-sided prior without masks: pixels clearly brighter than the background are pushed to
    full opacity (the object is there), the others are free.

    Args:
        opacity: [B]; is_fg: [B] 1 where the photo is brighter than the background colour by
            ``loss.fg_threshold``; weight: the prior's weight.
    """
    op = opacity.clamp(min=1e-3)
    return {"foreground": -(weight * (is_fg * torch.log(op)).mean())}


def background_ramp(p: float, start_frac: float) -> float:
    """Ramp-in factor of the background prior: 0 at ``start_frac`` of the run, 1 from twice it.

    Args:
        p: training progress in [0, 1]; start_frac: ``loss.bg_start_frac`` (0 = full weight at once).
    Returns:
        The factor in [0, 1] (the caller applies the term only once ``p >= start_frac``).
    """
    return min(1.0, (p - start_frac) / start_frac) if start_frac > 0 else 1.0


def surface_prior(value: torch.Tensor, weight: float) -> dict[str, torch.Tensor]:
    """The decoded / swept surface kept as a fading prior.

    Args:
        value: [] scalar, ``SurfacePrior.loss`` of the field (fastneus.train.geometry_init).
        weight: the faded weight, :func:`prior_fade`.
    Returns:
        {"prior": weight * value}.
    """
    return {"prior": weight * value}


def prior_fade(p: float, weight: float, frac: float) -> float:
    """Weight of the surface prior at progress ``p``: ``init.prior_weight`` fading linearly to 0 at
    ``init.prior_frac`` of the run (the caller evaluates the prior only while ``p < frac``).

    Args:
        p: training progress; weight: ``init.prior_weight``; frac: ``init.prior_frac`` (> 0).
    """
    return weight * (1.0 - p / frac)


def curvature(curv: torch.Tensor, weight: float, valid: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Smoothness prior |f(x+e) + f(x-e) - 2 f(x)| (one-shot).

    Args:
        curv: [N] Laplacian-like residuals of the SDF at the samples; weight: ``loss.curvature_weight``.
        valid: [N] 0/1, the samples that count (padded buffers); None: all.
    """
    return {"curvature": weight * _mean(curv.abs(), valid)}


def highlight(rendered: torch.Tensor, weight: float) -> dict[str, torch.Tensor]:
    """L1 on the rendered highlight (``network.highlight``): what every lit pixel shares is i_b's
    (one scalar, free), so the highlight is left only where the photos are brighter than that.

    Args:
        rendered: [B] each ray's sum of w_i e_i (the weights held); weight: ``loss.highlight_weight``.
    Returns:
        {"highlight": weight * mean, "spec": the unweighted mean (for the log, not summed)}.
    """
    r = rendered.mean()
    return {"highlight": weight * r, "spec": r.detach()}


def total(terms: dict[str, torch.Tensor]) -> torch.Tensor:
    """Sum of the loss terms present in ``terms``, in :data:`TERMS` order (log-only entries skipped)."""
    out = None
    for name in TERMS:
        if name in terms:
            out = terms[name] if out is None else out + terms[name]
    if out is None:
        raise ValueError("no loss term")
    return out
