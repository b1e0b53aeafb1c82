"""Peak training memory against the number of patterns per viewpoint (issue 11, part 2).

    python scripts/multishot_memory.py [--device cuda|cpu] [--size 800] [--views 10] [--shots 1,2,5,10,20]
                                       [--steps 100] [--out DIR] [--no-md] [key=value ...]

One Gray-code scene (one projector at 0.6 m, ``--views`` viewpoints of ``--size`` px, 20 shots
per viewpoint for a 1024x768 projector) is synthesised once; then, each in a fresh process so
the peaks do not mix, the default preset (fewview on GPU, cpu-quick on CPU) trains ``--steps``
steps on the first N shots of every viewpoint for each N of ``--shots``:

- ``grouped``: the default (one ray per viewpoint pixel carrying ``shots_per_ray`` = 4 random shots);
- ``grouped, all shots``: ``shots_per_ray=0`` (every shot of the pixel in every step), largest N only;
- ``separate rays``: ``group_shots=false`` (every shot's pixels are rays of their own, the pre-#11
  path), largest N only.

Memory: ``torch.cuda.max_memory_allocated`` / ``max_memory_reserved`` over building the trainer
and training (CUDA); the process's peak RSS (CPU; includes ~0.5 GB of Python/torch/Warp). The
ratio column is peak / peak of the N = 1 run (the single-pattern run). Results: ``OUT/multishot-
memory-<device>.json`` and ``.md``, and the section ``multishot-memory-<device>`` of
docs/benchmarks/multishot-memory.md (unless ``--no-md``).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import fastneus  # noqa: F401 - before torch: it sets torch's OpenMP spin (GOMP_SPINCOUNT), read when torch loads
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchutil import (ROOT, cached_scene, command_line, make_trainer, md_table, peak_mem_mb,  # noqa: E402
                       provenance_line, update_section, write_results)


def make_scene(path: Path, size: int, views: int, device: str):
    return cached_scene(path, shape="toy", views=views, size=(size, size), pattern="graycode", baselines=(0.6,),
                        seed=0, device=device, contact_sheet=False)


def child(args) -> None:
    """Train one cell and print one JSON line."""
    from fastneus.data import Scene

    spec = json.loads(args.child)
    dev = args.device
    scene = Scene.load(spec["scene"])
    frames = [i for idx in scene.views().values() for i in idx[:spec["shots"]]]
    if dev.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    base = torch.cuda.memory_allocated() if dev.startswith("cuda") else 0
    tr = make_trainer(scene, dev, spec["overrides"] + [f"steps={spec['steps']}", f"frames={json.dumps(frames)}"],
                      Path(spec["run"]))
    tr.prime()
    warm = min(10, spec["steps"] // 4)
    for _ in range(warm):
        tr.train_step()
    if dev.startswith("cuda"):
        torch.cuda.synchronize()
    t = time.perf_counter()
    samples = 0
    for _ in range(spec["steps"] - warm):
        rec = tr.train_step()
        samples += rec["samples"] if rec else 0
    if dev.startswith("cuda"):
        torch.cuda.synchronize()
    dt = time.perf_counter() - t
    row = {"shots": spec["shots"], "mode": spec["mode"], "frames": len(frames),
           "store_MB": tr.bank.store_bytes() / 2**20, "shots_per_ray_used": getattr(tr.bank, "k", 1),
           "steps_s": (spec["steps"] - warm) / dt, "samples_s": samples / dt, "rays": tr.n_rays}
    if dev.startswith("cuda"):
        row["peak_alloc_MB"] = (torch.cuda.max_memory_allocated() - base) / 2**20
        row["peak_reserved_MB"] = torch.cuda.max_memory_reserved() / 2**20
    else:
        row["peak_rss_MB"] = peak_mem_mb(dev)
    print("ROW " + json.dumps(row), flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--size", type=int, default=800)
    ap.add_argument("--views", type=int, default=10)
    ap.add_argument("--shots", default="1,2,5,10,20")
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--out", default="/tmp/fastneus-multishot")
    ap.add_argument("--no-md", action="store_true")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    ap.add_argument("overrides", nargs="*", help="key=value for every cell")
    args = ap.parse_args()
    if args.child:
        return child(args)

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    scene_dir = out / f"gray-{args.views}v-{args.size}"
    scene = make_scene(scene_dir, args.size, args.views, args.device)
    print(f"scene {scene_dir}: {len(scene.frames)} frames ({time.perf_counter() - t:.1f} s)", flush=True)
    shots = [int(s) for s in args.shots.split(",")]
    cells = [(n, "grouped", []) for n in shots]
    cells += [(max(shots), "grouped, all shots", ["shots_per_ray=0"]),
              (max(shots), "separate rays", ["group_shots=false"])]
    rows = []
    for n, mode, ov in cells:
        spec = {"scene": str(scene_dir), "shots": n, "mode": mode, "steps": args.steps,
                "overrides": list(args.overrides) + ov, "run": str(out / "runs" / f"{n}-{mode.replace(' ', '')}")}
        p = subprocess.run([sys.executable, __file__, "--device", args.device, "--child", json.dumps(spec)],
                           capture_output=True, text=True)
        line = [x for x in p.stdout.splitlines() if x.startswith("ROW ")]
        if p.returncode != 0 or not line:
            print(p.stdout[-2000:], p.stderr[-4000:], file=sys.stderr)
            raise SystemExit(f"cell {n} {mode} failed")
        row = json.loads(line[-1][4:])
        rows.append(row)
        print(json.dumps(row), flush=True)
    key = "peak_alloc_MB" if args.device.startswith("cuda") else "peak_rss_MB"
    ref = next(r[key] for r in rows if r["shots"] == 1 and r["mode"] == "grouped") if 1 in shots else rows[0][key]
    for r in rows:
        r["ratio_to_1_pattern"] = r[key] / ref
    cols = ["shots", "mode", "frames", "shots_per_ray_used", "store_MB", key] + \
        (["peak_reserved_MB"] if key == "peak_alloc_MB" else []) + ["ratio_to_1_pattern", "steps_s", "samples_s"]
    table = md_table(rows, cols)
    print(table)
    kind = "cuda" if args.device.startswith("cuda") else "cpu"
    cmd = command_line("multishot_memory.py")
    head = (f"### Memory against the number of patterns ({kind.upper()})\n\n{provenance_line(args.device, cmd)} "
            f"Gray code, one "
            f"projector (0.6 m), {args.views} viewpoints of {args.size}x{args.size}, the first N of the 20 shots "
            f"of each viewpoint; default preset, {args.steps} steps, one process per row. "
            + ("Peak = torch.cuda.max_memory_allocated over building the trainer and training."
               if kind == "cuda" else "Peak = the process's max RSS (includes ~0.5 GB of Python, torch and Warp).")
            + " ratio = peak / peak of the 1-pattern run.\n\n")
    write_results(out, f"multishot-memory-{kind}", {"size": args.size, "views": args.views, "steps": args.steps,
                                                    "rows": rows}, head + table, args.device, cmd)
    if not args.no_md:
        update_section(ROOT / "docs" / "benchmarks" / "multishot-memory.md", f"multishot-memory-{kind}", head + table)


if __name__ == "__main__":
    main()
