"""CPU threads: steps of a time-budgeted ``fastneus train`` run at several thread counts (issue 22, target 5).

    python scripts/threads_bench.py SCENE [--threads 1,2] [--pairs 4] [--budget 30] [--out DIR]
        [--runs DIR] [key=value ...]

The target's own measure: the same command a user runs, ``fastneus train SCENE --device cpu
--threads T time_budget=B`` (cpu-quick), one process per run, the thread counts interleaved
(1, 2, 1, 2, ...: a VM whose speed drifts hits both alike). A 2-core VM's one-thread step count
moves by +-10 % from run to run, so one pair says little: the script reports every run, the
ratio of each round (same position in the interleaving) and the ratio of the medians. Extra
``key=value`` arguments go to every run. Writes ``OUT/threads-bench.json`` and ``.md`` (machine,
commit, command; default OUT /tmp/fastneus-threads-bench); each run's folder is replaced
(``--overwrite``) under ``--runs``.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchutil import command_line, md_table, median, parse_counts, provenance_line, write_results  # noqa: E402

KEYS = ("steps", "train_seconds", "chamfer_sym_mm", "fscore")


def run_once(scene: str, threads: int, budget: float, run: Path, extra: list[str]) -> dict:
    """One ``fastneus train`` process; its metrics.json's steps and quality, and the wall seconds."""
    cmd = [sys.executable, "-m", "fastneus", "train", scene, "--device", "cpu", "--threads", str(threads),
           "--out", str(run), "--overwrite", f"time_budget={budget:g}", *extra]
    t = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t
    if p.returncode != 0:
        tail = (p.stderr or p.stdout).strip().splitlines()[-3:]
        raise SystemExit(f"threads={threads}: fastneus train failed (exit {p.returncode}): " + " | ".join(tail))
    m = json.loads((run / "metrics.json").read_text())
    return {"threads": threads, **{k: m.get(k) for k in KEYS}, "wall_s": round(wall, 1)}


def summarise(rows: list[dict], counts: list[int]) -> list[dict]:
    """One row per thread count: its steps per round, their median, the ratio of each round's steps to
    the first count's in the same round, and the ratio of the medians."""
    ref = counts[0]
    steps = {t: [x["steps"] for x in rows if x["threads"] == t] for t in counts}
    out = []
    for t in counts:
        per_round = [a / b for a, b in zip(steps[t], steps[ref]) if b]
        syms = [x["chamfer_sym_mm"] for x in rows if x["threads"] == t and x.get("chamfer_sym_mm") is not None]
        out.append({"threads": t, "steps (per round)": " / ".join(str(s) for s in steps[t]),
                    "median steps": median(steps[t]),
                    f"ratio to {ref} (per round)": " / ".join(f"{x:.2f}" for x in per_round),
                    f"ratio of medians to {ref}": round(median(steps[t]) / median(steps[ref]), 3),
                    "median symmetric mm": round(median(syms), 2) if syms else None})
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--threads", default="1,2", help="comma-separated thread counts (the first is the reference)")
    ap.add_argument("--pairs", type=int, default=4, help="rounds of the interleaving")
    ap.add_argument("--budget", type=float, default=30.0, help="time_budget of every run (seconds)")
    ap.add_argument("--out", default="/tmp/fastneus-threads-bench")
    ap.add_argument("--runs", default="/tmp/threads-bench-runs")
    ap.add_argument("overrides", nargs="*", help="key=value for every run")
    args = ap.parse_intermixed_args(argv)
    counts = parse_counts(args.threads, "--threads")
    rows = []
    for r in range(args.pairs):
        for t in counts:
            row = {"round": r, **run_once(args.scene, t, args.budget, Path(args.runs) / f"t{t}-r{r}", args.overrides)}
            rows.append(row)
            print(json.dumps(row), flush=True)
    summary = summarise(rows, counts)
    command = command_line("threads_bench.py", argv)
    text = "\n\n".join([provenance_line("cpu", command),
                        md_table(summary, list(summary[0].keys())),
                        md_table(rows, ["round", "threads", *KEYS, "wall_s"])])
    write_results(Path(args.out), "threads-bench", {"runs": rows, "summary": summary}, text, "cpu", command)
    print(text)


if __name__ == "__main__":
    main()
