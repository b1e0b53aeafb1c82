"""Where a run's surplus surface is (rec->GT error): its pieces far from the ground truth, located.

    python scripts/floaters.py SCENE RUN [--tau-mm T] [--json OUT.json]

The run's ``mesh.ply`` (world units) is compared with the scene's ground-truth mesh. Faces whose
centre lies farther than ``tau`` from the GT surface (default: 0.25 % of the GT's bounding-box
diagonal, 5.4 mm on synth's ~2 m objects: a quarter of the F-score's threshold, which a floater a
few mm off the surface never crosses) are grouped into edge-connected pieces; each piece is printed with its
area, its share of the mesh's area-weighted rec->GT error, its centroid, its mean / largest
distance, and how many of the photos' masks cover its centroid (all of them: the piece sits inside
the masks' visual hull, where only the photos' colours can remove it; fewer: a mask says empty
space there, so the mask term failed to carve it). Also: whether the piece is attached to the
main surface (shares an edge with a near face) or floats on its own, and how much of the far error
lies inside the GT solid (a generalised winding number over an area-weighted sample of the far
faces): surface inside the object is an empty pocket in the field, surface outside it a floater or a
fattened part.

Written for issue 23's masked realistic ant, whose GPU runs show rec->GT 4.2-6.3 mm against GT->rec
~3.2 mm (docs/benchmarks/quality-matrix-gpu-capture-axis.md).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def load_masks(scene) -> list:
    """[(mask [H, W], K [3, 3], world->camera [4, 4])] of every frame with a mask, read once."""
    out = []
    for i in range(len(scene.frames)):
        m = scene.mask(i)
        if m is not None:
            out.append((m, scene.frame_camera(i).K, np.linalg.inv(scene.cam_to_world(i))))
    return out


def mask_cover(masks: list, point: np.ndarray) -> tuple[int, int]:
    """(masks whose pixel at ``point`` is set, frames with a mask that see ``point``); ``masks`` from
    :func:`load_masks`."""
    covered = seen = 0
    for m, K, w2c in masks:
        xc = w2c[:3, :3] @ point + w2c[:3, 3]
        if xc[2] <= 0:
            continue
        u, v, _ = K @ (xc / xc[2])
        c, r = int(np.floor(u)), int(np.floor(v))
        if not (0 <= r < m.shape[0] and 0 <= c < m.shape[1]):
            continue
        seen += 1
        covered += int(m[r, c] > 0.5)
    return covered, seen


def winding_number(mesh, points: np.ndarray, chunk: int = 1 << 20) -> np.ndarray:
    """Generalised winding number of ``mesh`` at each point (~1 inside a closed surface, ~0 outside).

    Args:
        mesh: trimesh.Trimesh (oriented faces; need not be watertight: the value degrades smoothly).
        points: [P, 3].
        chunk: triangle-point pairs per numpy batch (memory bound).
    Returns:
        [P] float: the sum over faces of the solid angle each subtends at the point, / 4 pi
        (Van Oosterom and Strackee's formula).
    """
    tri = np.asarray(mesh.triangles, dtype=np.float64)  # [F, 3, 3]
    t0, t1, t2 = (np.ascontiguousarray(tri[:, k].T) for k in range(3))  # [3, F] each: x, y, z rows
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    out = np.zeros(len(pts))
    step = max(1, chunk // max(len(tri), 1))
    for s in range(0, len(pts), step):
        q = pts[s:s + step, :, None]  # [p, 3, 1]
        a, b, c = t0[None] - q, t1[None] - q, t2[None] - q  # [p, 3, F]
        la, lb, lc = (np.sqrt((x * x).sum(1)) for x in (a, b, c))  # [p, F]
        det = (a[:, 0] * (b[:, 1] * c[:, 2] - b[:, 2] * c[:, 1]) + a[:, 1] * (b[:, 2] * c[:, 0] - b[:, 0] * c[:, 2])
               + a[:, 2] * (b[:, 0] * c[:, 1] - b[:, 1] * c[:, 0]))
        den = la * lb * lc + (a * b).sum(1) * lc + (b * c).sum(1) * la + (c * a).sum(1) * lb
        out[s:s + step] = np.arctan2(det, den).sum(1) / (2.0 * np.pi)
    return out


def pieces(scene_dir: Path, run: Path, tau_mm: float | None = None, inside_samples: int = 2000) -> dict:
    """The far pieces of ``run``'s mesh against ``scene_dir``'s GT mesh (see the module docstring)."""
    import trimesh
    from scipy.spatial import cKDTree

    from fastneus.data import Scene
    from fastneus.eval.metrics import sample_surface

    scene = Scene.load(scene_dir)
    if not scene.gt_mesh:
        raise SystemExit(f"{scene_dir}: the scene has no ground-truth mesh (scene.json gt.mesh)")
    gt = trimesh.load(scene.path(scene.gt_mesh), force="mesh", process=False)
    rec = trimesh.load(run / "mesh.ply", force="mesh", process=False)
    diag = float(np.linalg.norm(gt.bounds[1] - gt.bounds[0]))
    tau = (tau_mm / 1000.0) if tau_mm is not None else 0.0025 * diag
    # dense enough that a sample lies within ~tau / 4 of every GT point (the distances are to samples)
    n = int(np.clip(16.0 * gt.area / tau ** 2, 400_000, 4_000_000))
    tree = cKDTree(sample_surface(gt, n, seed=0))
    centres = rec.triangles_center
    dist = tree.query(centres, k=1, workers=-1)[0]
    area = rec.area_faces
    far = dist > tau
    w = area * dist  # each face's share of the area-weighted rec->GT error
    total_err = float(w.sum())
    # edge-connected components of the far faces
    adj = rec.face_adjacency
    keep = far[adj[:, 0]] & far[adj[:, 1]]
    labels = trimesh.graph.connected_component_labels(adj[keep], node_count=len(rec.faces))
    near_nb = np.zeros(len(rec.faces), bool)  # far faces that share an edge with a near face
    mixed = far[adj[:, 0]] != far[adj[:, 1]]
    near_nb[adj[mixed].ravel()] = True
    masks = load_masks(scene)
    # inside or outside the GT solid: an area-weighted sample of the far faces (a winding number per
    # face centre costs a pass over the GT's faces)
    idx = np.flatnonzero(far)
    inside = np.zeros(len(rec.faces), bool)
    sampled = np.zeros(len(rec.faces), bool)
    if len(idx):
        pick = idx if len(idx) <= inside_samples else np.random.default_rng(0).choice(
            idx, inside_samples, replace=False, p=area[idx] / area[idx].sum())
        sampled[pick] = True
        inside[pick] = winding_number(gt, centres[pick]) > 0.5
    out = []
    for lab in np.unique(labels[far]):
        sel = far & (labels == lab)
        a = float(area[sel].sum())
        c = (centres[sel] * area[sel, None]).sum(0) / max(a, 1e-18)
        cov, seen = mask_cover(masks, c)
        out.append({
            "faces": int(sel.sum()), "area_cm2": a * 1e4,
            "error_share": _share(w, sel, np.ones_like(sel)),
            "centroid_m": [round(float(x), 4) for x in c],
            "mean_mm": float(dist[sel].mean() * 1000), "max_mm": float(dist[sel].max() * 1000),
            "attached": bool(near_nb[sel].any()), "masks_covering": cov, "masks_seeing": seen,
            "inside_share": _share(w, sel & sampled & inside, sel & sampled),
        })
    out.sort(key=lambda p: -p["error_share"])
    rec2gt = total_err / max(float(area.sum()), 1e-18) * 1000
    return {"run": str(run), "scene": str(scene_dir), "tau_mm": tau * 1000, "rec2gt_area_weighted_mm": rec2gt,
            "far_area_share": float(area[far].sum() / max(area.sum(), 1e-18)),
            "far_error_share": _share(w, far, np.ones_like(far)),
            "far_inside_error_share": _share(w, sampled & inside, sampled), "inside_sampled": int(sampled.sum()),
            "pieces": out}


def _share(w: np.ndarray, part: np.ndarray, whole: np.ndarray) -> float | None:
    """Share of ``w`` on ``part`` within ``whole`` (None where ``whole`` is empty)."""
    if not whole.any():
        return None
    return float(w[part].sum()) / max(float(w[whole].sum()), 1e-18)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("run", type=Path)
    ap.add_argument("--tau-mm", type=float, default=None, help="distance that makes a face far (default: 0.25 %% of the GT diagonal)")
    ap.add_argument("--top", type=int, default=10, help="pieces printed")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    res = pieces(a.scene, a.run, a.tau_mm)
    from benchutil import command_line, provenance

    res["provenance"] = provenance("cpu", command_line("scripts/floaters.py", argv))
    print(f"{a.run}: rec->GT (area-weighted) {res['rec2gt_area_weighted_mm']:.2f} mm; faces beyond "
          f"{res['tau_mm']:.1f} mm: {100 * res['far_area_share']:.1f} % of the area, "
          f"{100 * res['far_error_share']:.1f} % of the error, in {len(res['pieces'])} pieces")
    if res["far_inside_error_share"] is not None:
        print(f"inside the GT solid: {100 * res['far_inside_error_share']:.1f} % of the far faces' error "
              f"({res['inside_sampled']} far faces sampled by area)")
    print("| share of error | area cm^2 | mean / max mm | centroid (m) | attached | masks covering / seeing | inside |")
    print("|---|---|---|---|---|---|---|")
    for p in res["pieces"][:a.top]:
        ins = "-" if p["inside_share"] is None else f"{100 * p['inside_share']:.0f} %"
        print(f"| {100 * p['error_share']:.1f} % | {p['area_cm2']:.1f} | {p['mean_mm']:.1f} / {p['max_mm']:.1f} | "
              f"{p['centroid_m']} | {'yes' if p['attached'] else 'no'} | {p['masks_covering']} / {p['masks_seeing']} | {ins} |")
    if a.json:
        from fastneus.io import atomic_write_text

        atomic_write_text(a.json, json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
