"""Verbs ``train`` and ``oneshot``."""
from __future__ import annotations

import argparse
from pathlib import Path

from fastneus.cli import add_device_arg, add_threads_arg, resolve_device, threads_override
from fastneus.cli.formats import scene_help
from fastneus.errors import FastneusError


def _default_out(scene_path: str, tag: str) -> Path:
    return Path("runs") / f"{Path(scene_path).resolve().name}-{tag}"


def _console():
    from rich.console import Console

    return Console(stderr=False)


# one-shot priors layered on cpu-quick when the oneshot verb runs on a CPU. 1200 steps, not
# cpu-quick's 600: one view has no other view to correct it, and the 400-px colourful-line toy
# went from 2.39 % to 0.76 % depth error (rock 0.137 -> 0.114 %), 2.2 min on 2 cores
# the one-shot keeps the eikonal weight of 0.1 that cpu-quick lowered for many views: the realistic
# colourful-line toy (1200 steps, one seed) went 0.207 -> 0.253 % mean depth error at 0.05
# (docs/benchmarks/eikonal-cpu.md)
ONESHOT_CPU = {"view_dependent": False, "curvature_weight": 5e-4, "steps": 1200, "eikonal_weight": 0.1}


def _run(args, tag: str, default_preset: str, oneshot_frame: int | None = None) -> int:
    from fastneus import timing
    from fastneus.config import load_config
    from fastneus.formats.detect import load_scene
    from fastneus.pipeline import print_run_summary, train_scene

    clock = timing.take_clock()  # from the process start (fastneus.cli)
    device = resolve_device(args.device)
    preset = args.config or (default_preset if device.startswith("cuda") else "cpu-quick")
    with clock.phase("scene_load"):
        scene = load_scene(args.scene)
    base: dict = {}
    if oneshot_frame is not None:
        i = oneshot_frame
        if not args.config and not device.startswith("cuda"):
            base.update(ONESHOT_CPU)
        if not 0 <= i < len(scene.frames):
            raise FastneusError(f"frame {i} out of range 0..{len(scene.frames) - 1}", field="--frame")
        view = scene.frames[i].view
        base["frames"] = [j for j, f in enumerate(scene.frames) if f.view == view]
    out = Path(args.out) if args.out else _default_out(args.scene, tag)
    if args.resume:  # the run's own config.yaml, with this command line's overrides on top
        from fastneus.train.runfolder import check_run_folder, resume_config

        check_run_folder(out, resume=True, overwrite=args.overwrite)  # --resume with --overwrite: refused first
        if args.config:
            raise FastneusError("--resume continues with the run's own config.yaml; give changes as key=value "
                                "(e.g. steps=5000)", field="--config")
        cfg = resume_config(out, list(args.overrides or []) + threads_override(args))
    else:
        cfg = load_config(preset, list(args.overrides or []) + threads_override(args), base=base)
    con = _console()
    con.print(f"[bold]fastneus {tag}[/bold]: scene {args.scene} ({len(scene.frames)} frames, "
              f"{len(cfg.run.frames) if cfg.run.frames else len(scene.frames)} used), preset {cfg.run.preset}, "
              f"device {device}, backend {cfg.run.backend} -> {out}")
    _, metrics = train_scene(scene, cfg, out, device, console=con, resume=args.resume, overwrite=args.overwrite,
                             clock=clock)
    show = [k for k in ("chamfer_gt2rec_mm", "chamfer_gt2rec_filtered_mm", "visible_gt2rec_mm", "fscore",
                        "depth_err_mm", "depth_err_pct", "depth_median_pct", "depth_within_1pct", "depth_lit_err_pct",
                        "psnr_pattern", "psnr_texture", "i_r", "i_b") if k in metrics]
    con.print("  ".join(f"{k} {metrics[k]:.4g}" for k in show))
    print_run_summary(metrics, con)
    con.print(f"report: {out / 'report.html'}")
    return 0


def add_config_args(p: argparse.ArgumentParser) -> None:
    """Add the options that choose a training run's config and machine: ``--config``, ``--device``,
    ``--threads`` (shared by ``train``, ``oneshot`` and ``batch``; the key=value overrides are added
    by each verb, as its positional arguments differ)."""
    p.add_argument("--config", help="preset name (fewview, oneshot, cpu-quick, passive, paper) or YAML file "
                                    "(default: fewview on cuda, cpu-quick on cpu)")
    add_device_arg(p)
    add_threads_arg(p)


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", help=scene_help())
    p.add_argument("--out", help="run folder (default runs/<scene>-<verb>)")
    p.add_argument("--resume", action="store_true", help="continue from the run folder's checkpoint "
                                                         "(also after Ctrl-C, which saves one)")
    p.add_argument("--overwrite", action="store_true", help="replace a run already in the run folder "
                                                            "(refused otherwise)")
    add_config_args(p)
    p.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides, e.g. steps=2000 lr=0.005")


def register(sub) -> None:
    p = sub.add_parser("train", help="reconstruct a scene: mesh, renders, metrics, report",
                       description="Train fastneus on a scene, then export mesh.ply, renders, metrics.json, "
                                   "illumination.json and report.html into the run folder.")
    _common(p)
    p.set_defaults(func=lambda a: _run(a, "train", "fewview"))

    q = sub.add_parser("oneshot", help="reconstruct from a single viewpoint (all patterns shown there)",
                       description="One-shot reconstruction: uses only the frames of one viewpoint "
                                   "(the view of --frame), with the oneshot preset.")
    _common(q)
    q.add_argument("--frame", type=int, default=0, help="a frame of the viewpoint to use (default 0)")
    q.set_defaults(func=lambda a: _run(a, "oneshot", "oneshot", oneshot_frame=a.frame))
