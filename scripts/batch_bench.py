"""Throughput of ``fastneus batch``: scenes per hour for each list of GPUs.

    python scripts/batch_bench.py --gpus 0 0,1 [--scenes 8 | --scene-dirs DIR ...]
        [--shape toy] [--views 10] [--size 400x400] [--work DIR] [--out DIR] [key=value ...]

Synthesises ``--scenes`` scenes once into ``WORK/scenes`` (the same shape and size, seeds 0..N-1;
reused on the next call), or takes ``--scene-dirs``. Then, for each ``--gpus`` entry (``0``,
``0,1``, ... or ``cpu`` for CPU workers), runs ``fastneus batch SCENES --out WORK/<entry>-<time>
--gpus ENTRY [key=value ...]`` as a subprocess, into a fresh folder (nothing is skipped), and reads
its ``summary.json``. Reported per entry: GPUs, scenes done / failed, wall time of the whole batch
(process start to exit: Python, CUDA and kernel start-up of every run included, as a user sees it),
scenes per hour (done / wall hours), the median seconds of one run, and the speed-up over the first
entry. Writes ``OUT/batch_bench.json`` (machine, commit, command, one record per entry) and
``OUT/batch_bench.md``. Only the CLI is driven: the script measures the verb as shipped.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from benchutil import ROOT, cached_scene, command_line, md_table, median, provenance_line, write_results


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--gpus", nargs="+", default=["0"], metavar="IDS",
                   help="GPU lists to compare, e.g. 0 0,1 (each a batch); 'cpu' for CPU workers")
    p.add_argument("--scenes", type=int, default=8, help="synthetic scenes to make (default 8)")
    p.add_argument("--scene-dirs", nargs="+", metavar="DIR", help="use these scene folders instead")
    p.add_argument("--shape", default="toy", help="synthetic shape (sphere, torus, toy, rock)")
    p.add_argument("--views", type=int, default=10)
    p.add_argument("--size", default="400x400", help="image size WxH of the synthetic scenes")
    p.add_argument("--workers", type=int, help="passed to batch (runs at once; default one per GPU)")
    p.add_argument("--work", type=Path, default=ROOT / "runs" / "batch-bench", help="scenes and batch folders (default runs/batch-bench)")
    p.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks", help="where the JSON + Markdown go")
    p.add_argument("overrides", nargs="*", metavar="key=value", help="train overrides for every run, e.g. steps=2000")
    return p.parse_args(argv)


def make_scenes(args) -> list[Path]:
    if args.scene_dirs:
        return [Path(d).resolve() for d in args.scene_dirs]
    import torch

    w, h = (int(x) for x in args.size.lower().split("x"))
    # rendered on the GPU when there is one (a GPU machine may have no CPU compiler for Warp)
    dev = "cuda" if torch.cuda.is_available() and any(e != "cpu" for e in args.gpus) else "cpu"
    out = []
    for i in range(args.scenes):
        path = args.work / "scenes" / f"{args.shape}-{args.views}v-{w}x{h}-s{i:02d}"
        cached_scene(path, shape=args.shape, views=args.views, size=(w, h), seed=i, contact_sheet=False, device=dev)
        out.append(path.resolve())
    return out


def run_batch(scenes: list[Path], entry: str, args) -> dict:
    """One ``fastneus batch`` over ``scenes`` with GPU list ``entry``; its record."""
    label = "cpu" if entry == "cpu" else "gpu" + entry.replace(",", "_")
    out = args.work / f"{label}-{time.strftime('%Y%m%d-%H%M%S')}"
    sched = ["--device", "cpu"] if entry == "cpu" else ["--gpus", entry]
    cmd = [sys.executable, "-m", "fastneus", "batch", *map(str, scenes), "--out", str(out), *sched,
           *(["--workers", str(args.workers)] if args.workers else []), *args.overrides]
    print("$", " ".join(cmd[2:]), flush=True)
    t = time.perf_counter()
    rc = subprocess.run(cmd, cwd=ROOT).returncode
    wall = time.perf_counter() - t
    try:
        summary = json.loads((out / "summary.json").read_text())
    except (OSError, ValueError):
        summary = {"scenes": [], "counts": {}}
    done = [s for s in summary["scenes"] if s["state"] == "done"]
    return {"gpus": entry, "gpu_count": 0 if entry == "cpu" else len(entry.split(",")), "exit_status": rc,
            "workers": summary.get("workers"), "decision": summary.get("decision"), "scenes": len(scenes),
            "done": len(done), "failed": summary.get("counts", {}).get("failed", 0), "wall_s": round(wall, 1),
            "scenes_per_hour": round(len(done) / (wall / 3600), 2) if done else 0.0,
            "median_run_s": round(median(s["seconds"] for s in done if s.get("seconds") is not None), 1),
            "median_chamfer_mm": median(s["chamfer_gt2rec_mm"] for s in done if s.get("chamfer_gt2rec_mm") is not None),
            "batch_folder": str(out)}


def main(argv=None) -> int:
    args = parse_args(argv)
    device = "cpu" if all(e == "cpu" for e in args.gpus) else "cuda"
    command = command_line("batch_bench.py", argv)
    scenes = make_scenes(args)
    rows = [run_batch(scenes, entry, args) for entry in args.gpus]
    base = rows[0]["scenes_per_hour"] or float("nan")
    for r in rows:
        r["speedup"] = round(r["scenes_per_hour"] / base, 2) if base == base else None
    cols = ["gpus", "gpu_count", "done", "failed", "wall_s", "scenes_per_hour", "speedup", "median_run_s",
            "median_chamfer_mm"]
    scene_note = (f"{len(scenes)} scene folders given" if args.scene_dirs else
                  f"{len(scenes)} synthetic scenes ({args.shape}, {args.views} views of {args.size}, seeds 0..{len(scenes) - 1})")
    text = (f"# fastneus batch: scenes per hour\n\n{provenance_line(device, command)}\n\n{scene_note}; train "
            f"overrides: {' '.join(args.overrides) or 'none (the device default preset)'}. Wall time is the whole "
            f"`fastneus batch` command (every run's start-up included).\n\n{md_table(rows, cols)}")
    path = write_results(args.out, "batch_bench", {"scenes": [str(s) for s in scenes], "overrides": args.overrides,
                                                   "results": rows}, text, device, command)
    print(text)
    print(f"-> {path}")
    return 0 if all(r["exit_status"] == 0 for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
