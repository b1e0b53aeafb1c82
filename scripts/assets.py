"""Real meshes for the benchmarks, taken from an installed package (no download).

    python scripts/assets.py [--out DIR]

warp-lang ships example assets as USD files, among them the Stanford bunny (a real range
scan, hole-filled, 12,200 triangles) and a bear. This script converts them to PLY (Z up,
as fastneus synth's orbit expects) into ``--out`` (default ``scripts/.assets``, ignored by
git). It needs the USD reader once: ``pip install usd-core`` (a benchmark-only tool; not a
fastneus dependency). ``scripts/quality.py`` reads the PLYs from there.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

DEFAULT_OUT = Path(__file__).resolve().parent / ".assets"
# name -> (file in warp/examples/assets, note)
ASSETS = {"bunny": ("bunny.usd", "Stanford bunny (range scan), from warp-lang's example assets"),
          "bear": ("bear.usd", "bear, from warp-lang's example assets")}


def usd_mesh(path: Path):
    """The first mesh of a USD file as a trimesh (polygons fanned into triangles), Z up."""
    import trimesh
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(path))
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.Mesh):
            m = UsdGeom.Mesh(prim)
            pts = np.asarray(m.GetPointsAttr().Get(), dtype=np.float64)
            counts = np.asarray(m.GetFaceVertexCountsAttr().Get())
            idx = np.asarray(m.GetFaceVertexIndicesAttr().Get())
            faces, o = [], 0
            for c in counts:
                f = idx[o:o + c]
                o += c
                faces += [[f[0], f[k], f[k + 1]] for k in range(1, c - 1)]
            if UsdGeom.GetStageUpAxis(stage) == "Y":  # Y up -> Z up: (x, y, z) -> (x, -z, y)
                pts = np.stack([pts[:, 0], -pts[:, 2], pts[:, 1]], 1)
            return trimesh.Trimesh(pts, np.asarray(faces), process=True)
    raise SystemExit(f"{path}: no mesh found")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(DEFAULT_OUT))
    args = ap.parse_args()
    try:
        import pxr  # noqa: F401
    except ImportError:
        sys.exit("scripts/assets.py needs the USD reader once: pip install usd-core")
    import warp

    src = Path(warp.__file__).parent / "examples" / "assets"
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for name, (fname, note) in ASSETS.items():
        if not (src / fname).is_file():
            sys.exit(f"{src / fname}: not found (this warp-lang build has no example assets)")
        m = usd_mesh(src / fname)
        m.export(out / f"{name}.ply")
        print(f"{name}: {len(m.vertices)} vertices, {len(m.faces)} faces, watertight {m.is_watertight} -> "
              f"{out / f'{name}.ply'} ({note})")


if __name__ == "__main__":
    main()
