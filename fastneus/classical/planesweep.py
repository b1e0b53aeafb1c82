"""One-shot depth from a single structured-light photo: a plane sweep against the pattern.

For a dense one-shot pattern (the colourful line: random binary-colour stripes) each camera
pixel's neighbourhood is a code: the projector shows a different colour sequence at every
depth along the pixel's ray. The sweep tries ``n_depths`` camera z-depths across the scene's
bounds. At each depth it predicts what the projectors put on every pixel (the patterns,
pre-blurred by the camera pixel's footprint on the projector image, summed over the frame's
projectors). It scores the prediction against the photo by zero-mean normalised
cross-correlation (ZNCC) over a window, per colour channel. ZNCC ignores the unknown albedo's
gain and the ambient offset of each channel. Per pixel the best-scoring depth wins, refined by
a parabola through its neighbours. It is kept only when the score is high and clearly better
than the best score at any other depth (the pattern is random, so a wrong depth can match a
window too).

This is what the photometric optimisation cannot do from a sphere with one view: it searches
every depth at once instead of following a gradient into the nearest minimum (which, for a
striped pattern, is one stripe away). ``fastneus.train.geometry_init`` fits the SDF to these points
before training (``init_geometry=auto`` on one-shot scenes); the neural training then refines
them. torch only (CPU or GPU); one depth map per frame.
"""
from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from fastneus.data.kinds import get_projector_kind


def lit_shares(scene, i: int) -> list[float] | None:
    """Share of lit pixels of each pattern that lights frame ``i`` (one per active projector), or
    None when no projector is active or one of them shows no pattern image (a laser, ...)."""
    act = scene.active_projectors(i)
    if not act or any(not get_projector_kind(scene.projectors[pid].kind).images for pid, _ in act):
        return None
    return [float((scene.pattern_image(pat).max(axis=2) > 0).mean()) for _, pat in act]


def dense_pattern_frame(scene, i: int, min_lit: float = 0.3) -> bool:
    """Whether frame ``i`` is lit by image projectors whose patterns cover at least ``min_lit`` of
    their pixels (colourful lines, not sparse lines, grids or dots, and not laser planes)."""
    shares = lit_shares(scene, i)
    return shares is not None and min(shares) >= min_lit


def photo_grid(scene, i: int, max_width: int) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Frame ``i``'s photo [h, w, 3] uint8, mask [h, w] (or None) and K [3, 3], area-downsampled to
    ``max_width`` when wider (K scaled with the grid)."""
    import cv2

    photo = scene.image(i)
    msk = scene.mask(i)
    K = np.asarray(scene.frame_camera(i).K, dtype=np.float64).copy()
    if photo.shape[1] > max_width:
        f = max_width / photo.shape[1]
        size = (max_width, max(1, int(round(photo.shape[0] * f))))
        fx, fy = size[0] / photo.shape[1], size[1] / photo.shape[0]
        photo = cv2.resize(photo, size, interpolation=cv2.INTER_AREA)
        if msk is not None:
            msk = cv2.resize(msk.astype(np.float32), size, interpolation=cv2.INTER_AREA)
        K[0] *= fx  # continuous pixel coordinates scale with the grid
        K[1] *= fy
    return photo, msk, K


def _window_nanmedian(x: torch.Tensor, window: int) -> torch.Tensor:
    """Median of the finite values of x [H, W] in each ``window`` square (NaN where none)."""
    r = window // 2
    pad = F.pad(x[None, None], (r, r, r, r), value=math.nan)
    return F.unfold(pad, window)[0].nanmedian(0).values.reshape(x.shape)


def _window_range(x: torch.Tensor, r: int) -> torch.Tensor:
    """max - min of the finite values of x [H, W] in each (2 r + 1)^2 square."""
    hi = F.max_pool2d(torch.nan_to_num(x, nan=-math.inf)[None, None], 2 * r + 1, 1, r)[0, 0]
    lo = -F.max_pool2d(torch.nan_to_num(-x, nan=-math.inf)[None, None], 2 * r + 1, 1, r)[0, 0]
    return hi - lo


def box_mean(x: torch.Tensor, kh: int, kw: int) -> torch.Tensor:
    """Mean over a kh x kw window (edges: over the part inside), x [B, C, H, W]."""
    return F.avg_pool2d(x, (kh, kw), stride=1, padding=(kh // 2, kw // 2), count_include_pad=False)


@torch.no_grad()
def planesweep_depth(scene, i: int, n_depths: int = 256, window: tuple[int, int] | None = None,
                     min_score: float = 0.6, min_margin: float = 0.05, device="cpu",
                     chunk: int = 16, max_width: int = 480, refine: int = 13, edge_radius: int | None = None,
                     edge_jump: float = 0.02) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera z-depth of frame ``i`` by a plane sweep against its projected patterns.

    Args:
        scene: the scene (frame ``i`` lit by one or more image projectors).
        n_depths: depth hypotheses, uniform in z across the bounds sphere.
        window: (rows, cols) of the ZNCC window; default 7 x 7 up to 400 px, then with the width.
        min_score: smallest accepted ZNCC (mean over the informative channels).
        min_margin: smallest lead of the best score over the best score farther than 3 depth
            steps away (uniqueness).
        device: torch device for the sweep. chunk: depths per batch.
        max_width: wider photos are swept at this width (area-downsampled; the score volume is
            n_depths x H x W floats, and an initialisation needs no more).
        refine: hypotheses of the second, per-pixel sweep across +-1.5 steps around each winner
            (0: none).
        edge_radius, edge_jump: pixels within ``edge_radius`` of a relative depth jump over
            ``edge_jump``, and the object's outermost pixel ring, are dropped (0: keep them;
            default: 1 pixel per 200 of width, like the window).
    Returns:
        depth [h, w] float32 (world units, NaN where rejected), score [h, w] float32, and K [3, 3]
        of that (possibly downsampled) pixel grid.
    """
    import cv2

    if refine != 0 and refine < 3:
        raise ValueError(f"refine must be 0 (off) or at least 3 hypotheses, got {refine}")
    dev = torch.device(device)
    photo, msk, K = photo_grid(scene, i, max_width)
    img = torch.tensor(photo, dtype=torch.float32, device=dev).permute(2, 0, 1)[None] / 255.0  # [1,3,H,W]
    H, W = img.shape[-2:]
    c2w = scene.cam_to_world(i)
    s = max(1.0, W / 200.0)
    if window is None:
        # 7 x 7 up to 400 px, then with the width (the sweep runs at most max_width wide). Scaled from
        # 200 px (13 x 13 at 400 px) it mixed thin parts with what lies behind them: 400-px colourful
        # lines, one photo, ideal / realistic: coverage toy 60 / 51 -> 65 / 54 %, rock 63 / 59 ->
        # 72 / 65 %, airplane 47 / 31 -> 68 / 56 %, no less accurate (docs/benchmarks/oneshot-realistic-cpu.md)
        wn = 2 * round(3 * max(1.0, W / 400.0)) + 1
        window = (wn, wn)
    if edge_radius is None:
        edge_radius = round(s)
    kh, kw = window
    # the depth range: the bounds sphere along the optical axis
    ctr = np.linalg.inv(c2w) @ np.r_[np.asarray(scene.bounds.center, dtype=np.float64), 1.0]
    r = float(scene.bounds.radius)
    z0, z1 = max(float(ctr[2]) - r, 1e-3), float(ctr[2]) + r
    zs = torch.linspace(z0, z1, n_depths, dtype=torch.float64, device=dev)
    # camera rays at z = 1 in the camera frame, as world points X(z) = C + z * Rd
    v, u = torch.meshgrid(torch.arange(H, device=dev, dtype=torch.float64) + 0.5,
                          torch.arange(W, device=dev, dtype=torch.float64) + 0.5, indexing="ij")
    d_cam = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1)  # [H,W,3]
    R = torch.tensor(c2w[:3, :3], dtype=torch.float64, device=dev)
    C = torch.tensor(c2w[:3, 3], dtype=torch.float64, device=dev)
    d_w = d_cam @ R.T                                                                        # [H,W,3]
    projs = []
    for pid, pat in scene.active_projectors(i):
        pj = scene.projectors[pid]
        p = scene.pattern_image(pat).astype(np.float32) / 255.0
        # a camera pixel covers ~ f_proj / f_cam projector pixels at equal distance: pre-blur by it
        ratio = float(pj.K[0, 0]) / float(K[0, 0])
        k = 2 * max(0, int(round((ratio - 1) / 2))) + 1  # odd: an even box would shift the pattern by half a pixel
        if k > 1:
            p = cv2.blur(p, (k, k), borderType=cv2.BORDER_CONSTANT)
        w2p = np.linalg.inv(scene.proj_to_world(i, pid))
        projs.append((torch.tensor(p, device=dev).permute(2, 0, 1)[None],                       # [1,3,h,w]
                      torch.tensor(pj.K, dtype=torch.float64, device=dev),
                      torch.tensor(w2p, dtype=torch.float64, device=dev), p.shape[1], p.shape[0]))

    def predict(zc: torch.Tensor) -> torch.Tensor:
        """Projected light for depth hypotheses zc [D] (planes) or [D, H, W] (per pixel): [D, 3, H, W]."""
        zc = zc[:, None, None] if zc.dim() == 1 else zc
        X = C + zc[..., None] * d_w[None]                                                    # [D,H,W,3]
        q = torch.zeros(zc.shape[0], 3, H, W, device=dev)
        for pat, Kp, w2p, pw, ph in projs:
            Xp = X @ w2p[:3, :3].T + w2p[:3, 3]
            z = Xp[..., 2]
            uv = (Xp @ Kp.T)[..., :2] / z.clamp_min(1e-9)[..., None]
            # grid_sample's align_corners=False maps -1..1 to the outer pixel edges: x_pix = uv
            g = torch.stack([uv[..., 0] / pw * 2 - 1, uv[..., 1] / ph * 2 - 1], -1).float()
            s = F.grid_sample(pat.expand(zc.shape[0], -1, -1, -1), g, mode="bilinear", padding_mode="zeros",
                              align_corners=False)
            q += s * (z > 1e-6)[:, None].float()
        return q

    # foreground weights: the window statistics skip background pixels, so a window that
    # straddles a silhouette still scores the object's part (thin parts: the torus's ring)
    fg = (torch.tensor(msk, device=dev) > 0.5) if msk is not None else (img[0].max(0).values > 8 / 255.0)
    M = fg.float().reshape(1, 1, H, W)
    nM = box_mean(M, kh, kw).clamp_min(1e-6)
    wbox = lambda x: box_mean(M * x, kh, kw) / nM  # noqa: E731
    # photo statistics per channel (constant over depths)
    mI = wbox(img)
    vI = (wbox(img * img) - mI * mI).clamp_min(0)

    def sweep(hyp: torch.Tensor) -> torch.Tensor:
        """Mean ZNCC over the informative channels for hypotheses hyp [D] or [D, H, W]: [D, H, W]."""
        out = torch.empty((hyp.shape[0], H, W), device=dev)
        for a in range(0, hyp.shape[0], chunk):
            q = predict(hyp[a:a + chunk])                                                    # [D,3,H,W]
            mQ = wbox(q)
            vQ = (wbox(q * q) - mQ * mQ).clamp_min(0)
            cov = wbox(q * img) - mQ * mI
            ok = (vQ > 1e-4) & (vI > 1e-5)
            zn = torch.where(ok, cov / (vQ * vI).clamp_min(1e-12).sqrt(), torch.zeros_like(cov))
            wsum = ok.float().sum(1)
            out[a:a + q.shape[0]] = torch.where(wsum >= 2, zn.sum(1) / wsum.clamp_min(1), torch.full_like(wsum, -1.0))
        return out

    def peak(scores: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Best score [H, W], its index, and the index refined by a parabola through its neighbours."""
        best, k = scores.max(0)
        n = scores.shape[0]
        sm = scores.gather(0, (k - 1).clamp(0, n - 1)[None])[0]
        sp = scores.gather(0, (k + 1).clamp(0, n - 1)[None])[0]
        den = sm - 2 * best + sp
        off = torch.where(den < -1e-9, 0.5 * (sm - sp) / den, torch.zeros_like(den)).clamp(-0.5, 0.5)
        return best, k, k.double() + off.double()

    scores = sweep(zs)                                                                       # [D, H, W]
    best, best_k, kf = peak(scores)
    # uniqueness: the best score farther than 3 steps from the winner
    idx = torch.arange(n_depths, device=dev)[:, None, None]
    far = (idx - best_k[None]).abs() > 3
    second = torch.where(far, scores, torch.full_like(scores, -2.0)).max(0).values
    del scores, far
    step = (z1 - z0) / max(n_depths - 1, 1)
    z = z0 + kf * step                                                                       # [H, W] float64
    keep = (best >= min_score) & (best - second >= min_margin) & (best_k > 0) & (best_k < n_depths - 1) \
        & fg & (nM[0, 0] >= 0.3)
    on_object = lambda x: torch.where(fg, x, torch.full_like(x, math.nan))  # noqa: E731
    if refine > 0:
        # A finer sweep around each pixel's winner, a quarter step apart. Its hypotheses are
        # offsets from the coarse surface (median-smoothed, so one pixel's noise does not bend
        # its neighbours' windows), so a slanted or curved surface is scored against itself,
        # not against one fronto-parallel plane across the window.
        base = _window_nanmedian(on_object(z), 2 * ((kh // 2 + 1) // 2) + 1)
        z = torch.where(torch.isfinite(base), base, z)
        offs = torch.linspace(-1.5, 1.5, refine, dtype=torch.float64, device=dev) * step
        best_f, _, kf2 = peak(sweep(z[None] + offs[:, None, None]))
        z = z + (-1.5 + kf2 * 3.0 / (refine - 1)) * step
        keep &= best_f >= min_score
    if edge_radius > 0:
        # Windows straddling a depth edge take the nearer side's depth a pixel or two past the
        # edge ("foreground fattening"), and a silhouette pixel mixes the object with the
        # background: centimetres off. Skip the outer ring of the object and every pixel whose
        # (2 r + 1)^2 neighbourhood of swept depths jumps by more than edge_jump.
        keep &= -F.max_pool2d(-M, 3, stride=1, padding=1)[0, 0] > 0.5
        keep &= _window_range(on_object(z), edge_radius) <= edge_jump * z
    depth = torch.where(keep, z.float(), torch.full_like(best, math.nan))
    return depth.cpu().numpy().astype(np.float32), best.cpu().numpy().astype(np.float32), K
