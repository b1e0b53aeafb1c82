"""The README picture from a demo run: per frame, photo / with pattern / texture only / depth / normals.

    fastneus demo --device cpu && fastneus render fastneus-demo/run --frame 0 --frame 5
    python scripts/demo_figure.py fastneus-demo/run --frames 0,5 --out docs/demo.png
"""
from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

PANELS = [("photo", "photo (4 cross-laser projectors)"), ("color", "rendered with pattern"),
          ("texture", "texture only"), ("depth", "depth"), ("normal", "normals")]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run")
    ap.add_argument("--frames", default="0,5")
    ap.add_argument("--scale", type=int, default=1, help="integer upscaling of each panel")
    ap.add_argument("--out", default="docs/demo.png")
    args = ap.parse_args()
    rd = Path(args.run) / "renders"
    rows = []
    for i in [int(f) for f in args.frames.split(",")]:
        ims = []
        for key, _ in PANELS:
            f = rd / f"{i:03d}_{key}.png"
            im = cv2.imread(str(f), cv2.IMREAD_COLOR)
            if im is None:
                raise SystemExit(f"{f}: missing; run `fastneus render {args.run} --frame {i}` first")
            im = cv2.resize(im, None, fx=args.scale, fy=args.scale, interpolation=cv2.INTER_NEAREST)
            ims.append(np.pad(im, ((0, 4), (0, 4), (0, 0)), constant_values=255))
        rows.append(np.concatenate(ims, 1))
    w = rows[0].shape[1] // len(PANELS)
    head = np.full((22, rows[0].shape[1], 3), 255, np.uint8)
    for k, (_, label) in enumerate(PANELS):
        cv2.putText(head, label, (k * w + 4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(args.out), np.concatenate([head] + rows, 0))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
