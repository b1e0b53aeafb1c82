"""Real-rig recovery protocols (issue 12): does each model extension recover what a real rig
gets wrong, and how much worse is the mesh without it?

    python scripts/rig_recovery.py --device cuda --out DIR [--parts pose,blur,laser,water]
                                   [--budget 15] [--size 320] [--views 12] [--shape toy] [key=value ...]

All four parts are 11 training runs of ``--budget`` seconds each, plus synthesis, meshing
(256^3) and evaluation per run: about 11 x (budget + ~10 s) on one H100, plus the first
compilation of the Warp kernels on a fresh machine. Parts can run as separate calls
(``--parts pose,blur`` then ``--parts laser,water`` with another ``--out``).

Every part synthesises a scene with ``fastneus synth``'s rig (4 cross-laser projectors,
known ground truth), then trains a few variants with the same time budget (the device's
default preset: fewview on GPU, cpu-quick on CPU, plus the part's keys) and compares
Chamfer (mm), PSNR and what was recovered:

- ``pose``: the poses given to training are perturbed (every viewpoint but the first, and
  every projector: 0.5 deg about a random axis and 1 cm in a random direction, seeded).
  Runs: exact poses; perturbed without refinement; perturbed with ``pose_refine=true``.
  Targets: recovered poses within 0.05 deg / 1 mm, symmetric Chamfer within 1.2x of the
  exact-pose run.

- ``blur``: the projectors are defocused (a Gaussian of ``--blur-sigma`` projector pixels,
  5x5 taps). Runs: the same scene in focus (reference); defocused without a blur model;
  defocused with ``projector_blur=5``. Reported: Chamfer, PSNR and the L1 distance of the
  learned kernel to the true one (the identity's distance for the runs without a model).

- ``laser``: the projectors are laser line projectors (the cross-laser lines as light
  planes, the exact model, ``synth --laser-planes``). Runs: the exact plane model; the
  pattern-image approximation of the same rig (the planes rasterised into a pattern at the
  orbit distance, ``fastneus.light.lasers.pattern_approximation``), same photos.

- ``water``: the same geometry (seed, poses) rendered in air and under water (``synth
  --medium water``: flat ports on the camera and the projectors, attenuation and
  back-scatter). Runs: in air (reference); under water with the model (refraction at the
  ports, learned attenuation / back-scatter: the defaults for a scene with ports); under
  water with it off (``refraction=false medium=off``). Target: Chamfer with the model
  within 1.5x of the in-air run.

Results: a table on stdout, ``OUT/rig-recovery.json`` (every row, all metrics) and
``OUT/rig-recovery.md`` (the tables, for docs/benchmarks/rig-recovery.md). Run folders (mesh, report)
stay under ``OUT/runs``. On CPU use tiny sizes (``--size 32 --views 4 --budget 4``): that
proves the protocol runs, not the targets.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import fastneus  # noqa: F401 - before torch: it sets torch's OpenMP spin (GOMP_SPINCOUNT), read when torch loads
import torch

from benchutil import default_preset, git_rev, machine, md_table, write_results

PARTS = ("pose", "blur", "laser", "water")
args_points = 100_000  # --points
args_steps = 0  # --steps: a fixed step count instead of the time budget (deterministic CPU checks)
GEOM = ["chamfer_sym_mm", "chamfer_gt2rec_mm", "fscore", "psnr_pattern", "psnr_texture"]


def train(scene, device: str, budget: float, out: Path, extra: list[str]) -> tuple[object, dict]:
    from functools import partial

    import fastneus.eval.metrics as ev
    from fastneus.config import load_config
    from fastneus.pipeline import train_scene

    if not isinstance(ev.geometry_metrics, partial):  # --points: Chamfer sample count (finish_run's metrics)
        ev.geometry_metrics = partial(ev.geometry_metrics, n_points=args_points)

    preset = default_preset(device)
    length = [f"steps={args_steps}"] if args_steps else [f"time_budget={budget}"]
    cfg = load_config(preset, length + ["mesh_resolution=256"] + list(extra))
    t = time.perf_counter()
    trainer, m = train_scene(scene, cfg, out, device)
    m = {k: m.get(k) for k in GEOM + ["steps", "train_seconds"]}
    m["wall_s"] = round(time.perf_counter() - t, 1)
    return trainer, m


def synth(out: Path, args, **kw):
    from fastneus.synth.render import synthesize

    return synthesize(out, shape=args.shape, views=args.views, size=(args.size, args.size), pattern="crosslaser",
                      illum="normal", seed=args.seed, device=args.device, progress=False, contact_sheet=False,
                      proj_size=tuple(args.proj_size), **kw)


# --------------------------------------------------------------------------- parts
def part_pose(args, out: Path) -> list[dict]:
    from fastneus.eval.poses import pose_errors
    from fastneus.synth.perturb import perturb_scene

    truth = synth(out / "scenes" / "pose", args)
    frames = list(range(len(truth.frames)))
    pert = perturb_scene(truth, args.pose_deg, args.pose_m, seed=args.seed + 1)
    pert.save(out / "scenes" / "pose-perturbed")  # same images, poses off by the perturbation
    given = pose_errors(pert, truth, frames)
    rows = []
    for name, scene, keys in (("exact poses", truth, []), ("perturbed, no refinement", pert, []),
                              ("perturbed, pose_refine", pert, ["pose_refine=true"])):
        tr, m = train(scene, args.device, args.budget, out / "runs" / f"pose-{len(rows)}", keys + args.extra)
        errs = pose_errors(tr.rig.refined_scene(), truth, frames) if tr.rig.pose_on else \
            (given if scene is pert else pose_errors(truth, truth, frames))
        rows.append({"part": "pose", "run": name, **m, **errs})
    exact = rows[0]["chamfer_sym_mm"]
    for r in rows:
        r["chamfer_vs_exact"] = r["chamfer_sym_mm"] / exact if exact else float("nan")
    ref = rows[2]
    ref["target_met"] = bool(ref["cam_rot_deg_max"] <= 0.05 and ref["proj_rot_deg_max"] <= 0.05
                             and ref["cam_trans_mm_max"] <= 1.0 and ref["proj_trans_mm_max"] <= 1.0
                             and ref["chamfer_vs_exact"] <= 1.2)
    return rows


def part_blur(args, out: Path) -> list[dict]:
    import numpy as np

    sharp = synth(out / "scenes" / "blur-sharp", args)
    blurred = synth(out / "scenes" / "blur", args, projector_blur=args.blur_sigma)
    true_k = np.asarray(blurred.meta["projector_blur_kernel"]).reshape(-1)
    ident = np.zeros_like(true_k)
    ident[len(ident) // 2] = 1.0
    rows = []
    for name, scene, keys in (("in focus, no blur model", sharp, []), ("defocused, no blur model", blurred, []),
                              ("defocused, projector_blur=5", blurred, ["projector_blur=5"])):
        tr, m = train(scene, args.device, args.budget, out / "runs" / f"blur-{len(rows)}", keys + args.extra)
        if tr.rig.blur_on:
            ks = tr.rig.blur_kernels().detach().double().cpu().numpy()
            l1 = float(np.mean([np.abs(k - true_k).sum() for k in ks]))
            centre = float(np.mean(ks[:, len(true_k) // 2]))
        else:
            l1, centre = (float(np.abs(ident - true_k).sum()) if scene is blurred else 0.0), 1.0
        rows.append({"part": "blur", "run": name, **m, "kernel_l1": l1, "kernel_centre": centre,
                     "true_centre": float(true_k[len(true_k) // 2]) if scene is blurred else 1.0})
    sharp_c = rows[0]["chamfer_sym_mm"]
    for r in rows:
        r["chamfer_vs_in_focus"] = r["chamfer_sym_mm"] / sharp_c if sharp_c else float("nan")
    return rows


def part_laser(args, out: Path) -> list[dict]:
    from fastneus.light.lasers import pattern_approximation

    exact = synth(out / "scenes" / "laser", args, laser_planes=True)
    approx = pattern_approximation(exact, out / "scenes" / "laser-as-pattern", args.proj_size[0], args.proj_size[1],
                                   60.0, float(exact.meta["cam_distance"]))
    rows = []
    for name, scene in (("laser planes (exact model)", exact), ("pattern-image approximation", approx)):
        _, m = train(scene, args.device, args.budget, out / "runs" / f"laser-{len(rows)}", args.extra)
        rows.append({"part": "laser", "run": name, **m})
    ref = rows[0]["chamfer_sym_mm"]
    for r in rows:
        r["chamfer_vs_exact_model"] = r["chamfer_sym_mm"] / ref if ref else float("nan")
    return rows


def part_water(args, out: Path) -> list[dict]:
    air = synth(out / "scenes" / "water-air", args)
    wet = synth(out / "scenes" / "water", args, medium="water")
    true = wet.meta["medium"]
    rows = []
    for name, scene, keys in (("in air", air, []), ("under water, model on", wet, []),
                              ("under water, model off", wet, ["refraction=false", "medium=off"])):
        tr, m = train(scene, args.device, args.budget, out / "runs" / f"water-{len(rows)}", keys + args.extra)
        row = {"part": "water", "run": name, **m}
        if tr.rig.medium_on:
            bd, bb, binf = ([round(float(v), 3) for v in x.detach().double().cpu()] for x in tr.rig.medium_params())
            row.update(beta_d=bd, beta_b=bb, b_inf=binf, beta_d_true=true["beta_d"], b_inf_true=true["b_inf"])
        rows.append(row)
    ref = rows[0]["chamfer_sym_mm"]
    for r in rows:
        r["chamfer_vs_air"] = r["chamfer_sym_mm"] / ref if ref else float("nan")
    rows[1]["target_met"] = bool(rows[1]["chamfer_vs_air"] <= 1.5)
    return rows


TABLES = {
    "pose": ["run", "chamfer_sym_mm", "chamfer_vs_exact", "chamfer_gt2rec_mm", "psnr_pattern", "cam_rot_deg_mean",
             "cam_rot_deg_max", "cam_trans_mm_max", "cam_shift_px_mean", "cam_shift_px_max", "proj_rot_deg_mean", "proj_rot_deg_max", "proj_trans_mm_max",
             "steps", "target_met"],
    "blur": ["run", "chamfer_sym_mm", "chamfer_vs_in_focus", "chamfer_gt2rec_mm", "psnr_pattern", "psnr_texture",
             "kernel_l1", "kernel_centre", "true_centre", "steps"],
    "water": ["run", "chamfer_sym_mm", "chamfer_vs_air", "chamfer_gt2rec_mm", "psnr_pattern", "psnr_texture",
              "beta_d", "beta_d_true", "b_inf", "b_inf_true", "steps", "target_met"],
    "laser": ["run", "chamfer_sym_mm", "chamfer_vs_exact_model", "chamfer_gt2rec_mm", "psnr_pattern", "psnr_texture",
              "steps"],
}
TITLES = {
    "pose": "Pose refinement: poses perturbed by {pose_deg} deg / {pose_m_mm:g} mm (targets: <= 0.05 deg, "
            "<= 1 mm, symmetric Chamfer <= 1.2x the exact-pose run); errors are max over viewpoints "
            "(the first is the anchor) and projectors",
    "blur": "Projector blur: projectors defocused by a Gaussian of sigma {blur_sigma} px (5x5 taps); "
            "kernel_l1 = sum |learned - true| over the 25 taps (mean over projectors)",
    "water": "Underwater (flat ports, attenuation, back-scatter) vs the same geometry in air (target: model on "
             "<= 1.5x the in-air Chamfer); beta in 1/m per RGB channel",
    "laser": "Laser-plane projectors: photos rendered with the exact plane model; trained with the plane model vs "
             "the pattern-image approximation (planes rasterised at the orbit distance)",
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--out", required=True, help="results folder (created)")
    ap.add_argument("--parts", default=",".join(PARTS), help=f"comma list of {', '.join(PARTS)}")
    ap.add_argument("--budget", type=float, default=15.0, help="training seconds per run")
    ap.add_argument("--steps", type=int, default=0, help="train this many steps instead of --budget seconds")
    ap.add_argument("--points", type=int, default=100_000, help="surface points per mesh for Chamfer")
    ap.add_argument("--size", type=int, default=320, help="image size (square)")
    ap.add_argument("--proj-size", default="512x384", help="projector WxH")
    ap.add_argument("--views", type=int, default=12)
    ap.add_argument("--shape", default="toy")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--pose-deg", type=float, default=0.5)
    ap.add_argument("--pose-m", type=float, default=0.01)
    ap.add_argument("--blur-sigma", type=float, default=1.0, help="projector defocus (projector pixels)")
    ap.add_argument("extra", nargs="*", help="key=value applied to every run")
    args = ap.parse_args()
    global args_steps, args_points
    args_steps, args_points = args.steps, args.points
    args.proj_size = [int(v) for v in args.proj_size.lower().split("x")]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    bad = [p for p in parts if p not in PARTS]
    if bad:
        raise SystemExit(f"--parts: unknown {bad}; known: {', '.join(PARTS)}")
    t0 = time.perf_counter()
    rows: list[dict] = []
    done: list[str] = []
    for p in parts:
        tp = time.perf_counter()
        try:
            rows += globals()[f"part_{p}"](args, out)
        except Exception as e:  # noqa: BLE001 - keep the other parts' results
            rows.append({"part": p, "run": f"FAILED: {type(e).__name__}: {e}"})
            print(f"[{p}] failed: {type(e).__name__}: {e}", flush=True)
        done.append(p)
        print(f"[{p}] {time.perf_counter() - tp:.0f} s", flush=True)
        report(args, out, done, rows, time.perf_counter() - t0)  # after every part: a killed run keeps its tables
    print((out / "rig-recovery.md").read_text())


def report(args, out: Path, parts: list[str], rows: list[dict], seconds: float) -> None:
    cmd = (f"python scripts/rig_recovery.py --device {args.device} --parts {','.join(parts)} "
           f"{'--steps ' + str(args.steps) if args.steps else '--budget ' + format(args.budget, 'g')} "
           f"--size {args.size} --views {args.views} --shape {args.shape}")  # the parts done so far
    head = f"`{cmd}` on {machine(args.device)}, git {git_rev()}, {seconds:.0f} s in all. Chamfer in mm.\n"
    md = [head]
    fmt = dict(vars(args), pose_m_mm=args.pose_m * 1000)
    for p in parts:
        sub = [r for r in rows if r["part"] == p]
        md.append(f"\n**{TITLES[p].format(**fmt)}**\n\n" + md_table(sub, TABLES[p]))
    write_results(out, "rig-recovery", {"args": dict(vars(args)), "rows": rows, "seconds": round(seconds, 1)},
                  "".join(md), args.device, cmd)

if __name__ == "__main__":
    main()
