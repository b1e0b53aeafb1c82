"""Train fastneus on the official ActiveNeuS sample and evaluate novel views.

    python scripts/run_sample.py [--sample DIR] [--device cpu|cuda] [--preset cpu-quick|fewview]
                                 [--out DIR] [--illum both|fixed|learn] [--downscale N]
                                 [--views-eval N] [key=value ...]

Protocol (like the official default run): train on frames 0, 4, ..., 36 (10 of 40 views),
evaluate on the 30 others: PSNR of the render *with the pattern* against the photo, and
mask IoU (opacity > 0.5 vs mask > 0.5). Two illumination settings:

- ``fixed``: i_r, i_b from the file (0.4 / 0.1), not learned (``illum_init=scene``,
  ``learn_illum=false``);
- ``learn``: from the file's values, learned after the warm-up (``illum_init=scene``,
  ``learn_illum=true``), as the official code does (i_r = diffuse / a with a starting at 1);
- ``blind``: from i_r = i_b = 1, learned (``illum_init=ones``, ``learn_illum=true``).

Background: the sample's photos are exactly black outside the mask (checked at start and
reported), so ``background=0`` (our default) matches them. The official run also uses the
masks (BCE weight 1.0); fastneus uses them by default (``masks=auto``, ``mask_weight`` 0.1).
Writes ``results.json``, ``results.md``, ``grid.png`` + ``index.html``
(held-out photos next to renders) into ``--out`` and updates the section
``activeneus-sample-<device>`` of docs/benchmarks/activeneus-sample.md.
"""
from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchutil import ROOT, git_rev, machine, md_table, update_section, write_json  # noqa: E402

DEFAULT_SAMPLE = ROOT.parent / "shared" / "data" / "activeneus_sample"
TRAIN = list(range(0, 40, 4))
VARIANTS = {
    "fixed": ["illum_init=scene", "learn_illum=false"],
    "learn": ["illum_init=scene", "learn_illum=true"],
    "blind": ["illum_init=ones", "learn_illum=true"],
}


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR (dB) of two float images in [0, 1]."""
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return -10.0 * math.log10(max(mse, 1e-12))


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two boolean masks."""
    u = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / u) if u else 1.0


def background_level(scene, frames: list[int]) -> float:
    """Mean photo value (0..1) outside the masks: the colour to render behind the object."""
    vals = []
    for i in frames:
        m = scene.mask(i)
        if m is not None:
            vals.append(scene.image(i)[m < 0.01].astype(np.float64).mean() / 255.0)
    return float(np.mean(vals)) if vals else 0.0


def load_sample(sample: Path, downscale: int, cache: Path):
    """The sample as a Scene, optionally shrunk by ``downscale`` (a copy written via the writer)."""
    from fastneus.formats.activeneus import read_activeneus, write_activeneus

    scene = read_activeneus(sample)
    if downscale > 1:
        small = cache / f"activeneus_sample_ds{downscale}"
        if not (small / "cameras_sphere.npz").is_file():
            write_activeneus(scene, small, downscale=downscale)
        scene = read_activeneus(small)
    return scene


def evaluate(trainer, scene, frames: list[int]) -> tuple[dict, dict]:
    """Per-frame PSNR / IoU on ``frames`` and the renders (for the grid)."""
    from fastneus.eval.metrics import render_frames

    renders = render_frames(trainer, frames)
    per = {}
    for i in frames:
        r = renders[i]
        photo = r["photo"].astype(np.float64)
        photo = photo / 255.0 if photo.max() > 1.0 else photo
        m = scene.mask(i)
        per[i] = {"psnr": psnr(np.clip(r["color"], 0, 1), photo),
                  "iou": iou(r["opacity"] > 0.5, m > 0.5) if m is not None else float("nan")}
    return per, renders


def to_u8(x: np.ndarray) -> np.ndarray:
    x = x.astype(np.float64)
    if x.max() > 1.0:
        x = x / 255.0
    x = np.clip(x, 0, 1)
    if x.ndim == 2:
        x = np.repeat(x[..., None], 3, axis=2)
    return (x * 255 + 0.5).astype(np.uint8)


def grid_image(rows: list[list[np.ndarray]]) -> np.ndarray:
    """Tile equally sized RGB uint8 images into rows (2 px gaps)."""
    h, w = rows[0][0].shape[:2]
    ncol = max(len(r) for r in rows)
    out = np.full((len(rows) * (h + 2), ncol * (w + 2), 3), 255, np.uint8)
    for y, r in enumerate(rows):
        for x, im in enumerate(r):
            out[y * (h + 2):y * (h + 2) + h, x * (w + 2):x * (w + 2) + w] = im
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sample", type=Path, default=DEFAULT_SAMPLE)
    ap.add_argument("--device", default=None, help="cpu or cuda (default: cuda when available)")
    ap.add_argument("--preset", default=None, help="config preset (default: cpu-quick on CPU, fewview on CUDA)")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "activeneus_sample")
    ap.add_argument("--illum", choices=("all", "both", "fixed", "learn", "blind"), default="all",
                    help="which illumination variants to run (both = fixed and learn)")
    ap.add_argument("--downscale", type=int, default=1, help="shrink the images by this factor (fast CPU runs)")
    ap.add_argument("--views-eval", type=int, default=None, help="evaluate only N of the 30 held-out views")
    ap.add_argument("--grid-views", type=int, default=4, help="held-out views shown in grid.png")
    ap.add_argument("--no-bench-md", action="store_true", help="do not update docs/benchmarks/activeneus-sample.md")
    ap.add_argument("overrides", nargs="*", help="config key=value")
    args = ap.parse_args(argv)

    from rich.console import Console

    from fastneus.cli import resolve_device
    from fastneus.config import load_config
    from fastneus.io import atomic_write_image, atomic_write_text
    from fastneus.pipeline import train_scene

    console = Console()
    device = resolve_device(args.device)
    preset = args.preset or ("fewview" if device.startswith("cuda") else "cpu-quick")
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    scene = load_sample(args.sample, args.downscale, Path(tempfile.gettempdir()) / "fastneus_sample_cache")
    n = len(scene.frames)
    train = [i for i in TRAIN if i < n]
    held = [i for i in range(n) if i not in train]
    if args.views_eval is not None and args.views_eval < len(held):
        held = [held[int(k)] for k in np.linspace(0, len(held) - 1, max(args.views_eval, 1)).round()]
    bg = background_level(scene, train)
    console.print(f"sample: {n} frames {scene.frame_camera(0).width}x{scene.frame_camera(0).height}, "
                  f"train {train}, eval {len(held)} views; photo level outside the masks {bg:.4f} "
                  f"-> background={round(bg, 3)}")
    base = [f"background={round(bg, 3)}"]

    variants = {"all": list(VARIANTS), "both": ["fixed", "learn"]}.get(args.illum, [args.illum])
    results, renders_by = {}, {}
    for v in variants:
        cfg = load_config(preset, overrides=base + VARIANTS[v] + list(args.overrides))
        cfg = cfg.replace(frames=train)
        console.rule(f"{v}: preset {preset}, {cfg.run.steps} steps on {device}")
        t = time.perf_counter()
        trainer, _ = train_scene(scene, cfg, out / v, device, console=console, finish=False, overwrite=True)
        train_s = time.perf_counter() - t
        t = time.perf_counter()
        per, renders = evaluate(trainer, scene, held)
        eval_s = time.perf_counter() - t
        i_r, i_b = (float(x.detach().cpu().reshape(-1)[0]) for x in trainer.illumination())
        ps = [p["psnr"] for p in per.values()]
        ious = [p["iou"] for p in per.values()]
        results[v] = {"psnr_mean": float(np.mean(ps)), "psnr_median": float(np.median(ps)),
                      "iou_mean": float(np.nanmean(ious)), "i_r": i_r, "i_b": i_b,
                      "steps": int(trainer.step), "train_s": round(train_s, 1), "eval_s": round(eval_s, 1),
                      "per_frame": {str(i): p for i, p in per.items()}}
        renders_by[v] = renders
        console.print(f"{v}: PSNR {results[v]['psnr_mean']:.2f} dB, IoU {results[v]['iou_mean']:.3f}, "
                      f"i_r {i_r:.3f}, i_b {i_b:.3f} (train {train_s:.0f}s, eval {eval_s:.0f}s)")

    cam = scene.frame_camera(0)
    meta = {"device": device, "machine": machine(device), "git": git_rev(), "preset": preset,
            "overrides": base + list(args.overrides), "downscale": args.downscale,
            "image_size": [cam.width, cam.height], "train_frames": train, "eval_frames": held,
            "background": round(bg, 3)}
    write_json(out / "results.json", {"meta": meta, "results": results})

    rows = [{"illumination": v, "eval views": len(held), "PSNR (dB)": r["psnr_mean"], "mask IoU": r["iou_mean"],
             "i_r": r["i_r"], "i_b": r["i_b"], "steps": r["steps"], "train s": r["train_s"]}
            for v, r in results.items()]
    cols = ["illumination", "eval views", "PSNR (dB)", "mask IoU", "i_r", "i_b", "steps", "train s"]
    text = (f"### ActiveNeuS sample (hotdog, 10 train / {len(held)} held-out views), {device}\n\n"
            f"{meta['machine']}, git {meta['git']}, preset `{preset}`, images {cam.width}x{cam.height} "
            f"(downscale {args.downscale}), overrides `{' '.join(meta['overrides'])}`. "
            "PSNR: render with the pattern vs the photo on held-out views; IoU: opacity > 0.5 vs mask > 0.5. "
            "fixed = i_r, i_b from the file (0.4 / 0.1); learn = from the file's values, learned (as the "
            "official code); blind = from 1, learned. "
            "Command: `python scripts/run_sample.py " + " ".join(sys.argv[1:] if argv is None else argv) + "`\n\n"
            + md_table(rows, cols))
    atomic_write_text(out / "results.md", text + "\n")
    console.print(text)

    # grid: per held-out view, the photo then each variant's render with the pattern and its texture
    show = held[:: max(1, len(held) // max(1, args.grid_views))][: args.grid_views]
    grid_rows = []
    for i in show:
        row = [to_u8(renders_by[variants[0]][i]["photo"])]
        for v in variants:
            row += [to_u8(renders_by[v][i]["color"]), to_u8(renders_by[v][i]["texture"])]
        grid_rows.append(row)
    if grid_rows:
        atomic_write_image(out / "grid.png", grid_image(grid_rows))
        head = "photo | " + " | ".join(f"{v}: render, texture" for v in variants)
        html = (f"<html><body><h2>fastneus on the ActiveNeuS sample ({device})</h2>{text_to_html(rows, cols)}"
                f"<p>held-out views {show}, columns: {head}</p><img src='grid.png' style='max-width:100%'>"
                "</body></html>")
        atomic_write_text(out / "index.html", html)
    if not args.no_bench_md:
        update_section(ROOT / "docs" / "benchmarks" / "activeneus-sample.md", f"activeneus-sample-{device.split(':')[0]}", text)
    console.print(f"wrote {out / 'results.json'}, {out / 'results.md'}, {out / 'grid.png'}")
    return 0


def text_to_html(rows: list[dict], cols: list[str]) -> str:
    def f(v):
        return f"{v:.3f}" if isinstance(v, float) else str(v)
    head = "".join(f"<th>{c}</th>" for c in cols)
    body = "".join("<tr>" + "".join(f"<td>{f(r[c])}</td>" for c in cols) + "</tr>" for r in rows)
    return f"<table border=1 cellpadding=4><tr>{head}</tr>{body}</table>"


if __name__ == "__main__":
    from fastneus.errors import FastneusError

    try:
        sys.exit(main())
    except FastneusError as e:
        print(f"run_sample: error: {e}", file=sys.stderr)
        sys.exit(2)
