"""One-shot depth on the lit pixels of a photo under thin projected lines (cross lasers).

A thin line pattern is no code: a red pixel may be lit by any of the red light sheets of any
projector (4 cross-laser projectors x 8 vertical lines = 32 sheets), and the window sweep of
:mod:`fastneus.classical.planesweep` finds no unique match. But along one camera ray, inside the
scene's bounds, only a few of those sheets are crossed, and the true one is among them:

1. Lit pixels per colour channel: the channel well above the pixel's darkest one (a grey
   albedo scales all channels alike; ambient light lifts them alike). A channel that this marks
   on more than ``max_share`` of the object is a coloured surface, not lines, and is skipped.
   (A weakly coloured or textured albedo that passes this is a known limit: tested on grey
   albedo only.)
2. Sub-pixel line centres: the lit channel's excess-weighted centroid over a 5 x 5 window. A ray
   through the centre of the imaged line meets the centre of the light sheet, so the depth is
   not blurred by the sheet's thickness (3 projector pixels are 1-4 % of depth at a 0.2-0.6 m
   baseline).
3. Candidates: the pattern channel sampled along that ray at ``n_depths`` points of its chord
   through the bounds sphere, summed over the frame's projectors; every run of lit samples is a
   candidate at its intensity-weighted centre. A run longer than ``max_run`` of the chord means
   the sheet contains the ray (a sheet through the camera centre, e.g. the horizontal lines of a
   horizontal-baseline rig): that observation says nothing about depth and is dropped.
4. Labelling: an observation with one candidate is accepted. The others take the candidate
   nearest the median of the accepted neighbours (3 or more), when it is within a tolerance of it (relative
   depth) and every other candidate is farther than a margin; first along the same line
   (4 px: within 1 %, others beyond 5 %), then across to the neighbouring lines (12 px: 1.5 %,
   8 %). Candidates of one ray come from different projectors and lie tens of centimetres apart,
   so a smooth surface picks one. A label the wider neighbourhood disagrees with by more than
   ``outlier`` is dropped. Over 14 random toy scenes (400 px, the default 4-projector rig) this
   labels a median 56 % (11-67 %) of the red-lit pixels, median depth error <= 0.26 %, with a median
   0.3 % (at most 11 %) of labels on a wrong sheet (> 5 % off); a third stage at 24 px labelled
   ~20 % more pixels, with 6 % (at most 29 %) of them wrong.

``fastneus.train.geometry_init`` fits the SDF to these points (2-3 one-shot viewpoints lit by thin lines) and
keeps them as a prior; the pixels between the lines stay unconstrained by them. torch only.
"""
from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from fastneus.classical.planesweep import box_mean, lit_shares, photo_grid
from fastneus.geometry.projection import normalised_world_to_proj, pattern_at_points, pixel_rays, unit_sphere_chord


def sparse_line_frame(scene, i: int, max_lit: float = 0.3) -> bool:
    """Whether frame ``i`` is lit only by image projectors whose patterns light less than ``max_lit``
    of their pixels (thin lines, a grid, dots), at least one of them; never with grey photos.

    The labelling tells a line's sheet family by its colour (the red vertical and the green
    horizontal sheets of a cross laser); a monochrome camera's photo does not. Tried with lit
    pixels found against their darkest neighbours instead: 13-56 % of the labels were on a wrong
    sheet (toy, 200 px, three seeds; 0.5-4 % on the colour photos), so grey one-shot line frames
    start from the sphere."""
    if getattr(scene, "grey", False):
        return False
    shares = lit_shares(scene, i)
    return shares is not None and max(shares) < max_lit


@torch.no_grad()
def laser_line_depth(scene, i: int, n_depths: int = 1024, device="cpu", max_width: int = 480,
                     ratio: float = 2.5, min_level: float = 0.02, max_run: float = 0.2,
                     stages: tuple = ((4, 0.01, 0.05), (12, 0.015, 0.08)), outlier: float = 0.05,
                     max_share: float = 0.4, chunk: int = 2048
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera z-depth of the line-lit pixels of frame ``i`` (see the module docstring).

    Args:
        scene: the scene (frame ``i`` lit by image projectors with thin-line patterns).
        n_depths: samples along each ray's chord through the bounds sphere.
        device: torch device. max_width: wider photos are area-downsampled to this width.
        ratio, min_level: a channel is lit where it exceeds ``ratio`` x the pixel's darkest channel
            + ``min_level`` (0..1 scale).
        max_share: a channel lit on more than this share of the foreground is skipped (albedo).
        max_run: a lit run longer than this share of the chord drops the observation.
        stages: (radius in pixels, tol, margin as relative depths) of the neighbour labelling,
            run in turn, each until nothing changes.
        outlier: then drop a label farther than this (relative) from the mean of the other labels
            within the last stage's radius (0 = keep all).
        chunk: rays per batch.
    Returns:
        depth [h, w] float32 (world units, NaN where not accepted), uv [h, w, 2] float32 the
        sub-pixel image point (continuous pixel coordinates) whose ray has that depth, and K [3, 3]
        of that (possibly downsampled) pixel grid.
    """
    dev = torch.device(device)
    photo, msk, K = photo_grid(scene, i, max_width)
    img = torch.tensor(photo, dtype=torch.float32, device=dev) / 255.0                    # [H,W,3]
    H, W = img.shape[:2]
    fg = (torch.tensor(msk, device=dev) > 0.5) if msk is not None else (img.max(-1).values > 2 / 255.0)
    low = img.min(-1).values
    excess = (img - ratio * low[..., None] - min_level).clamp_min(0)                    # [H,W,3]
    c2w = scene.cam_to_world(i)
    # rays and candidates in the bounds' normalised space: the chord is through the unit sphere
    S = np.eye(4)
    S[:3, :3] *= float(scene.bounds.radius)
    S[:3, 3] = np.asarray(scene.bounds.center, dtype=np.float64)
    cam_z = torch.tensor(c2w[:3, 2], dtype=torch.float64, device=dev)  # optical axis (world = normalised)
    projs = []
    for pid, pat in scene.active_projectors(i):
        w2p = normalised_world_to_proj(np.linalg.inv(scene.proj_to_world(i, pid)), S)
        projs.append((torch.tensor(scene.pattern_image(pat), device=dev), scene.projectors[pid].K, w2p))
    used = [c for c in range(3) if any(int(p[..., c].max()) > 0 for p, _, _ in projs)]
    yy, xx = torch.meshgrid(torch.arange(H, device=dev, dtype=torch.float32) + 0.5,
                            torch.arange(W, device=dev, dtype=torch.float32) + 0.5, indexing="ij")
    depth = torch.full((H, W), math.nan, dtype=torch.float64, device=dev)
    uv = torch.stack([xx, yy], -1).clone()
    obs = []  # per channel: (v, u, cu, cv, candidate z [N, M] NaN-padded)
    for c in used:
        e = excess[..., c]
        lit = (e > 0) & fg
        # thin lines light a small share of the object: a channel "lit" over much of it is a
        # coloured albedo, and its "lines" would be labelled anywhere
        if not bool(lit.any()) or float(lit.sum()) > max_share * float(fg.sum()):
            continue
        e4 = (e * lit).reshape(1, 1, H, W)
        den = box_mean(e4, 5, 5).clamp_min(1e-12)
        cu = (box_mean(e4 * xx, 5, 5) / den)[0, 0]
        cv = (box_mean(e4 * yy, 5, 5) / den)[0, 0]
        v, u = torch.nonzero(lit, as_tuple=True)
        pu, pv = cu[v, u].double(), cv[v, u].double()
        o, dn = pixel_rays(K, c2w, torch.stack([pu, pv], -1), S)
        t0, t1 = unit_sphere_chord(o, dn)
        s = torch.linspace(0, 1, n_depths, device=dev, dtype=torch.float64)
        chan = [(pat[..., c:c + 1].contiguous(), Kp, w2p) for pat, Kp, w2p in projs]  # one channel, once
        cands = []
        for a in range(0, v.numel(), chunk):
            sl = slice(a, a + chunk)
            t = t0[sl, None] + s[None] * (t1[sl] - t0[sl])[:, None]                      # [n, D]
            X = (o[sl, None] + t[..., None] * dn[sl, None]).reshape(-1, 3)                 # [n * D, 3]
            q = sum(pattern_at_points(X, Kp, w2p, pat)[:, 0] for pat, Kp, w2p in chan)
            cands.append(_runs(q.reshape(t.shape), t, t1[sl] - t0[sl], max_run))
        # normalised distance along the ray -> camera z-depth in world units
        cz = torch.cat(cands) * float(scene.bounds.radius) * (dn @ cam_z)[:, None]
        obs.append((v, u, pu.float(), pv.float(), cz))
    # labelling: unique first, then by accepted neighbours, near ones first
    for radius, tol, margin in stages:
        while _label(depth, uv, obs, radius, tol, margin):
            pass
    if outlier > 0:  # a label its wider neighbourhood disagrees with (a wrong sheet, a mixed silhouette pixel)
        acc = torch.isfinite(depth)
        r = stages[-1][0]
        k = 2 * r + 1
        dz = torch.where(acc, depth, torch.zeros_like(depth)).reshape(1, 1, H, W)
        cnt = F.avg_pool2d(acc.double().reshape(1, 1, H, W), k, stride=1, padding=r)[0, 0] * k * k
        tot = F.avg_pool2d(dz, k, stride=1, padding=r)[0, 0] * k * k
        others = (tot - dz[0, 0]) / (cnt - 1).clamp_min(1)
        bad = acc & (cnt > 3) & ((depth - others).abs() > outlier * others)
        depth[bad] = math.nan
    return depth.float().cpu().numpy(), uv.cpu().numpy(), K


def _label(depth: torch.Tensor, uv: torch.Tensor, obs: list, radius: int, tol: float, margin: float,
           min_votes: int = 3) -> int:
    """One labelling pass (in place): accept unique observations, and ambiguous ones whose candidate
    nearest the median accepted depth within ``radius`` pixels (at least ``min_votes`` of them) is
    within ``tol`` of it while every other candidate is more than ``margin`` away (the median: one
    wrong neighbour must not carry a wrong sheet along a line). Returns how many were accepted."""
    H, W = depth.shape
    pad = F.pad(depth[None, None], (radius, radius, radius, radius), value=math.nan)[0, 0]
    off = torch.arange(-radius, radius + 1, device=depth.device)
    changed = 0
    for v, u, pu, pv, cz in obs:
        free = ~torch.isfinite(depth[v, u])
        if not bool(free.any()):
            continue
        unique = torch.isfinite(cz).sum(1) == 1
        take = free & unique
        amb = torch.nonzero(free & ~unique, as_tuple=True)[0]
        if amb.numel():
            win = pad[(v[amb, None, None] + radius + off[None, :, None]),
                      (u[amb, None, None] + radius + off[None, None, :])].reshape(amb.numel(), -1)
            votes = torch.isfinite(win).sum(1)
            m = win.nanmedian(1).values
            rel = ((cz[amb] - m[:, None]).abs() / m[:, None].clamp_min(1e-9)).nan_to_num(math.inf)
            rs, _ = rel.sort(1)
            second = rs[:, 1] if rs.shape[1] > 1 else torch.full_like(m, math.inf)
            ok = (votes >= min_votes) & (rs[:, 0] < tol) & (second > margin)
            take[amb[ok]] = True
        if bool(take.any()):
            m_all = torch.full((v.numel(),), math.nan, dtype=depth.dtype, device=depth.device)
            if amb.numel():
                m_all[amb] = m
            rel = ((cz - m_all[:, None]).abs()).nan_to_num(math.inf)
            best = cz.gather(1, rel.argmin(1, keepdim=True))[:, 0]
            z = torch.where(unique, torch.nan_to_num(cz, nan=0).sum(1), best)
            depth[v[take], u[take]] = z[take]
            uv[v[take], u[take]] = torch.stack([pu[take], pv[take]], -1)
            changed += int(take.sum())
    return changed


def _runs(q: torch.Tensor, t: torch.Tensor, chord: torch.Tensor, max_run: float, level: float = 0.3,
          max_cands: int = 8) -> torch.Tensor:
    """Candidate distances along rays: the q-weighted centre of every run of samples with q > level.

    Args:
        q: [n, D] pattern light along each ray; t: [n, D] the distances; chord: [n] chord lengths.
    Returns:
        [n, max_cands] float64 candidates (NaN-padded; all NaN when a run is longer than
        ``max_run`` x chord, or the ray has more than ``max_cands`` runs).
    """
    on = q > level
    start = on & ~torch.cat([torch.zeros_like(on[:, :1]), on[:, :-1]], 1)
    rid = torch.cumsum(start.long(), 1) * on                                                # 0 = off, 1.. = run
    n_runs = start.sum(1)
    R = max_cands + 1
    idx = rid.clamp(max=R - 1)
    w = q.double() * on
    sw = torch.zeros(q.shape[0], R, dtype=torch.float64, device=q.device).scatter_add_(1, idx, w)
    swt = torch.zeros_like(sw).scatter_add_(1, idx, w * t)
    length = torch.zeros_like(sw).scatter_add_(1, idx, on.double())
    dt = (t[:, -1] - t[:, 0]) / max(q.shape[1] - 1, 1)
    cz = (swt / sw.clamp_min(1e-12))[:, 1:]
    valid = torch.arange(1, R, device=q.device)[None] <= n_runs[:, None]
    cz = torch.where(valid, cz, torch.full_like(cz, math.nan))
    bad = ((length[:, 1:] * dt[:, None]) > max_run * chord[:, None]).any(1) | (n_runs > max_cands)
    cz[bad] = math.nan
    return cz
