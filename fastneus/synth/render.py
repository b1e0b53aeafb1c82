"""Synthetic structured-light scenes (the paper's protocol) + the ``synth`` verb.

A mesh (built-in shape or file) is rendered from cameras on an orbit, lit by projectors
rigidly attached to the camera. Image formation follows DESIGN.md exactly:

    D = ambient * albedo * (0.3 + 0.7 * max(0, n . l))            (view-independent)
    c = D + sum_k (i_r * D + i_b) * Q_k * V_k                       (pattern projection)

with Q_k the bilinear pattern sample (fastneus.geometry.projection) and V_k = 1 when the point
sees projector k (a shadow ray from the point toward the projector centre). Then
Gaussian noise and 8-bit quantisation; background is black. Ray casting runs through
``fastneus.kernels.raycast`` (Warp BVH, CPU or CUDA); everything else is vectorised torch.
"""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import torch
import trimesh

from fastneus.data.model import Bounds, Camera, FlatPort, Frame, FrameProjector, Illumination, Pattern, Projector
from fastneus.data.scene import Scene
from fastneus.errors import FastneusError
from fastneus.geometry.cameras import camera_intrinsics, look_at, projector_intrinsics, rig_proj_to_cam
from fastneus.data.kinds import get_projector_kind
from fastneus.light.patterns import pattern_kinds, sequence_kinds
from fastneus.light.patterns import make_pattern, write_png
from fastneus.geometry.projection import Z_MIN, pixel_rays, project_points, refract_rays, sample_pattern
from fastneus.synth.albedo import Albedo
from fastneus.synth.capture import (apply_speckle, blinn_phong, channel_gains, finish, frame_gains, make_capture,
                                    sensor_pixels)
from fastneus.synth.shapes import load_mesh, make_shape, normalise_mesh
from fastneus.synth.water import WATER, WATER_PORT, Water, port_exit

ILLUMS = {"normal": 1.0, "dark": 0.1}
RIG_BASELINES = (-0.6, -0.2, 0.2, 0.6)  # metres, horizontal, in camera coordinates
SEQUENCE_BASELINES = (0.6,)  # a sequence is shown by one projector
GENERATOR = "fastneus synth"
_OUR_DIRS = ("images", "masks", "depth", "normals", "clean", "patterns")
BOUNCE_RAYS = 32  # rays per camera pixel for capture.interreflection (Monte Carlo; the bounce is smooth)


# --------------------------------------------------------------------------- geometry
def orbit_poses(n: int, distance: float, seed: int = 0, elevation_deg=(10.0, 65.0)) -> list[np.ndarray]:
    """``n`` cam_to_world poses on the upper hemisphere (z up) at ``distance``, looking at 0.

    A Fibonacci spiral (evenly spread), rotated and jittered by ``seed``.
    """
    rng = np.random.default_rng(seed)
    lo, hi = (math.sin(math.radians(e)) for e in elevation_deg)
    az0 = rng.uniform(0, 2 * math.pi)
    golden = math.pi * (3.0 - math.sqrt(5.0))
    out = []
    for k in range(n):
        s = lo + (hi - lo) * ((k + 0.5) / n if n > 1 else 0.5)
        s = float(np.clip(s + rng.uniform(-0.03, 0.03), -0.99, 0.99))
        el = math.asin(s)
        az = az0 + k * golden
        eye = distance * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        out.append(look_at(eye, np.zeros(3), up=(0.0, 0.0, 1.0)))
    return out


def blur_kernel(sigma: float, n: int = 5) -> np.ndarray:
    """[n, n] Gaussian of ``sigma`` pixels truncated to n x n taps, normalised to sum 1."""
    h = (n - 1) / 2
    x = np.arange(n) - h
    g = np.exp(-0.5 * (x / sigma) ** 2)
    k = np.outer(g, g)
    return k / k.sum()


def _sample_blurred(pattern: torch.Tensor, px: torch.Tensor, valid: torch.Tensor, taps) -> torch.Tensor:
    """Pattern light through a blur: sum_ab taps[a, b] * sample(px + (b - h, a - h)); taps None = sharp."""
    if taps is None:
        return sample_pattern(pattern, px, valid)
    n = taps.shape[0]
    h = (n - 1) / 2
    q = torch.zeros(px.shape[0], 3, dtype=px.dtype, device=px.device)
    for a in range(n):
        for b in range(n):
            off = torch.tensor([b - h, a - h], dtype=px.dtype, device=px.device)
            q = q + float(taps[a, b]) * sample_pattern(pattern, px + off, valid)
    return q


# --------------------------------------------------------------------------- output folder
def _is_previous_synth(out: Path) -> bool:
    sj = out / "scene.json"
    try:
        return sj.is_file() and json.loads(sj.read_text()).get("meta", {}).get("generator") == GENERATOR
    except (OSError, ValueError, AttributeError, RecursionError):
        return False


def _check_out(out: Path) -> None:
    """Refuse an ``out`` holding anything but a previous synth output (before any rendering)."""
    from fastneus.io import check_out_dir

    check_out_dir(out)
    if out.is_dir() and any(out.iterdir()) and not _is_previous_synth(out):
        raise FastneusError("folder exists and is not empty (and is not a previous synth output); "
                            "choose a new --out", file=out, field="--out")


def _adopt_previous(out: Path) -> set[str]:
    """The files of a synth output written before manifests existed (what synth used to replace)."""
    if not _is_previous_synth(out):
        return set()
    files = {f for f in ("scene.json", "gt_mesh.ply", "contact_sheet.png") if (out / f).is_file()}
    for d in _OUR_DIRS:
        if (out / d).is_dir() and not (out / d).is_symlink():
            files |= {p.relative_to(out).as_posix() for p in (out / d).iterdir() if p.is_file() and not p.is_symlink()}
    return files


def _quantise(c: torch.Tensor, bits: int = 8) -> torch.Tensor:
    """[0, 1] values as uint8 codes, or with ``bits=16`` as 16-bit codes (int32 on the device: torch
    has no uint16 arithmetic on every device; written as uint16)."""
    if bits == 16:
        return torch.round(c.clamp(0, 1) * 65535.0).to(torch.int32)
    return torch.round(c.clamp(0, 1) * 255.0).to(torch.uint8)


def _noise(shape, sigma: float, key: tuple, device) -> torch.Tensor | float:
    if sigma <= 0:
        return 0.0
    rng = np.random.default_rng(key)
    return torch.from_numpy(rng.normal(0.0, sigma, shape).astype(np.float32)).to(device)


# --------------------------------------------------------------------------- main entry
def synthesize(out, shape: str | None = None, mesh=None, views: int = 20, size=(800, 800),
               pattern="crosslaser", illum: str = "normal", albedo: str = "procedural", noise: float = 0.005,
               seed: int = 0, device: str = "cpu", *, ambient: float | None = None, i_r: float = 0.4,
               i_b: float = 0.1, proj_size=(1024, 768), proj_fov_deg: float = 60.0, baselines=None,
               cam_distance: float = 4.0, focal: float | None = None, poses=None, normalise: bool = True,
               pattern_opts: dict | None = None, light_dir=(0.35, -0.4, 0.85), contact_sheet: bool = True,
               progress: bool = True, threads: int | None = 1, projector_blur: float = 0.0,
               laser_planes: bool = False, medium: str = "air", realistic: bool = False,
               capture: dict | None = None) -> Scene:
    """Render a synthetic structured-light scene into ``out`` and return it (loaded back).

    Args:
        out: output folder (created; the files of a previous synth output there are replaced, on
            success only: it is rendered aside and swapped in; other files are kept).
        shape: built-in shape name (``sphere``, ``torus``, ``toy``), or
        mesh: a mesh file path or a ``trimesh.Trimesh`` (exactly one of shape / mesh).
        views: number of viewpoints on the orbit (ignored when ``poses`` is given).
        size: camera image (width, height).
        pattern: a pattern kind (``fastneus.light.patterns.pattern_kinds()``) or a uint8 [h, w, 3] RGB
            array shown by every projector. Sequence kinds (graycode, phaseshift) make one
            frame per pattern per viewpoint, sharing the view id.
        illum: ``normal`` (ambient 1.0) or ``dark`` (ambient 0.1); ``ambient`` overrides.
        albedo: uniform | procedural (value noise) | checker | vertex (mesh vertex colours).
        noise: Gaussian noise sigma on [0, 1] values before 8-bit quantisation.
        seed: makes poses, patterns, albedo and noise deterministic.
        device: torch device for the rendering ("cpu" or "cuda").
        i_r, i_b: ground-truth pattern reflectance / bias.
        proj_size, proj_fov_deg: projector resolution and horizontal field of view.
        baselines: projector x offsets (m) on the rig (default: -0.6, -0.2, 0.2, 0.6; a
            single 0.6 for sequence patterns).
        cam_distance: orbit radius (m); the projectors are toed in to this distance.
        focal: camera focal length in pixels (default 1111.11 * width / 800).
        poses: explicit list of [4, 4] cam_to_world poses (overrides ``views``).
        normalise: centre and scale the mesh to a bounding-sphere radius of 1 m.
        pattern_opts: extra options for :func:`fastneus.light.patterns.make_pattern`.
        light_dir: world direction toward the light of the Lambertian shading.
        contact_sheet: write ``contact_sheet.png`` (first frames, for a person to look at).
        progress: show a rich progress bar and print a summary.
        projector_blur: defocus of every projector, the sigma (projector pixels) of a Gaussian
            truncated to 5 x 5 taps and normalised (:func:`blur_kernel`); the pattern is
            correlated with it (zero outside the pattern) before sampling, exactly the model of
            ``projector_blur=5`` in training. 0 = sharp.
        laser_planes: the projectors are laser line projectors defined by light planes
            (``Projector.planes``, the exact model): the planes of the ``crosslaser`` pattern's
            lines (same seed per projector, :func:`fastneus.light.lasers.crosslaser_planes`), sheet
            thickness = the line width at ``cam_distance``. Needs ``pattern="crosslaser"``.
        medium: ``air`` or ``water``: cameras and projectors sit behind flat ports
            (:data:`WATER_PORT`: 3 cm to the glass, 1 cm of glass, n = 1 / 1.5 / 1.333), rays
            refract there, and the water attenuates and back-scatters (:data:`WATER`): the
            surface colour c (pattern light included, each projector's light attenuated by
            exp(-beta_d |X_k|) on its way) is seen as ``c exp(-beta_d r) + b_inf (1 - exp(-beta_b r))``,
            r = the ray's length in the water (``far`` for rays that hit nothing). The same
            geometry, seed and poses in air give the reference.
        threads: torch CPU threads while rendering (restored afterwards; None = leave as is).
            Default 1: the per-view tensors are ~1e5 elements, where intra-op threading
            gains little and costs up to 8x when the cores are shared (measured).
        realistic: a real camera's effects (:data:`fastneus.synth.capture.REALISTIC`: sRGB response,
            +-25% exposure, speckle, highlights, 0.7 px defocus, vignetting, read + shot noise,
            saturation) applied to the linear render; ground truth stays linear.
        capture: individual capture options (:class:`fastneus.synth.capture.Capture` fields), on
            top of the realistic mix when ``realistic``; None / {} with ``realistic`` off = ideal.

    Returns:
        The written :class:`Scene` (loaded back, so it is validated).
    """
    kwargs = {k: v for k, v in locals().items() if k not in ("threads", "out")}  # first: only the arguments
    from fastneus.io import staged_output

    out = Path(out)
    _check_out(out)
    prev_threads = torch.get_num_threads()
    if threads is not None and torch.device(device).type == "cpu":
        torch.set_num_threads(int(threads))
    try:
        # rendered aside and swapped in on success: bad values, errors or Ctrl-C leave the previous scene
        with staged_output(out, adopt=_adopt_previous) as stage:
            info = _synthesize(out=stage, **kwargs)
    finally:
        torch.set_num_threads(prev_threads)
    loaded = Scene.load(out)
    if progress:
        _summary(loaded, out, *info)
    return loaded


def _synthesize(out, shape, mesh, views, size, pattern, illum, albedo, noise, seed, device, ambient, i_r, i_b,
                proj_size, proj_fov_deg, baselines, cam_distance, focal, poses, normalise, pattern_opts,
                light_dir, contact_sheet, progress, projector_blur, laser_planes, medium, realistic=False,
                capture=None) -> tuple:
    """Render into the fresh folder ``out`` (the staging folder); returns (seconds, stats, faces) for the summary."""
    from fastneus.kernels.raycast import raycast_mesh

    t_start = time.perf_counter()
    out = Path(out)
    W, H = (int(v) for v in size)
    PW, PH = (int(v) for v in proj_size)
    if (shape is None) == (mesh is None):
        raise FastneusError("give exactly one of --shape or --mesh", field="--shape")
    if illum not in ILLUMS:
        raise FastneusError(f"unknown illumination {illum!r}; use normal or dark", field="--illum")
    if views < 1 and poses is None:
        raise FastneusError("need at least one view", field="--views")
    if noise < 0:
        raise FastneusError("noise sigma must be >= 0", field="--noise")
    if projector_blur < 0:
        raise FastneusError("projector blur sigma must be >= 0", field="--projector-blur")
    # checked up front (not found by Scene.load after rendering): nan passes every "< 0" test
    for v, flag, lo in ((ambient, "--ambient", 0.0), (i_r, "i_r", None), (i_b, "i_b", None), (noise, "--noise", 0.0),
                        (projector_blur, "--projector-blur", 0.0), (cam_distance, "cam_distance", 0.0),
                        (proj_fov_deg, "proj_fov_deg", 0.0), (focal, "focal", 0.0)):
        if v is None:
            continue
        try:
            ok = not isinstance(v, bool) and math.isfinite(float(v)) and (lo is None or float(v) >= lo)
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise FastneusError(f"expected a finite number{'' if lo is None else f' >= {lo:g}'}, got {v!r}",
                                field=flag)
    taps = blur_kernel(projector_blur) if projector_blur > 0 else None
    cap = make_capture(capture, realistic)  # None: the ideal capture (the linear model, quantised)
    if medium not in ("air", "water"):
        raise FastneusError(f"unknown medium {medium!r}; use air or water", field="--medium")
    wet = medium == "water"
    if wet and cap is not None and cap.interreflection > 0:
        raise FastneusError("inter-reflection under water is not modelled", field="capture.interreflection")
    if wet and laser_planes:
        raise FastneusError("laser planes under water are not modelled (their sheets bend at the port)",
                            field="--medium")
    port = FlatPort(**WATER_PORT) if wet else None
    amb = float(ILLUMS[illum] if ambient is None else ambient)
    dev = torch.device(device)
    port_row_t = torch.tensor(port.row(), dtype=torch.float32, device=dev) if wet else None
    if wet:
        from fastneus.kernels.project import port_dir_torch

    # ---- mesh
    if shape is not None:
        src = {"shape": shape}
        m = make_shape(shape)
        name = shape
    elif isinstance(mesh, trimesh.Trimesh):
        src = {"mesh": "<in-memory>"}
        m, name = mesh, "mesh"
    else:
        src = {"mesh": str(Path(mesh).resolve())}
        m, name = load_mesh(mesh), Path(mesh).stem
    if normalise:
        m, scale, offset = normalise_mesh(m)
        src.update(scale=scale, offset=offset.tolist(), note="x_scene = scale * (x_source + offset)")
    centre = m.bounds.mean(axis=0)
    obj_radius = float(np.linalg.norm(m.vertices - centre, axis=1).max())
    V = torch.tensor(np.asarray(m.vertices), dtype=torch.float32, device=dev)
    F = torch.tensor(np.asarray(m.faces), dtype=torch.int32, device=dev)
    alb = Albedo(albedo, m, obj_radius, seed, dev)

    # ---- rig and patterns
    seq = isinstance(pattern, str) and pattern in sequence_kinds()  # one frame per pattern per viewpoint
    if baselines is None:
        baselines = SEQUENCE_BASELINES if seq else RIG_BASELINES
    Kp = projector_intrinsics(PW, PH, proj_fov_deg)
    projectors = {f"proj{k}": Projector(id=f"proj{k}", K=Kp, width=PW, height=PH,
                                        proj_to_cam=rig_proj_to_cam(b, cam_distance))
                  for k, b in enumerate(baselines)}
    for p in projectors.values():
        p.port = port
    if laser_planes:
        from fastneus.light.lasers import crosslaser_planes

        if pattern != "crosslaser" or projector_blur > 0:
            raise FastneusError("laser planes replace the crosslaser pattern (and have no blur)", field="--laser-planes")
        lo = dict(pattern_opts or {})
        for k, p in enumerate(projectors.values()):
            p.planes = crosslaser_planes(Kp, PW, PH, cam_distance, seed=seed + k, count=lo.get("count", 8),
                                         line_width=lo.get("line_width", 3))
            p.K, p.width, p.height, p.kind = np.eye(3), 1, 1, "laser"
    pids = list(projectors)
    opts = dict(pattern_opts or {})
    # per shot j of a view: {projector id -> pattern id}; images by pattern id
    pat_images: dict[str, np.ndarray] = {}
    shots: list[dict[str, str]] = []
    if laser_planes:
        kind = "laserplanes"
        shots.append({p: None for p in pids})
    elif isinstance(pattern, np.ndarray):
        if pattern.dtype != np.uint8 or pattern.shape != (PH, PW, 3):
            raise FastneusError(f"a custom pattern must be uint8 [{PH}, {PW}, 3]", field="pattern")
        pat_images["custom"] = pattern
        shots.append({p: "custom" for p in pids})
        kind = "custom"
    else:
        kind = pattern
        if kind not in pattern_kinds():
            raise FastneusError(f"unknown pattern {kind!r}; use one of {', '.join(pattern_kinds())}",
                                field="--pattern")
        if seq:
            for j, im in enumerate(make_pattern(kind, PW, PH, seed=seed, **opts)):
                pat_images[f"{kind}_{j:02d}"] = im
                shots.append({p: f"{kind}_{j:02d}" for p in pids})
        else:  # one-shot: each projector its own seeded pattern (lines do not coincide)
            shot = {}
            for k, p in enumerate(pids):
                pat_images[f"{p}_{kind}"] = make_pattern(kind, PW, PH, seed=seed + k, **opts)[0]
                shot[p] = f"{p}_{kind}"
            shots.append(shot)
    pat_t = {q: torch.from_numpy(np.ascontiguousarray(im)).to(dev) for q, im in pat_images.items()}

    # ---- cameras
    K = camera_intrinsics(W, H, focal)
    if poses is None:
        poses = orbit_poses(views, cam_distance, seed)
    poses = [np.asarray(p, dtype=np.float64) for p in poses]
    n_views, n_shots = len(poses), len(shots)
    gains = frame_gains(n_views * n_shots, cap.exposure if cap else 0.0, seed)  # frame 0 = 1
    wb = channel_gains(n_views * n_shots, cap.white_balance if cap else 0.0, seed)  # [F, 3], frame 0 = 1

    for d in _OUR_DIRS:
        (out / d).mkdir(exist_ok=True)
    for q, im in pat_images.items():
        write_png(out / "patterns" / f"{q}.png", im)
    m.export(out / "gt_mesh.ply")

    light = torch.tensor(light_dir, dtype=torch.float32, device=dev)
    light = light / light.norm()
    jj, ii = torch.meshgrid(torch.arange(W, device=dev), torch.arange(H, device=dev), indexing="xy")
    uv = torch.stack([jj.reshape(-1), ii.reshape(-1)], dim=1).to(torch.float32) + 0.5  # pixel centres
    sub = cap.supersample if cap is not None and cap.blur > 0 else 1  # sub-pixel rays per side
    uv_sub = parent = None
    if sub > 1:  # [H*sub * W*sub, 2] sub-pixel centres (row-major), and the camera pixel of each
        js, is_ = torch.meshgrid(torch.arange(W * sub, device=dev), torch.arange(H * sub, device=dev), indexing="xy")
        uv_sub = (torch.stack([js.reshape(-1), is_.reshape(-1)], dim=1).to(torch.float32) + 0.5) / sub
        parent = (is_.reshape(-1) // sub) * W + js.reshape(-1) // sub
    eps = 2e-4 * obj_radius  # shadow-ray offset (float32 safe at metre scale)

    def light_at(c2w, P, fh, nh):
        """The direct light at surface points ``P`` [N, 3] (faces ``fh`` [N], unit normals ``nh``)
        with the projectors of the view ``c2w``: albedo [N, 3], D [N, 3] (ambient-lit colour),
        Q[shot][projector] [N, 3] pattern samples, vis[projector] [N] shadow tests, to_proj
        [projector] [N, 3] unit directions toward each projector."""
        a = alb(P, fh, V, F)
        D = amb * a * (0.3 + 0.7 * (nh @ light).clamp_min(0))[:, None]

        # projector terms: Q per shot and projector, V per projector (shadow rays where lit)
        Q = [[None] * len(pids) for _ in range(n_shots)]
        vis, to_proj = [], []  # to_proj: [nv, 3] unit directions toward each projector (highlights)
        for k, p in enumerate(pids):
            p2w = c2w @ projectors[p].proj_to_cam
            w2p = np.linalg.inv(p2w)
            px, z = project_points(P, Kp, w2p)
            if wet:  # the pixel whose light reaches P through the port (the air-side direction)
                Xp = P @ torch.tensor(w2p[:3, :3].T, dtype=P.dtype, device=dev) + \
                    torch.tensor(w2p[:3, 3], dtype=P.dtype, device=dev)
                Vd = port_dir_torch(Xp, port_row_t)
                px, z = project_points(Vd, Kp, np.eye(4))
                att_k = torch.exp(-torch.tensor(WATER["beta_d"], device=dev) * Xp.norm(dim=-1, keepdim=True))
            front = z > Z_MIN
            need = torch.zeros(P.shape[0], dtype=torch.bool, device=dev)
            pkind = get_projector_kind(projectors[p].kind)
            for j, shot in enumerate(shots):
                if not pkind.images:  # an emitter (laser planes, ...): its kind's synth hook
                    q = pkind.call("synth", P, w2p, projectors[p]).to(P.dtype)
                else:
                    q = _sample_blurred(pat_t[shot[p]], px, front, taps)
                if wet:
                    q = q * att_k
                Q[j][k] = q
                need |= q.amax(dim=1) > 0
            C = torch.tensor(p2w[:3, 3], dtype=torch.float32, device=dev)
            if wet:  # shadow rays follow the water segment, toward where the light leaves the port
                C = port_exit(Xp, Vd, port_row_t) @ torch.tensor(p2w[:3, :3].T, dtype=P.dtype, device=dev) + \
                    torch.tensor(p2w[:3, 3], dtype=P.dtype, device=dev)
            to_c = C - P
            dist = to_c.norm(dim=1)
            dirp = to_c / dist[:, None]
            to_proj.append(dirp)
            facing = (nh * dirp).sum(1) > 0  # the lit side must face the projector
            sel = (need & facing).nonzero().squeeze(1)
            Vk = torch.zeros(P.shape[0], dtype=torch.float32, device=dev)
            if sel.numel():
                so = P[sel] + eps * nh[sel] + eps * dirp[sel]
                ts, _, _ = raycast_mesh(V, F, so, dirp[sel], (dist[sel] - 2 * eps).clamp_min(0))
                Vk[sel] = (~torch.isfinite(ts)).to(torch.float32)
            vis.append(Vk)
        return a, D, Q, vis, to_proj

    def trace(c2w, uv_px):
        """Cast camera rays through ``uv_px`` [N, 2] (continuous pixel coordinates) of the view
        ``c2w`` and light their hits: what the photo of every shot is made of."""
        o, d = pixel_rays(K, c2w, uv_px)  # world space (S = identity)
        if wet:  # refract at the camera's port: rays start on its outer face, in the water
            R = torch.tensor(c2w[:3, :3], dtype=torch.float32, device=dev)
            b, w = refract_rays(d @ R, port_row_t)
            o, d = o + b @ R.T, w @ R.T
        t, face, n = raycast_mesh(V, F, o, d, 1e6)
        hit = face >= 0
        hidx = hit.nonzero().squeeze(1)
        dh, th, nh = d[hidx], t[hidx], n[hidx]
        P = o[hidx] + th[:, None] * dh
        zc = torch.tensor(c2w[:3, 2], dtype=torch.float32, device=dev)
        depth = torch.zeros(uv_px.shape[0], dtype=torch.float32, device=dev)
        depth[hidx] = (P - torch.tensor(c2w[:3, 3], dtype=torch.float32, device=dev)) @ zc  # z-depth
        a, D, Q, vis, to_proj = light_at(c2w, P, face[hidx], nh)
        return dict(hit=hit, hidx=hidx, dh=dh, th=th, nh=nh, P=P, depth=depth, albedo=a, D=D, Q=Q, vis=vis,
                    to_proj=to_proj)

    def bounce(c2w, P, nh, v):
        """One diffuse bounce of the view ``c2w``'s light onto the points ``P`` [N, 3] (normals ``nh``).

        ``BOUNCE_RAYS`` cosine-weighted rays per point find the surfaces it sees; each hit's
        outgoing light is what the camera would see of it (D plus every projector's diffuse light,
        shadows included; no speckle or highlights). Returns (ambient [N, 3], [per shot [N, 3]]):
        the mean light arriving along those rays (misses bring none), the ambient's and each shot's
        projectors'. Times a point's albedo it is the light the point sends on (a Lambertian
        surface's one-bounce radiance, Monte Carlo); the caller scales it by the capture's strength.
        """
        n_pts = P.shape[0]
        zero = torch.zeros(n_pts, 3, dtype=torch.float32, device=dev)
        if n_pts == 0:
            return zero, [zero.clone() for _ in shots]
        gen = torch.Generator(device=dev).manual_seed(int(seed) * 1000003 + 17 * v + 5)
        u = torch.rand(n_pts, BOUNCE_RAYS, 2, device=dev, generator=gen)
        r, phi = u[..., 0].sqrt(), 2 * math.pi * u[..., 1]
        local = torch.stack([r * phi.cos(), r * phi.sin(), (1 - u[..., 0]).clamp_min(0).sqrt()], -1)
        helper = torch.where(nh[:, :1].abs() < 0.9, torch.tensor([1.0, 0, 0], device=dev),
                             torch.tensor([0, 1.0, 0], device=dev))
        t1 = torch.nn.functional.normalize(torch.cross(nh, helper, dim=1), dim=1)
        t2 = torch.cross(nh, t1, dim=1)
        dirs = (local[..., :1] * t1[:, None] + local[..., 1:2] * t2[:, None] + local[..., 2:] * nh[:, None]).reshape(-1, 3)
        org = (P + eps * nh).repeat_interleave(BOUNCE_RAYS, 0)
        tb, fb, nb = raycast_mesh(V, F, org.contiguous(), dirs.contiguous(), 1e6)
        ok = (fb >= 0) & ((nb * dirs).sum(1) < 0)  # a surface facing the point (not a mesh's inside)
        idx = ok.nonzero().squeeze(1)
        owner = idx // BOUNCE_RAYS
        Py = org[idx] + tb[idx, None] * dirs[idx]
        _, Dy, Qy, visy, _ = light_at(c2w, Py, fb[idx], nb[idx])
        amb_in = zero.index_add(0, owner, Dy) / BOUNCE_RAYS
        per_shot = []
        for j in range(len(shots)):
            Ly = torch.zeros_like(Dy)
            for k in range(len(pids)):
                Ly = Ly + (i_r * Dy + i_b) * Qy[j][k] * visy[k][:, None]
            per_shot.append(zero.index_add(0, owner, Ly) / BOUNCE_RAYS)
        return amb_in, per_shot

    frames: list[Frame] = []
    sheet_rows = []
    stats = {"coverage": [], "lit": []}

    prog = None
    if progress:
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

        prog = Progress(TextColumn("synth {task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                        TimeElapsedColumn(), TimeRemainingColumn(), transient=False)
        prog.start()
        task = prog.add_task(name, total=n_views)
    try:
        for v, c2w in enumerate(poses):
            g = trace(c2w, uv)
            hit, hidx, dh, th, nh, depth, D, Q, vis, to_proj = (g[k] for k in (
                "hit", "hidx", "dh", "th", "nh", "depth", "D", "Q", "vis", "to_proj"))
            # a camera integrates each pixel's area: the photos of a blurred capture are formed from
            # sub x sub rays per pixel (the lens blur on that grid, then the box average)
            gs = trace(c2w, uv_sub) if sub > 1 else g
            nv = hidx.numel()
            bounce_on = cap is not None and cap.interreflection > 0
            if bounce_on:  # light arriving from other surfaces at the pixel centres' hits (smooth:
                # the sub-pixel rays of a pixel share it, each times its own albedo)
                b_amb, b_shot = bounce(c2w, g["P"], nh, v)
                rows = parent[gs["hidx"]] if sub > 1 else gs["hidx"]

                def sent_on(b):  # [hits of g, 3] arriving light -> light leaving gs's hits
                    arrive = torch.zeros(H * W, 3, dtype=torch.float32, device=dev)
                    arrive[hidx] = b
                    return cap.interreflection * gs["albedo"] * arrive[rows]

                ind_amb, ind_shot = sent_on(b_amb), [sent_on(b) for b in b_shot]
            mask = hit.view(H, W)
            water = Water(th, hidx, H * W, dev) if wet else None
            clean = torch.zeros(H * W, 3, dtype=torch.uint8, device=dev)
            if wet:
                clean[:] = _quantise(water.background())
            D_off = D + cap.interreflection * g["albedo"] * b_amb if bounce_on else D  # the projectors off
            off = water.seen(D_off) if wet else D_off
            if cap is not None and cap.mono:  # what the monochrome camera sees with the projectors off
                off = off.mean(dim=1, keepdim=True).expand(-1, 3)
            clean[hidx] = _quantise(off + _noise((nv, 3), noise, (seed, 1, v), dev))
            if cap is not None and cap.mono:
                clean[:] = clean[:, :1].expand(-1, 3)
            normal_img = torch.zeros(H * W, 3, dtype=torch.uint8, device=dev)
            normal_img[hidx] = torch.round((nh + 1) * 0.5 * 255).clamp(0, 255).to(torch.uint8)
            vname = f"{v:03d}"
            write_png(out / "masks" / f"{vname}.png", (mask.to(torch.uint8) * 255).cpu().numpy())
            write_png(out / "clean" / f"{vname}.png", clean.view(H, W, 3).cpu().numpy())
            write_png(out / "normals" / f"{vname}.png", normal_img.view(H, W, 3).cpu().numpy())
            depth_np = depth.view(H, W).cpu().numpy()
            np.save(out / "depth" / f"{vname}.npy", depth_np)
            stats["coverage"].append(nv / (H * W))
            if cap is not None and cap.specular > 0:  # highlights: the ambient light's, each projector's lobe
                lobe_amb = amb * cap.specular * blinn_phong(gs["nh"], -gs["dh"], light, cap.shininess)[:, None]
                lobes = [cap.specular * blinn_phong(gs["nh"], -gs["dh"], gs["to_proj"][k], cap.shininess)[:, None]
                         for k in range(len(pids))]
            for j, shot in enumerate(shots):
                fi = len(frames)
                c = D.clone()
                lit = torch.zeros(nv, dtype=torch.bool, device=dev)
                for k, p in enumerate(pids):
                    qv = Q[j][k] * vis[k][:, None]
                    if cap is None:
                        c = c + (i_r * D + i_b) * qv
                    lit |= qv.amax(dim=1) > 0
                bits = cap.bits if cap is not None else 8
                img = torch.zeros(H * W, 3, dtype=torch.int32 if bits == 16 else torch.uint8, device=dev)
                if cap is not None:  # the camera sees the whole linear image (blur crosses the silhouette)
                    hs, Ds, ns = gs["hidx"], gs["D"], H * W * sub * sub
                    lp = torch.zeros_like(Ds)  # the projected light alone (speckle multiplies it only)
                    for k, p in enumerate(pids):
                        qv = gs["Q"][j][k] * gs["vis"][k][:, None]
                        lp = lp + (i_r * Ds + i_b + (lobes[k] if cap.specular > 0 else 0.0)) * qv
                    # speckle: one grain value per camera pixel (its sub-pixel rays share it)
                    c = Ds + apply_speckle(lp, cap.speckle, (seed, 7, fi), None if sub == 1 else
                                           (parent[hs], H * W)) + (lobe_amb if cap.specular > 0 else 0.0)
                    if bounce_on:  # the surfaces' light reflected once more (ambient and this shot's)
                        c = c + ind_amb + ind_shot[j]
                    lin = torch.zeros(ns, 3, dtype=torch.float32, device=dev)
                    if wet:
                        ws = Water(gs["th"], hs, ns, dev) if sub > 1 else water
                        lin[:] = ws.background()
                        c = ws.seen(c)
                    lin[hs] = c
                    lin = lin.view(H * sub, W * sub, 3)
                    if sub > 1:  # the image noise is the sensor's: added to camera pixels, after the area average
                        lin = sensor_pixels(lin, cap.blur, sub)
                        lin = lin + _noise((H, W, 3), noise, (seed, 2, fi), dev)
                    else:
                        lin = lin.view(H * W, 3)
                        if wet:
                            lin = lin + _noise((H * W, 3), noise, (seed, 3, fi), dev) * (~hit)[:, None]
                        lin[hidx] = lin[hidx] + _noise((nv, 3), noise, (seed, 2, fi), dev)
                        lin = lin.view(H, W, 3)
                    img[:] = _quantise(finish(lin, cap, gains[fi] * wb[fi], (seed, 9, fi), blurred=sub > 1).reshape(-1, 3), bits)
                else:
                    if wet:
                        img[:] = _quantise(water.background() + _noise((H * W, 3), noise, (seed, 3, fi), dev))
                        c = water.seen(c)
                    img[hidx] = _quantise(c + _noise((nv, 3), noise, (seed, 2, fi), dev))
                img_np = img.view(H, W, 3).cpu().numpy()
                photo = img_np[:, :, 0] if cap is not None and cap.mono else img_np  # a grey PNG
                if bits == 16:  # written as 16 bits; the contact sheet shows the top 8
                    write_png(out / "images" / f"{fi:03d}.png", photo.astype(np.uint16))
                    img_np = (img_np >> 8).astype(np.uint8)
                else:
                    write_png(out / "images" / f"{fi:03d}.png", photo)
                stats["lit"].append(float(lit.float().mean()) if nv else 0.0)
                frames.append(Frame(
                    image=f"images/{fi:03d}.png", camera="cam0", cam_to_world=c2w, view=v,
                    projectors={p: FrameProjector(pattern=shot[p], on=True) for p in pids}, mask=f"masks/{vname}.png",
                    gt={"depth": f"depth/{vname}.npy", "normal": f"normals/{vname}.png",
                        "clean": f"clean/{vname}.png"}))
                if contact_sheet and len(sheet_rows) < 4:
                    sheet_rows.append((fi, img_np, mask.cpu().numpy(), depth_np, clean.view(H, W, 3).cpu().numpy()))
            if prog is not None:
                prog.advance(task)
    finally:
        if prog is not None:
            prog.stop()

    scene = Scene(
        root=out.resolve(), cameras={"cam0": Camera(id="cam0", K=K, width=W, height=H, port=port)},
        projectors=projectors, patterns={q: Pattern(id=q, file=f"patterns/{q}.png") for q in pat_images},
        frames=frames, bounds=Bounds(center=centre.astype(np.float64), radius=1.1 * obj_radius),
        illumination=Illumination(i_r=i_r, i_b=i_b, ambient=amb, known=True), gt_mesh="gt_mesh.ply",
        units="m", name=name, response=cap.response if cap is not None else "linear",
        meta={"generator": GENERATOR, "source": src, "pattern": kind, "illum": illum, "albedo": albedo,
              "noise": noise, "seed": seed, "light_dir": list(map(float, light_dir)), "cam_distance": cam_distance,
              "baselines": list(map(float, baselines)), "projector_hfov_deg": proj_fov_deg,
              **({"projector_blur_sigma_px": float(projector_blur), "projector_blur_kernel": taps.tolist()}
                 if taps is not None else {}),
              **({"medium": dict(WATER, kind="water")} if wet else {}),
              **({"capture": cap.to_meta(gains, wb)} if cap is not None else {})})
    if contact_sheet and sheet_rows:
        write_png(out / "contact_sheet.png", _contact_sheet(sheet_rows))
    scene.save(out)
    Scene.load(out)  # validated here, before it replaces the previous output
    return time.perf_counter() - t_start, stats, len(F)


# --------------------------------------------------------------------------- reporting
def _contact_sheet(rows) -> np.ndarray:
    """First frames as rows of image | mask | depth | pattern-free, each tile labelled."""
    import cv2

    tiles_h = 200
    out_rows = []
    for fi, img, mask, depth, clean in rows:
        H, W = mask.shape
        s = tiles_h / H
        size = (max(1, round(W * s)), tiles_h)
        dn = np.zeros((H, W, 3), np.uint8)
        if mask.any():
            lo, hi = depth[mask].min(), depth[mask].max()
            g = ((depth - lo) / max(hi - lo, 1e-9) * 255).clip(0, 255).astype(np.uint8)
            dn = cv2.applyColorMap(255 - g, cv2.COLORMAP_VIRIDIS)[:, :, ::-1].copy()
            dn[~mask] = 0
        tiles = []
        for label, t in ((f"frame {fi}", img), ("mask", np.repeat((mask * 255).astype(np.uint8)[:, :, None], 3, 2)),
                         ("depth", dn), ("pattern-free", clean)):
            t = cv2.resize(np.ascontiguousarray(t), size, interpolation=cv2.INTER_AREA)
            cv2.putText(t, label, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 3, cv2.LINE_AA)
            cv2.putText(t, label, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
            tiles.append(t)
            tiles.append(np.full((tiles_h, 4, 3), 64, np.uint8))
        out_rows.append(np.concatenate(tiles[:-1], axis=1))
        out_rows.append(np.full((4, out_rows[-1].shape[1], 3), 64, np.uint8))
    return np.concatenate(out_rows[:-1], axis=0)


def _summary(scene: Scene, out: Path, seconds: float, stats, n_faces: int) -> None:
    from rich.console import Console
    from rich.table import Table

    cam = scene.cameras["cam0"]
    t = Table(title=f"synthetic scene: {out}", show_header=False)
    t.add_row("object", f"{scene.name} ({n_faces} faces), bounds radius {scene.bounds.radius:.3f} m")
    t.add_row("frames", f"{len(scene.frames)} ({len(scene.views())} views), {cam.width}x{cam.height}")
    t.add_row("projectors", f"{len(scene.projectors)} x {next(iter(scene.projectors.values())).width}x"
                            f"{next(iter(scene.projectors.values())).height}, pattern {scene.meta['pattern']}")
    il = scene.illumination
    t.add_row("illumination", f"{scene.meta['illum']}: ambient {il.ambient}, i_r {il.i_r}, i_b {il.i_b}")
    t.add_row("object pixels", f"{100 * np.mean(stats['coverage']):.1f}% of the image, "
                               f"{100 * np.mean(stats['lit']):.1f}% of them pattern-lit")
    if "capture" in scene.meta:
        cp = scene.meta["capture"]
        t.add_row("capture", ", ".join(f"{k} {v}" for k, v in cp.items() if k != "gains" and v) +
                  f"; gains {min(cp['gains']):.2f}..{max(cp['gains']):.2f}")
    t.add_row("time", f"{seconds:.1f} s")
    Console().print(t)
