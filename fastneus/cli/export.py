"""Verbs ``mesh``, ``render`` and ``eval`` on a trained run folder."""
from __future__ import annotations

from pathlib import Path

from fastneus.cli import add_device_arg, resolve_device
from fastneus.errors import FastneusError
from fastneus.io import check_out_dir, confined, json_text
from fastneus.pipeline import open_run, run_mesh

RUN_HELP = "run folder of a trained run (holds checkpoint.pt and config.yaml)"
SCENE_HELP = "scene folder (default: the one the run was trained on, from run.json)"


def _check_frames(frames: list[int], scene) -> list[int]:
    for i in frames:
        if not 0 <= i < len(scene.frames):
            raise FastneusError(f"frame {i} out of range 0..{len(scene.frames) - 1}", field="--frame")
    return frames


def _check_resolution(res: int | None) -> None:
    if res is not None and not 8 <= res <= 4096:
        raise FastneusError(f"must be between 8 and 4096, got {res}", field="--resolution")


def _mesh(args) -> int:
    from fastneus.export.mesh import MESH_SUFFIXES, save_mesh

    _check_resolution(args.resolution)
    if args.out is not None:
        kinds = ", ".join(MESH_SUFFIXES[:-1]) + f" or {MESH_SUFFIXES[-1]}"
        if Path(args.out).is_dir():
            raise FastneusError(f"is a folder; give a mesh file path ending in {kinds}", file=args.out, field="--out")
        if Path(args.out).suffix.lower() not in MESH_SUFFIXES:
            raise FastneusError(f"mesh output must end in {kinds}", file=args.out, field="--out")
        check_out_dir(Path(args.out).parent)
    device = resolve_device(args.device)
    scene, tr = open_run(args.run, device, args.scene)
    mesh = run_mesh(tr, args.resolution, scene)
    out = Path(args.out) if args.out else Path(args.run) / "mesh.ply"
    with confined(out.parent):  # mesh.ply as a link into another folder is refused, not followed
        save_mesh(mesh, out)
    print(f"{out}: {len(mesh.vertices)} vertices, {len(mesh.faces)} faces (world units, {scene.units})")
    return 0


def _render(args) -> int:
    from fastneus.eval.metrics import render_frames, save_renders

    if args.out is not None:
        check_out_dir(args.out)
    device = resolve_device(args.device)
    scene, tr = open_run(args.run, device, args.scene)
    frames = _check_frames(args.frame or [0], scene)
    out = Path(args.out) if args.out else Path(args.run) / "renders"
    renders = render_frames(tr, frames)
    with confined(Path(args.run) if args.out is None else out):  # RUN/renders as a link is refused, not followed
        paths = save_renders(renders, out)
    for i, p in paths.items():
        print(f"frame {i}: " + ", ".join(f"{k} {out / Path(v).name}" for k, v in p.items()))
    return 0


def _eval(args) -> int:
    from fastneus.pipeline import finish_run
    from fastneus.train.runfolder import run_lock

    _check_resolution(args.resolution)
    device = resolve_device(args.device)
    if not Path(args.run).is_dir():
        raise FastneusError("run folder not found", file=args.run)
    # one writer at a time; nothing it writes in the run follows a symbolic link
    with confined(args.run), run_lock(Path(args.run)):
        scene, tr = open_run(args.run, device, args.scene)
        if args.frame:
            _check_frames(args.frame, scene)  # before anything in the run folder is rewritten
        try:
            metrics = finish_run(tr, eval_frames=args.frame, mesh_resolution=args.resolution)
        except KeyboardInterrupt:  # say what state the run folder is in, not a bare "interrupted"
            raise KeyboardInterrupt(
                f"evaluation stopped before it finished; the checkpoint is untouched, and each of mesh.ply, renders/, "
                f"metrics.json and report.html in {args.run} is its earlier or its new version, never half-written "
                f"(the set may mix both: run eval again)") from None
    print(json_text(metrics, indent=1))
    return 0


def register(sub) -> None:
    p = sub.add_parser("mesh", help="extract the mesh of a run (marching cubes, world units)",
                       description="Extract the surface of a trained run with marching cubes, in world units, "
                                   "with vertex normals and the learned colours.")
    p.add_argument("run", help=RUN_HELP)
    p.add_argument("--resolution", type=int, default=None, help="marching-cubes grid (default: the run's export.mesh_resolution)")
    p.add_argument("--out", help="PLY, OBJ, GLB, STL or OFF path (default RUN/mesh.ply; vertex normals and colours where the "
                        "format holds them)")
    p.add_argument("--scene", help=SCENE_HELP)
    add_device_arg(p)
    p.set_defaults(func=_mesh)

    r = sub.add_parser("render", help="render frames: with pattern, texture only, depth, normals",
                       description="Render frames of the scene with a trained run: the image with the "
                                   "pattern, the pattern-free texture, depth and normals, as PNGs.")
    r.add_argument("run", help=RUN_HELP)
    r.add_argument("--frame", type=int, action="append", help="frame index (repeatable; default 0)")
    r.add_argument("--out", help="output folder (default RUN/renders)")
    r.add_argument("--scene", help=SCENE_HELP)
    add_device_arg(r)
    r.set_defaults(func=_render)

    e = sub.add_parser("eval", help="metrics (Chamfer, F-score, PSNR, depth, illumination) and report.html",
                       description="Evaluate a trained run again: mesh, renders, metrics.json (Chamfer, F-score, "
                                   "PSNR, depth and illumination errors against the scene's ground truth) "
                                   "and report.html.")
    e.add_argument("run", help=RUN_HELP)
    e.add_argument("--frame", type=int, action="append", help="frames to render for image metrics")
    e.add_argument("--resolution", type=int, default=None, help="mesh resolution (default: the run's)")
    e.add_argument("--scene", help=SCENE_HELP)
    add_device_arg(e)
    e.set_defaults(func=_eval)
