"""Verb ``synth``: render a synthetic structured-light scene with ground truth."""
from __future__ import annotations

import math
from pathlib import Path

from fastneus.cli import add_device_arg, resolve_device
from fastneus.errors import FastneusError
from fastneus.light.patterns import parse_size, pattern_kinds
from fastneus.synth.albedo import ALBEDOS
from fastneus.synth.render import ILLUMS, synthesize
from fastneus.synth.shapes import SHAPES


def register(subparsers) -> None:
    p = subparsers.add_parser("synth", help="render a synthetic structured-light scene",
                              description="Render a mesh lit by projectors on a camera rig (the ActiveNeuS "
                                          "protocol) into a fastneus scene folder with ground truth.")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--mesh", help="mesh file (PLY/OBJ/STL/GLB...)")
    src.add_argument("--shape", choices=SHAPES, help="built-in shape")
    p.add_argument("--views", type=int, default=20, help="viewpoints (default 20; 1 = one-shot)")
    p.add_argument("--size", default="800x800", help="image size WxH (default 800x800)")
    p.add_argument("--pattern", default="crosslaser", choices=pattern_kinds(), help="pattern kind (default crosslaser)")
    p.add_argument("--illum", default="normal", choices=list(ILLUMS), help="normal (ambient 1) or dark (0.1)")
    p.add_argument("--ambient", type=float, default=None, help="override the ambient level")
    p.add_argument("--albedo", default="procedural", choices=ALBEDOS,
                   help=f"surface colour: {', '.join(ALBEDOS)} (default procedural)")
    p.add_argument("--noise", type=float, default=0.005, help="Gaussian noise sigma (default 0.005)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the poses, patterns, albedo and noise (default 0)")
    p.add_argument("--proj-size", default="1024x768", help="projector size WxH (default 1024x768)")
    p.add_argument("--baselines", default=None,
                   help="projector x offsets on the rig in metres, comma-separated (default: -0.6,-0.2,0.2,0.6 "
                        "for one-shot patterns, 0.6 for sequences); '0.6' = the paper's one-projector pattern study")
    p.add_argument("--medium", default="air", choices=("air", "water"),
                   help="water: cameras and projectors behind flat ports, attenuation and back-scatter")
    p.add_argument("--laser-planes", action="store_true",
                   help="projectors are laser line projectors defined by light planes (the crosslaser lines)")
    p.add_argument("--projector-blur", type=float, default=0.0, metavar="SIGMA",
                   help="projector defocus: Gaussian sigma in projector pixels, 5x5 taps (default 0 = sharp)")
    g = p.add_argument_group("realistic capture (applied to the linear render; ground truth stays linear)")
    g.add_argument("--realistic", action="store_true",
                   help="a real camera's mix: sRGB, +-25%% exposure, speckle, highlights, 0.7 px defocus, "
                        "vignetting, read + shot noise, saturation (the options below override its parts)")
    g.add_argument("--response", default=None, help="camera response of the photos: linear | srgb | gamma=G")
    for name, what in (("exposure", "per-frame auto-exposure spread (0.25 = gains 0.8..1.25)"),
                       ("speckle", "speckle contrast of the projected light (std/mean)"),
                       ("specular", "Blinn-Phong highlight strength"), ("shininess", "Blinn-Phong exponent"),
                       ("defocus", "camera defocus, Gaussian sigma in pixels"),
                       ("supersample", "with defocus: rays per pixel side, the pixel's area averaged (default 4)"),
                       ("vignetting", "relative fall-off at the image corner"),
                       ("read-noise", "read-noise sigma (linear units)"),
                       ("shot-noise", "shot-noise variance per unit signal"),
                       ("interreflection", "one diffuse bounce between surfaces, its strength (1 = physical; "
                                           "not in --realistic)"),
                       ("white-balance", "per-photo auto white balance: each colour channel's gain spread "
                                         "(0.1 = 0.91..1.1; not in --realistic)")):
        g.add_argument(f"--{name}", type=float, default=None, help=what)
    g.add_argument("--bits", type=int, default=None, choices=(8, 16),
                   help="bits per channel of the photos (16: a machine-vision camera's PNGs; default 8)")
    g.add_argument("--mono", action="store_true",
                   help="a monochrome camera: grey photos, each pixel the mean of the light's channels")
    p.add_argument("--no-contact-sheet", action="store_true",
                   help="do not write contact_sheet.png (all views in one image)")
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads while rendering (default 1)")
    add_device_arg(p)
    p.add_argument("--out", required=True, help="output folder")
    p.set_defaults(func=_run)


def parse_baselines(text: str | None) -> tuple[float, ...] | None:
    """``"-0.6,0.6"`` -> (-0.6, 0.6) metres; None stays None (the pattern's default rig)."""
    if text is None:
        return None
    try:
        vals = tuple(float(v) for v in str(text).split(",") if v.strip())
    except ValueError:
        raise FastneusError(f"expected comma-separated metres such as 0.6 or -0.2,0.2, got {text!r}",
                            field="--baselines") from None
    if not vals or len(vals) > 8 or not all(math.isfinite(v) and v != 0 for v in vals):
        raise FastneusError("give 1 to 8 non-zero finite offsets (a projector on the camera centre "
                            "cannot triangulate)", field="--baselines")
    return vals


def capture_options(args) -> dict:
    """The capture options given on the command line (``fastneus.synth.capture.Capture`` fields)."""
    opts = {"response": args.response, "exposure": args.exposure, "speckle": args.speckle,
            "specular": args.specular, "shininess": args.shininess, "blur": args.defocus,
            "supersample": args.supersample, "vignetting": args.vignetting, "read_noise": args.read_noise, "shot_noise": args.shot_noise,
            "interreflection": args.interreflection, "bits": args.bits, "white_balance": args.white_balance,
            "mono": 1 if getattr(args, "mono", False) else None}
    return {k: v for k, v in opts.items() if v is not None}


def _run(args) -> int:
    device = resolve_device(args.device)
    size = parse_size(args.size)
    psize = parse_size(args.proj_size, field="--proj-size")
    if args.mesh is not None and not Path(args.mesh).is_file():
        raise FastneusError("mesh file not found", file=args.mesh, field="--mesh")
    synthesize(args.out, shape=args.shape, mesh=args.mesh, views=args.views, size=size, pattern=args.pattern,
               illum=args.illum, albedo=args.albedo, noise=args.noise, seed=args.seed, device=device,
               ambient=args.ambient, proj_size=psize, contact_sheet=not args.no_contact_sheet,
               threads=args.threads, baselines=parse_baselines(args.baselines), projector_blur=args.projector_blur,
               laser_planes=args.laser_planes, medium=args.medium, realistic=args.realistic,
               capture=capture_options(args))
    return 0
