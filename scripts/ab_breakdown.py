"""Paired A/B per-phase step breakdown of two fastneus configs on one scene.

    python scripts/ab_breakdown.py SCENE --device cpu|cuda --a "sdf_grad=fd" --b "sdf_grad=analytic"
        [--train-steps 60] [--steps 60] [--threads 1] [--json OUT.json]

Builds two trainers (the device's default preset, cpu-quick or fewview, plus the A or B
overrides), trains both for --train-steps steps (so the occupancy grid and sample counts
are those of a run under way, not of step 0), then alternates real training steps A, B, A,
B, ... timed phase by phase (``benchutil.phase_breakdown``: ``Trainer.train_step`` with its
parts wrapped by a device-synchronising timer): on a shared machine whose load drifts, both
see the same conditions. Prints the median ms per phase (the occupancy update: its mean, as it
runs every ``occ_update_every`` steps), their sum, the samples per step and the B/A ratio.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import fastneus  # noqa: F401 - before torch: it sets torch's OpenMP spin (GOMP_SPINCOUNT), read when torch loads
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchutil import PHASES, make_trainer, phase_breakdown, ratio, sync  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--a", default="", help="space-separated key=value overrides of config A")
    ap.add_argument("--b", default="", help="space-separated key=value overrides of config B")
    ap.add_argument("--train-steps", type=int, default=60)
    ap.add_argument("--steps", type=int, default=60, help="timed steps per config")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--out", default="/tmp/fastneus-ab")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    from fastneus.formats.detect import load_scene
    from fastneus.kernels import prepare_kernels

    scene = load_scene(Path(args.scene))
    prepare_kernels(args.device, say=print)
    trainers = {name: make_trainer(scene, args.device, ov.split(), Path(args.out) / name)
                for name, ov in (("A", args.a), ("B", args.b))}
    for _ in range(args.train_steps):
        for tr in trainers.values():
            tr.train_step()
    sync(args.device)
    bd = phase_breakdown(trainers, args.steps, warmup=3)
    res = {n: {**{p["phase"]: p["ms"] for p in r["phases"]}, "total": r["total_ms"]} for n, r in bd.items()}
    print(f"{'phase':<18} {'A ms':>8} {'B ms':>8} {'B/A':>6}   A: {args.a!r}  B: {args.b!r}")
    for p in PHASES + ("total",):
        a, b = res["A"][p], res["B"][p]
        print(f"{p:<18} {a:8.2f} {b:8.2f} {ratio(b, a):6.2f}")
    sa, sb = bd["A"]["samples_median"], bd["B"]["samples_median"]
    print(f"{'samples/step':<18} {sa:8.0f} {sb:8.0f}")
    if args.json:
        Path(args.json).write_text(json.dumps({"a": args.a, "b": args.b, "ms": res, "samples": {"A": sa, "B": sb},
                                               "steps": args.steps, "device": args.device}, indent=1))


if __name__ == "__main__":
    main()
