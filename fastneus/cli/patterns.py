"""Verb ``patterns``: write projector pattern PNGs."""
from __future__ import annotations

from fastneus.io import make_out_dir
from fastneus.light.patterns import make_pattern, parse_size, pattern_kinds, write_png


def register(subparsers) -> None:
    p = subparsers.add_parser("patterns", help="write projector pattern PNGs",
                              description="Generate projector patterns (" + ", ".join(pattern_kinds()) + ") as PNG files.")
    p.add_argument("--kind", required=True, choices=pattern_kinds(),
                   help=f"pattern kind: {', '.join(pattern_kinds())}")
    p.add_argument("--size", default="1024x768", help="projector resolution WxH (default 1024x768)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--seed", type=int, default=0, help="random seed of random patterns, e.g. dots (default 0)")
    p.add_argument("--count", type=int, default=None,
                   help="lines per axis (crosslaser, grid), dots (dots) or steps (phaseshift)")
    p.add_argument("--line-width", type=int, default=None, help="line / stripe / dot width in pixels")
    p.add_argument("--inverse", action="store_true", help="graycode: add inverse patterns")
    p.set_defaults(func=_run)


def _run(args) -> int:
    w, h = parse_size(args.size)
    ims = make_pattern(args.kind, w, h, seed=args.seed, count=args.count, line_width=args.line_width,
                       inverse=args.inverse or None)
    out = make_out_dir(args.out)
    for k, im in enumerate(ims):
        write_png(out / f"{args.kind}_{k:02d}.png", im)
    print(f"wrote {len(ims)} {args.kind} pattern{'s' if len(ims) != 1 else ''} "
          f"({w}x{h}) to {out}/{args.kind}_NN.png")
    return 0
