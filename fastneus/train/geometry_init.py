"""Geometry initialisation from the pattern itself: start the SDF at the decoded surface.

When every training viewpoint holds a complete Gray-code sequence, the classical decoder
(:mod:`fastneus.classical.graycode`) gives a depth map per viewpoint in a fraction of a second.
Fitting the SDF to those points first (zero at the points, positive just in front of them along
the camera ray, negative just behind, unit gradient) replaces the sphere initialisation, so the
photometric training refines a surface that is already right to a projector pixel instead of
carving it out of a sphere. Coarse-to-fine is switched off then: it exists to find the topology
from a sphere, and it would hide the fine levels the fit just set.

One-shot runs (at most ``MAX_SWEEP_VIEWS`` viewpoints, every frame lit by a dense pattern such
as the colourful lines) get the same from a plane sweep of each photo against its patterns
(:mod:`fastneus.classical.planesweep`): without it, one view of a striped pattern leaves the
photometric optimisation free to settle a stripe away from the truth (the toy's torus at 3.7 %
depth error).

Thin coloured lines (cross lasers from image projectors) are no code, but along one camera ray
only a few light sheets are crossed inside the bounds: :mod:`fastneus.classical.laserlines`
labels the lit pixels with their sheet (unique candidates, then by neighbours), and those points
initialise the surface where the lines fall (2 or 3 viewpoints; one view's lines are too sparse).

``init_geometry``: ``auto`` (decode when every training viewpoint is a decodable Gray-code
sequence or the run is such a one-shot, else the sphere), ``decode`` (required; error otherwise)
or ``sphere``. The decoding and fit time counts toward the run's training time.
"""
from __future__ import annotations

import time

import numpy as np
import torch

from fastneus.data.scene import view_frames
from fastneus.errors import FastneusError
from fastneus.geometry.projection import unit_sphere_chord
from fastneus.train.adam import Adam


def decodable_views(scene, frames: list[int]) -> list[list[int]] | None:
    """Frame indices per viewpoint when every viewpoint of ``frames`` is one projector's full
    Gray-code sequence (and nothing else), else None."""
    from fastneus.light.patterns import gray_bits

    groups = list(view_frames(scene, frames).values())
    for g in groups:
        pids = {pid for i in g for pid, _ in scene.active_projectors(i)}
        if len(pids) != 1:
            return None
        pj = scene.projectors[next(iter(pids))]
        if len(g) != gray_bits(pj.width) + gray_bits(pj.height):
            return None
        if any(len(scene.active_projectors(i)) != 1 for i in g):
            return None
    return groups


def decoded_points(scene, groups: list[list[int]], max_free: int = 200_000) -> dict[str, np.ndarray]:
    """What the Gray-code decoder says about space, over all viewpoints (world units).

    Returns:
        dict: ``points`` [N, 3] triangulated surface points, ``dirs`` [N, 3] their unit camera-ray
        directions, ``origins`` [N, 3] their camera centres; ``bg_origins`` / ``bg_dirs`` [M, 3] rays
        of background pixels (black in every shot: nothing there, the whole ray is free space).
    """
    from fastneus.classical.graycode import graycode_depth

    def views():
        for g in groups:
            z = graycode_depth(scene, g)
            dark = np.ones(z.shape, bool)
            for j in g:
                dark &= scene.image(j).max(axis=2) <= 2
            yield z, scene.frame_camera(g[0]).K, scene.cam_to_world(g[0]), dark

    return _rays_of_depths(views(), len(groups), max_free)


def _rays_of_depths(views, n_views: int, max_free: int) -> dict[str, np.ndarray]:
    """Surface points and free-space rays from per-view depth maps (the dict of :func:`decoded_points`).

    Args:
        views: iterable of (z [H, W] camera z-depth, NaN where unknown; K [3, 3] of that grid;
            cam_to_world [4, 4]; bg [H, W] bool pixels that see nothing; optionally uv [H, W, 2],
            the sub-pixel image point whose ray z belongs to, instead of the pixel centre).
        n_views: how many; max_free: background rays kept in all (a random subset per view).
    """
    out: dict[str, list] = {"points": [], "dirs": [], "origins": [], "bg_origins": [], "bg_dirs": []}
    rng = np.random.default_rng(0)
    for z, K, c2w, bg, *sub in views:
        for key, (v, u) in (("", np.nonzero(np.isfinite(z))), ("bg_", np.nonzero(bg))):
            if key and v.size > max_free // n_views:
                sel = rng.choice(v.size, max_free // n_views, replace=False)
                v, u = v[sel], u[sel]
            x, y = (sub[0][v, u, 0], sub[0][v, u, 1]) if sub and not key else (u + 0.5, v + 0.5)
            d_cam = np.linalg.inv(K) @ np.stack([x, y, np.ones(u.size)])
            d = (c2w[:3, :3] @ d_cam).T
            if not key:
                out["points"].append((c2w[:3, :3] @ (d_cam * z[v, u]) + c2w[:3, 3:4]).T)
            out[key + "dirs"].append(d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12))
            out[key + "origins"].append(np.broadcast_to(c2w[:3, 3], d.shape))
    return {k: np.concatenate(v) if v else np.zeros((0, 3)) for k, v in out.items()}


MAX_SWEEP_VIEWS = 3  # the plane sweep initialises one-shot / few-view runs; more views find the surface anyway


def _one_shot_frames(scene, frames: list[int], lit_by, min_views: int) -> list[int] | None:
    """The training frames when the run has ``min_views`` to ``MAX_SWEEP_VIEWS`` viewpoints of one
    frame each (one-shot: a partial multi-shot sequence is no code frame by frame), no flat port
    (the sweeps' rays are straight; behind a port, underwater, they bend) and ``lit_by(scene, i)``
    holds for every frame, else None."""
    groups = view_frames(scene, frames)
    if not min_views <= len(groups) <= MAX_SWEEP_VIEWS or any(len(g) != 1 for g in groups.values()):
        return None
    if any(scene.frame_camera(i).port is not None for i in frames) or \
            any(getattr(pj, "port", None) is not None for pj in scene.projectors.values()):
        return None
    if not all(lit_by(scene, i) for i in frames):
        return None
    return list(frames)


def sweepable_frames(scene, frames: list[int]) -> list[int] | None:
    """:func:`_one_shot_frames` for a dense pattern (:func:`fastneus.classical.planesweep.dense_pattern_frame`),
    1 to ``MAX_SWEEP_VIEWS`` viewpoints."""
    from fastneus.classical.planesweep import dense_pattern_frame

    return _one_shot_frames(scene, frames, dense_pattern_frame, 1)


MIN_LINE_VIEWS = 2  # one view of labelled lines: H100 10 s 4.8 -> 7.3 % (CPU 6.6 -> 3.2 %); 3 views 2.2 -> 1.3 %


def line_frames(scene, frames: list[int]) -> list[int] | None:
    """:func:`_one_shot_frames` for thin-line patterns (cross lasers from image projectors,
    :func:`fastneus.classical.laserlines.sparse_line_frame`), ``MIN_LINE_VIEWS`` to
    ``MAX_SWEEP_VIEWS`` viewpoints. With one view the labelled lines are a few curves; fitted alone
    they leave blobs between them, which the GPU's 10-s run does not recover from
    (docs/BENCHMARKS.md, issue 11)."""
    from fastneus.classical.laserlines import sparse_line_frame

    return _one_shot_frames(scene, frames, sparse_line_frame, MIN_LINE_VIEWS)


def lined_points(scene, frames: list[int], device="cpu", max_free: int = 200_000) -> dict[str, np.ndarray]:
    """:func:`decoded_points` for thin-line one-shot frames: the line-lit pixels labelled with their
    light sheet (:func:`fastneus.classical.laserlines.laser_line_depth`); background as
    :func:`swept_points`."""
    from fastneus.classical.laserlines import laser_line_depth

    def views():
        for i in frames:
            z, uv, K = laser_line_depth(scene, i, device=device)
            yield z, K, scene.cam_to_world(i), _background(scene, i, z.shape), uv

    return _rays_of_depths(views(), len(frames), max_free)


def _background(scene, i: int, shape: tuple[int, int]) -> np.ndarray:
    """Pixels that see nothing, on a grid of ``shape``: outside the mask, else black in the photo."""
    import cv2

    m = scene.mask(i)
    img = scene.image(i)
    if img.shape[:2] != tuple(shape):
        size = (shape[1], shape[0])
        m = None if m is None else cv2.resize(m.astype(np.float32), size, interpolation=cv2.INTER_AREA)
        img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
    return (m < 0.5) if m is not None else (img.max(axis=2) <= 2)


def swept_points(scene, frames: list[int], device="cpu", max_free: int = 200_000) -> dict[str, np.ndarray]:
    """:func:`decoded_points` for one-shot frames: the surface from a plane sweep of each frame
    against its projected patterns; background rays from the mask (outside it) or, without one,
    from black pixels."""
    from fastneus.classical.planesweep import planesweep_depth

    def views():
        for i in frames:
            z, _, K = planesweep_depth(scene, i, device=device)  # K of the swept (maybe downsampled) grid
            yield z, K, scene.cam_to_world(i), _background(scene, i, z.shape)

    return _rays_of_depths(views(), len(frames), max_free)


class SurfacePrior:
    """Surface points seen along camera rays and background rays (normalised space), with the loss
    that pulls an SDF's zero set onto them: the geometry init fits it alone, and training keeps it
    as a fading prior (``prior_weight``) so the photometric loss refines the decoded surface rather
    than drifting from it where one view leaves depth loosely constrained.

    Args:
        points, dirs, origins: [N, 3] float32 surface points, unit ray directions, camera centres.
        bg_origins, bg_dirs: [M, 3] background rays (optional; the whole chord is free space).
        offset: normalised distance of the in-front / behind probes.
    """

    def __init__(self, points: torch.Tensor, dirs: torch.Tensor, origins: torch.Tensor,
                 bg_origins: torch.Tensor | None = None, bg_dirs: torch.Tensor | None = None, offset: float = 0.02):
        self.points, self.dirs, self.origins, self.offset = points, dirs, origins, offset
        self.t_surf = (points - origins).norm(dim=-1)
        self.t_in, _ = unit_sphere_chord(origins, dirs)
        self.nb = 0
        if bg_dirs is not None and bg_dirs.shape[0]:
            bg_in, bg_out = unit_sphere_chord(bg_origins, bg_dirs)
            hit = bg_out > bg_in
            self.bg_origins, self.bg_dirs, self.bg_in, self.bg_out = bg_origins[hit], bg_dirs[hit], bg_in[hit], bg_out[hit]
            self.nb = int(self.bg_dirs.shape[0])

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def loss(self, field, m: int, generator: torch.Generator | None = None, eikonal: bool = True) -> torch.Tensor:
        """|f(p)| (on the surface) + relu(offset/2 - f(p - offset d)) (just in front is outside) +
        relu(f(p + offset d / 2) + offset/4) (just behind is inside) + relu(-f(q)) for q uniform on the
        free part of a ray (camera to surface; whole chord for background rays) on a random batch of
        ``m`` points (and m/2 background rays); with ``eikonal``, + 0.1 (|grad f| - 1)^2 on a quarter
        batch of surface and as many uniform points. Plain L1 on every point: ignoring points far
        from the current zero set (a robust prior) lets a drifting surface escape it, which on the
        GPU study made one view 10x worse (docs/BENCHMARKS.md, issue 11). Returns a scalar."""
        n, off, dev = len(self), self.offset, self.points.device
        rand = lambda *s: torch.rand(*s, device=dev, generator=generator)  # noqa: E731
        m = min(m, n)
        idx = torch.randint(0, n, (m,), device=dev, generator=generator)
        p, d = self.points[idx], self.dirs[idx]
        lo, hi = self.t_in[idx], (self.t_surf[idx] - off).clamp_min(self.t_in[idx])
        q = [self.origins[idx] + d * (lo + rand(m) * (hi - lo))[:, None]]
        if self.nb:
            j = torch.randint(0, self.nb, (m // 2,), device=dev, generator=generator)
            q.append(self.bg_origins[j] + self.bg_dirs[j] * (self.bg_in[j] + rand(m // 2) * (self.bg_out[j] - self.bg_in[j]))[:, None])
        q = torch.cat(q)
        f = field.sdf(torch.cat([p, p - off * d, p + 0.5 * off * d, q]))
        f0, f_out, f_in, f_free = f[:m], f[m:2 * m], f[2 * m:3 * m], f[3 * m:]
        loss = (f0.abs().mean() + torch.relu(0.5 * off - f_out).mean() + torch.relu(f_in + 0.25 * off).mean()
                + torch.relu(-f_free).mean())
        if eikonal:
            xr = rand(m // 4, 3) * 2 - 1
            _, _, g, _ = field.sdf_and_grad(torch.cat([p[: m // 4], xr]))
            loss = loss + 0.1 * ((g.norm(dim=-1) - 1) ** 2).mean()
        return loss


def fit_batch(cfg) -> int:
    """Points per step of the init fit (an eighth of the step's sample budget, 1024-8192); the
    training prior uses half of it."""
    return int(min(8192, max(1024, cfg.rays.target_samples // 8)))


def fit_sdf_to_points(field, prior: SurfacePrior, steps: int, lr: float = 1e-2, batch: int = 8192,
                      generator: torch.Generator | None = None) -> float:
    """Fit the field's SDF to a :class:`SurfacePrior` (normalised space) with its own Adam.

    Args:
        field: :class:`fastneus.field.model.SDFField` (its own optimiser is not touched).
        prior: the points and rays. steps: Adam steps. lr: learning rate. batch: points per step.
    Returns:
        the last loss.
    """
    params = [field.table] + list(field.sdf_net.parameters())
    opt = Adam(params, lr=lr, betas=(0.9, 0.99), eps=1e-15)
    loss = torch.zeros(())
    for _ in range(steps):
        loss = prior.loss(field, batch, generator)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    return float(loss.detach())


def initialise_geometry(trainer) -> str | None:
    """Apply ``init_geometry`` to a fresh trainer (step 0): fit the SDF to the decoded points and keep
    them as the prior. On a resumed trainer (step > 0) only the prior is rebuilt (no fit), while it
    still has weight, so a resumed run goes on as it would have. Returns a one-line note, or None
    when the sphere initialisation stays (nothing to say)."""
    cfg = trainer.cfg
    mode = cfg.init.init_geometry
    resumed = trainer.step != 0
    if mode == "sphere" or resumed and (cfg.init.prior_weight <= 0 or trainer.progress() >= cfg.init.prior_frac):
        return None
    groups = decodable_views(trainer.scene, trainer.frames)
    swept = None if groups is not None else sweepable_frames(trainer.scene, trainer.frames)
    lined = None if groups is not None or swept is not None else line_frames(trainer.scene, trainer.frames)
    if groups is None and swept is None and lined is None:
        if mode == "decode":
            raise FastneusError("init_geometry=decode needs every training viewpoint to be one projector's "
                                "complete Gray-code sequence, or at most "
                                f"{MAX_SWEEP_VIEWS} viewpoints lit by a dense one-shot pattern (colourful lines) "
                                "or by thin coloured lines (cross lasers)",
                                field="init_geometry")
        return None
    t = time.perf_counter()
    scene = trainer.scene
    if groups is not None:
        dec, what = decoded_points(scene, groups), "decoded Gray code"
        n_src = f"{len(groups)} view(s)"
    elif swept is not None:
        dec, what = swept_points(scene, swept, device=trainer.device), "plane sweep of the one-shot pattern"
        n_src = f"{len(swept)} frame(s)"
    else:
        dec, what = lined_points(scene, lined, device=trainer.device), "labelled lines of the one-shot pattern"
        n_src = f"{len(lined)} frame(s)"
    if len(dec["points"]) < 100:
        return f"geometry init: {mode} -> sphere (the {what} found only {len(dec['points'])} points)"
    b = scene.bounds
    norm = lambda x: (x - np.asarray(b.center)) / float(b.radius)  # noqa: E731
    pn = norm(dec["points"])
    keep = np.linalg.norm(pn, axis=1) < 0.999
    f32 = dict(dtype=torch.float32, device=trainer.device)
    tt = lambda a: torch.tensor(np.ascontiguousarray(a), **f32)  # noqa: E731
    P, D, O = tt(pn[keep]), tt(dec["dirs"][keep]), tt(norm(dec["origins"][keep]))
    batch = fit_batch(cfg)
    prior = SurfacePrior(P, D, O, bg_origins=tt(norm(dec["bg_origins"])), bg_dirs=tt(dec["bg_dirs"]))
    if resumed:
        trainer.prior = prior
        return (f"geometry prior rebuilt on resume: {what} ({P.shape[0]} points from {n_src}, "
                f"{time.perf_counter() - t:.1f} s)")
    # see the module docstring; recorded in the run's saved config so a resumed run keeps it
    trainer.cfg = cfg = cfg.replace(c2f_start_levels=0)
    trainer.field.without_coarse_to_fine()
    trainer.field.set_progress(0.0)
    loss = fit_sdf_to_points(trainer.field, prior, cfg.init.init_geometry_steps, lr=cfg.optim.lr, batch=batch,
                             generator=trainer.gen)
    if cfg.init.prior_weight > 0:
        trainer.prior = prior
    return (f"geometry init: {mode} -> {what} ({P.shape[0]} points from {n_src}, "
            f"{cfg.init.init_geometry_steps} fit steps, loss {loss:.4f}, {time.perf_counter() - t:.1f} s of the budget); "
            "coarse-to-fine off")


def grey_photos_note(scene, frames: list[int]) -> str | None:
    """The run summary's line on grey photos (a monochrome camera), None for colour ones; with a
    warning when the run is a one-shot of a pattern coded by colour (:func:`sweepable_frames`
    with patterns whose channels differ): grey photos keep only its brightness, and the plane
    sweep and the photometric fit then confuse its stripes (toy, colourful lines, 400 px, 10 s on
    an H200: 5.3 % mean depth error against 0.21 % on colour photos of the same capture)."""
    if not getattr(scene, "grey", False):
        return None
    note = "photos: grey (a monochrome camera); the projectors' light is seen as its grey (the mean of its colour)"
    if sweepable_frames(scene, frames) is not None:
        from fastneus.data.images import read_rgb

        used = sorted({pat for i in frames for _, pat in scene.active_projectors(i)})
        coloured = []
        for pid in used:
            im = read_rgb(scene.path(scene.patterns[pid].file), scene.root / "scene.json", f"patterns.{pid}.file")
            if (im.max(-1).astype(np.int16) - im.min(-1) > 32).mean() > 0.01:
                coloured.append(pid)
        if coloured:
            note += (f"; warning: pattern {', '.join(coloured)} is coded by colour, which grey photos do not "
                     "record: a one-shot of it is unreliable (use a pattern coded in brightness or time, e.g. "
                     "Gray code or phase shift, or a colour camera)")
    return note
