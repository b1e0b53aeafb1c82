"""Speed comparison: fastneus (Warp kernels), fastneus (torch twins) and the paper-faithful
ActiveNeuS baseline (NeuS MLPs, plain torch), each trained for the same wall-clock budgets.

    python scripts/speed_compare.py SCENE --device cpu|cuda --budgets 10,30,120
        [--target-chamfer MM] [--out DIR] [--no-md] [--methods warp,torch,baseline]
        [--breakdown] [--set key=value ...] [--baseline-set key=value ...]

One training run per method up to the largest budget. The clock (training time only,
device-synchronised after every step) is paused at each evaluation point: the budgets plus a
few geometrically spaced earlier times and t = 0. There the model is meshed (extract_mesh,
256^3 on GPU / 64^3 on CPU) and scored with geometry_metrics (Chamfer GT->reconstruction, mm),
and one frame is rendered for PSNR (with the pattern, vs the photo): the held-out last frame
when the scene has >= 3 frames (training uses the others), else frame 0. On GPU the whole
image is rendered (render_frames); on CPU a fixed random subset of its pixels (--psnr-pixels,
same pixels for every method), because a full image through the baseline's 8x256 MLP with
128 samples per ray takes minutes there.

Reported per method and budget: steps, steps/s, training samples/s (composited samples:
fastneus's marched samples, the baseline's 64 + 64 per ray), peak memory (GPU:
torch.cuda.max_memory_allocated over training, torch's allocator only; CPU: the process's
maxrss, each method in its own process unless --no-isolate), Chamfer and PSNR at the budget,
and the training time from which the Chamfer stays at or below the target (default: the
baseline's Chamfer at the largest budget), read off the evaluation points (so quantised to them).

fastneus is the real trainer, built as `fastneus train` builds it (fastneus.train.trainer.Trainer;
the fewview preset on CUDA and cpu-quick on CPU, plus --set), with time_budget = the largest
budget (its cosine lr and inv_s-floor schedules span that budget, so an early budget sees an
early-schedule model). Like Trainer.fit, the kernels are loaded before the clock starts and the
geometry initialisation (init_geometry) counts as training time; every step is the unmodified
Trainer.train_step (masks, background prior, rig corrections, multi-shot, NaN guard included). The baseline keeps the paper's step-based schedule (lr warm-up 5000
steps, ...), which is what "the paper's method for the same wall-clock time" means.

fastneus's SDF gradient follows its config (`--set sdf_grad=analytic` for the fused
features + Jacobian path, default fd: 4 finite-difference taps).

--breakdown (always on with --device cuda) times --breakdown-steps more real training steps
after the comparison run (the trained state) phase by phase (benchutil.StepPhases: the step's
parts are wrapped with a device-synchronising timer; nothing is re-implemented): median ms per
phase, the occupancy update as its mean over the steps (it runs every occ_update_every steps).

Outputs in --out: speed-compare-<device>.json, .md, chamfer-vs-time-<device>.png; the
Markdown is printed and (unless --no-md) written to the "speed-compare-<device>" section of
docs/benchmarks/speed-compare.md.

--wallclock: instead of the comparison, the product end to end. For each budget (and
--repeat), a fresh process runs `fastneus train SCENE --device D time_budget=B` (the CLI's
default preset; --set adds overrides, --mesh-res sets mesh_resolution) and the per-phase wall
clock it writes to metrics.json is collected: startup (interpreter + imports before the first
phase, from the process start), scene load, imports, CUDA init, trainer setup, kernel
load/compile, training, checkpoints, mesh, renders, evaluation, report, total, plus when
mesh.ply was written (mesh_ready, the number to keep under budget + 5 s), the process's own
wall time measured from outside, and peak GPU / host memory. --cold-kernels gives the first
repeat of each budget an empty Warp kernel cache (measures a first-ever run's compile).

    python scripts/speed_compare.py SCENE --wallclock --budgets 20 [--repeat 3] [--device cuda]
        [--mesh-res 512] [--cold-kernels] [--set key=value ...] [--out DIR] [--no-md]

Outputs wallclock-<device>.json and .md (and the "wallclock-<device>" section of
docs/benchmarks/wallclock.md unless --no-md).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import fastneus  # noqa: F401 - before torch: it sets torch's OpenMP spin (GOMP_SPINCOUNT), read when torch loads
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchutil import (ROOT, command_line, git_rev, machine, make_trainer, md_table, parse_sets,  # noqa: E402
                       peak_mem_mb, phase_breakdown, provenance_line, ratio, sync, update_section, write_json,
                       write_results)

METHODS = ("warp", "torch", "baseline")
LABELS = {"warp": "fastneus (Warp)", "torch": "fastneus (torch twins)", "baseline": "ActiveNeuS baseline (NeuS MLP)"}


# ----------------------------------------------------------------------------- helpers
def eval_times(budgets: list[float], extra: int) -> list[float]:
    """t = 0, the budgets, and ``extra`` halvings of the largest budget below it (geometric spacing)."""
    top = max(budgets)
    ts = {0.0, *budgets}
    ts.update(top * 2.0 ** -k for k in range(1, extra + 1))
    return sorted(round(t, 3) for t in ts)


def split_frames(scene) -> tuple[list[int], int, bool]:
    """(training frames, evaluation frame, whether it is held out)."""
    n = len(scene.frames)
    if n >= 3:
        return list(range(n - 1)), n - 1, True
    return list(range(n)), 0, False


# ----------------------------------------------------------------------------- trainers
def build_trainer(method: str, scene, args, out: Path, frames: list[int], warmup: bool = False):
    """The real fastneus Trainer (backend warp or torch) or the baseline trainer."""
    if method == "baseline":
        from fastneus.baselines import BaselineTrainer

        sets = parse_sets(args.baseline_set)
        if warmup:
            sets["n_rays"] = "16"
        return BaselineTrainer(scene, out, args.device, frames=frames, **sets)
    ov = [f"backend={method}", "steps=100000000", f"time_budget={max(args.budgets)}", f"frames={json.dumps(frames)}"]
    ov += ([f"threads={args.threads}"] if args.threads else []) + list(args.set)
    return make_trainer(scene, args.device, ov, out)


def warm_up(method: str, scene, args, out: Path, frames: list[int]) -> None:
    """Load/compile kernels, CUDA context and BLAS handles on a throwaway trainer (not timed):
    two steps in the occupancy warm-up, two after it (the first of which updates the grid)."""
    tr = build_trainer(method, scene, args, out / "warmup", frames, warmup=True)
    if method != "baseline":
        tr.prime()
    for i in range(4):
        if i == 2 and method != "baseline":
            tr.elapsed = 0.5 * tr.cfg.run.time_budget  # past the occupancy warm-up: the real grid update runs
        tr.train_step()
    sync(args.device)
    del tr
    if args.device.startswith("cuda"):
        torch.cuda.empty_cache()


def start_clock(method: str, tr) -> float:
    """What Trainer.fit does before its loop: kernels loaded (not timed), then the geometry
    initialisation (timed: it counts as training). Returns the seconds it took."""
    if method == "baseline":
        return 0.0
    from fastneus.train.geometry_init import initialise_geometry

    tr.prime()
    t = time.perf_counter()
    note = initialise_geometry(tr)
    sync(str(tr.device))
    if note:
        print(f"[{method}] {note}", flush=True)
    return time.perf_counter() - t if note else 0.0


# ----------------------------------------------------------------------------- evaluation
@torch.no_grad()
def render_rays_any(trainer, o, d, fidx, proj, chunk: int) -> dict:
    """Render rays with either kind of trainer (no gradients kept)."""
    if hasattr(trainer, "render_image_rays"):
        return trainer.render_image_rays(o, d, fidx, chunk=chunk, proj=proj)
    from fastneus.field.renderer import render_image

    i_r, i_b = (x.detach() for x in trainer.illumination())
    return render_image(trainer.field, trainer.grid.bits, trainer.grid.resolution, proj, o, d, fidx, trainer.cfg,
                        i_r=i_r, i_b=i_b, chunk=chunk)


def psnr_subset(trainer, scene, frame: int, n_pix: int, chunk: int) -> float:
    """PSNR (with the pattern, vs the photo) on ``n_pix`` fixed random pixels of ``frame``."""
    from fastneus.train.rays import RayBank, build_projection

    bank = RayBank(scene, [frame], trainer.device)
    proj = build_projection(scene, [frame], trainer.device)
    w, h = (int(x) for x in bank.wh[0].tolist())
    rng = np.random.default_rng(1234)  # the same pixels for every method and time
    flat = torch.as_tensor(rng.choice(w * h, size=min(n_pix, w * h), replace=False), device=trainer.device)
    col, row = flat % w, flat // w
    fidx0 = torch.zeros_like(flat)
    o, d = bank.rays(fidx0, col.float() + 0.5, row.float() + 0.5)
    r = render_rays_any(trainer, o, d, fidx0.to(torch.int32), proj, chunk)
    pred = r["color"] + knob_of(trainer.cfg, 'rays', 'background') * (1 - r["opacity"])[:, None]
    gt = bank.rgb[flat].float().cpu() / 255.0
    mse = float(((pred.clamp(0, 1) - gt) ** 2).mean())
    return -10 * math.log10(max(mse, 1e-12))


def knob_of(cfg, section: str, name: str):
    """A knob of fastneus's sectioned config, or of the NeuS-MLP baseline's flat one."""
    return getattr(getattr(cfg, section), name) if hasattr(cfg, section) else getattr(cfg, name)


def evaluate(trainer, scene, args, frames: list[int], eval_frame: int) -> dict:
    """Chamfer (mm) of the mesh and PSNR of the evaluation frame (not timed)."""
    from fastneus.eval.metrics import geometry_metrics, image_metrics, render_frames
    from fastneus.export.mesh import extract_mesh

    t = time.perf_counter()
    mesh = extract_mesh(trainer.field, scene, args.mesh_res, trainer.device, bound=knob_of(trainer.cfg, 'rays', 'bound'))
    g = geometry_metrics(mesh, scene, frames, n_points=args.points)
    if args.psnr_pixels > 0:
        psnr = psnr_subset(trainer, scene, eval_frame, args.psnr_pixels, args.chunk)
    else:
        psnr = image_metrics(scene, render_frames(trainer, [eval_frame], chunk=args.chunk))["psnr_pattern"]
    return {"chamfer_mm": g.get("chamfer_gt2rec_mm", math.nan), "chamfer_sym_mm": g.get("chamfer_sym_mm", math.nan),
            "fscore": g.get("fscore", math.nan), "psnr": psnr, "eval_s": round(time.perf_counter() - t, 2)}


# ----------------------------------------------------------------------------- one method
def run_method(method: str, args) -> dict:
    """Train one method up to the largest budget, evaluating at each evaluation point."""
    from fastneus.formats.detect import load_scene

    torch.manual_seed(0)
    scene = load_scene(Path(args.scene))
    frames, eval_frame, held = split_frames(scene)
    out = Path(args.out) / method
    cuda = args.device.startswith("cuda")
    if not args.no_warmup:
        warm_up(method, scene, args, out, frames)
    tr = build_trainer(method, scene, args, out, frames)
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    times = eval_times(args.budgets, args.extra_points)
    clock, steps, samples, peak_train = start_clock(method, tr), 0, 0, 0.0
    tr.elapsed = clock
    points, cache = [], None
    print(f"[{method}] training to {max(args.budgets)} s; evaluation at {times}", flush=True)
    for t_eval in times:
        while clock < t_eval:
            t0 = time.perf_counter()
            rec = tr.train_step()
            sync(args.device)  # the step's GPU work belongs to its time
            clock += time.perf_counter() - t0
            tr.elapsed = clock  # drives the time-based schedules, as in Trainer.fit
            steps += 1
            if rec is not None:
                samples += int(rec["samples"])
        if cuda:
            peak_train = max(peak_train, peak_mem_mb(args.device))
        # a model that has not stepped since the last evaluation scores the same
        ev = cache[1] if cache is not None and cache[0] == tr.step else evaluate(tr, scene, args, frames, eval_frame)
        cache = (tr.step, ev)
        p = {"t_target": t_eval, "t": round(clock, 3), "steps": steps, "samples": samples,
             "steps_per_s": steps / clock if clock > 0 else 0.0, "samples_per_s": samples / clock if clock > 0 else 0.0,
             "peak_mem_mb": peak_train if cuda else peak_mem_mb(args.device), **ev}
        points.append(p)
        print(f"[{method}] t={clock:7.2f}s steps={steps:6d} chamfer={p['chamfer_mm']:.2f} mm "
              f"psnr={p['psnr']:.2f} dB (eval {ev['eval_s']} s)", flush=True)
        if cuda:
            torch.cuda.reset_peak_memory_stats()  # evaluation allocations do not count as training peak
    res = {"method": method, "label": LABELS[method], "points": points, "eval_frame": eval_frame,
           "threads": getattr(tr, "threads", torch.get_num_threads()),
           "eval_frame_held_out": held, "train_frames": frames,
           "config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in tr.cfg.to_dict().items()}}
    if method != "baseline" and (args.breakdown or cuda):
        res["breakdown"] = phase_breakdown({method: tr}, args.breakdown_steps)[method]
    return res


# ----------------------------------------------------------------------------- end-to-end wall clock
WALL_PHASES = ("startup", "scene_load", "imports", "cuda_init", "setup", "kernels", "train", "checkpoint", "mesh",
               "renders", "eval", "report", "other", "total")


def wallclock_run(args, budget: float, rep: int, out: Path) -> dict:
    """One `fastneus train` process with ``time_budget=budget``; its timing, memory and result."""
    import shutil

    run = out / f"wall-{budget:g}s-{rep}"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    if args.cold_kernels and rep == 0:
        cache = out / f"warp-cache-{budget:g}s"
        shutil.rmtree(cache, ignore_errors=True)
        env["WARP_CACHE_PATH"] = str(cache)
    cmd = [sys.executable, "-m", "fastneus.cli", "train", str(args.scene), "--out", str(run), "--device",
           args.device, "--overwrite", f"time_budget={budget:g}"]
    if args.mesh_res_given is not None:
        cmd.append(f"mesh_resolution={args.mesh_res_given}")
    cmd += list(args.set)
    print("$ " + " ".join(cmd), flush=True)
    t = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t
    if r.returncode != 0:
        raise SystemExit(f"fastneus train failed (exit {r.returncode}):\n{r.stderr[-3000:]}")
    m = json.loads((run / "metrics.json").read_text())
    tm = m["timing"]
    notes = tm.get("notes", {})
    row = {"budget_s": budget, "repeat": rep, **{p: tm.get(p, 0.0) for p in WALL_PHASES},
           "mesh_ready_s": tm.get("mesh_ready_at"), "process_s": round(wall, 3), "steps": m.get("steps"),
           "peak_gpu_mb": m.get("peak_gpu_mb"), "peak_gpu_torch_mb": m.get("peak_gpu_torch_mb"),
           "peak_gpu_warp_mb": m.get("peak_gpu_warp_mb"), "peak_rss_mb": m.get("peak_rss_mb"),
           "chamfer_mm": m.get("chamfer_gt2rec_mm"), "mesh_faces": m.get("mesh_faces"),
           "compiled": notes.get("kernels_compiled", []), "mesh_detail": notes.get("mesh", {}),
           "preset": json.loads((run / "run.json").read_text()).get("preset"), "run": str(run)}
    row["over_budget_s"] = round(row["mesh_ready_s"] - budget, 3) if row["mesh_ready_s"] is not None else None
    print(f"  budget {budget:g} s: mesh.ply at {row['mesh_ready_s']} s (+{row['over_budget_s']} s), total "
          f"{row['total']} s, process {row['process_s']} s, steps {row['steps']}", flush=True)
    return row


def wallclock(args) -> None:
    """--wallclock: end-to-end CLI runs, a per-phase table -> stdout, JSON, Markdown."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()
    rows = [wallclock_run(args, b, rep, out) for b in args.budgets for rep in range(args.repeat)]
    kind = "cuda" if args.device.startswith("cuda") else "cpu"
    cols = [f"{r['budget_s']:g} s #{r['repeat']}" for r in rows]
    table_rows = []
    for p in WALL_PHASES[:-1] + ("total", "mesh_ready_s", "over_budget_s", "process_s"):
        d = {"phase": f"**{p}**" if p in ("total", "mesh_ready_s") else p}
        d.update({c: r.get(p) if r.get(p) is not None else "" for c, r in zip(cols, rows)})
        table_rows.append(d)
    for p in ("steps", "peak_gpu_mb", "peak_gpu_torch_mb", "peak_gpu_warp_mb", "peak_rss_mb", "chamfer_mm",
              "mesh_faces"):
        if any(r.get(p) is not None for r in rows):
            table_rows.append({"phase": p, **{c: r.get(p) if r.get(p) is not None else "" for c, r in zip(cols, rows)}})
    mesh_rows = [{"run": c, "res": r["mesh_detail"].get("resolution", ""), "mc": r["mesh_detail"].get("mc", ""),
                  "points_M": r["mesh_detail"].get("points", 0) / 1e6,
                  "dense_M": r["mesh_detail"].get("dense_points", 0) / 1e6, "cells": r["mesh_detail"].get("cells", ""),
                  **{k: r["mesh_detail"].get(k, "") for k in ("coarse_s", "fine_s", "cells_s", "mc_s", "filter_s")}}
                 for c, r in zip(cols, rows)]
    compiled = sorted({m for r in rows for m in r["compiled"]})
    cmd = command_line("speed_compare.py")
    text = (f"### End-to-end wall clock on {kind.upper()}: {Path(args.scene).name}\n\n"
            f"{provenance_line(args.device, cmd)}\n"
            f"One fresh `fastneus train` process per column (preset {rows[0]['preset']}); seconds from the process "
            f"start (metrics.json `timing`). startup = interpreter, torch import and argument parsing; mesh_ready_s ="
            f" when mesh.ply was written; over_budget_s = mesh_ready_s - budget (target <= 5 s); process_s = the "
            f"process's wall time measured by this script (includes exit). Peak GPU = torch allocator peak + "
            f"Warp memory-pool peak (an upper bound). Kernels compiled in these runs: "
            f"{', '.join(compiled) if compiled else 'none (warm cache)'}.\n\n"
            + md_table(table_rows, ["phase"] + cols)
            + "\nMesh extraction detail (seconds; points evaluated vs the dense grid):\n\n"
            + md_table(mesh_rows, ["run", "res", "mc", "points_M", "dense_M", "cells", "coarse_s", "fine_s", "cells_s",
                                   "mc_s", "filter_s"]))
    print(text)
    write_results(out, f"wallclock-{kind}", {"scene": str(args.scene), "rows": rows,
                                              "wall_s": round(time.perf_counter() - t_all, 1)}, text, args.device, cmd)
    print(f"wrote {out / f'wallclock-{kind}.json'} and .md")
    if not args.no_md:
        update_section(ROOT / "docs" / "benchmarks" / "wallclock.md", f"wallclock-{kind}", text)


# ----------------------------------------------------------------------------- report
def time_to_target(points: list[dict], target: float) -> float | None:
    """Training time from which the Chamfer stays at or below ``target`` at every later
    evaluation point (robust to a curve that dips below once and comes back up)."""
    t = None
    for p in points:
        if p["chamfer_mm"] <= target:
            t = p["t"] if t is None else t
        else:
            t = None
    return t


def plot(results: list[dict], target: float | None, path: Path, title: str) -> None:
    """Chamfer vs training time (log axis), drawn with OpenCV."""
    import cv2

    W, H, L, R, T, B = 960, 600, 90, 30, 50, 70
    img = np.full((H, W, 3), 255, np.uint8)
    pts = [(p["t"], p["chamfer_mm"]) for r in results for p in r["points"]
           if p["t"] > 0 and math.isfinite(p["chamfer_mm"])]
    if not pts:
        cv2.imwrite(str(path), img)
        return
    ts, cs = [a for a, _ in pts], [b for _, b in pts] + ([target] if target and math.isfinite(target) else [])
    lx0, lx1 = math.floor(math.log10(min(ts))), math.ceil(math.log10(max(ts)))
    lx1 = max(lx1, lx0 + 1)
    y0, y1 = 0.0, max(cs) * 1.05
    fx = lambda t: int(L + (math.log10(t) - lx0) / (lx1 - lx0) * (W - L - R))  # noqa: E731
    fy = lambda c: int(H - B - (c - y0) / (y1 - y0) * (H - T - B))  # noqa: E731
    black, grey = (0, 0, 0), (200, 200, 200)
    font = cv2.FONT_HERSHEY_SIMPLEX
    for e in range(lx0, lx1 + 1):
        for m in (1, 2, 5):
            t = m * 10.0 ** e
            if 10 ** lx0 <= t <= 10 ** lx1:
                cv2.line(img, (fx(t), T), (fx(t), H - B), grey, 1)
                cv2.putText(img, f"{t:g}", (fx(t) - 12, H - B + 20), font, 0.45, black, 1, cv2.LINE_AA)
    for k in range(6):
        c = y0 + (y1 - y0) * k / 5
        cv2.line(img, (L, fy(c)), (W - R, fy(c)), grey, 1)
        cv2.putText(img, f"{c:.3g}", (8, fy(c) + 5), font, 0.45, black, 1, cv2.LINE_AA)
    cv2.rectangle(img, (L, T), (W - R, H - B), black, 1)
    cv2.putText(img, "training time (s, log)", (W // 2 - 90, H - 20), font, 0.55, black, 1, cv2.LINE_AA)
    cv2.putText(img, "Chamfer GT->rec (mm)", (8, T - 18), font, 0.55, black, 1, cv2.LINE_AA)
    cv2.putText(img, title, (L + 200, T - 18), font, 0.5, black, 1, cv2.LINE_AA)
    colors = {"warp": (40, 120, 230), "torch": (60, 170, 60), "baseline": (200, 60, 60)}  # BGR
    if target and math.isfinite(target):
        y = fy(target)
        for x in range(L, W - R, 12):
            cv2.line(img, (x, y), (min(x + 6, W - R), y), (120, 120, 120), 1)
        cv2.putText(img, f"target {target:.3g} mm", (W - R - 150, y - 6), font, 0.45, (90, 90, 90), 1, cv2.LINE_AA)
    for j, r in enumerate(results):
        col = colors.get(r["method"], (0, 0, 0))
        xy = [(fx(p["t"]), fy(p["chamfer_mm"])) for p in r["points"] if p["t"] > 0 and math.isfinite(p["chamfer_mm"])]
        for a, b in zip(xy, xy[1:]):
            cv2.line(img, a, b, col, 2, cv2.LINE_AA)
        for a in xy:
            cv2.circle(img, a, 4, col, -1, cv2.LINE_AA)
        cv2.line(img, (L + 15, T + 20 + 22 * j), (L + 45, T + 20 + 22 * j), col, 2)
        cv2.putText(img, r["label"], (L + 52, T + 25 + 22 * j), font, 0.5, black, 1, cv2.LINE_AA)
    cv2.imwrite(str(path), img)


def summarise(results: list[dict], args) -> tuple[list[dict], float | None, str]:
    """Rows per method and budget, the target Chamfer and where it came from."""
    top = max(args.budgets)
    byname = {r["method"]: r for r in results}
    if args.target_chamfer is not None:
        target, src = args.target_chamfer, "given"
    elif "baseline" in byname:
        bp = [p for p in byname["baseline"]["points"] if p["t_target"] == round(top, 3)]
        target, src = (bp[0]["chamfer_mm"], f"baseline at {top:g} s") if bp else (None, "none")
    else:
        target, src = None, "none"
    t_base = time_to_target(byname["baseline"]["points"], target) if target is not None and "baseline" in byname else None
    rows = []
    for r in results:
        ttt = time_to_target(r["points"], target) if target is not None else None
        for b in sorted(args.budgets):
            p = next(p for p in r["points"] if p["t_target"] == round(b, 3))
            row = {"method": r["label"], "budget_s": b, "train_s": p["t"], "steps": p["steps"],
                   "steps/s": p["steps_per_s"], "samples/s": p["samples_per_s"], "peak_mem_MB": p["peak_mem_mb"],
                   "chamfer_mm": p["chamfer_mm"], "psnr_dB": p["psnr"],
                   "t_to_target_s": "not reached" if ttt is None and target is not None else (ttt if ttt is not None else ""),
                   }
            if ttt is not None and t_base:
                row["speed-up_to_target"] = f"{ratio(t_base, ttt):.1f}x" if ttt > 0 else "at t=0"
            rows.append(row)
    return rows, target, src


def breakdown_md(results: list[dict]) -> str:
    parts = []
    for r in results:
        bd = r.get("breakdown")
        if not bd:
            continue
        rows = [{"phase": p["phase"], "ms": p["ms"], "share_%": p["share_pct"]} for p in bd["phases"]]
        rows.append({"phase": "**total**", "ms": bd["total_ms"], "share_%": 100.0})
        parts.append(f"Per-phase breakdown, {r['label']} ({r.get('threads', '?')} threads; median of {bd['steps']} "
                     f"real Trainer.train_step calls after the comparison run; "
                     f"{bd['rays']} rays, {bd['samples_median']:.0f} samples per step; occupancy update: mean over "
                     f"the steps (it runs every {bd['occ_update_every']}); device synchronised around each phase, so "
                     f"the sum exceeds an unsynchronised step):\n\n" + md_table(rows, ["phase", "ms", "share_%"]))
    return "\n".join(parts)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", help="scene folder (any format fastneus reads)")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--budgets", default="10,30,120", help="comma-separated training-time budgets (s)")
    ap.add_argument("--methods", default="warp,torch,baseline")
    ap.add_argument("--target-chamfer", type=float, default=None, help="mm (default: the baseline's at the largest budget)")
    ap.add_argument("--out", default="/tmp/fastneus-speed-compare")
    ap.add_argument("--no-md", action="store_true", help="do not write docs/benchmarks/speed-compare.md or wallclock.md")
    ap.add_argument("--extra-points", type=int, default=4, help="halvings of the largest budget also evaluated")
    ap.add_argument("--mesh-res", type=int, default=None, help="marching-cubes grid (default 256 GPU / 64 CPU)")
    ap.add_argument("--points", type=int, default=50_000, help="surface points per side for Chamfer")
    ap.add_argument("--psnr-pixels", type=int, default=None,
                    help="random pixels of the eval frame for PSNR; 0 = whole image (default: 0 GPU / 1024 CPU)")
    ap.add_argument("--chunk", type=int, default=None, help="rays per rendering chunk")
    ap.add_argument("--breakdown", action="store_true", help="per-phase step breakdown (always on with cuda)")
    ap.add_argument("--breakdown-steps", type=int, default=50)
    ap.add_argument("--set", nargs="*", default=[], help="fastneus config key=value for both backends")
    ap.add_argument("--baseline-set", nargs="*", default=[], help="baseline config key=value (e.g. n_rays=256)")
    ap.add_argument("--threads", type=int, default=None,
                    help="CPU threads: fastneus's config key threads (Warp kernels and torch) and the baseline's "
                         "torch threads (default: every CPU)")
    ap.add_argument("--no-warmup", action="store_true", help="skip the untimed kernel/BLAS warm-up")
    ap.add_argument("--no-isolate", action="store_true", help="run all methods in this process")
    ap.add_argument("--report-from", default=None, help="re-write the outputs from a previous run's JSON (no training)")
    ap.add_argument("--wallclock", action="store_true",
                    help="end-to-end `fastneus train` processes: per-phase wall clock from process start")
    ap.add_argument("--repeat", type=int, default=1, help="--wallclock: runs per budget")
    ap.add_argument("--cold-kernels", action="store_true",
                    help="--wallclock: the first run of each budget starts with an empty Warp kernel cache")
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--worker-out", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    cuda = args.device.startswith("cuda")
    if args.threads:
        torch.set_num_threads(args.threads)
    args.budgets = sorted(float(b) for b in args.budgets.split(","))
    args.mesh_res_given = args.mesh_res
    args.mesh_res = args.mesh_res or (256 if cuda else 64)
    args.psnr_pixels = (0 if cuda else 1024) if args.psnr_pixels is None else args.psnr_pixels
    args.chunk = args.chunk or (8192 if cuda else 2048)

    if args.worker:
        write_json(Path(args.worker_out), run_method(args.worker, args))
        return

    if args.wallclock:
        if args.repeat < 1:
            raise SystemExit("--repeat must be >= 1")
        wallclock(args)
        return

    if args.report_from:
        prev = json.loads(Path(args.report_from).read_text())
        report(prev["results"], args, prev["command"], prev["machine"], prev["git"], prev.get("wall_s"))
        return
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    bad = [m for m in methods if m not in METHODS]
    if bad:
        raise SystemExit(f"unknown methods {bad}; choose from {METHODS}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = []
    t_all = time.perf_counter()
    for m in methods:
        if args.no_isolate:
            results.append(run_method(m, args))
            continue
        # one process per method: CPU peak RSS is per process, and no method inherits another's caches
        part = out / f"part-{m}.json"
        cmd = [sys.executable, str(Path(__file__).resolve())] + sys.argv[1:] + ["--worker", m, "--worker-out", str(part)]
        subprocess.run(cmd, check=True)
        results.append(json.loads(part.read_text()))
    cmd = command_line("speed_compare.py")
    report(results, args, cmd, machine(args.device), git_rev(), round(time.perf_counter() - t_all, 1))


def report(results: list[dict], args, cmd: str, mach: str, rev: str, wall_s: float | None) -> None:
    """Table, curves, breakdown -> stdout, JSON, Markdown (+ docs/benchmarks/speed-compare.md section) and the plot."""
    cuda = args.device.startswith("cuda")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows, target, src = summarise(results, args)
    kind = "cuda" if cuda else "cpu"
    cols = ["method", "budget_s", "train_s", "steps", "steps/s", "samples/s", "peak_mem_MB", "chamfer_mm", "psnr_dB",
            "t_to_target_s", "speed-up_to_target"]
    table = md_table(rows, cols)
    curve_rows = [{"method": r["label"], "t_s": p["t"], "steps": p["steps"], "chamfer_mm": p["chamfer_mm"],
                   "psnr_dB": p["psnr"]} for r in results for p in r["points"]]
    bd = breakdown_md(results)
    scene_name = Path(args.scene).name
    threads_note = ", ".join(f"{r['method']} {r.get('threads', '?')}" for r in results)
    ev = results[0]
    mem_note = ("torch.cuda.max_memory_allocated during training" if cuda else
                "process max RSS (training + evaluation" + (", one process per method)" if not args.no_isolate else
                                                           ", cumulative over methods: --no-isolate)"))
    text = (f"### Speed comparison on {kind.upper()}: {scene_name}\n\n"
            f"Machine: {mach}; commit {rev}; {time.strftime('%Y-%m-%d')}. Command: `{cmd}`.\n"
            f"Same wall-clock training budgets for each method (one run each, clock paused for evaluation). "
            f"Chamfer GT->reconstruction in mm (mesh {args.mesh_res}^3); PSNR with the pattern on frame "
            f"{ev['eval_frame']} ({'held out' if ev['eval_frame_held_out'] else 'a training frame'}; "
            f"{'whole image' if args.psnr_pixels == 0 else f'{args.psnr_pixels} fixed random pixels'}); "
            f"memory: {mem_note}; CPU threads {threads_note}. Target Chamfer: "
            f"{'none' if target is None else f'{target:.3g} mm ({src})'}; time to target = training time from "
            f"which the Chamfer stays at or below it, read at the "
            f"evaluation points {eval_times(args.budgets, args.extra_points)} s. fastneus: preset "
            f"{results[0]['config'].get('preset', '?')} with its time-based schedules spanning the largest budget; "
            f"baseline: the paper's hyper-parameters (512 rays, 64 + 64 samples, lr 5e-4 with a 5000-step "
            f"warm-up, ...) unless overridden. train_s may pass a budget by up to one step (the step in "
            f"flight finishes).\n\n{table}\n"
            f"Quality vs time (all evaluation points):\n\n{md_table(curve_rows, ['method', 't_s', 'steps', 'chamfer_mm', 'psnr_dB'])}\n"
            f"{bd}")
    print(text)
    write_json(out / f"speed-compare-{kind}.json",
               {"machine": mach, "git": rev, "command": cmd, "scene": str(args.scene),
                "budgets": args.budgets, "target_chamfer_mm": target, "target_source": src, "rows": rows,
                "results": results, "wall_s": wall_s})
    (out / f"speed-compare-{kind}.md").write_text(text)
    plot(results, target, out / f"chamfer-vs-time-{kind}.png", f"{scene_name} ({kind})")
    print(f"wrote {out / f'speed-compare-{kind}.json'}, .md and chamfer-vs-time-{kind}.png")
    if not args.no_md:
        update_section(ROOT / "docs" / "benchmarks" / "speed-compare.md", f"speed-compare-{kind}", text)


if __name__ == "__main__":
    main()
