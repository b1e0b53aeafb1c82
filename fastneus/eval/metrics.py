"""Renders and metrics of a trained run against the scene's ground truth.

Geometry (world units, reported in mm): Chamfer GT->reconstruction as in the paper,
with and without the 1-sigma outlier filter; symmetric Chamfer; F-score at 1% of the
bounding-box diagonal; for few-view/one-shot scenes the error of the GT surface visible
from the training cameras (GT depth back-projected). Images: PSNR with the pattern
(vs the photo) and without it (vs the GT pattern-free image), depth error, mask IoU.
Illumination: |i_r - gt| and |i_b - gt|.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

from fastneus.errors import FastneusError
from fastneus.field.renderer import render_image
from fastneus.data.response import decode_lut, encode
from fastneus.train.rays import RayBank, build_projection


def _nn_dist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from each point of ``a`` [N,3] to its nearest neighbour in ``b`` [M,3]."""
    if len(b) == 0:
        return np.full(len(a), np.inf)
    return cKDTree(b).query(a, k=1, workers=-1)[0]


def sample_surface(mesh: trimesh.Trimesh, n: int, seed: int = 0) -> np.ndarray:
    """[n, 3] points uniformly on the mesh surface (deterministic for a seed)."""
    if len(mesh.faces) == 0:
        return np.zeros((0, 3))
    pts, _ = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return np.asarray(pts)


def chamfer_metrics(gt_pts: np.ndarray, rec_pts: np.ndarray, diag: float, prefix: str = "") -> dict:
    """Distances in mm between point sets in metres.

    Args:
        gt_pts: [N, 3] points on the GT surface; rec_pts: [M, 3] on the reconstruction.
        diag: bounding-box diagonal of the GT (metres), for the F-score threshold (1%).
    """
    if len(rec_pts) == 0:
        return {f"{prefix}chamfer_gt2rec_mm": math.inf, f"{prefix}fscore": 0.0}
    d_g2r = _nn_dist(gt_pts, rec_pts)
    d_r2g = _nn_dist(rec_pts, gt_pts)
    mu, sd = d_g2r.mean(), d_g2r.std()
    filt = d_g2r[d_g2r <= mu + sd]
    tau = 0.01 * diag
    prec, rec = float((d_r2g < tau).mean()), float((d_g2r < tau).mean())
    f = 2 * prec * rec / (prec + rec) if prec + rec > 0 else 0.0
    return {
        f"{prefix}chamfer_gt2rec_mm": float(mu * 1000),
        f"{prefix}chamfer_gt2rec_filtered_mm": float(filt.mean() * 1000),
        f"{prefix}chamfer_rec2gt_mm": float(d_r2g.mean() * 1000),
        f"{prefix}chamfer_sym_mm": float(0.5 * (mu + d_r2g.mean()) * 1000),
        f"{prefix}fscore": f, f"{prefix}precision": prec, f"{prefix}recall": rec,
        f"{prefix}fscore_tau_mm": float(tau * 1000),
    }


def visible_gt_points(scene, frames: list[int], max_points: int = 200_000, seed: int = 0) -> np.ndarray:
    """GT surface points seen by ``frames``' cameras: GT z-depth back-projected to world [N, 3]."""
    pts = []
    for i in frames:
        depth = scene.gt_depth(i)
        if depth is None:
            continue
        cam = scene.frame_camera(i)
        v, u = np.nonzero(depth > 0)
        z = depth[v, u]
        pix = np.stack([u + 0.5, v + 0.5, np.ones_like(z)], 0)
        xc = (np.linalg.inv(cam.K) @ pix) * z[None]
        c2w = scene.cam_to_world(i)
        pts.append((c2w[:3, :3] @ xc + c2w[:3, 3:4]).T)
    if not pts:
        return np.zeros((0, 3))
    p = np.concatenate(pts)
    if len(p) > max_points:
        p = p[np.random.default_rng(seed).choice(len(p), max_points, replace=False)]
    return p


def geometry_metrics(mesh: trimesh.Trimesh, scene, train_frames: list[int], n_points: int = 100_000) -> dict:
    """Chamfer/F-score against the scene's GT mesh (if any) and the visible GT surface."""
    out: dict = {"mesh_vertices": int(len(mesh.vertices)), "mesh_faces": int(len(mesh.faces))}
    rec = sample_surface(mesh, n_points, seed=1)
    if scene.gt_mesh:
        try:
            gt_mesh = trimesh.load(scene.path(scene.gt_mesh), force="mesh", process=False)
        except Exception as e:  # noqa: BLE001 - trimesh raises many types for bad files
            raise FastneusError(f"cannot load the ground-truth mesh {scene.path(scene.gt_mesh)}: "
                                f"{type(e).__name__}: {e}".splitlines()[0], file=Path(scene.root) / "scene.json",
                                field="gt.mesh") from None
        gt = sample_surface(gt_mesh, n_points, seed=0)
        diag = float(np.linalg.norm(gt_mesh.bounds[1] - gt_mesh.bounds[0]))
        out.update(chamfer_metrics(gt, rec, diag))
        vis = visible_gt_points(scene, train_frames, n_points)
        if len(vis):
            d = _nn_dist(vis, rec)
            out["visible_gt2rec_mm"] = float(d.mean() * 1000) if len(rec) else math.inf
            out["visible_gt2rec_filtered_mm"] = float(d[d <= d.mean() + d.std()].mean() * 1000) if len(rec) else math.inf
    return out


def _psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    d = (a.astype(np.float64) - b.astype(np.float64)) ** 2
    if mask is not None:
        d = d[mask]
    mse = float(d.mean()) if d.size else 0.0
    return -10 * math.log10(max(mse, 1e-12))


def to_u8(x: np.ndarray) -> np.ndarray:
    return (np.clip(x, 0, 1) * 255 + 0.5).astype(np.uint8)


def depth_to_z(scene, i: int, t: np.ndarray, h: int, w: int) -> np.ndarray:
    """Normalised ray distance t [H*W] -> world z-depth [H, W] of frame i's camera."""
    cam = scene.frame_camera(i)
    v, u = np.mgrid[0:h, 0:w]
    d = np.linalg.inv(cam.K) @ np.stack([u.ravel() + 0.5, v.ravel() + 0.5, np.ones(h * w)])
    cos = 1.0 / np.linalg.norm(d, axis=0)  # z-component of the unit camera ray
    return (t * float(scene.bounds.radius) * cos).reshape(h, w)


def render_frames(trainer, frames: list[int], chunk: int = 8192) -> dict[int, dict]:
    """Full-image renders (numpy, [H,W,...]) of scene frames with the trained model.

    A trainer with its own renderer (``render_image_rays(origins, dirs, fidx, chunk, proj=...)``,
    e.g. the reference baseline) is used through it; otherwise the fastneus field and grid.
    """
    scene, cfg = trainer.scene, trainer.cfg
    # fastneus's sectioned config; the NeuS-MLP baseline's flat one has no ports
    refr = trainer.cfg.rig.refraction if hasattr(trainer.cfg, "rig") else True
    rig = getattr(trainer, "rig", None)
    posed = rig.eval_scene() if rig is not None else scene  # learned pose corrections, if any
    bank = RayBank(posed, frames, trainer.device, refraction=refr)
    proj = build_projection(posed, frames, trainer.device, refraction=refr,
                           camera_blur=getattr(trainer, "pattern_blur", 0.0))
    if getattr(trainer, "rig", None) is not None:  # learned light model (blur...); poses are per training frame
        proj = trainer.rig.light_model(proj)
    i_r, i_b = (x.detach() for x in trainer.illumination())
    # the camera: the learned exposure of training frames (1 elsewhere) and the response (linear: none)
    response = str(getattr(trainer, "response", "linear"))
    lut = decode_lut(response)
    gain = {}
    if getattr(trainer, "log_gain", None) is not None:
        from fastneus.train.losses import frame_log_gains

        gain = dict(zip(trainer.frames, frame_log_gains(trainer.log_gain.detach()).exp().cpu().tolist()))
    out = {}
    for a, i in enumerate(frames):
        o, d, (h, w) = bank.image_rays(a)
        fidx = torch.full((o.shape[0],), a, dtype=torch.int32, device=o.device)
        if hasattr(trainer, "render_image_rays"):
            r = trainer.render_image_rays(o, d, fidx, chunk=chunk, proj=proj)
        else:
            r = render_image(trainer.field, trainer.grid.bits, trainer.grid.resolution, proj, o, d, fidx, cfg,
                             i_r=i_r, i_b=i_b, chunk=chunk)
        if rig is not None:  # in water: attenuation + back-scatter (fastneus.train.rig)
            with torch.no_grad():
                color, texture = (rig.composite(r[k], r, cfg.rays.background) for k in ("color", "texture"))
        else:
            bg = cfg.rays.background * (1 - r["opacity"])[:, None]
            color, texture = r["color"] + bg, r["texture"] + bg
        photo = bank.image(a).cpu().numpy()
        back = 1.0 / float(getattr(trainer, "photo_gain", 1.0))  # trained on scaled photos (illum.level)
        black = float(getattr(trainer, "photo_black", 0.0))  # and without the camera's black level (illum.black)
        out[i] = {
            # the photo's prediction (linear; with the black level taken off in training, put back)
            "color": color.numpy().reshape(h, w, 3) * (gain.get(i, 1.0) * back) * (1.0 - black) + black,
            "texture": texture.numpy().reshape(h, w, 3) * back,
            "opacity": r["opacity"].numpy().reshape(h, w),
            "depth": depth_to_z(scene, i, r["depth"].numpy() / np.maximum(r["opacity"].numpy(), 1e-6), h, w),
            "normal": r["normal"].numpy().reshape(h, w, 3),
            "photo": photo,
            "photo_linear": lut[photo],
            "response": response,
        }
    return out


def image_metrics(scene, renders: dict[int, dict]) -> dict:
    """PSNR with/without pattern, depth error (mm), mask IoU, averaged over rendered frames."""
    acc: dict[str, list[float]] = {}
    add = lambda k, v: acc.setdefault(k, []).append(v)  # noqa: E731
    for i, r in renders.items():
        add("psnr_pattern", _psnr(np.minimum(r["color"], 1.0), r.get("photo_linear", r["photo"] / 255.0)))
        clean = scene.gt_clean(i)
        if clean is not None:
            add("psnr_texture", _psnr(r["texture"], clean / 255.0))
        gtd = scene.gt_depth(i)
        m = scene.mask(i)
        if m is not None:
            pm, gm = r["opacity"] > 0.5, m > 0.5
            union = (pm | gm).sum()
            add("mask_iou", float((pm & gm).sum() / union) if union else 1.0)
        if gtd is not None:
            valid = (gtd > 0) & (r["opacity"] > 0.5)
            if valid.any():
                add("depth_mae_mm", float(np.abs(r["depth"][valid] - gtd[valid]).mean() * 1000))
    return {k: float(np.mean(v)) for k, v in acc.items()}


def illumination_metrics(trainer) -> dict:
    if hasattr(trainer, "photo_illumination"):  # in the photos' units (illum.level)
        i_r, i_b = trainer.photo_illumination()
    else:
        i_r, i_b = (float(x.detach()) for x in trainer.illumination())
    out = {"i_r": i_r, "i_b": i_b}
    ill = trainer.scene.illumination
    if ill is not None and ill.known:
        out.update({"i_r_gt": float(ill.i_r), "i_b_gt": float(ill.i_b),
                    "i_r_err": abs(i_r - float(ill.i_r)), "i_b_err": abs(i_b - float(ill.i_b))})
    out.update(exposure_metrics(trainer))
    return out


def exposure_metrics(trainer) -> dict:
    """The learned per-photo exposure gains (training frames, the first = 1) and, when the scene
    records the true ones (``meta.capture.gains`` of ``fastneus synth``), their error relative to
    the first training frame's: ``exposure_err`` = max |learned / true - 1|."""
    if getattr(trainer, "log_gain", None) is None:
        return {}
    from fastneus.train.losses import frame_log_gains

    g = frame_log_gains(trainer.log_gain.detach()).exp().cpu().numpy()
    out = {"exposure_gains": [round(float(v), 5) for v in g]}
    true = (trainer.scene.meta or {}).get("capture", {}).get("gains")
    if isinstance(true, list) and len(true) == len(trainer.scene.frames):
        t = np.asarray([float(true[i]) for i in trainer.frames])
        t = t / t[0]
        out["exposure_err"] = float(np.abs(g / t - 1).max())
    return out


def save_renders(renders: dict[int, dict], folder: Path) -> dict[int, dict[str, str]]:
    """Write PNGs per frame (photo, color, texture, depth, normals); returns relative paths."""
    from fastneus.io import atomic_write_image

    folder.mkdir(parents=True, exist_ok=True)
    paths: dict[int, dict[str, str]] = {}
    for i, r in renders.items():
        d = r["depth"]
        valid = r["opacity"] > 0.5
        dv = np.zeros_like(d)
        if valid.any():
            lo, hi = np.percentile(d[valid], [1, 99])
            dv = np.where(valid, 1 - (d - lo) / max(hi - lo, 1e-6) * 0.8, 0)
        # normals only where the surface is solid: faint fog would show as a grey halo
        n = r["normal"] / np.maximum(np.linalg.norm(r["normal"], axis=-1, keepdims=True), 1e-6)
        resp = r.get("response", "linear")  # renders are linear: encoded like the photos to compare with them
        imgs = {"photo": r["photo"], "color": to_u8(encode(r["color"], resp)), "texture": to_u8(encode(r["texture"], resp)),
                "depth": to_u8(np.repeat(dv[..., None], 3, -1)), "normal": to_u8((n + 1) * 0.5 * valid[..., None])}
        paths[i] = {}
        for k, img in imgs.items():
            p = folder / f"{i:03d}_{k}.png"
            atomic_write_image(p, img)
            paths[i][k] = f"{folder.name}/{p.name}"
    return paths
