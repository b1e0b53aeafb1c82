"""Mesh extraction of a trained run: the dense reference (SDF on every node + scikit-image)
against the sparse path (coarse blocks, fine nodes near the surface, Warp or scikit-image).

    python scripts/bench_mesh.py RUN_FOLDER [--device cpu|cuda] [--res 256,512] [--repeat 3]
        [--no-dense] [--out DIR]

Per resolution: median seconds of each path (device-synchronised, after one warm-up call
that also loads the Warp marching-cubes module), the points evaluated, cells triangulated,
vertex/face counts, and the Chamfer distance between the two meshes (mean of both
directions, in voxels) as a check that they agree. Writes bench-mesh-<device>.json/.md.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import fastneus  # noqa: F401 - before torch: it sets torch's OpenMP spin (GOMP_SPINCOUNT), read when torch loads
import torch

from benchutil import command_line, md_table, median, provenance_line, ratio, sync, write_results


def dense(tr, res: int):
    from fastneus.export.mesh import mesh_from_grid, sdf_grid

    g = sdf_grid(tr.field, res, tr.device, bound=tr.cfg.rays.bound, allowed=tr.seen)
    return mesh_from_grid(g, tr.scene.bounds.center, float(tr.scene.bounds.radius))


def chamfer_voxels(a: np.ndarray, b: np.ndarray, voxel: float) -> float:
    from scipy.spatial import cKDTree

    if len(a) == 0 or len(b) == 0:
        return float("nan")
    return 0.5 * (cKDTree(b).query(a)[0].mean() + cKDTree(a).query(b)[0].mean()) / voxel


def timed(fn, device: str, repeat: int):
    ts, out = [], None
    for _ in range(repeat):
        sync(device)
        t = time.perf_counter()
        out = fn()
        sync(device)
        ts.append(time.perf_counter() - t)
    return median(ts), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", help="a run folder (run.json names its scene)")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--res", default="256,512")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--mc", default="auto", choices=("auto", "warp", "skimage"))
    ap.add_argument("--no-dense", action="store_true", help="skip the dense reference (slow on a CPU at 512)")
    ap.add_argument("--out", default="/tmp/fastneus-bench-mesh")
    args = ap.parse_args()

    from fastneus.cli.export import open_run
    from fastneus.export.mesh import extract_mesh_arrays

    _, tr = open_run(args.run, args.device)
    rows = []
    for res in [int(r) for r in args.res.split(",")]:
        radius = float(tr.scene.bounds.radius)
        voxel = 2.0 * radius / (res - 1)
        fast = lambda: extract_mesh_arrays(tr.field, tr.scene, res, tr.device, bound=tr.cfg.rays.bound,  # noqa: E731
                                           allowed=tr.seen, mc=args.mc)
        fast()  # warm-up: Warp module load, allocator
        t_fast, m = timed(fast, args.device, args.repeat)
        row = {"res": res, "sparse_s": t_fast, "points_M": m.stats["points"] / 1e6,
               "dense_points_M": m.stats["dense_points"] / 1e6, "cells": m.stats["cells"], "mc": m.stats["mc"],
               "vertices": len(m.vertices), "faces": len(m.faces),
               **{k: m.stats[k] for k in ("coarse_s", "fine_s", "cells_s", "mc_s", "filter_s")}}
        if not args.no_dense:
            t_dense, d = timed(lambda: dense(tr, res), args.device, 1 if args.device == "cpu" else args.repeat)
            row.update(dense_s=t_dense, dense_faces=len(d.faces), speedup=ratio(t_dense, t_fast),
                       chamfer_vox=chamfer_voxels(np.asarray(d.vertices), m.vertices, voxel))
        print(row, flush=True)
        rows.append(row)
    cols = ["res", "dense_s", "sparse_s", "speedup", "points_M", "dense_points_M", "cells", "mc", "coarse_s",
            "fine_s", "cells_s", "mc_s", "filter_s", "faces", "dense_faces", "chamfer_vox"]
    cmd = command_line("bench_mesh.py")
    text = (f"### Mesh extraction, {args.device}: {Path(args.run).name}\n\n{provenance_line(args.device, cmd)}"
            f" Median of {args.repeat} (dense on CPU: 1). chamfer_vox: mean two-sided vertex distance between the "
            f"dense and the sparse mesh, in voxels.\n\n" + md_table(rows, cols))
    print(text)
    write_results(Path(args.out), f"bench-mesh-{args.device.split(':')[0]}", {"rows": rows}, text, args.device, cmd)


if __name__ == "__main__":
    main()
