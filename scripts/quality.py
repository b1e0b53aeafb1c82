"""Quality benchmark: run the presets on synthetic scenes and tabulate metrics and wall times.

    python scripts/quality.py --device cuda|cpu [--only NAME ...] [--out DIR] [--no-md] [key=value ...]

Scenes (synthesised once into --cache): the built-in toy scene and a torus, 20 views in
Normal and Dark illumination with the paper's 4 cross-laser projectors; a one-shot
cross-laser view and a one-shot dense (colourful line) view. Illumination is estimated
from i_r = i_b = 1 where it is learned. Writes JSON, prints a table and updates the
"quality-<device>" section of docs/BENCHMARKS.md.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from benchutil import ROOT, git_rev, machine, md_table, update_section, write_json

# name -> (scene spec, preset, overrides); the scene spec feeds fastneus.synth.synthesize
SCENES = {
    "toy-dark20": dict(shape="toy", views=20, illum="dark", pattern="crosslaser"),
    "toy-normal20": dict(shape="toy", views=20, illum="normal", pattern="crosslaser"),
    "torus-dark20": dict(shape="torus", views=20, illum="dark", pattern="crosslaser"),
    "toy-oneshot-laser": dict(shape="toy", views=1, illum="normal", pattern="crosslaser"),
    "toy-oneshot-dense": dict(shape="toy", views=1, illum="normal", pattern="colorline"),
}
RUNS = [
    ("active-dark", "toy-dark20", "fewview", ["illum_init=ones"]),
    ("passive-dark", "toy-dark20", "passive", []),
    ("active-normal", "toy-normal20", "fewview", ["illum_init=ones"]),
    ("active-torus-dark", "torus-dark20", "fewview", ["illum_init=ones"]),
    ("oneshot-laser", "toy-oneshot-laser", "oneshot", []),
    ("oneshot-dense", "toy-oneshot-dense", "oneshot", []),
]
CPU_SIZE, GPU_SIZE = (200, 200), (800, 800)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--only", nargs="*", help="run names to run (default all)")
    ap.add_argument("--cache", default="/tmp/fastneus-quality-scenes")
    ap.add_argument("--out", default="/tmp/fastneus-quality-runs")
    ap.add_argument("--no-md", action="store_true")
    ap.add_argument("overrides", nargs="*", help="key=value for every run (e.g. steps=500)")
    args = ap.parse_args()

    from fastneus.config import load_config
    from fastneus.data import Scene
    from fastneus.pipeline import train_scene
    from fastneus.synth import synthesize

    gpu = args.device.startswith("cuda")
    size = GPU_SIZE if gpu else CPU_SIZE
    rows = []
    for name, scene_name, preset, extra in RUNS:
        if args.only and name not in args.only:
            continue
        spec = SCENES[scene_name]
        sdir = Path(args.cache) / f"{scene_name}-{size[0]}"
        t = time.perf_counter()
        if not (sdir / "scene.json").is_file():
            synthesize(sdir, size=size, seed=0, device=args.device, progress=False, **spec)
        t_synth = time.perf_counter() - t
        scene = Scene.load(sdir)
        if not gpu and preset != "paper":
            extra = extra + (["view_dependent=false", "curvature_weight=0.0005"] if preset == "oneshot" else [])
            preset = "cpu-quick"
        cfg = load_config(preset, extra + list(args.overrides))
        t = time.perf_counter()
        trainer, m = train_scene(scene, cfg, Path(args.out) / name, args.device)
        wall = time.perf_counter() - t
        row = {"run": name, "scene": f"{scene_name} {size[0]}x{size[1]}", "preset": cfg.preset, "steps": m["steps"],
               "train_s": m["train_seconds"], "total_s": wall, "synth_s": t_synth}
        for k in ("chamfer_gt2rec_mm", "chamfer_gt2rec_filtered_mm", "visible_gt2rec_mm", "chamfer_sym_mm", "fscore",
                  "psnr_pattern", "psnr_texture", "depth_mae_mm", "i_r", "i_b"):
            if k in m:
                row[k] = m[k]
        rows.append(row)
        print(json.dumps(row), flush=True)
    cols = ["run", "scene", "preset", "steps", "train_s", "chamfer_gt2rec_mm", "chamfer_gt2rec_filtered_mm",
            "visible_gt2rec_mm", "fscore", "psnr_pattern", "psnr_texture", "depth_mae_mm", "i_r", "i_b"]
    table = md_table(rows, cols)
    print(table)
    kind = "cuda" if gpu else "cpu"
    write_json(Path(args.out) / f"quality-{kind}.json", {"machine": machine(args.device), "git": git_rev(),
                                                         "overrides": args.overrides, "rows": rows})
    if not args.no_md:
        ov = " ".join(args.overrides)
        text = (f"### Reconstruction quality on {kind.upper()}\n\nMachine: {machine(args.device)}; commit {git_rev()}.\n"
                f"Command: `python scripts/quality.py --device {args.device} {ov}`. Chamfer in mm on objects ~2 m "
                f"across (GT->reconstruction as in the paper; 'filtered' drops distances beyond mean + 1 sigma); "
                f"i_r, i_b estimated from 1, 1 where learned (GT 0.4, 0.1).\n\n{table}")
        update_section(ROOT / "docs" / "BENCHMARKS.md", f"quality-{kind}", text)


if __name__ == "__main__":
    main()
