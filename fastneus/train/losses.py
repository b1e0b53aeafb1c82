"""The training loss, one function per term (DESIGN: L1 colour + lambda eikonal + beta mask BCE,
plus fastneus's priors). Each returns ``{name: weighted scalar}``; :func:`total` sums them in a
fixed order. Adding a term: a function here, its weight as a knob in the config's ``loss``
section, one line in ``Trainer.train_step``.
"""
from __future__ import annotations

import torch

# the order terms are summed in (fixed, so a run is reproducible bit for bit)
TERMS = ("rgb", "eikonal", "mask", "background", "prior", "curvature")


def photometric(pred: torch.Tensor, target: torch.Tensor) -> dict[str, torch.Tensor]:
    """L1 between rendered and photographed colour.

    Args:
        pred: [B, 3] or [B, K, 3] rendered colour (with the pattern), clipped at 1 like the camera.
        target: same shape, the photo.
    Returns:
        {"rgb": mean |pred - target|} (weight 1: the loss's unit), and "mse" (for the log's PSNR,
        from the same difference, not summed).
    """
    err = (pred - target).abs()
    return {"rgb": err.mean(), "mse": (err.detach() ** 2).mean()}


def eikonal(grads: torch.Tensor, weight: float) -> dict[str, torch.Tensor]:
    """Eikonal term: the SDF gradient has unit length.

    Args:
        grads: [N, 3] SDF gradients (at the samples and at uniform points).
        weight: ``loss.eikonal_weight``.
    Returns:
        {"eikonal": weight * mean (|g| - 1)^2, "eik": the unweighted mean (for the log, not summed)}.
    """
    r = ((grads.norm(dim=-1) - 1.0) ** 2).mean()
    return {"eikonal": weight * r, "eik": r.detach()}


def mask_bce(opacity: torch.Tensor, mask: torch.Tensor, weight: float) -> dict[str, torch.Tensor]:
    """Binary cross-entropy of the rendered opacity against the object mask.

    Args:
        opacity: [B] accumulated opacity; mask: [B] in {0, 1}; weight: ``loss.mask_weight``.
    """
    op = opacity.clamp(1e-3, 1 - 1e-3)
    return {"mask": weight * torch.nn.functional.binary_cross_entropy(op, mask)}


def background_free_space(opacity: torch.Tensor, is_bg: torch.Tensor, weight: float) -> dict[str, torch.Tensor]:
    """One-sided prior without masks: background-coloured pixels are pushed to zero opacity,
    the others are free.

    Args:
        opacity: [B]; is_bg: [B] 1 where the photo equals the background colour;
        weight: ``loss.bg_weight`` times the ramp-in factor.
    """
    op = opacity.clamp(max=1 - 1e-3)
    return {"background": -(weight * (is_bg * torch.log1p(-op)).mean())}


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


def curvature(curv: torch.Tensor, weight: float) -> dict[str, torch.Tensor]:
    """Smoothness prior |f(x+e) + f(x-e) - 2 f(x)| (one-shot).

    Args:
        curv: [N] Laplacian-like residuals of the SDF at the samples; weight: ``loss.curvature_weight``.
    """
    return {"curvature": weight * curv.abs().mean()}


def total(terms: dict[str, torch.Tensor]) -> torch.Tensor:
    """Sum of the loss terms present in ``terms``, in :data:`TERMS` order (log-only entries skipped)."""
    out = None
    for name in TERMS:
        if name in terms:
            out = terms[name] if out is None else out + terms[name]
    if out is None:
        raise ValueError("no loss term")
    return out
