"""A whole run: train -> mesh -> renders -> metrics -> illumination -> report, each phase timed."""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

from fastneus.config import Config
from fastneus.errors import FastneusError
from fastneus.io import atomic_write_json


def machine() -> dict:
    """The machine a run ran on: host, OS, CPU, cores, Python and torch, and the GPU when CUDA
    is up (read without initialising CUDA otherwise)."""
    import os
    import platform
    import sys

    import torch

    m = {"host": platform.node(), "os": platform.platform(), "cpu": platform.processor() or platform.machine(),
         "cores": os.cpu_count(), "python": sys.version.split()[0], "torch": torch.__version__}
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                if line.startswith("model name"):
                    m["cpu"] = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    if torch.cuda.is_initialized():
        m["gpu"] = torch.cuda.get_device_name()
    return m


def provenance() -> dict:
    """What made a run: fastneus's version, the command line, the machine and, for a git
    checkout of fastneus, its commit (``+dirty`` with uncommitted changes); recorded in run.json."""
    import shlex
    import subprocess
    import sys

    from fastneus import __version__

    prog = Path(sys.argv[0]).name if sys.argv and sys.argv[0] else "python"
    prog = "fastneus" if prog == "__main__.py" else prog  # python -m fastneus / fastneus.cli
    out = {"fastneus_version": __version__, "command": shlex.join([prog, *sys.argv[1:]]), "machine": machine()}
    src = Path(__file__).resolve().parent.parent
    try:
        git = lambda *a: subprocess.run(["git", "-C", str(src), *a], capture_output=True, text=True,  # noqa: E731
                                        timeout=5).stdout.strip()
        commit = git("rev-parse", "HEAD") if (src / ".git").exists() else ""
        if commit:
            out["git_commit"] = commit + ("+dirty" if git("status", "--porcelain", "--untracked-files=no") else "")
    except (OSError, subprocess.SubprocessError):
        pass
    return out


def default_eval_frames(scene, train_frames: list[int], limit: int = 3) -> list[int]:
    """Frames to render for the report: the first training frame plus a few held-out ones."""
    held = [i for i in range(len(scene.frames)) if i not in set(train_frames)]
    picks = [train_frames[0]]
    if held:
        step = max(1, len(held) // max(1, limit - 1))
        picks += held[::step][: limit - 1]
    return picks


def finish_run(trainer, console=None, eval_frames: list[int] | None = None, mesh_resolution: int | None = None,
               clock=None, save_checkpoint: bool = False) -> dict:
    """Mesh, renders, metrics, illumination.json and report.html for a trained ``trainer``.

    mesh.ply is written first and nothing heavy runs before it (the evaluation modules,
    trimesh and the ground truth are loaded after). Each phase is timed on ``clock`` (default:
    the trainer's, else the CLI's, else a new one); metrics.json and run.json get ``timing``
    (seconds per phase, ``mesh_ready_at`` and ``total`` from the clock's origin, the process
    start for a CLI run) and the peak host / GPU memory. ``save_checkpoint``: write the
    trainer's checkpoint right after mesh.ply (also if meshing fails).
    """
    from fastneus import timing
    from fastneus.export.mesh import save_mesh

    clock = clock or getattr(trainer, "clock", None) or timing.take_clock()
    say = console.print if console is not None else (lambda *a, **k: None)
    run, scene, cfg = trainer.out, trainer.scene, trainer.cfg
    try:
        with clock.phase("mesh"):
            t = time.perf_counter()
            res = mesh_resolution or cfg.export.mesh_resolution
            mesh = run_mesh(trainer, res)
            save_mesh(mesh, run / "mesh.ply")
            at = clock.mark("mesh_ready")
            dt = time.perf_counter() - t
    finally:
        if save_checkpoint:
            with clock.phase("checkpoint"):
                trainer.save()
    say(f"mesh: {len(mesh.vertices)} vertices, {len(mesh.faces)} faces -> {run / 'mesh.ply'} "
        f"({dt:.2f}s at {res}^3, {mesh.stats['mc']} marching cubes, "
        f"{100 * mesh.stats['points'] / mesh.stats['dense_points']:.0f}% of the grid evaluated; "
        f"{at:.1f}s after {clock.source})")
    clock.notes["mesh"] = {k: mesh.stats[k] for k in ("points", "dense_points", "cells", "mc", "coarse_s", "fine_s",
                                                     "cells_s", "mc_s", "filter_s") if k in mesh.stats}
    clock.notes["mesh"]["resolution"] = int(res)

    with clock.phase("validation"):  # the last validation render, kept off mesh.ply's path
        trainer.finish_progress()
    frames = eval_frames if eval_frames is not None else default_eval_frames(scene, trainer.frames)
    with clock.phase("renders"):
        t = time.perf_counter()
        from fastneus.eval.metrics import (geometry_metrics, illumination_metrics, image_metrics, render_frames,
                                              save_renders)
        from fastneus.eval.report import write_report
        from fastneus.io import atomic_write_image

        renders = render_frames(trainer, frames)
        paths = save_renders(renders, run / "renders")
        for i in frames:
            clean = scene.gt_clean(i)  # read once: it is a full-size PNG
            if clean is not None:
                atomic_write_image(run / "renders" / f"{i:03d}_clean.png", clean)
                paths[i]["clean"] = f"renders/{i:03d}_clean.png"
    say(f"renders of frames {frames} -> {run / 'renders'} ({time.perf_counter() - t:.1f}s)")
    with clock.phase("eval"):
        from fastneus.eval.depth import view_depth_metrics

        tm = mesh.to_trimesh()
        metrics: dict = {"steps": trainer.step, "train_seconds": round(trainer.elapsed, 2),
                         "train_frames": len(trainer.frames), "skipped_steps": trainer.skipped,
                         "masks_used": bool(trainer.masks_used), "bg_prior_used": bool(trainer.bg_used)}
        metrics.update(illumination_metrics(trainer))
        metrics.update(geometry_metrics(tm, scene, trainer.frames))
        metrics.update(view_depth_metrics(tm, scene, trainer.frames, trainer.device))  # visible-surface depth error
        metrics.update(image_metrics(scene, renders))
        metrics.update(timing.peak_memory(trainer.device))
        metrics["timing"] = clock.summary()
        atomic_write_json(run / "metrics.json", metrics)
        ill = {k: metrics[k] for k in ("i_r", "i_b", "i_r_gt", "i_b_gt", "i_r_err", "i_b_err", "exposure_gains",
                                       "exposure_err") if k in metrics}
        atomic_write_json(run / "illumination.json", ill)
    with clock.phase("report"):
        # the clock read here, after the eval phase closed: the page's wall-clock table has its eval row
        write_report(run, metrics, paths, cfg.to_dict(), title=f"fastneus: {scene.name or scene.root.name}",
                     renders=renders, scene=scene, mesh=mesh, timing=clock.summary())
    # the final word on time and memory: every phase done
    metrics.update(timing.peak_memory(trainer.device))
    metrics["timing"] = clock.summary()
    atomic_write_json(run / "metrics.json", metrics)
    _update_run_json(run, {"timing": metrics["timing"],
                           **{k: v for k, v in metrics.items() if k.startswith("peak_")}})
    return metrics


def _update_run_json(run: Path, extra: dict) -> None:
    """Merge ``extra`` into run.json (created if missing or unreadable)."""
    import json

    path = Path(run) / "run.json"
    try:
        data = json.loads(path.read_text()) if path.is_file() else {}
        if not isinstance(data, dict):
            data = {}
    except (OSError, ValueError, RecursionError):  # unreadable or absurdly nested: rewritten
        data = {}
    data.update(extra)
    atomic_write_json(path, data)


def print_run_summary(metrics: dict, console) -> None:
    """One line of time-to-mesh, total and peak memory, then the per-phase table."""
    from fastneus import timing

    tm = metrics.get("timing") or {}
    if not tm:
        return
    mem = f"peak RSS {metrics['peak_rss_mb']:.0f} MB" if "peak_rss_mb" in metrics else ""
    if "peak_gpu_mb" in metrics:
        mem += (f", peak GPU {metrics['peak_gpu_mb']:.0f} MB (torch {metrics['peak_gpu_torch_mb']:.0f}, "
                f"Warp {metrics['peak_gpu_warp_mb']:.0f})")
    ready = f"mesh.ply at {tm['mesh_ready_at']:.1f} s, " if "mesh_ready_at" in tm else ""
    console.print(f"wall clock from {tm.get('origin', 'start')}: {ready}total {tm['total']:.1f} s; {mem}")
    console.print(timing.table(tm), markup=False, highlight=False)


def check_inputs(scene, frames: list[int]) -> None:
    """Check what training and finish_run will read from ``scene`` that loading does not: focal
    lengths in pixels, and the ground truth (per-frame depth, normals and pattern-free images of
    ``frames``, the GT mesh). A bad file found after training would cost the run, and with
    ``--overwrite`` the previous one.

    Raises:
        FastneusError: naming the scene file and field.
    """
    import numpy as np

    file = Path(scene.root) / "scene.json"
    if not file.is_file():
        file = Path(scene.root)
    for kind, devs in (("cameras", scene.cameras), ("projectors", scene.projectors)):
        for did, d in devs.items():
            for f, n in ((d.K[0, 0], d.width), (d.K[1, 1], d.height)):
                # fx < 0.005 * width is a field of view over 179 degrees: not a pinhole in pixels
                if getattr(d, "planes", None) is None and not f >= 0.005 * n:
                    raise FastneusError(f"focal length {f:g} px is implausible for a {d.width}x{d.height} image "
                                        "(field of view over 179 degrees); K must be in pixels", file=file,
                                        field=f"{kind}.{did}.K")
    for i in frames:
        cam = scene.frame_camera(i)
        hw = (cam.height, cam.width)
        for key, read, shape in (("depth", scene.gt_depth, hw), ("normal", scene.gt_normal, hw + (3,)),
                                 ("clean", scene.gt_clean, hw + (3,))):
            a = read(i)
            if a is None:
                continue
            if a.shape != shape:
                raise FastneusError(f"has shape {a.shape}, expected {shape} (the frame's image size)", file=file,
                                    field=f"frames[{i}].gt.{key}")
            if key == "depth" and not (np.isfinite(a).all() and (a >= 0).all()):
                raise FastneusError("depths must be finite and >= 0 (0 = background)", file=file,
                                    field=f"frames[{i}].gt.depth")
    if scene.gt_mesh:
        # from its header: importing trimesh here cost ~1 s before training (the full parse is
        # evaluation's, after mesh.ply)
        from fastneus.data.groundtruth import mesh_file_problem

        path = scene.path(scene.gt_mesh)
        why = mesh_file_problem(Path(path))
        if why is not None:
            raise FastneusError(f"cannot use the ground-truth mesh {path}: {why}", file=file, field="gt.mesh")


def train_scene(scene, cfg: Config, out: Path, device: str, console=None, resume: bool = False,
                finish: bool = True, overwrite: bool = False, clock=None) -> tuple[object, dict]:
    """Train on ``scene`` into run folder ``out``; then mesh/render/evaluate/report.

    A folder that already holds a run is refused unless ``resume`` or ``overwrite``;
    Ctrl-C / SIGTERM during training saves a checkpoint and raises ``RunInterrupted``.
    Phases (imports, setup, kernels, train, then finish_run's) are timed on ``clock``
    (default: the CLI's, else a new one from now).

    Returns:
        (trainer, metrics) — metrics empty when ``finish`` is False.
    """
    from fastneus import timing

    clock = clock or timing.take_clock()
    with clock.phase("imports"):
        from fastneus.io import confined
        from fastneus.train.checkpoint import CKPT_NAME, load_checkpoint, restore
        from fastneus.train.interrupt import stop_on_signal
        from fastneus.train.runfolder import (PreviousRun, check_run_folder, mark_run, recover, remove_stale_temps,
                                              repair_log, run_lock)
        from fastneus.train.trainer import Trainer

    out = Path(out)
    # nothing written below `out` follows a symbolic link; one writer at a time
    with confined(out), run_lock(out):
        recover(out)  # a killed --overwrite: its previous run comes back (or goes, if the new one had a checkpoint)
        check_run_folder(out, resume=resume, overwrite=overwrite)
        remove_stale_temps(out)
        if resume:
            repair_log(out)
        if str(device).startswith("cuda"):
            with clock.phase("cuda_init"):  # the CUDA context (torch's; Warp's driver init is in imports)
                import torch

                torch.empty(1, device=device)
                torch.cuda.synchronize(device)
        with clock.phase("setup"):
            trainer = Trainer(scene, cfg, out, device, console)
            trainer.clock = clock
            if finish:  # what finish_run reads, checked before the folder changes or training starts
                check_inputs(scene, sorted(set(trainer.frames) | set(default_eval_frames(scene, trainer.frames))))
            if resume:
                if not (out / CKPT_NAME).is_file():
                    raise FastneusError("--resume given but the run folder has no checkpoint",
                                        file=str(out / CKPT_NAME))
                restore(trainer, load_checkpoint(out, map_location=device), out / CKPT_NAME)
            # inputs are valid by now: an earlier run is moved aside (not mixed in), and deleted only
            # once this run has saved its first checkpoint
            kept = {"prev": None if resume else PreviousRun.set_aside(out)}

        def first_checkpoint() -> None:
            trainer.on_saved = None
            if kept["prev"] is not None:
                kept["prev"].drop()
                kept["prev"] = None
        trainer.on_saved = first_checkpoint
        try:
            mark_run(out)
            return _train_and_finish(trainer, scene, cfg, out, device, console, finish, clock, stop_on_signal)
        except BaseException:
            if kept["prev"] is not None:  # failed before any checkpoint: the previous run comes back
                kept["prev"].restore()
            raise


def _train_and_finish(trainer, scene, cfg: Config, out: Path, device: str, console, finish: bool, clock,
                      stop_on_signal) -> tuple[object, dict]:
    """train_scene's part after the run folder is ready: run.json, training, then finish_run."""
    if console is not None:
        console.print(trainer.threads_note)
        if trainer.device.type == "cuda":
            console.print(trainer.matmul_note())
        console.print(trainer.masks_note)
        console.print(trainer.hull_note)
        console.print(trainer.table_note, soft_wrap=True, highlight=False, markup=False)
        console.print(trainer.bg_note)
        console.print(trainer.response_note)
        if trainer.level_note:
            console.print(trainer.level_note, soft_wrap=True, highlight=False, markup=False)
        if trainer.photos_note:
            console.print(trainer.photos_note, soft_wrap=True, highlight=False, markup=False)
        console.print(trainer.blur_note(), soft_wrap=True, highlight=False, markup=False)
        console.print(trainer.exposure_note(), soft_wrap=True, highlight=False, markup=False)
        length = f"time budget {cfg.run.time_budget:g} s" if cfg.run.time_budget > 0 else f"{cfg.run.steps} steps"
        console.print(f"run length: {length}; every schedule is a fraction of it")
    atomic_write_json(out / "run.json", {"scene": str(scene.root), "device": str(device), "preset": cfg.run.preset,
                                         "threads": trainer.threads, "matmul": trainer.matmul,
                                         "masks": trainer.masks_note,
                                         "background_prior": trainer.bg_note, "response": trainer.response_note,
                                         **({"photos": trainer.photos_note} if trainer.photos_note else {}),
                                         "photo_gain": trainer.photo_gain,
                                         **({"photo_level": trainer.level_note} if trainer.level_note else {}),
                                         "camera_blur": trainer.blur_decision, "camera_blur_note": trainer.blur_note(),
                                         "exposure": trainer.exposure_decision,
                                         "exposure_note": trainer.exposure_note(),
                                         "occupancy_updates": "near" if trainer.occ_near else "all",
                                         "occupancy_hull": trainer.hull_note, "hash_table": trainer.table_note,
                                         **provenance()})
    with stop_on_signal(trainer, out):
        last = trainer.fit(final_save=not finish)  # finish_run saves it right after mesh.ply
    # decided during the run (camera_blur=auto, exposure=auto): the decisions and their printed lines
    floor = trainer.floor_note()
    _update_run_json(out, {"camera_blur": trainer.blur_decision, "camera_blur_note": trainer.blur_note(),
                           "exposure": trainer.exposure_decision, "exposure_note": trainer.exposure_note(),
                           **({"sharpness_floor": floor} if floor else {}),
                           **({"cuda_graphs": last["cuda_graphs"]} if last and "cuda_graphs" in last else {})})
    if console is not None and last:
        console.print(f"trained {trainer.step} steps in {trainer.elapsed:.1f}s: loss {last['loss']:.4f}, "
                      f"PSNR {last['psnr']:.2f} dB, i_r {last['i_r']:.4f}, i_b {last['i_b']:.4f}")
        if floor:
            console.print(floor, soft_wrap=True, highlight=False, markup=False)
    metrics = finish_run(trainer, console, clock=clock, save_checkpoint=True) if finish else {}
    return trainer, metrics


# --------------------------------------------------------------------------- the public facade
def open_run(run: str, device: str, scene: str | None = None):
    """Scene + trainer (weights loaded) of a run folder."""
    from fastneus.formats.detect import load_scene  # lazily: the CLI start-up does not pay for them
    from fastneus.train.trainer import trainer_from_run

    rp = Path(run)
    if not rp.is_dir():
        raise FastneusError("run folder not found", file=run)
    if scene is None:
        meta = rp / "run.json"
        if not meta.is_file():
            raise FastneusError("run.json missing; pass --scene", file=str(meta))
        try:
            scene = json.loads(meta.read_text())["scene"]
        except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError, RecursionError) as e:
            raise FastneusError(f"unreadable run metadata: {type(e).__name__}: {e}".splitlines()[0],
                                file=str(meta), field="scene") from None
        if not isinstance(scene, str) or not scene:
            raise FastneusError(f"expected the scene folder's path, got {scene!r}", file=str(meta), field="scene")
        if not Path(scene).exists():
            raise FastneusError(f"the run's scene {scene} is gone (moved?); pass --scene DIR", file=str(meta),
                                field="scene")
    sc = load_scene(scene)
    return sc, trainer_from_run(sc, rp, device)


def reconstruct(scene, config=None, out: str | os.PathLike = "runs/fastneus", device: str | None = None, *,
                overrides: list[str] | None = None, resume: bool = False, overwrite: bool = False,
                console=None) -> tuple[object, dict]:
    """Reconstruct a scene: train, then write mesh.ply, renders, metrics and report.html into ``out``.

    Args:
        scene: a :class:`fastneus.data.Scene` or a scene folder of any supported format.
        config: a :class:`fastneus.config.Config`, a preset name or YAML path, or None (fewview on
            CUDA, cpu-quick on CPU).
        out: the run folder (refused if it holds another run, unless ``resume`` / ``overwrite``).
        device: ``cpu`` or ``cuda`` (default: cuda when available).
        overrides: ``["section.key=value", ...]`` applied on top of ``config``.
        console: a rich Console for progress (None: quiet).

    Returns:
        (trainer, metrics): the trained :class:`fastneus.train.trainer.Trainer` and the metrics dict.
    """
    import torch

    from fastneus.config import apply, load_config, parse_overrides
    from fastneus.formats.detect import load_scene

    if isinstance(scene, (str, os.PathLike)):
        scene = load_scene(scene)
    device = device or ("cuda" if torch.cuda.is_available() else "cpu")
    if config is None or isinstance(config, (str, os.PathLike)):
        cfg = load_config(str(config) if config else ("fewview" if device.startswith("cuda") else "cpu-quick"),
                          overrides)
    else:
        cfg = apply(config, parse_overrides(overrides), "overrides")
    return train_scene(scene, cfg, Path(out), device, console=console, resume=resume, overwrite=overwrite)


def run_mesh(trainer, resolution: int | None = None, scene=None):
    """The trained surface (marching cubes, world units) with vertex normals and the learned
    pattern-free colours in the photos' units and encoding: the one place mesh.ply, ``fastneus
    export mesh`` and :func:`extract_mesh` take it from.

    Args:
        trainer: a trained :class:`fastneus.train.trainer.Trainer`.
        resolution: grid resolution (default: the run's ``export.mesh_resolution``).
        scene: the scene to mesh in (default: the trainer's).
    Returns:
        :class:`fastneus.export.mesh.MeshArrays` with ``normals`` and ``colors``.
    """
    from fastneus.export.mesh import extract_mesh_arrays, shade_mesh

    scene = scene if scene is not None else trainer.scene
    res = resolution or trainer.cfg.export.mesh_resolution
    mesh = extract_mesh_arrays(trainer.field, scene, res, trainer.device, bound=trainer.cfg.rays.bound,
                               allowed=trainer.seen)
    # colours encoded like the photos, and divided back when a dim capture was trained brighter (illum.level)
    return shade_mesh(trainer.field, scene, mesh, trainer.device, response=getattr(trainer, "response", None),
                      scale=1.0 / getattr(trainer, "photo_gain", 1.0))


def extract_mesh(trainer, resolution: int | None = None):
    """The trained surface as a ``trimesh.Trimesh`` in world units (marching cubes), with vertex
    normals and the learned pattern-free vertex colours (:func:`run_mesh`).

    Args:
        trainer: a trained :class:`fastneus.train.trainer.Trainer` (e.g. from :func:`reconstruct`).
        resolution: grid resolution (default: the run's ``export.mesh_resolution``).
    """
    return run_mesh(trainer, resolution).to_trimesh()


def evaluate(run: str | os.PathLike, device: str | None = None, scene: str | None = None,
             frames: list[int] | None = None, resolution: int | None = None) -> dict:
    """Re-evaluate a run folder (mesh, renders, metrics.json, report.html); returns the metrics.

    Args:
        run: the run folder. scene: its scene folder when run.json's path moved.
        frames: frames to render (default: the run's choice). resolution: marching-cubes grid.
    """
    import torch

    from fastneus.io import confined
    from fastneus.train.runfolder import run_lock

    device = device or ("cuda" if torch.cuda.is_available() else "cpu")
    with confined(run), run_lock(Path(run)):
        _, tr = open_run(str(run), device, scene)
        return finish_run(tr, eval_frames=frames, mesh_resolution=resolution)
