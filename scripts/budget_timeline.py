"""Where a time-budgeted run's training clock goes: steady steps against everything else.

    python scripts/budget_timeline.py SCENE [--device cuda] [--budget 5] [--out DIR] [--top 15] [key=value ...]

Runs the real ``Trainer.fit`` of ``fastneus train SCENE time_budget=B`` (the device's default
preset plus the overrides) and times every ``train_step`` call on the host. With replayed CUDA
graphs the host runs at most about one step ahead of the device (the optimizer's per-step event
wait), so a step's host time is its device time in steady state; a step far above the median is
one where something else ran: a graph capture, the occupancy grid's update, the blur or exposure
estimate. The report gives the budget split into the steady part (steps x
median) and the excess of the slow steps, the slowest steps with their step number and fraction
of the run, the excess of the grid updates' steps (every ``occ_update_every``), the clock's time
outside the step calls (the log records' syncs every ``log_every``), and the time the trainer itself records for its estimates
(``blur_decision`` / ``exposure_decision`` seconds, CUDA graph counts).

Writes ``OUT/budget-timeline.json`` and ``OUT/budget-timeline.md``; prints the Markdown.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import fastneus  # noqa: F401 - before torch: it sets torch's OpenMP spin (GOMP_SPINCOUNT), read when torch loads
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchutil import (command_line, default_preset, make_trainer, md_table, median, provenance_line,  # noqa: E402
                       write_results)


def step_times(tr, budget: float) -> list[tuple[int, float]]:
    """Run ``tr.fit`` and return ``(step number during the call, host seconds)`` for each ``train_step``
    (the grid updates when that number is a multiple of ``occ_update_every``).

    The trainer's own method is wrapped on the instance, so the loop, its syncs and its budget are
    those of ``fastneus train``.
    """
    inner = tr.train_step
    rows: list[tuple[int, float]] = []

    def timed():
        step, t = tr.step, time.perf_counter()
        rec = inner()
        rows.append((step, time.perf_counter() - t))
        return rec

    tr.train_step = timed
    try:
        tr.fit(final_save=False)
    finally:
        tr.train_step = inner
    return rows


def summarise(rows: list[tuple[int, float]], steps_total: int, every: dict[str, int], top: int) -> dict:
    """The split of the summed step time into steady and excess.

    Args:
        rows: ``(step, seconds)`` per call; steps_total: the run's step count (for fractions);
        every: name -> period in steps (a step whose number is a multiple is counted under the
            first name that divides it; the others under ``other``); top: slow steps to list.
    Returns:
        dict: ``total_s``, ``median_ms``, ``steady_s`` (calls x median), ``excess_s``, ``by_period``
        (name -> excess seconds, calls), ``slowest`` (step, fraction, ms, excess_ms).
    """
    secs = [s for _, s in rows]
    med = median(secs)
    by: dict[str, list[float]] = {k: [0.0, 0] for k in list(every) + ["other"]}
    for step, s in rows:
        name = next((k for k, n in every.items() if n > 0 and step % n == 0), "other")
        by[name][0] += max(0.0, s - med)
        by[name][1] += 1
    slow = sorted(rows, key=lambda r: -r[1])[:top]
    return {"calls": len(rows), "total_s": sum(secs), "median_ms": 1e3 * med, "steady_s": med * len(rows),
            "excess_s": sum(max(0.0, s - med) for s in secs),
            "by_period": {k: {"excess_s": v[0], "calls": v[1]} for k, v in by.items()},
            "slowest": [{"step": st, "frac": round(st / max(1, steps_total), 3), "ms": 1e3 * s,
                         "excess_ms": 1e3 * (s - med)} for st, s in slow]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--budget", type=float, default=5.0, help="seconds of training (time_budget)")
    ap.add_argument("--out", default="budget-timeline")
    ap.add_argument("--top", type=int, default=15, help="slowest steps to list")
    ap.add_argument("overrides", nargs="*", help="key=value config overrides")
    args = ap.parse_intermixed_args()

    from fastneus.formats.detect import load_scene

    out = Path(args.out)
    scene = load_scene(Path(args.scene))
    preset = default_preset(args.device)
    from fastneus.config import load_config

    every = load_config(preset, list(args.overrides)).run.log_every  # make_trainer turns logging off; fit syncs there
    tr = make_trainer(scene, args.device, [f"time_budget={args.budget}", f"log_every={every}"] + args.overrides,
                      out / "run", preset)
    rows = step_times(tr, args.budget)
    c = tr.cfg
    res = summarise(rows, tr.step, {"grid update": c.occupancy.occ_update_every}, args.top)
    res["elapsed_s"] = tr.elapsed
    res["outside_steps_s"] = tr.elapsed - res["total_s"]  # the log records' syncs, geometry init
    res["steps"] = tr.step
    res["blur_s"] = float(tr.blur_decision.get("seconds", 0.0) or 0.0)
    res["exposure_s"] = float(tr.exposure_decision.get("seconds", 0.0) or 0.0)
    res["graphs"] = tr.graphs.summary() if tr.graphs is not None else None
    if tr.graphs is not None:
        tr.graphs.release()

    cmd = command_line("budget_timeline.py")
    md = (f"{provenance_line(args.device, cmd)} {preset} preset, a {args.budget:g}-s budget: {res['steps']} steps, "
          f"training clock {res['elapsed_s']:.3f} s, summed step calls {res['total_s']:.3f} s.\n\n")
    md += md_table([{"median_ms": round(res["median_ms"], 3), "steady_s": round(res["steady_s"], 3),
                     "excess_s": round(res["excess_s"], 3), "outside_steps_s": round(res["outside_steps_s"], 3),
                     "blur_s": res["blur_s"], "exposure_s": res["exposure_s"],
                     "graphs": res["graphs"]}],
                   ["median_ms", "steady_s", "excess_s", "outside_steps_s", "blur_s", "exposure_s", "graphs"])
    md += "\n\nExcess over the median by the step's period:\n\n"
    md += md_table([{"period": k, "calls": v["calls"], "excess_s": round(v["excess_s"], 3)}
                    for k, v in res["by_period"].items()], ["period", "calls", "excess_s"])
    md += "\n\nThe slowest steps:\n\n"
    md += md_table([{k: (round(v, 3) if isinstance(v, float) else v) for k, v in r.items()} for r in res["slowest"]],
                   ["step", "frac", "ms", "excess_ms"])
    write_results(out, "budget-timeline", res, md, args.device, cmd)
    print(md)


if __name__ == "__main__":
    main()
