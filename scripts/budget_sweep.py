"""Short-budget tuning sweep: named override sets x seeds x shapes x time budgets, paired.

    python scripts/budget_sweep.py --out DIR [--shapes rock,ant] [--budgets 5] [--seeds 0,1]
        [--variants "base:;lr2:lr=2e-2;..."] [--illum dark] [--masks on] [--views 20] [--size 200]
        [--cache /tmp/qc] [--runs /tmp/budget-sweep-runs] [--max-wall SECONDS] [--device cuda]
        [--report-from A.jsonl,B.jsonl]

Every cell is ``scripts/quality.py``'s cell (``train_scene`` with the device's default preset,
``time_budget=B``, ``seed=S`` and the variant's overrides), on quality.py's scenes (4 cross
lasers, ``--views`` views of ``--size`` px, object ~2 m across). The loop order is shape ->
budget -> seed -> variant, so the variants of one (shape, budget, seed) run back to back and a
drift of the machine hits them alike. One throw-away 2-s cell runs first (CUDA/cuBLAS warm-up
inside the process). Rows stream to ``DIR/budget-sweep.jsonl`` (a re-run skips cells already
there, so a call cut short by a time limit resumes); ``--max-wall`` stops before starting a
cell once that many seconds have passed. The summary (mean over seeds, and each seed) goes to
stdout and ``DIR/budget-sweep.md``.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import time
from pathlib import Path

KEYS = ["steps", "chamfer_gt2rec_mm", "chamfer_rec2gt_mm", "chamfer_sym_mm", "fscore"]
SHORT = {"steps": "steps", "chamfer_gt2rec_mm": "GT->rec", "chamfer_rec2gt_mm": "rec->GT",
         "chamfer_sym_mm": "sym", "fscore": "F"}


def parse_variants(text: str) -> dict[str, list[str]]:
    out = {}
    for part in text.split(";"):
        if part.strip():
            name, _, ov = part.partition(":")
            out[name.strip()] = ov.split()
    return out


def fmt(v, k):
    if v is None:
        return "-"
    if k == "steps":
        return f"{v:.0f}"
    if k == "fscore":
        return f"{v:.4f}"
    return f"{v:.2f}"


def summary(rows: list[dict]) -> str:
    """One table per (shape, budget): variant, mean of each metric over seeds, then each seed's."""
    groups: dict = {}
    order: list = []
    for r in rows:
        g = (r["shape"], r["budget"])
        if g not in groups:
            groups[g] = {}
        v = groups[g].setdefault(r["variant"], [])
        v.append(r)
        if r["variant"] not in order:
            order.append(r["variant"])
    lines = []
    for (shape, budget) in sorted(groups):
        lines.append(f"\n{shape}, {budget:g} s (mean over seeds; then per seed sym / F):\n")
        lines.append("| variant | n | " + " | ".join(SHORT[k] for k in KEYS) + " | per seed (steps, GT->rec, rec->GT, sym, F) |")
        lines.append("|---" * (len(KEYS) + 3) + "|")
        base = None
        for name in order:
            rs = groups[(shape, budget)].get(name)
            if not rs:
                continue
            rs = sorted(rs, key=lambda r: r["seed"])
            mean = {k: sum(r[k] for r in rs if r.get(k) is not None) / max(1, sum(r.get(k) is not None for r in rs))
                    for k in KEYS}
            if base is None:
                base = mean
            per = "; ".join(f"s{r['seed']}: " + " ".join(fmt(r.get(k), k) for k in KEYS) for r in rs)
            lines.append(f"| {name} | {len(rs)} | " + " | ".join(fmt(mean[k], k) for k in KEYS) + f" | {per} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True)
    ap.add_argument("--shapes", default="rock")
    ap.add_argument("--budgets", default="5")
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--variants", default="base:")
    ap.add_argument("--illum", default="dark")
    ap.add_argument("--masks", default="on", choices=["on", "off"])
    ap.add_argument("--views", type=int, default=20)
    ap.add_argument("--size", type=int, default=200)
    ap.add_argument("--cache", default="/tmp/qc")
    ap.add_argument("--runs", default="/tmp/budget-sweep-runs")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--max-wall", type=float, default=0.0, help="start no cell after this many seconds (0 = no limit)")
    ap.add_argument("--report-from", default=None, help="only summarise these JSONL files (comma-separated)")
    args = ap.parse_args()

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    jsonl = out / "budget-sweep.jsonl"
    if args.report_from:
        rows = [json.loads(x) for f in args.report_from.split(",") for x in Path(f).read_text().splitlines() if x.strip()]
        text = summary(rows)
        print(text)
        (out / "budget-sweep.md").write_text(text)
        return

    from quality import make_scene, run_cell, ASSETS

    t_start = time.perf_counter()
    variants = parse_variants(args.variants)
    seeds = [int(s) for s in args.seeds.split(",")]
    budgets = [float(b) for b in args.budgets.split(",")]
    done = set()
    if jsonl.is_file():
        for x in jsonl.read_text().splitlines():
            if x.strip():
                r = json.loads(x)
                done.add((r["variant"], r["shape"], r["budget"], r["seed"]))
    runs = Path(args.runs)
    warmed = False
    stopped = False
    for shape in args.shapes.split(","):
        scene = make_scene(Path(args.cache), shape, args.illum, args.views, args.size, args.device, ASSETS)
        for b in budgets:
            for seed in seeds:
                for name, ov in variants.items():
                    if (name, shape, b, seed) in done:
                        continue
                    if args.max_wall and time.perf_counter() - t_start > args.max_wall:
                        stopped = True
                        break
                    if not warmed:
                        run_cell(scene, args.device, 2.0, args.masks, ["seed=0"], runs / "warmup")
                        warmed = True
                    d = runs / f"{name}-{shape}-{b:g}s-s{seed}"
                    made = not os.path.lexists(d)  # only a run folder this call creates is removed below
                    cell = run_cell(scene, args.device, b, args.masks, [f"seed={seed}"] + ov, d)
                    cell.update(variant=name, shape=shape, budget=b, seed=seed, illum=args.illum, masks=args.masks,
                                overrides=ov)
                    print(json.dumps(cell), flush=True)
                    with open(jsonl, "a") as f:
                        f.write(json.dumps(cell) + "\n")
                    if made and d.is_dir() and not d.is_symlink():  # keep the device's disk small; metrics above
                        shutil.rmtree(d, ignore_errors=True)
    if stopped:
        print(f"stopped at --max-wall {args.max_wall:g} s: re-run to resume", flush=True)
    rows = [json.loads(x) for x in jsonl.read_text().splitlines() if x.strip()]
    text = summary(rows)
    print(text)
    (out / "budget-sweep.md").write_text(text)


if __name__ == "__main__":
    main()
