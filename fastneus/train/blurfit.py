"""``camera_blur=auto``: the camera's blur estimated by rendering the training rays through
patterns blurred by candidate sigmas (fastneus.train.camblur applies it; this module picks it).

The rendered colour is linear in the illumination, so for each candidate blur the best i_r, i_b
come in closed form (:func:`fit_illumination`) and the candidates compare by the residual left
(:func:`pick_sigma`); :func:`estimate_blur_by_render` does it on the trainer's field.
"""
from __future__ import annotations

import numpy as np
import torch

AUTO_SIGMAS = (0.0, 0.25, 0.5, 0.75, 1.0, 1.5)  # candidate blurs (camera px) tried by camera_blur=auto
AUTO_RAYS = 4096  # training rays rendered per candidate (CPU: ~4 s a round on 2 cores)
AUTO_OFF = 0.15  # px: an estimate below this is a sharp camera (the blur stays off, the run unchanged)
_NEAR = 0.05  # share of the widest candidate's light (99th pct.) that marks a line's neighbourhood
_SAT = 0.98  # a photo value at or above this (linear) is left out of the fit (clipped by the camera)


def fit_illumination(y: np.ndarray, c0: np.ndarray, a: np.ndarray, b: np.ndarray, iters: int = 6,
                     eps: float = 0.005, score: np.ndarray | None = None) -> tuple[float, float, float]:
    """Closed-form i_r, i_b of ``y ~ c0 + i_b * a + i_r * b``, robust (L1 by reweighted least squares).

    The rendered colour is linear in the illumination: with the field fixed, a sample's colour is
    ``D + (i_r D + i_b) Q`` (fastneus.kernels.render; Q the projected light), so a pixel is
    ``c0 + i_b * a + i_r * b`` with ``c0`` the render at i_r = i_b = 0 (D composited, plus what
    the rig adds, e.g. the background), ``a`` the composited Q and ``b`` the composited D Q.

    Args:
        y: [N] photo values (linear; every channel of every ray, saturated ones already left out).
        c0: [N] render with i_r = i_b = 0; a: [N] render with i_b = 1 minus c0; b: [N] render
            with i_r = 1 minus c0.
        iters: reweighting rounds (weights 1 / max(|r|, eps): an L1 fit like the training loss).
        eps: least residual in the weights.
        score: [N] bool, the values whose mean |residual| is returned (None: all).
    Returns:
        (i_r, i_b, residual): the fit (each >= 1e-4) and the mean |y - fit| over ``score``.
    """
    y, c0, a, b = (np.asarray(v, dtype=np.float64).ravel() for v in (y, c0, a, b))
    t = y - c0
    X = np.stack([a, b], 1)  # [N, 2]
    w = np.ones_like(t)
    coef = np.array([0.1, 0.4])
    for _ in range(max(1, iters)):
        Xw = X * w[:, None]
        G = X.T @ Xw + 1e-9 * np.eye(2)
        coef = np.linalg.solve(G, Xw.T @ t)
        coef = np.maximum(coef, 1e-4)  # the light is positive (a clamped coordinate: refit the other)
        if coef[0] == 1e-4 or coef[1] == 1e-4:
            k = 1 if coef[0] == 1e-4 else 0
            r0 = t - X[:, 1 - k] * coef[1 - k]
            coef[k] = max(1e-4, float((Xw[:, k] @ r0) / max(1e-12, float(Xw[:, k] @ X[:, k]))))
        r = t - X @ coef
        w = 1.0 / np.maximum(np.abs(r), eps)
    err = np.abs(t - X @ coef)
    if score is not None and np.any(score):
        err = err[np.asarray(score, dtype=bool).ravel()]
    return float(coef[1]), float(coef[0]), float(np.mean(err))


def pick_sigma(sigmas, residuals) -> float:
    """The blur of least residual: the grid's best, refined by a parabola through it and its
    neighbours when it is inside the grid (clipped to the neighbours' interval).

    Args:
        sigmas: [M] increasing candidate blurs; residuals: [M] their fit residuals.
    Returns:
        The blur (>= 0).
    """
    s, r = np.asarray(sigmas, dtype=np.float64), np.asarray(residuals, dtype=np.float64)
    k = int(np.argmin(r))
    if k == 0 or k == len(s) - 1:
        return float(s[k])
    x, y = s[k - 1:k + 2], r[k - 1:k + 2]
    c = np.polyfit(x, y, 2)
    if c[0] <= 0:
        return float(s[k])
    return float(np.clip(-c[1] / (2 * c[0]), x[0], x[2]))


class _FieldOnce:
    """A field that evaluates its first ``sdf_and_grad`` / ``color`` call and returns the same
    results after (the estimate renders one set of samples many times: only the patterns change)."""

    def __init__(self, field):
        self._field, self._geo, self._col = field, None, None

    def sdf_and_grad(self, x, with_curvature: bool = False):
        if self._geo is None:
            self._geo = self._field.sdf_and_grad(x, with_curvature=with_curvature)
        return self._geo

    def color(self, *args):
        return self.shade(*args)[0]

    def shade(self, *args):
        if self._col is None:
            self._col = self._field.shade(*args)
        return self._col

    def __getattr__(self, name):
        return getattr(self._field, name)


def march_capped(tr, batch: dict, max_samples: int | None = None) -> tuple[dict, dict]:
    """March a no-gradient batch of training rays, keeping its sample count within a few
    training steps' worth: rays are dropped (from the end) until the samples fit.

    A diagnostic batch is drawn at a fixed ray count while the training steps adapt theirs to
    ``rays.target_samples``; early in a run, when the occupancy grid is still loose, 16384 rays
    marched to ~10^7 samples (a 31-GB allocation on the H100).

    Args:
        tr: the trainer (grid, config). batch: :meth:`RayBank.sample` dict after the rig.
        max_samples: the cap (None: 4 x ``rays.target_samples``).
    Returns:
        (batch, samples): the batch, cut to the rays marched, and :func:`march_samples`' dict.
    """
    from fastneus.field.renderer import march_samples

    cfg = tr.cfg
    cap = 4 * int(cfg.rays.target_samples) if max_samples is None else int(max_samples)
    while True:
        smp = march_samples(tr.grid.bits, tr.grid.resolution, batch["origins"], batch["dirs"], cfg, jitter=False)
        n = int(batch["origins"].shape[0])
        if smp["n_samples"] <= cap or n <= 64:
            return batch, smp
        keep = max(64, int(n * 0.9 * cap / smp["n_samples"]))
        batch = {k: (v[:keep] if torch.is_tensor(v) and v.dim() > 0 and v.shape[0] == n else v) for k, v in batch.items()}


def diagnostic_batch(tr, n_rays: int, salt: int, bright_fraction: float = 0.0) -> tuple[dict, dict]:
    """A no-gradient batch of training rays for an in-run estimate, marched (:func:`march_capped`).

    Drawn with a generator of its own (seeded by the run's seed and ``salt``), so the run's random
    stream is untouched; at most 16 training steps' rays (``rays.max_rays``), so a small run's
    estimate stays small.

    Args:
        tr: the trainer. n_rays: rays wanted. salt: tells one estimate's stream from another's.
        bright_fraction: share of rays drawn by pixel brightness.
    Returns:
        (batch, samples) as :func:`march_capped`.
    """
    gen = torch.Generator(device=tr.device)
    gen.manual_seed(int(tr.cfg.run.seed) * 7919 + salt)
    n = min(int(n_rays), 16 * tr.cfg.rays.max_rays)
    return march_capped(tr, tr.rig.rays(tr.bank.sample(n, gen, bright_fraction=bright_fraction)))


def estimate_blur_by_render(tr, sigmas=AUTO_SIGMAS, n_rays: int = AUTO_RAYS) -> dict:
    """``camera_blur=auto``: the blur whose blurred patterns best explain the photos, by rendering.

    With no gradient, one batch of training rays (drawn with a generator of its own, so the run's
    random stream is untouched) is marched once and rendered with the trainer's field and
    projection, the pattern images blurred by each candidate sigma (camera px, as
    ``rays.camera_blur``). For each, i_r and i_b are refit in closed form
    (:func:`fit_illumination`; the rendered colour is linear in them) and the robust residual
    kept, measured where the projected light reaches (the composited light of the widest candidate
    above ``_NEAR`` of its 99th percentile: the lines and their flanks, where the candidates
    differ); the least residual's sigma (:func:`pick_sigma`) is the estimate. Refitting the
    illumination per candidate is what makes this work: a too-sharp pattern is otherwise
    explained by a lower i_r (the bias this corrects), not by a larger residual.

    Args:
        tr: the :class:`fastneus.train.trainer.Trainer` (its field, grid, rig, bank, exposure gains).
        sigmas: the candidate blurs, increasing, starting at 0.
        n_rays: rays in the batch (:func:`diagnostic_batch`: at most 16 x ``rays.max_rays``).
    Returns:
        {"sigma", "fit_i_r", "fit_i_b" (the closed-form fit at sigma: low while the field is not
        aligned, a diagnostic), "sigmas", "residuals", "rays", "seconds"}; sigma
        is 0 when nothing was rendered or the estimate is below :data:`AUTO_OFF`.
    """
    import dataclasses
    import time

    from fastneus.field.renderer import shade_samples
    from fastneus.train import losses

    t_start = time.perf_counter()
    cfg, dev = tr.cfg, tr.device
    info = {"sigma": 0.0, "sigmas": [float(s) for s in sigmas], "residuals": [], "rays": 0}
    with torch.no_grad():
        batch, smp = diagnostic_batch(tr, n_rays, 17, bright_fraction=max(0.5, cfg.rays.bright_fraction))
        if smp["n_samples"] == 0 or not tr.proj.has_pattern:
            info["seconds"] = round(time.perf_counter() - t_start, 3)
            return info
        cos = tr.cos_anneal()
        field = _FieldOnce(tr.field)  # one field evaluation for every render below

        def render(proj, i_r: float, i_b: float) -> torch.Tensor:
            """[N, 3] on the device (read back together below: one host sync, not one per render)."""
            ir = torch.full((1,), float(i_r), device=dev)
            ib = torch.full((1,), float(i_b), device=dev)
            out = shade_samples(field, smp, proj, batch["origins"], batch["dirs"], batch["fidx"], cfg,
                                i_r=ir, i_b=ib, cos_anneal=cos)
            pred = tr.rig.composite(out["color"], out, cfg.rays.background)
            if tr.log_gain is not None:
                pred = pred * losses.exposure_gain(tr.log_gain, batch["fidx"])
            return pred

        def candidate(s: float) -> tuple[torch.Tensor, torch.Tensor]:
            """The renders with i_b = 1 and with i_r = 1 through the patterns blurred by ``s`` (on a
            GPU the candidates were built before the clock: Trainer.prime)."""
            proj = tr.rig.projection(dataclasses.replace(tr.proj, store=tr.blurred_store(s, keep=True)))
            return render(proj, 0.0, 1.0), render(proj, 1.0, 0.0)

        dev_renders = [render(tr.rig.projection(), 0.0, 0.0)] + [r for s in sigmas for r in candidate(s)]
        host = torch.stack(dev_renders).double().cpu()  # [1 + 2 M, N, 3]
        c0 = host[0]
        y = batch["rgb"].double().cpu().expand_as(c0)
        keep = y < _SAT
        if batch.get("sat") is not None:
            keep &= ~batch["sat"].cpu().expand_as(c0)
        y, c0n = y[keep].numpy(), c0[keep].numpy()
        info["rays"] = int(batch["rgb"].shape[0])

        def parts(ib: torch.Tensor, ir: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
            """(a, b) of :func:`fit_illumination` from a candidate's two renders (host, float64)."""
            return (ib - c0)[keep].numpy(), (ir - c0)[keep].numpy()

        ab = {float(s): parts(host[1 + 2 * k], host[2 + 2 * k]) for k, s in enumerate(sigmas)}
        wide = ab[float(max(sigmas))][0]
        near = wide > _NEAR * max(1e-6, float(np.percentile(wide, 99))) if wide.size else None

        def fit(s: float) -> tuple[float, float, float]:
            a, b = ab[float(s)] if float(s) in ab else parts(*(r.double().cpu() for r in candidate(s)))
            return fit_illumination(y, c0n, a, b, score=near)

        fits = [fit(s) for s in sigmas]
        info["residuals"] = [round(f[2], 6) for f in fits]
        s = pick_sigma(sigmas, [f[2] for f in fits])
        if s < AUTO_OFF:
            s = 0.0
        k = int(np.argmin(np.abs(np.asarray(sigmas) - s)))
        i_r, i_b, _ = fits[k] if abs(sigmas[k] - s) < 1e-9 else fit(s)
    info.update(sigma=round(s, 3), fit_i_r=round(i_r, 4), fit_i_b=round(i_b, 4),
                seconds=round(time.perf_counter() - t_start, 3))
    return info
