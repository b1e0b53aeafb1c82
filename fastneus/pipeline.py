"""A whole run: train -> mesh -> renders -> metrics -> illumination -> report."""
from __future__ import annotations

import time
from pathlib import Path

from fastneus.config import Config
from fastneus.errors import FastneusError
from fastneus.io import atomic_write_json


def default_eval_frames(scene, train_frames: list[int], limit: int = 3) -> list[int]:
    """Frames to render for the report: the first training frame plus a few held-out ones."""
    held = [i for i in range(len(scene.frames)) if i not in set(train_frames)]
    picks = [train_frames[0]]
    if held:
        step = max(1, len(held) // max(1, limit - 1))
        picks += held[::step][: limit - 1]
    return picks


def finish_run(trainer, console=None, eval_frames: list[int] | None = None, mesh_resolution: int | None = None) -> dict:
    """Mesh, renders, metrics, illumination.json and report.html for a trained ``trainer``."""
    from fastneus.export.evaluate import geometry_metrics, illumination_metrics, image_metrics, render_frames, save_renders
    from fastneus.export.mesh import extract_mesh, save_mesh
    from fastneus.export.report import write_report

    say = console.print if console is not None else (lambda *a, **k: None)
    run, scene, cfg = trainer.out, trainer.scene, trainer.cfg
    t = time.perf_counter()
    res = mesh_resolution or cfg.mesh_resolution
    mesh = extract_mesh(trainer.field, scene, res, trainer.device, bound=cfg.bound, allowed=trainer.seen)
    save_mesh(mesh, run / "mesh.ply")
    say(f"mesh: {len(mesh.vertices)} vertices, {len(mesh.faces)} faces -> {run / 'mesh.ply'} "
        f"({time.perf_counter() - t:.1f}s)")
    frames = eval_frames if eval_frames is not None else default_eval_frames(scene, trainer.frames)
    t = time.perf_counter()
    renders = render_frames(trainer, frames)
    paths = save_renders(renders, run / "renders")
    from fastneus.io import atomic_write_image

    for i in frames:
        clean = scene.gt_clean(i)  # read once: it is a full-size PNG
        if clean is not None:
            atomic_write_image(run / "renders" / f"{i:03d}_clean.png", clean)
            paths[i]["clean"] = f"renders/{i:03d}_clean.png"
    say(f"renders of frames {frames} -> {run / 'renders'} ({time.perf_counter() - t:.1f}s)")
    metrics: dict = {"steps": trainer.step, "train_seconds": round(trainer.elapsed, 2),
                     "train_frames": len(trainer.frames), "skipped_steps": trainer.skipped,
                     "masks_used": bool(trainer.masks_used), "bg_prior_used": bool(trainer.bg_used)}
    metrics.update(illumination_metrics(trainer))
    metrics.update(geometry_metrics(mesh, scene, trainer.frames))
    from fastneus.export.depth import view_depth_metrics

    metrics.update(view_depth_metrics(mesh, scene, trainer.frames, trainer.device))  # visible-surface depth error
    metrics.update(image_metrics(scene, renders))
    atomic_write_json(run / "metrics.json", metrics)
    ill = {k: metrics[k] for k in ("i_r", "i_b", "i_r_gt", "i_b_gt", "i_r_err", "i_b_err") if k in metrics}
    atomic_write_json(run / "illumination.json", ill)
    write_report(run, metrics, paths, cfg.to_dict(), title=f"fastneus: {scene.name or scene.root.name}")
    return metrics


def train_scene(scene, cfg: Config, out: Path, device: str, console=None, resume: bool = False,
                finish: bool = True, overwrite: bool = False) -> tuple[object, dict]:
    """Train on ``scene`` into run folder ``out``; then mesh/render/evaluate/report.

    A folder that already holds a run is refused unless ``resume`` or ``overwrite``;
    Ctrl-C / SIGTERM during training saves a checkpoint and raises ``RunInterrupted``.

    Returns:
        (trainer, metrics) — metrics empty when ``finish`` is False.
    """
    from fastneus.train.checkpoint import CKPT_NAME, load_checkpoint, restore
    from fastneus.train.interrupt import stop_on_signal
    from fastneus.train.runfolder import check_run_folder, clear_run_folder
    from fastneus.train.trainer import Trainer

    out = Path(out)
    check_run_folder(out, resume=resume, overwrite=overwrite)
    trainer = Trainer(scene, cfg, out, device, console)
    if resume:
        if not (out / CKPT_NAME).is_file():
            raise FastneusError("--resume given but the run folder has no checkpoint", file=str(out / CKPT_NAME))
        restore(trainer, load_checkpoint(out, map_location=device), out / CKPT_NAME)
    else:
        clear_run_folder(out)  # inputs are valid by now: an earlier run is replaced, not mixed in
    if console is not None:
        console.print(trainer.threads_note)
        console.print(trainer.masks_note)
        console.print(trainer.bg_note)
        length = f"time budget {cfg.time_budget:g} s" if cfg.time_budget > 0 else f"{cfg.steps} steps"
        console.print(f"run length: {length}; every schedule is a fraction of it")
    atomic_write_json(out / "run.json", {"scene": str(scene.root), "device": str(device), "preset": cfg.preset,
                                         "threads": trainer.threads, "masks": trainer.masks_note,
                                         "background_prior": trainer.bg_note})
    with stop_on_signal(trainer, out):
        last = trainer.fit()
    if console is not None and last:
        console.print(f"trained {trainer.step} steps in {trainer.elapsed:.1f}s: loss {last['loss']:.4f}, "
                      f"PSNR {last['psnr']:.2f} dB, i_r {last['i_r']:.4f}, i_b {last['i_b']:.4f}")
    metrics = finish_run(trainer, console) if finish else {}
    return trainer, metrics
