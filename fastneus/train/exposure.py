"""``exposure=auto``: whether the photos were taken at different exposures, decided from the data.

A camera in auto-exposure scales each photo by its own gain; a fixed-exposure rig does not, and
learning a gain per photo there only costs accuracy (4-10 % Chamfer on CPU test scenes). So at
``exposure_at_frac`` of the run one batch of training rays is rendered with the trainer's field
(no gradient, a generator of its own: the run's random stream is untouched), each photo's gain
against the render is fit in closed form (:func:`fit_frame_gains`), and the per-photo gains are
learned from then on only when they spread by more than :data:`SPREAD_ON` (their log's standard
deviation, with the fit's noise taken out: :func:`split_gain_spread`); they then start at the
fitted values. The decision is printed and saved (run.json,
checkpoint) like ``camera_blur``.
"""
from __future__ import annotations

import numpy as np

# std of the photos' log-gains above which they are learned (split_gain_spread; measured: docs/REAL-RIGS.md)
SPREAD_ON = 0.06
SPLITS = 4  # independent ray batches whose gain fits are compared (split_gain_spread)
AUTO_RAYS = 16384  # training rays rendered for the decision
_FLOOR = 0.01  # rendered values below this (linear) say little about a gain: left out
_SAT = 0.98  # photo values at or above this are clipped by the camera: left out
_MIN_VALUES = 30  # a photo with fewer usable values keeps gain 1 in the fit


def weighted_median(x: np.ndarray, w: np.ndarray) -> float:
    """The weighted median of ``x`` [N] with weights ``w`` [N] >= 0 (the minimiser of sum w |x - m|)."""
    o = np.argsort(x)
    c = np.cumsum(w[o])
    return float(x[o][min(len(x) - 1, int(np.searchsorted(c, 0.5 * c[-1])))])


def fit_frame_gains(y: np.ndarray, pred: np.ndarray, fidx: np.ndarray, n_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Each photo's gain against the render, robustly: argmin_g sum |y - g * pred| (an L1 fit, the
    training loss's), i.e. the pred-weighted median of y / pred over the photo's usable values.

    Args:
        y: [N, C] photo values (linear). pred: [N, C] rendered values at gain 1.
        fidx: [N] the training-frame row of each ray. n_frames: F.
    Returns:
        (log_gains [F] relative to frame 0 (0 for photos with too few values), counts [F]).
    """
    y, pred = np.asarray(y, np.float64), np.asarray(pred, np.float64)
    f = np.broadcast_to(np.asarray(fidx).reshape(-1, 1), y.shape)
    use = (pred > _FLOOR) & (y > 0) & (y < _SAT)
    y, pred, f = y[use], pred[use], f[use]
    logs, counts = np.zeros(n_frames), np.zeros(n_frames, dtype=np.int64)
    for k in range(n_frames):
        sel = f == k
        counts[k] = int(sel.sum())
        if counts[k] >= _MIN_VALUES:
            logs[k] = np.log(max(1e-6, weighted_median(y[sel] / pred[sel], pred[sel])))
    ok = counts >= _MIN_VALUES
    ref = logs[0] if ok[0] else (float(np.median(logs[ok])) if ok.any() else 0.0)
    return np.where(ok, logs - ref, 0.0), counts


def split_gain_spread(y: np.ndarray, pred: np.ndarray, fidx: np.ndarray, group: np.ndarray,
                      n_frames: int) -> tuple[float, np.ndarray, np.ndarray]:
    """How much the photos' gains differ, with most of the fit's own noise taken out.

    The gains are fit on each group of rows (independent ray batches); a true gain difference
    shows in every fit, the noise of each fit (few rays per photo early in a short run, speckle,
    a field that does not fit the photos yet) does not. The spread is sqrt(max(0, mean cov)) of
    the fits' log-gains over pairs of groups, over the photos with enough values in both (the
    plain spread when the noise is 0). CPU, 600-step runs at 20 %, four batches of ~3 k rays:
    one exposure 0-0.050 (rock, ant; Normal, Dark; masks or none; four draws each) where one
    fit's plain spread read 0.036-0.091; +-25 % exposures 0.106-0.173 (true 0.118).

    Args:
        y, pred: [N, C] photo and rendered values (linear). fidx: [N] training-frame row of each
            value row. group: [N] the batch (0, 1, ...) of each row. n_frames: F.
    Returns:
        (spread, log_gains [F] fit on all rows relative to the first photo, counts [F]).
    """
    logs, counts = fit_frame_gains(y, pred, fidx, n_frames)
    fits = [fit_frame_gains(y[group == k], pred[group == k], fidx[group == k], n_frames)
            for k in range(int(group.max()) + 1)]
    covs = []
    for i in range(len(fits)):
        for j in range(i + 1, len(fits)):
            ok = (fits[i][1] >= _MIN_VALUES) & (fits[j][1] >= _MIN_VALUES)
            if ok.sum() >= 2:
                a, b = fits[i][0][ok], fits[j][0][ok]
                covs.append(float(np.mean((a - a.mean()) * (b - b.mean()))))
    if not covs:
        return 0.0, logs, counts
    return float(np.sqrt(max(0.0, float(np.mean(covs))))), logs, counts


def estimate_exposure(tr, n_rays: int = AUTO_RAYS, canonical: bool = True) -> dict:
    """Fit every training photo's gain against the trainer's current render (no gradient).

    Args:
        tr: the :class:`fastneus.train.trainer.Trainer` (field, grid, rig, bank, illumination).
        n_rays: rays in each of the :data:`SPLITS` batches, uniform over the photos' pixels
            (:func:`fastneus.train.blurfit.diagnostic_batch`: at most 16 x ``rays.max_rays``).
        canonical: render every surface's colour as seen along its normal, one colour for all the
            photos that see it. By the decision the view-dependent colour network has fitted part
            of each photo's gain as a view effect (H200, rock +-25 %: the spread of the gains
            against the render 0.032-0.038 at 20 % of a 10-s run against 0.118 true, so the gains
            were never learned); the canonical render leaves it to the gains (0.110-0.115).
    Returns:
        {"spread": the batches' agreed spread of the log-gains (:func:`split_gain_spread`),
        "log_gains": [F] relative to the first photo (fit on all batches), "rays" (all batches),
        "seconds"}.
    """
    import time

    import torch

    from fastneus.field.renderer import shade_samples
    from fastneus.train.blurfit import diagnostic_batch

    t0 = time.perf_counter()
    cfg = tr.cfg
    n_frames = len(tr.frames)
    ys, preds, fids, groups, rays = [], [], [], [], 0
    with torch.no_grad():
        i_r, i_b = tr.illumination()
        proj, cos_anneal = tr.rig.projection(), tr.cos_anneal()
        for k in range(SPLITS):  # independent batches: their fits' noise differs, a true gain does not
            batch, smp = diagnostic_batch(tr, n_rays, 29 + k)
            if smp["n_samples"] == 0:
                continue
            out = shade_samples(tr.field, smp, proj, batch["origins"], batch["dirs"], batch["fidx"], cfg,
                                i_r=i_r, i_b=i_b, cos_anneal=cos_anneal, canonical_view=canonical)
            pred = tr.rig.composite(out["color"], out, cfg.rays.background).clamp(max=1.0)
            c = pred.shape[-1]  # multi-shot rays carry [B, K] frames: one value row per (ray, shot)
            rays += int(batch["rgb"].shape[0])
            ys.append(batch["rgb"].reshape(-1, c).cpu().numpy())
            preds.append(pred.reshape(-1, c).cpu().numpy())
            fids.append(batch["fidx"].reshape(-1).cpu().numpy())
            groups.append(np.full(fids[-1].shape[0], k))
    if not ys:
        return {"spread": 0.0, "log_gains": [0.0] * n_frames, "rays": 0, "seconds": round(time.perf_counter() - t0, 3)}
    spread, logs, _ = split_gain_spread(np.concatenate(ys), np.concatenate(preds), np.concatenate(fids),
                                        np.concatenate(groups), n_frames)
    return {"spread": round(spread, 5), "log_gains": [round(float(v), 5) for v in logs],
            "rays": rays, "seconds": round(time.perf_counter() - t0, 3)}
