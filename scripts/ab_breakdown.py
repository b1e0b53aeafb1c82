"""Paired A/B per-phase step breakdown of two fastneus configs on one scene.

    python scripts/ab_breakdown.py SCENE --device cpu|cuda --a "sdf_grad=fd" --b "sdf_grad=analytic"
        [--train-steps 60] [--steps 60] [--threads 1] [--json OUT.json]

Builds two trainers (the device's default preset, cpu-quick or fewview, plus the A or B
overrides), trains both for --train-steps steps (so the occupancy grid and sample counts
are those of a run under way, not of step 0), then alternates phase-timed steps
(``speed_compare.phased_step``, device-synchronised between phases) A, B, A, B, ...: on a
shared machine whose load drifts, both see the same conditions. Prints the median ms per
phase and per step, the samples per step and the B/A ratio.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from speed_compare import PHASES, PhaseTimer, phased_step, sync  # noqa: E402


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
    from fastneus.config import load_config
    from fastneus.formats.detect import load_scene
    from fastneus.kernels import prepare_kernels
    from fastneus.train.trainer import Trainer

    scene = load_scene(Path(args.scene))
    preset = "fewview" if args.device.startswith("cuda") else "cpu-quick"
    prepare_kernels(args.device, say=print)
    trainers = {}
    for name, ov in (("A", args.a), ("B", args.b)):
        cfg = load_config(preset, ["log_every=1000000", "save_every=100000000"] + ov.split())
        torch.manual_seed(0)
        trainers[name] = Trainer(scene, cfg, Path(args.out) / name, args.device)
    for _ in range(args.train_steps):
        for tr in trainers.values():
            tr.train_step()
    sync(args.device)
    per = {n: {p: [] for p in PHASES + ("total",)} for n in trainers}
    samples = {n: [] for n in trainers}
    for i in range(args.steps + 3):
        for n, tr in trainers.items():
            pt = PhaseTimer(args.device)
            s = phased_step(tr, pt)
            if i < 3:
                continue
            pt.ms["occupancy update"] /= tr.cfg.occ_update_every
            for p in PHASES:
                per[n][p].append(pt.ms[p])
            per[n]["total"].append(sum(pt.ms.values()))
            samples[n].append(s)
    res = {n: {p: statistics.median(v) for p, v in per[n].items()} for n in trainers}
    print(f"{'phase':<18} {'A ms':>8} {'B ms':>8} {'B/A':>6}   A: {args.a!r}  B: {args.b!r}")
    for p in PHASES + ("total",):
        a, b = res["A"][p], res["B"][p]
        print(f"{p:<18} {a:8.2f} {b:8.2f} {b / max(a, 1e-9):6.2f}")
    sa, sb = statistics.median(samples["A"]), statistics.median(samples["B"])
    print(f"{'samples/step':<18} {sa:8.0f} {sb:8.0f}")
    if args.json:
        Path(args.json).write_text(json.dumps({"a": args.a, "b": args.b, "ms": res, "samples": {"A": sa, "B": sb},
                                               "steps": args.steps, "device": args.device}, indent=1))


if __name__ == "__main__":
    main()
