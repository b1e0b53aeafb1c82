"""Where a time-budgeted run's training clock goes: steady steps against everything else.

    python scripts/budget_timeline.py SCENE [--device cuda] [--budget 5] [--out DIR] [--top 15]
                                      [--sync-each] [key=value ...]

Runs the real ``Trainer.fit`` of ``fastneus train SCENE time_budget=B`` (the device's default
preset plus the overrides) and times every ``train_step`` call on the host. With replayed CUDA
graphs the host runs at most about one step ahead of the device (the optimizer's per-step event
wait), so a step's host time is its device time in steady state; a step far above the median of
the plain replays is one where something else ran. Each step gets a cause: the blur or exposure
estimate ran in it, a CUDA graph was captured, it ran eagerly (a new key), the occupancy grid was
updated (every ``occ_update_every``), its sample count was read back (a host sync), or other.
The report gives the budget split into the steady part (steps x median) and the excess by cause,
the slowest steps, and the clock's time outside the step calls (the log records' syncs every
``log_every``); the JSON keeps every step's row.

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


def step_times(tr, budget: float, sync_each: bool = False) -> list[dict]:
    """Run ``tr.fit`` and return one row per ``train_step`` call: ``step`` (the number during the
    call; the grid updates when it is a multiple of ``occ_update_every``), ``s`` (host seconds),
    ``grid_s`` (seconds inside the occupancy grid's update), ``kind`` (``capture``: a CUDA graph recorded; ``eager``: no graph; ``counted``: a replay whose
    sample count was read back, a host sync; ``replay``: a replay without one; ``cpu``) and
    ``rays``.

    The trainer's own method is wrapped on the instance, so the loop, its syncs and its budget are
    those of ``fastneus train``. ``sync_each``: synchronise after each call (each step's device
    time lands in its own row; the steps no longer overlap, so the run makes fewer of them).
    """
    inner, grid_update = tr.train_step, tr.grid.update
    rows: list[dict] = []
    cuda = tr.device.type == "cuda"
    g = tr.graphs
    in_grid = [0.0]

    def timed_grid(*a, **k):  # the grid update's own share of its step (with sync_each: device time included)
        if sync_each and cuda:
            torch.cuda.synchronize(tr.device)
        t = time.perf_counter()
        grid_update(*a, **k)
        if sync_each and cuda:
            torch.cuda.synchronize(tr.device)
        in_grid[0] += time.perf_counter() - t

    def counters():
        return (0, 0, 0, 0) if g is None else (g.captured, g.eager, g.replayed, g.unsynced)

    def timed():
        step, before, t = tr.step, counters(), time.perf_counter()
        in_grid[0] = 0.0
        rec = inner()
        if sync_each and cuda:
            torch.cuda.synchronize(tr.device)
        d = [a - b for a, b in zip(counters(), before)]
        kind = ("capture" if d[0] else "eager" if d[1] else "counted" if d[2] > d[3] else "replay") \
            if g is not None else "cpu"
        rows.append({"step": step, "s": time.perf_counter() - t, "kind": kind, "rays": int(tr.n_rays),
                     "grid_s": in_grid[0]})
        return rec

    tr.train_step, tr.grid.update = timed, timed_grid
    try:
        tr.fit(final_save=False)
    finally:
        tr.train_step, tr.grid.update = inner, grid_update
    return rows


def summarise(rows: list[dict], steps_total: int, grid_every: int, estimates: dict[str, list[int]],
              top: int) -> dict:
    """The split of the summed step time into steady and excess.

    Args:
        rows: :func:`step_times`'s rows; steps_total: the run's step count (for fractions);
        grid_every: the grid's update period in steps; estimates: name -> the step numbers at which
            it ran (the blur and exposure estimates), counted under that name; top: slow steps to list.
    Returns:
        dict: ``calls``, ``total_s``, ``median_ms`` (of the plain replays, or of all calls when there
        are none), ``steady_s`` (calls x median), ``excess_s``, ``by_cause`` (cause -> excess seconds,
        calls; a step's cause is the first of: an estimate, ``capture``, ``eager``, ``grid update``,
        ``counted``, ``other``), ``slowest`` (step, fraction, kind, ms, excess_ms).
    """
    plain = [r["s"] for r in rows if r["kind"] in ("replay", "cpu")]
    med = median(plain or [r["s"] for r in rows])
    at = {st: name for name, steps in estimates.items() for st in steps}

    def cause(r):
        if r["step"] in at:
            return at[r["step"]]
        if r["kind"] in ("capture", "eager"):
            return r["kind"]
        if grid_every > 0 and r["step"] % grid_every == 0:
            return "grid update"
        return "counted" if r["kind"] == "counted" else "other"

    by: dict[str, list] = {}
    for r in rows:
        e = by.setdefault(cause(r), [0.0, 0])
        e[0] += max(0.0, r["s"] - med)
        e[1] += 1
    slow = sorted(rows, key=lambda r: -r["s"])[:top]
    return {"calls": len(rows), "total_s": sum(r["s"] for r in rows), "median_ms": 1e3 * med,
            "steady_s": med * len(rows), "excess_s": sum(max(0.0, r["s"] - med) for r in rows),
            "by_cause": {k: {"excess_s": v[0], "calls": v[1]} for k, v in sorted(by.items(), key=lambda kv: -kv[1][0])},
            "slowest": [{"step": r["step"], "frac": round(r["step"] / max(1, steps_total), 3), "kind": r["kind"],
                         "ms": 1e3 * r["s"], "excess_ms": 1e3 * (r["s"] - med)} for r in slow]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--budget", type=float, default=5.0, help="seconds of training (time_budget)")
    ap.add_argument("--out", default="budget-timeline")
    ap.add_argument("--top", type=int, default=15, help="slowest steps to list")
    ap.add_argument("--sync-each", action="store_true",
                    help="synchronise after every step (its device time in its own row; fewer steps in the budget)")
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
    rows = step_times(tr, args.budget, args.sync_each)
    c = tr.cfg
    est = {"blur estimate": [int(r["step"]) for r in tr.blur_decision.get("rounds", [])],
           "exposure estimate": [int(tr.exposure_decision["step"])] if "step" in tr.exposure_decision else []}
    res = summarise(rows, tr.step, c.occupancy.occ_update_every, est, args.top)
    res["rows"] = rows
    ups = [r["grid_s"] for r in rows if r["grid_s"] > 0]
    res["grid_update_ms"] = {"calls": len(ups), "median": 1e3 * median(ups) if ups else 0.0, "sum_s": sum(ups)}
    res["elapsed_s"] = tr.elapsed
    res["outside_steps_s"] = tr.elapsed - res["total_s"]  # the log records' syncs, geometry init
    res["steps"] = tr.step
    res["blur_s"] = float(tr.blur_decision.get("seconds", 0.0) or 0.0)
    res["exposure_s"] = float(tr.exposure_decision.get("seconds", 0.0) or 0.0)
    res["graphs"] = tr.graphs.summary() if tr.graphs is not None else None  # (fit released the graphs' memory)

    cmd = command_line("budget_timeline.py")
    md = (f"{provenance_line(args.device, cmd)} {preset} preset, a {args.budget:g}-s budget: {res['steps']} steps, "
          f"training clock {res['elapsed_s']:.3f} s, summed step calls {res['total_s']:.3f} s.\n\n")
    md += md_table([{"median_ms": round(res["median_ms"], 3), "steady_s": round(res["steady_s"], 3),
                     "excess_s": round(res["excess_s"], 3), "outside_steps_s": round(res["outside_steps_s"], 3),
                     "grid_updates": res["grid_update_ms"]["calls"],
                     "grid_update_ms": round(res["grid_update_ms"]["median"], 3),
                     "blur_s": res["blur_s"], "exposure_s": res["exposure_s"],
                     "graphs": None if res["graphs"] is None else
                     {k: res["graphs"][k] for k in ("captured", "eager", "replayed", "unsynced")}}],
                   ["median_ms", "steady_s", "excess_s", "outside_steps_s", "grid_updates", "grid_update_ms", "blur_s",
                    "exposure_s", "graphs"])
    md += "\n\nExcess over the median by the step's cause:\n\n"
    md += md_table([{"cause": k, "calls": v["calls"], "excess_s": round(v["excess_s"], 3)}
                    for k, v in res["by_cause"].items()], ["cause", "calls", "excess_s"])
    md += "\n\nThe slowest steps:\n\n"
    md += md_table([{k: (round(v, 3) if isinstance(v, float) else v) for k, v in r.items()} for r in res["slowest"]],
                   ["step", "frac", "kind", "ms", "excess_ms"])
    write_results(out, "budget-timeline", res, md, args.device, cmd)
    print(md)


if __name__ == "__main__":
    main()
