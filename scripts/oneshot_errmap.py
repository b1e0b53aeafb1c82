"""Where a one-shot run's depth error is (issue 23): per-pixel error of the run's mesh, by region.

    python scripts/oneshot_errmap.py SCENE RUN [--sweep DEPTH.npy] [--png OUT.png] [--json OUT.json]

The run's ``mesh.ply`` is ray-cast from the scene's frame 0 (as ``fastneus eval`` does) and the
relative depth error |z_rec - z_gt| / z_gt is split over regions of the ground-truth depth map:

- ``silhouette``: within 3 px of the object's outline;
- ``depth_jump``: within 3 px of a jump of more than 2 % between neighbouring GT depths (an
  occlusion inside the object, e.g. the toy's fin behind the cup's rim), outline excluded;
- ``interior``: the rest;
- ``saturated``: a channel of the photo at 254 or more;
- ``sweep`` / ``no_sweep``: pixels with / without a plane-sweep point (``--sweep``: a [H, W] or
  [2, H, W] .npy of camera z-depth, NaN where rejected, e.g. from
  ``fastneus.classical.planesweep.planesweep_depth``).

Per region: pixels, mean error %, its share of the summed error of all pixels, share within 1 %.
Then the same per connected part of the GT depth map (split at the depth jumps), with its bbox,
which names the part (on the toy: cup, fin, torus, sphere). ``--png``: photo | error map (0-2 %,
magenta = missing surface).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

import fastneus
from fastneus.eval.depth import error_map, mesh_depth


def regions(gt, photo, sweep=None) -> dict[str, np.ndarray]:
    """[H, W] bool masks of the regions in the module docstring.

    Args:
        gt: [H, W] GT z-depth (<= 0: background); photo: [H, W, 3] uint8; sweep: [H, W] or None.
    """
    import cv2

    has = gt > 0
    sil = has & (cv2.erode(has.astype(np.uint8), np.ones((7, 7), np.uint8)) == 0)
    g = np.where(has, gt, np.nan)
    jump = np.zeros(gt.shape, bool)
    with np.errstate(invalid="ignore"):
        for shift in ((0, 1), (1, 0), (0, -1), (-1, 0)):
            jump |= np.abs(np.roll(g, shift, (0, 1)) - g) > 0.02 * g
    jump = cv2.dilate(jump.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool) & has & ~sil
    out = {"all": has, "silhouette": sil, "depth_jump": jump, "interior": has & ~sil & ~jump,
           "saturated": has & (photo >= 254).any(2)}
    if sweep is not None:
        out["sweep"] = has & np.isfinite(sweep)
        out["no_sweep"] = has & ~np.isfinite(sweep)
    return out


def summarise(rel, masks: dict[str, np.ndarray]) -> dict[str, dict]:
    """Per region: px, mean %, share of the summed error, within 1 % (holes count as misses).

    Args:
        rel: [H, W] relative error in % (NaN: background or missing surface).
        masks: name -> [H, W] bool.
    """
    total = float(np.nansum(rel))
    out = {}
    for name, m in masks.items():
        r = rel[m]
        r = r[np.isfinite(r)]
        out[name] = {"px": int(m.sum()), "mean_pct": float(r.mean()) if r.size else None,
                     "share_of_error": float(r.sum() / total) if total > 0 else None,
                     "within_1pct": float((r < 1).sum() / max(1, int(m.sum())))}
    return out


def main(argv=None) -> None:
    import cv2
    import trimesh

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene")
    ap.add_argument("run")
    ap.add_argument("--sweep", help=".npy plane-sweep depth of frame 0 ([H, W] or [2, H, W], first = depth)")
    ap.add_argument("--png")
    ap.add_argument("--json")
    a = ap.parse_args(argv)
    sc = fastneus.load_scene(a.scene)
    mesh = trimesh.load(Path(a.run) / "mesh.ply", process=False)
    cam = sc.frame_camera(0)
    z = mesh_depth(mesh.vertices, mesh.faces, cam.K, sc.cam_to_world(0), cam.width, cam.height)
    gt = sc.gt_depth(0)
    ok = (gt > 0) & np.isfinite(z) & (z > 0)
    rel = np.full(gt.shape, np.nan)
    rel[ok] = np.abs(z[ok] - gt[ok]) / gt[ok] * 100.0
    sweep = None
    if a.sweep:
        sweep = np.load(a.sweep)
        sweep = sweep[0] if sweep.ndim == 3 else sweep
    masks = regions(gt, sc.image(0), sweep)
    res = {"regions": summarise(rel, masks)}
    n, lab = cv2.connectedComponents((masks["all"] & ~masks["depth_jump"] & ~masks["silhouette"]).astype(np.uint8))
    parts = {}
    for j in range(1, n):
        m = lab == j
        if m.sum() >= 200:
            ys, xs = np.nonzero(m)
            parts[f"part{j} x{xs.min()}-{xs.max()} y{ys.min()}-{ys.max()}"] = m
    res["parts"] = summarise(rel, parts)
    for group, rows in res.items():
        for name, r in rows.items():
            print(f"{group:8s} {name:32s} px {r['px']:6d} mean {r['mean_pct'] or 0:6.3f} % "
                  f"share {r['share_of_error'] or 0:5.2f} within 1 % {r['within_1pct']:.3f}")
    if a.png:
        cv2.imwrite(a.png, np.concatenate([sc.image(0), error_map(z, gt, 2.0)], 1)[:, :, ::-1])
    if a.json:
        Path(a.json).write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
