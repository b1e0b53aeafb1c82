"""Empty pockets in a run's field: how deep they go, which cameras see into them, what filling them would change.

A realistic capture without masks leaves the lit-room ant with surface inside the object
(``scripts/floaters.py``: 73 % of its far error lies inside the GT solid). This script answers the
next questions on the field itself, from a dense SDF grid:

- **where**: the positive (empty) grid nodes inside the GT solid and deeper than ``--depth-mm``
  below its surface, their volume and their spread along each axis;
- **seen?**: for each of those nodes, how many training views have it in frame and how many see it
  (it lies in front of the first surface along the camera's ray, from per-view depth maps marched
  through the same grid). A pocket no camera sees could be filled after training for free;
  one that some views see into is open to the outside;
- **hidden space**: positive nodes inside the unit ball that some view frames and none sees;
- **filling narrow pockets**: the positive nodes that the outside cannot reach once openings
  narrower than a ball of ``r`` grid cells are closed (a morphological closing used only to decide
  reachability), set negative, and the mesh's Chamfer / F-score against the GT for each ``r``.

Usage::

    python scripts/pockets.py SCENE RUN [--res 256] [--save-grid G.npz] [--json OUT]
    python scripts/pockets.py SCENE --grid G.npz          # a grid saved earlier (e.g. on a GPU machine)

The grid is ``fastneus.export.mesh.sdf_grid`` of the run's field with the run's clamps (bound and
the views' volume), saved clipped to +-0.05 (normalised units) as int16: near the surface that is
1.5e-6 per step; pockets and their walls lie well inside that band.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import fastneus  # noqa: F401  (before torch: it sets the OpenMP spin the product runs with)
import numpy as np
import torch

CLIP = 0.05  # normalised SDF units kept in a saved grid (beyond: saturated)


# ----------------------------------------------------------------------------- the grid
def save_grid(path: Path, grid: np.ndarray, frames: list[int]) -> None:
    """[N, N, N] float SDF (indexed [x, y, z], nodes of linspace(-1, 1, N)) as clipped int16 + the frames."""
    from fastneus.io import atomic_write

    q = (np.clip(grid, -CLIP, CLIP) * (32767 / CLIP)).round().astype(np.int16)

    def write(tmp: str) -> None:  # a file object: numpy adds no ".npz" to the name
        with open(tmp, "wb") as f:
            np.savez_compressed(f, sdf=q, frames=np.asarray(frames, dtype=np.int64))
    atomic_write(path, write)  # built aside and renamed: a link at ``path`` is replaced, never written through


def load_grid(path: Path) -> tuple[np.ndarray, list[int]]:
    """The grid and training frames of :func:`save_grid` (no pickles: plain arrays only)."""
    with np.load(path, allow_pickle=False) as z:
        g = z["sdf"]
        if g.dtype != np.int16 or g.ndim != 3 or len(set(g.shape)) != 1:
            raise SystemExit(f"{path}: sdf must be an int16 N^3 grid, got {g.dtype} {g.shape}")
        return g.astype(np.float32) * (CLIP / 32767), [int(x) for x in z["frames"]]


def run_grid(run: Path, res: int, device: str) -> tuple[np.ndarray, list[int], object]:
    """The dense SDF grid of a run folder's field (its checkpoint), the training frames and the scene."""
    from fastneus.export.mesh import sdf_grid
    from fastneus.pipeline import open_run

    scene, tr = open_run(str(run), device)
    g = sdf_grid(tr.field, res, device, bound=tr.cfg.rays.bound, allowed=tr.seen)
    return g, list(tr.frames), scene


def _world(scene, idx: np.ndarray, n: int) -> np.ndarray:
    """[M, 3] grid node subscripts -> world positions [M, 3]."""
    S = scene.normalisation()
    return (-1.0 + idx * (2.0 / (n - 1))) * S[0, 0] + S[:3, 3]


# ----------------------------------------------------------------------------- visibility
@torch.no_grad()
def depth_maps(grid: np.ndarray, scene, frames: list[int], steps: int = 768, chunk: int = 4096) -> dict[int, np.ndarray]:
    """Per view, the camera-z depth [H, W] (world units) of the first negative SDF sample along each
    pixel-centre ray inside the unit ball (inf where the ray meets none), trilinear in ``grid``."""
    from fastneus.geometry.projection import pixel_rays, unit_sphere_chord

    G = torch.from_numpy(np.ascontiguousarray(grid.transpose(2, 1, 0)))[None, None]  # grid_sample: [z, y, x]
    S = scene.normalisation()
    ts = torch.linspace(0.0, 1.0, steps, dtype=torch.float64)
    out = {}
    for i in frames:
        cam = scene.frame_camera(i)
        c2w = np.asarray(scene.cam_to_world(i), dtype=np.float64)
        v, u = torch.meshgrid(torch.arange(cam.height, dtype=torch.float64) + 0.5,
                              torch.arange(cam.width, dtype=torch.float64) + 0.5, indexing="ij")
        o, d = pixel_rays(np.asarray(cam.K, dtype=np.float64), c2w, torch.stack([u, v], -1).reshape(-1, 2), S)
        t0, t1 = unit_sphere_chord(o, d)                                   # normalised units along unit d
        to_z = (d @ torch.from_numpy(c2w[:3, 2])) * S[0, 0]              # camera z per normalised t
        depth = torch.full((d.shape[0],), float("inf"), dtype=torch.float64)
        hits = torch.nonzero(t1 > t0)[:, 0]
        for k in range(0, len(hits), chunk):
            sel = hits[k:k + chunk]
            T = t0[sel, None] + (t1[sel] - t0[sel])[:, None] * ts[None]    # [m, steps]
            p = o[sel, None] + T[..., None] * d[sel, None]
            f = torch.nn.functional.grid_sample(G, p.float()[None, None], align_corners=True,
                                                padding_mode="border")[0, 0, 0]
            neg = f < 0
            t_hit = T.gather(1, neg.float().argmax(1, keepdim=True))[:, 0]
            depth[sel] = torch.where(neg.any(1), t_hit * to_z[sel], depth[sel])
        out[i] = depth.reshape(cam.height, cam.width).numpy()
    return out


def view_counts(world: np.ndarray, scene, frames: list[int], depth: dict[int, np.ndarray],
                margin: float) -> tuple[np.ndarray, np.ndarray]:
    """For points [M, 3] (world): in how many views each is in frame, and in how many it is seen
    (its camera z at most its pixel's first-surface depth + ``margin``, world units)."""
    from fastneus.geometry.projection import project_points

    framed = np.zeros(len(world), dtype=np.int64)
    seen = np.zeros(len(world), dtype=np.int64)
    pts = torch.from_numpy(np.asarray(world, dtype=np.float64))
    for i in frames:
        cam = scene.frame_camera(i)
        uv, zc = project_points(pts, np.asarray(cam.K, dtype=np.float64), scene.world_to_cam(i))
        uv, zc = uv.numpy(), zc.numpy()
        ui, vi = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
        ok = (zc > 1e-6) & (ui >= 0) & (ui < cam.width) & (vi >= 0) & (vi < cam.height)
        d = np.full(len(world), -np.inf)
        d[ok] = depth[i][vi[ok], ui[ok]]
        framed += ok
        seen += ok & (zc <= d + margin)
    return framed, seen


# ----------------------------------------------------------------------------- pockets
def _ball(n: int) -> np.ndarray:
    lin = np.linspace(-1.0, 1.0, n)
    return (lin[:, None, None] ** 2 + lin[None, :, None] ** 2 + lin[None, None, :] ** 2) < 1.0


def narrow_pockets(grid: np.ndarray, radius: int) -> np.ndarray:
    """[N, N, N] bool: positive nodes behind openings narrower than a ball of ``radius`` nodes
    (0: enclosed voids only).

    The solid (negative nodes) is closed by that ball only to decide what the outside reaches:
    the free nodes still connected to the outside of the unit ball after the closing are the
    exterior. A free node is a pocket when the exterior is more than ``radius`` steps away
    through free space, so the closing's own fill near the exterior (a concave corner, a shallow
    dent, an opening's first ``radius`` nodes) is never marked and the solid is not grown there.
    """
    from scipy import ndimage

    solid = grid < 0
    free = ~solid
    if radius > 0:
        a = np.arange(-radius, radius + 1)
        k = (a[:, None, None] ** 2 + a[None, :, None] ** 2 + a[None, None, :] ** 2) <= radius * radius
        solid_c = ndimage.binary_closing(solid, structure=k, border_value=0)
    else:
        solid_c = solid
    lab, _ = ndimage.label(~solid_c)
    outside = ~_ball(grid.shape[0])
    reach = np.unique(lab[outside & ~solid_c])
    ext = np.isin(lab, reach[reach > 0])
    if radius > 0:  # the exterior grown by ``radius`` steps through free space
        ext = ndimage.binary_dilation(ext, ndimage.generate_binary_structure(3, 1), iterations=radius, mask=free)
    return free & ~ext


def mesh_metrics(grid: np.ndarray, scene, frames: list[int]) -> dict:
    """The export's dense reference mesh of the grid (marching cubes, world units, small pieces
    dropped) against the GT."""
    from fastneus.eval.metrics import geometry_metrics
    from fastneus.export.mesh import mesh_from_grid

    m = geometry_metrics(mesh_from_grid(grid, scene.bounds.center, float(scene.bounds.radius)), scene, frames)
    return {k: round(float(m[k]), 3) for k in ("chamfer_gt2rec_mm", "chamfer_rec2gt_mm", "chamfer_sym_mm", "fscore")
            if k in m}


def analyse(scene, grid: np.ndarray, frames: list[int], depth_mm: float = 10.0, closings=(0, 1, 2, 3),
            margin_cells: float = 1.0, views: bool = True) -> dict:
    """Everything the module docstring lists, as one JSON-able dict (``views`` False: the fill only)."""
    import trimesh
    from scipy.spatial import cKDTree

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from floaters import winding_number

    from fastneus.eval.metrics import sample_surface

    n = grid.shape[0]
    S = scene.normalisation()
    cell = 2.0 / (n - 1) * S[0, 0]
    res: dict = {"resolution": n, "cell_mm": round(cell * 1000, 2), "margin_mm": round(margin_cells * cell * 1000, 2)}
    if views:
        depth = depth_maps(grid, scene, frames)
        # hidden space: positive nodes inside the ball that a view frames and none sees
        idx = np.argwhere((grid > 0) & _ball(n))
        framed, seen = view_counts(_world(scene, idx, n), scene, frames, depth, margin_cells * cell)
        res["hidden_positive_nodes"] = int(((framed > 0) & (seen == 0)).sum())
    if views and scene.gt_mesh:
        gt = trimesh.load(scene.path(scene.gt_mesh), force="mesh", process=False)
        pos = np.argwhere(grid > 1e-3)
        w = _world(scene, pos, n)
        lo, hi = gt.bounds
        w = w[np.all((w > lo) & (w < hi), 1)]
        ins = w[winding_number(gt, w) > 0.5]
        d, _ = cKDTree(sample_surface(gt, 300000, seed=0)).query(ins)  # seeded: the same nodes every run
        deep = ins[d > depth_mm / 1000]
        f2, s2 = view_counts(deep, scene, frames, depth, margin_cells * cell)
        res["inside_gt"] = {
            "depth_mm": depth_mm, "nodes": int(len(deep)), "volume_cm3": round(len(deep) * cell ** 3 * 1e6, 1),
            "axis_percentiles_5_50_95_m": np.round(np.percentile(deep, [5, 50, 95], axis=0), 3).T.tolist() if len(deep) else [],
            "views_framing_hist": np.bincount(f2, minlength=len(frames) + 1).tolist(),
            "views_seeing_hist": np.bincount(s2, minlength=len(frames) + 1).tolist()}
    if scene.gt_mesh:
        res["fill"] = []
        for r in closings:
            pk = narrow_pockets(grid, r)
            filled = np.where(pk, -np.abs(grid) - 1e-4, grid)
            res["fill"].append({"radius_cells": r, "radius_mm": round(r * cell * 1000, 1), "filled_nodes": int(pk.sum()),
                                **mesh_metrics(filled, scene, frames)})
    return res


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("run", type=Path, nargs="?", help="run folder (its checkpoint); or --grid")
    ap.add_argument("--grid", type=Path, help="a grid saved by --save-grid")
    ap.add_argument("--save-grid", type=Path, help="write the run's grid here and stop")
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--depth-mm", type=float, default=10.0)
    ap.add_argument("--closing", default="0,1,2,3", help="closing radii in grid cells")
    ap.add_argument("--fill-only", action="store_true", help="skip the views and the depth below the GT")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args(argv)
    from fastneus.data import Scene

    if (a.run is None) == (a.grid is None):
        raise SystemExit("give a run folder or --grid, not both")
    if a.grid is not None:
        grid, frames = load_grid(a.grid)
        scene = Scene.load(a.scene)
    else:
        grid, frames, scene = run_grid(a.run, a.res, a.device)
        if a.save_grid:
            save_grid(a.save_grid, grid, frames)
            print(f"grid {grid.shape[0]}^3 -> {a.save_grid}")
            return
    res = analyse(scene, grid, frames, a.depth_mm, [int(x) for x in a.closing.split(",") if x.strip()],
                  views=not a.fill_only)
    print(json.dumps(res, indent=1))
    if a.json:
        from fastneus.io import atomic_write_text

        atomic_write_text(a.json, json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
