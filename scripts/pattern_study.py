"""The paper's pattern study: Gray code, grid, colourful line (and cross lasers) at 1, 3, 10 viewpoints,
fastneus against the classical Gray-code decoder (issue 11, parts 4 and 5).

    python scripts/pattern_study.py [--device cuda|cpu] [--patterns graycode,grid,colorline,crosslaser]
                                    [--views 1,3,10] [--budget 10] [--size 400] [--shape toy]
                                    [--out DIR] [--no-md] [key=value ...]

Scenes (``fastneus synth``, synthesised once per pattern at 10 viewpoints; a run on V viewpoints
uses V of them spread over the orbit): the paper's pattern-study rig, one projector with a 0.6 m
baseline, Normal light, for ``graycode`` (20 shots per viewpoint), ``grid`` and ``colorline``
(one shot each); ``crosslaser`` is the project's default rig instead: 4 red/green cross-laser
projectors at +-0.2 / +-0.6 m in Dark light (only the laser curves constrain the surface).
Object ~2 m across at 4 m.

Methods: fastneus with the device's default preset (``oneshot`` on one viewpoint, with the CPU
one-shot priors on CPU as ``fastneus oneshot`` does; ``fewview`` / ``cpu-quick`` otherwise) for a
training budget of ``--budget`` seconds; for Gray code also the classical baseline (per-pixel
threshold decoding + ray/column-plane triangulation + epipolar row check, numpy), timed from
reading the photos to the depth maps.

Metric (``fastneus.eval.depth``): on every used viewpoint, the mesh ray-cast (fastneus) or the
decoded depth map (baseline) against the ground-truth depth of the visible surface: mean absolute
depth error (mm, % of depth) over pixels where both have a surface, the share of all GT pixels
within 1% of depth (holes count as misses) and the coverage; for one-shot frames also on the
pattern-lit pixels. Rows stream to ``OUT/pattern-study-<device>.jsonl`` (a re-run skips rows
already there, so the study can be run in parts with the same ``--out``); the table goes to
``.md``/``.json`` and a figure (per pattern: photo, depth, depth-error map; 0-1 % of depth on a
turbo ramp, magenta = missed surface) to ``OUT/pattern-study-<device>.png``; with docs updating
on, the section ``pattern-study-<device>`` of docs/benchmarks/pattern-study.md (figure beside it).
"""
from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import numpy as np
import fastneus  # noqa: F401 - before torch: it sets torch's OpenMP spin (GOMP_SPINCOUNT), read when torch loads
import torch

from benchutil import (ROOT, cached_scene, command_line, default_preset, md_table, provenance_line,
                       update_section, write_results)

N_SCENE_VIEWS = 10


def make_scene(cache: Path, pattern: str, size: int, shape: str, device: str):
    d = cache / f"{shape}-{pattern}-{N_SCENE_VIEWS}v-{size}"
    rig = dict(baselines=None, illum="dark") if pattern == "crosslaser" else dict(baselines=(0.6,), illum="normal")
    return cached_scene(d, shape=shape, views=N_SCENE_VIEWS, size=(size, size), pattern=pattern, seed=0,
                        device=device, contact_sheet=False, **rig)


def pick_views(n: int) -> list[int]:
    """``n`` of the scene's viewpoints, spread over the orbit (1 -> [0], 3 -> [0, 3, 7], 10 -> all)."""
    return sorted({int(round(k * N_SCENE_VIEWS / n)) % N_SCENE_VIEWS for k in range(n)})


def run_fastneus(scene, views: list[int], device: str, budget: float, extra: list[str], out: Path) -> tuple[dict, object]:
    from fastneus.config import load_config
    from fastneus.pipeline import train_scene
    from fastneus.cli.train import ONESHOT_CPU

    frames = [i for v in views for i in scene.views()[v]]
    gpu = device.startswith("cuda")
    base = {"frames": frames}
    if len(views) == 1:
        preset = "oneshot" if gpu else "cpu-quick"
        if not gpu:
            base.update(ONESHOT_CPU)
    else:
        preset = default_preset(device)
    cfg = load_config(preset, [f"time_budget={budget}"] + list(extra), base=base)
    t = time.perf_counter()
    trainer, m = train_scene(scene, cfg, out, device)
    m["wall_s"] = time.perf_counter() - t
    m["preset"] = preset
    return m, trainer


def rec_depth(run: Path, scene, frame: int, device: str, mesh=None) -> np.ndarray:
    """The run's mesh (read from ``run`` unless given) ray-cast from ``frame``'s camera."""
    import trimesh

    from fastneus.eval.depth import mesh_depth

    mesh = trimesh.load(run / "mesh.ply", force="mesh", process=False) if mesh is None else mesh
    cam = scene.frame_camera(frame)
    return mesh_depth(mesh.vertices, mesh.faces, cam.K, scene.cam_to_world(frame), cam.width, cam.height, device)


def figure(panels: list[tuple[str, list[tuple[str, np.ndarray]]]], tile: int = 220) -> np.ndarray:
    """Rows of labelled tiles: [(row label, [(tile label, uint8 [H, W, 3]), ...]), ...]."""
    import cv2

    ncol = max(len(t) for _, t in panels)
    rows = []
    for label, tiles in panels:
        cells = []
        for name, img in tiles + [("", np.zeros((tile, tile, 3), np.uint8))] * (ncol - len(tiles)):
            im = cv2.resize(np.ascontiguousarray(img), (tile, tile), interpolation=cv2.INTER_AREA)
            for text, y in ((f"{label}: {name}" if name and not cells else name, 16),):
                cv2.putText(im, text, (5, y), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 3, cv2.LINE_AA)
                cv2.putText(im, text, (5, y), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (255, 255, 255), 1, cv2.LINE_AA)
            cells += [im, np.full((tile, 3, 3), 80, np.uint8)]
        rows += [np.concatenate(cells[:-1], 1), np.full((3, ncol * (tile + 3) - 3, 3), 80, np.uint8)]
    return np.concatenate(rows[:-1], 0)


def common_pixels(run: Path, scene, depths: dict[int, np.ndarray], device: str) -> dict:
    """fastneus (mesh ray-cast) and decoder depth error on the same pixels: those where the GT, the
    decoder and the mesh all have a surface. The decoder leaves out what it cannot decode (shadows,
    silhouette pixels that mix foreground and background), and those are the pixels where any
    reconstruction is worst; the plain rows score each method on its own coverage."""
    import trimesh

    mesh = trimesh.load(run / "mesh.ply", force="mesh", process=False)
    err_f, err_b = [], []
    for i, b in depths.items():
        gt = scene.gt_depth(i)
        rec = rec_depth(run, scene, i, device, mesh)
        ok = (gt > 0) & np.isfinite(b) & np.isfinite(rec)
        err_f.append(np.abs(rec[ok] - gt[ok]) / gt[ok])
        err_b.append(np.abs(b[ok] - gt[ok]) / gt[ok])
    ef, eb = np.concatenate(err_f), np.concatenate(err_b)
    return {"pixels": int(ef.size), "fastneus_pct": 100 * float(ef.mean()), "decoder_pct": 100 * float(eb.mean()),
            "fastneus_median_pct": 100 * float(np.median(ef)), "decoder_median_pct": 100 * float(np.median(eb))}


KEYS = ["depth_err_mm", "depth_err_pct", "depth_within_1pct", "depth_coverage", "depth_lit_err_pct",
        "depth_lit_within_1pct", "depth_unlit_err_pct", "visible_gt2rec_mm", "chamfer_gt2rec_mm"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--patterns", default="graycode,grid,colorline,crosslaser")
    ap.add_argument("--views", default="1,3,10")
    ap.add_argument("--budget", type=float, default=None, help="training seconds (default 10 on GPU, 60 on CPU)")
    ap.add_argument("--size", type=int, default=400)
    ap.add_argument("--shape", default="toy")
    ap.add_argument("--out", default="/tmp/fastneus-pattern-study")
    ap.add_argument("--no-md", action="store_true", help="do not update docs/benchmarks/pattern-study.md and its figure")
    ap.add_argument("overrides", nargs="*", help="key=value for every fastneus run (tuning only)")
    args = ap.parse_args()

    gpu = args.device.startswith("cuda")
    kind = "cuda" if gpu else "cpu"
    budget = args.budget if args.budget is not None else (10.0 if gpu else 60.0)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    jsonl = out / f"pattern-study-{kind}.jsonl"
    done = set()
    if jsonl.is_file():
        for line in jsonl.read_text().splitlines():
            r = json.loads(line)
            done.add((r["pattern"], r["views"], r["method"]))
    from fastneus.classical.graycode import graycode_baseline
    from fastneus.eval.depth import baseline_depth_metrics
    from fastneus.eval.depth import depth_image, error_map

    for pattern in args.patterns.split(","):
        scene = make_scene(out / "scenes", pattern, args.size, args.shape, args.device)
        for nv in (int(v) for v in args.views.split(",")):
            views = pick_views(nv)
            frames = [i for v in views for i in scene.views()[v]]
            first = frames[0]
            run = out / "runs" / f"{kind}-{pattern}-{nv}v"
            tiles = []
            if (pattern, nv, "fastneus") not in done:
                m, _ = run_fastneus(scene, views, args.device, budget, args.overrides, run)
                row = {"pattern": pattern, "views": nv, "method": "fastneus", "preset": m["preset"],
                       "time_s": m["train_seconds"], "steps": m["steps"], **{k: m.get(k) for k in KEYS}}
                with open(jsonl, "a") as f:
                    f.write(json.dumps(row) + "\n")
                print(json.dumps(row), flush=True)
            if pattern == "graycode" and (pattern, nv, "baseline") not in done:
                depths, sec = graycode_baseline(scene, frames)
                m = baseline_depth_metrics(scene, depths)
                row = {"pattern": pattern, "views": nv, "method": "Gray-code decode + triangulation",
                       "time_s": sec, **{k: m.get(k) for k in KEYS}}
                with open(jsonl, "a") as f:
                    f.write(json.dumps(row) + "\n")
                print(json.dumps(row), flush=True)
                np.save(out / "runs" / f"{kind}-{pattern}-{nv}v-baseline-depth.npy", depths[first])
                if (run / "mesh.ply").is_file():
                    row = {"pattern": pattern, "views": nv, "method": "common", **common_pixels(run, scene, depths, args.device)}
                    with open(jsonl, "a") as f:
                        f.write(json.dumps(row) + "\n")
            # figure tiles for this cell (from what is on disk, so a resumed study still draws it)
            if nv == 1 and (run / "mesh.ply").is_file():
                gt = scene.gt_depth(first)
                lo, hi = np.percentile(gt[gt > 0], [1, 99])
                photo = scene.image(frames[min(len(frames) - 1, 4)])  # a mid-sequence Gray-code plane
                rec = rec_depth(run, scene, first, args.device)
                tiles = [("photo", photo), ("GT depth", depth_image(gt, lo, hi)),
                         ("fastneus depth", depth_image(rec, lo, hi)), ("fastneus error", error_map(rec, gt))]
                bp = out / "runs" / f"{kind}-{pattern}-{nv}v-baseline-depth.npy"
                if bp.is_file():
                    b = np.load(bp)
                    tiles += [("decoder depth", depth_image(b, lo, hi)), ("decoder error", error_map(b, gt))]
                np.save(out / "runs" / f"{kind}-{pattern}-tiles.npy", np.stack([t for _, t in tiles]))
                (out / "runs" / f"{kind}-{pattern}-tiles.json").write_text(json.dumps([n for n, _ in tiles]))

    rows = [json.loads(line) for line in jsonl.read_text().splitlines() if line.strip()]
    order = {p: k for k, p in enumerate(["graycode", "grid", "colorline", "crosslaser"])}
    rows.sort(key=lambda r: (order.get(r["pattern"], 9), r["views"], r["method"] != "fastneus"))
    cols = ["pattern", "views", "method", "time_s", "depth_err_mm", "depth_err_pct", "depth_within_1pct",
            "depth_coverage", "depth_lit_err_pct", "depth_unlit_err_pct", "visible_gt2rec_mm"]
    common = {r["views"]: r for r in rows if r["method"] == "common"}
    rows = [r for r in rows if r["method"] != "common"]
    table = md_table([{k: v for k, v in r.items() if v is not None} for r in rows], cols)
    # side by side: fastneus vs the decoder on Gray code at equal views
    cmp_rows = []
    for nv in sorted({r["views"] for r in rows if r["pattern"] == "graycode"}):
        f = next((r for r in rows if r["pattern"] == "graycode" and r["views"] == nv and r["method"] == "fastneus"), None)
        b = next((r for r in rows if r["pattern"] == "graycode" and r["views"] == nv and r["method"] != "fastneus"), None)
        if f and b:
            c = common.get(nv)
            # judged on the same pixels when known (mean % of depth there), else on each one's own coverage
            better = (c["fastneus_pct"] < c["decoder_pct"]) if c else f["depth_err_pct"] < b["depth_err_pct"]
            same = (f"{c['fastneus_pct']:.3g} / {c['decoder_pct']:.3g} ({c['pixels']} px)" if c else "")
            cmp_rows.append({"views": nv, "fastneus % / within 1%": f"{f['depth_err_pct']:.3g} / {f['depth_within_1pct']:.3g}",
                             "decoder % / within 1%": f"{b['depth_err_pct']:.3g} / {b['depth_within_1pct']:.3g}",
                             "same pixels: fastneus % / decoder %": same,
                             "fastneus s": f"{f['time_s']:.3g}", "decoder s": f"{b['time_s']:.3g}",
                             "more accurate": "fastneus" if better else "decoder"})
    cmp = md_table(cmp_rows, ["views", "fastneus % / within 1%", "decoder % / within 1%",
                              "same pixels: fastneus % / decoder %", "fastneus s", "decoder s",
                              "more accurate"]) if cmp_rows else ""
    print(table)
    print(cmp)
    panels = []
    for p in sorted(order, key=order.get):
        tp = out / "runs" / f"{kind}-{p}-tiles.npy"
        if tp.is_file():
            names = json.loads((out / "runs" / f"{kind}-{p}-tiles.json").read_text())
            panels.append((p, list(zip(names, np.load(tp)))))
    fig_path = None
    if panels:
        from fastneus.light.patterns import write_png

        fig_path = out / f"pattern-study-{kind}.png"
        write_png(fig_path, figure(panels))
    cmd = command_line("pattern_study.py")
    head = (f"### Pattern study ({kind.upper()}): {args.shape}, {args.size}x{args.size}, {budget:g} s of training\n\n"
            f"{provenance_line(args.device, cmd)} One projector "
            "at 0.6 m, Normal light (crosslaser: 4 projectors, Dark); 1, 3, 10 viewpoints of one orbit; depth error "
            "of the visible surface on every used viewpoint (mesh ray-cast vs GT depth; % of depth; within 1% counts "
            "holes as misses; lit/unlit = pattern-lit pixels of one-shot frames). time_s: training seconds "
            "(fastneus) or decoding + triangulation seconds (decoder). One run per row.\n\n")
    text = head + table + (("\nGray code, fastneus against the decoder at equal viewpoints (same pixels: mean error where the "
                          "GT, the decoder and the mesh all have a surface; 'more accurate' is judged there):\n\n") + cmp if cmp else "")
    write_results(out, f"pattern-study-{kind}", {"budget": budget, "size": args.size, "shape": args.shape,
                                                 "rows": rows}, text, args.device, cmd)
    if not args.no_md:
        if fig_path is not None:
            dst = ROOT / "docs" / "benchmarks" / fig_path.name
            shutil.copyfile(fig_path, dst)
            text += (f"\n![pattern study, one viewpoint: photo, GT depth, fastneus depth and error, decoder depth "
                     f"and error]({fig_path.name})\n")
        update_section(ROOT / "docs" / "benchmarks" / "pattern-study.md", f"pattern-study-{kind}", text)


if __name__ == "__main__":
    main()
