"""Verbs ``convert`` (between scene formats) and ``import-calib`` (procam calibration -> scene)."""
from __future__ import annotations

import math
import warnings
from pathlib import Path

from fastneus.errors import FastneusError
from fastneus.formats.detect import load_scene
from fastneus.formats.registry import formats, get_format, writable


def scene_help(lead: str = "scene folder") -> str:
    """Help text for a scene argument naming every registered scene format (the formats
    registry, :mod:`fastneus.formats.registry`): a format registered later shows up in
    ``--help`` without touching the CLI.

    Args:
        lead: what the argument is, e.g. ``"scene folder"``.
    Returns:
        One argparse help string (``%`` escaped).
    """
    kinds = "; ".join(f"{f.name}: {f.help}" for f in formats())
    return f"{lead} in any format fastneus reads, detected from its files ({kinds})".replace("%", "%%")


def _convert(args) -> int:
    from fastneus.io import check_out_dir

    check_out_dir(args.out)
    if args.downscale < 1:
        raise FastneusError(f"must be an integer >= 1, got {args.downscale}", field="--downscale")
    fmt = get_format(args.to)
    scene = load_scene(args.scene)
    small = [c for c in scene.cameras.values() if min(c.width, c.height) < args.downscale]
    if "downscale" in fmt.writer_options and small:
        c = small[0]
        raise FastneusError(f"{args.downscale} shrinks camera {c.id}'s {c.width}x{c.height} images to nothing "
                            f"(at most {min(c.width, c.height)})", field="--downscale")
    if Path(args.out).resolve() == Path(scene.root).resolve():
        raise FastneusError("output folder is the input folder; choose another --out", file=args.out, field="--out")
    # each writer builds aside and swaps in at the end (fastneus.io.staged_output): an unreadable image
    # found half-way leaves --out as it was, and files there that fastneus did not write are never touched
    fmt.write(scene, args.out, **{k: getattr(args, k) for k in fmt.writer_options})
    print(f"wrote {args.to} scene with {len(scene.frames)} frames -> {args.out}")
    return 0


def _list_images(folder: str, what: str) -> list[Path]:
    from fastneus.formats.activeneus import image_files

    p = Path(folder)
    if p.is_file():
        return [p]
    files = image_files(p)
    if not files:
        raise FastneusError("no images found", file=p, field=what)
    return files


def _import_calib(args) -> int:
    from fastneus.formats.opencv_calib import make_scene_from_calibration
    from fastneus.light.lasers import read_laser_planes

    if not args.patterns and not args.laser_planes:
        raise FastneusError("give --patterns (a pattern projector) and/or --laser-planes FILE", field="--patterns")

    from fastneus.io import check_out_dir

    check_out_dir(args.out)
    bounds = None
    if args.bounds:
        try:
            v = [float(x) for x in args.bounds.split(",")]
            assert len(v) == 4 and v[3] > 0
        except (ValueError, AssertionError):
            raise FastneusError(f"expected cx,cy,cz,radius with radius > 0, got {args.bounds!r}",
                                field="--bounds") from None
        bounds = (v[:3], v[3])
    if not (math.isfinite(args.colmap_scale) and args.colmap_scale > 0):  # nan passes "<= 0"
        raise FastneusError(f"must be a finite number > 0 (metres per COLMAP unit), got {args.colmap_scale}",
                            field="--colmap-scale")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scene = make_scene_from_calibration(
            args.calib if len(args.calib) > 1 else args.calib[0], _list_images(args.images, "--images"),
            _list_images(args.patterns, "--patterns") if args.patterns else [], args.poses or args.colmap, args.out,
            units=args.units, proj_size=args.proj_size, colmap_scale=args.colmap_scale, bounds=bounds,
            lasers=read_laser_planes(args.laser_planes, units=args.units) if args.laser_planes else None)
    for w in caught:
        print(f"warning: {w.message}")
    print(f"wrote fastneus scene with {len(scene.frames)} frames -> {Path(args.out) / 'scene.json'}")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("convert", help="convert a scene between formats (fastneus, ActiveNeuS, NeRF transforms.json; reads NeuS too)",
                              description="Read a scene of any supported format and write it as TO.")
    p.add_argument("scene", help=scene_help("scene folder to read,"))
    p.add_argument("--to", required=True, choices=writable(),
                   help=f"format to write: {', '.join(writable())} (the formats with a writer)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--downscale", type=int, default=1, help="activeneus target: shrink images by this factor")
    p.set_defaults(func=_convert)

    p = subparsers.add_parser("import-calib", help="make a scene from an OpenCV projector-camera calibration",
                              description="Build a fastneus scene from a procam calibration file (Moreno-Taubin, "
                                          "OpenCV stereo, procam-calibration layouts), photos, patterns and poses.")
    p.add_argument("calib", nargs="+", help="calibration YAML/XML (several files are merged)")
    p.add_argument("--images", required=True, help="folder of photos (sorted = frame order)")
    p.add_argument("--patterns", help="folder (one pattern per photo, or one for all) or a file")
    p.add_argument("--laser-planes", help="laser plane calibration (YAML/JSON, layout in docs/REAL-RIGS.md): laser "
                                          "line projectors lit in every photo")
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--poses", help="scene.json whose frames give cam_to_world in order")
    g.add_argument("--colmap", help="COLMAP model folder, text (cameras.txt, images.txt) or binary "
                   "(cameras.bin, images.bin), or a COLMAP project folder holding sparse/0")
    p.add_argument("--proj-size", help="projector WIDTHxHEIGHT when the file lacks it")
    p.add_argument("--units", default="mm", choices=("mm", "cm", "m"), help="units of the calibration's T")
    p.add_argument("--colmap-scale", type=float, default=1.0, help="metres per COLMAP unit (default 1)")
    p.add_argument("--bounds", help="cx,cy,cz,radius of the region of interest in metres")
    p.add_argument("--out", required=True, help="output scene folder")
    p.set_defaults(func=_import_calib)
