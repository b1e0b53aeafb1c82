"""Quality matrix: the default run on {shapes} x {Normal, Dark} x {captures} x {masks, no masks} x {budgets}.

    python scripts/quality.py [--device cuda|cpu] [--shapes bunny,rock,toy,bear] [--illums normal,dark]
                              [--captures ideal,realistic] [--masks on,off] [--budgets 5,10,20,60] [--size 200] [--views 20]
                              [--out DIR] [--tag NAME] [--report-from A.jsonl,B.jsonl] [--no-md]
                              [--variants "name:k=v k=v;name2:k=v"] [--seeds 0,1,2] [key=value ...]

Every cell is ``fastneus train SCENE time_budget=B`` with the device's default preset
(fewview on GPU, cpu-quick on CPU) and nothing else, except ``masks=off`` in the no-mask
column (the scene's masks are hidden from the run, as for a capture without masks). Extra
``key=value`` arguments apply to every cell, and ``--variants`` runs every cell once per named
set of overrides (both for tuning sweeps; the published matrix uses neither); ``--seeds`` runs every
cell once per training seed (``seed=S``; the scene stays the same) and the tables and checks use the
mean over the seeds (the full table lists each run). Scenes: the paper's rig (4 cross-laser projectors at +-0.2 / +-0.6 m), ``--views``
views of ``--size`` px, object ~2 m across at 4 m; shapes:

- ``bunny``: the Stanford bunny (a real range scan), ``bear``: warp-lang's bear asset
  (both converted once by ``scripts/assets.py`` into ``scripts/.assets``);
- ``rock``: a procedural scanned-stone-like surface (``fastneus synth --shape rock``);
- ``toy``: the built-in composite (cup, 2-cm fin, torus, sphere).

Captures: ``ideal`` (the linear image model, quantised) and ``realistic`` (``fastneus synth
--realistic``: sRGB, +-25% exposure, speckle, highlights, defocus, vignetting, noise, saturation);
``realistic:KEY=VALUE[:...]`` changes fields of that mix (``fastneus.synth.capture.Capture``:
``realistic:blur=0`` a sharp lens, ``realistic:speckle=0``, ``realistic:response=linear``, ...), to
find which effect costs what.

Metrics (mm; F-score at 1% of the GT bounding-box diagonal): Chamfer GT->rec (the paper's
number), the same with the paper's 1-sigma filter, rec->GT (floaters show here), symmetric,
F-score, |i_r - 0.4| and |i_b - 0.1| (learned from the file's values, the default), texture
PSNR (pattern-free render vs the GT pattern-free image). Results stream to
``OUT/quality-<tag>.jsonl`` (one line per cell; a re-run skips cells already there), then a
table goes to ``OUT/quality-<tag>.md`` and to the section ``quality-matrix-<device>`` of
docs/benchmarks/quality-matrix.md.
"""
from __future__ import annotations

import argparse
import itertools
import json
import time
from pathlib import Path

import fastneus  # noqa: F401 - before torch: it sets torch's OpenMP spin (GOMP_SPINCOUNT), read when torch loads
import torch

from benchutil import (ROOT, cached_scene, command_line, default_preset, md_table, median, provenance_line,
                       update_section, write_results)

ASSETS = Path(__file__).resolve().parent / ".assets"
BUILTIN = ("rock", "toy", "torus", "sphere", "ant", "airplane", "hexnut")  # fastneus synth --shape
METRICS = ["chamfer_gt2rec_mm", "chamfer_gt2rec_filtered_mm", "chamfer_rec2gt_mm", "chamfer_sym_mm", "fscore",
           "i_r_err", "i_b_err", "psnr_texture", "exposure_err"]
SHORT = {"chamfer_gt2rec_mm": "GT->rec", "chamfer_gt2rec_filtered_mm": "1-sigma", "chamfer_rec2gt_mm": "rec->GT",
         "chamfer_sym_mm": "sym", "fscore": "F", "i_r_err": "i_r err", "i_b_err": "i_b err",
         "psnr_texture": "tex PSNR", "exposure_err": "gain err"}


def parse_capture(capture: str) -> dict | None:
    """A ``--captures`` entry as synth's capture options: None for ``ideal``, ``{}`` for ``realistic``
    (synth --realistic), ``{"blur": 0.0, ...}`` for ``realistic:blur=0:...`` (the realistic mix with
    those :class:`fastneus.synth.capture.Capture` fields changed: one effect left out at a time)."""
    if capture == "ideal":
        return None
    head, *parts = capture.split(":")
    if head != "realistic":
        raise SystemExit(f"--captures: unknown capture {capture!r}; use ideal, realistic or realistic:KEY=VALUE[:...]")
    opts = {}
    for part in parts:
        key, eq, val = part.partition("=")
        if not eq or not key:
            raise SystemExit(f"--captures: {capture!r}: expected KEY=VALUE after 'realistic:', got {part!r}")
        opts[key] = val
    from fastneus.errors import FastneusError
    from fastneus.synth.capture import make_capture

    try:  # synth's own validation and conversion: unknown keys and bad values are one line, before any rendering
        cap = make_capture(opts, realistic=True)
    except FastneusError as e:
        raise SystemExit(f"--captures: {capture!r}: {e}") from None
    return {k: getattr(cap, k) for k in opts}


def parse_seeds(text: str | None) -> list[int | None]:
    """``--seeds`` as a list of ints; [None] (the config's seed, no override) when not given."""
    if not text:
        return [None]
    try:
        seeds = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise SystemExit(f"--seeds: expected integers separated by commas, got {text!r}") from None
    if not seeds or len(set(seeds)) != len(seeds):
        raise SystemExit(f"--seeds: expected distinct integers, got {text!r}")
    return seeds


def scene_dir(cache: Path, shape: str, illum: str, views: int, size: int, capture: str = "ideal") -> Path:
    tag = "" if capture == "ideal" else "-" + "".join(c if c.isalnum() or c in "-." else "-" for c in capture)
    return cache / f"{shape}-{illum}{views}-{size}{tag}"


def make_scene(cache: Path, shape: str, illum: str, views: int, size: int, device: str, assets: Path,
               capture: str = "ideal"):
    """Synthesise (once) and load a matrix scene."""
    opts = parse_capture(capture)
    d = scene_dir(cache, shape, illum, views, size, capture)
    src = dict(shape=shape) if shape in BUILTIN else dict(mesh=assets / f"{shape}.ply")
    if not (d / "scene.json").is_file() and "mesh" in src and not src["mesh"].is_file():
        raise SystemExit(f"{src['mesh']}: missing; run `python scripts/assets.py` once (needs usd-core)")
    return cached_scene(d, views=views, size=(size, size), illum=illum, pattern="crosslaser", seed=0, device=device,
                        contact_sheet=True, realistic=opts is not None, capture=opts or None, **src)


def run_cell(scene, device: str, budget: float, masks: str, extra: list[str], out: Path) -> dict:
    from fastneus.config import load_config
    from fastneus.pipeline import train_scene

    preset = default_preset(device)
    ov = [f"time_budget={budget}"] + (["masks=off"] if masks == "off" else []) + list(extra)
    cfg = load_config(preset, ov)
    t = time.perf_counter()
    trainer, m = train_scene(scene, cfg, out, device, overwrite=True)  # a re-run replaces its cell
    row = {k: m.get(k) for k in METRICS + ["steps", "train_seconds", "i_r", "i_b", "masks_used", "bg_prior_used"]}
    row["wall_s"] = round(time.perf_counter() - t, 1)
    return row


CELL_MARK = "QUALITY-CELL "  # the line a --cell child prints its row on


def run_one_cell(device: str, cell: dict) -> None:
    """The --cell child: load the (cached) scene, run the cell, print its row after :data:`CELL_MARK`."""
    from fastneus.data import Scene

    r = run_cell(Scene.load(Path(cell["scene"])), device, float(cell["budget"]), cell["masks"], list(cell["ov"]),
                 Path(cell["run"]))
    print(CELL_MARK + json.dumps(r), flush=True)


def run_cell_isolated(scene, device: str, budget: float, masks: str, extra: list[str], out: Path) -> dict | None:
    """:func:`run_cell` in a child process (a fresh CUDA context per cell). Returns its row, or None
    (the child's last lines printed) when it failed."""
    import subprocess
    import sys

    cell = {"scene": str(scene.root), "budget": budget, "masks": masks, "ov": extra, "run": str(out)}
    p = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--device", device, "--cell", json.dumps(cell)],
                       capture_output=True, text=True)
    rows = [line[len(CELL_MARK):] for line in p.stdout.splitlines() if line.startswith(CELL_MARK)]
    if p.returncode != 0 or not rows:
        tail = (p.stderr or p.stdout).strip().splitlines()[-3:]
        print(f"cell {out.name} failed (exit {p.returncode}): " + " | ".join(tail), flush=True)
        return None
    return json.loads(rows[-1])


def row_seed(row: dict) -> int | None:
    """The training seed of a row: its ``seed``, else a ``seed=S`` among its overrides (rows written
    before ``--seeds``), else None (the config's)."""
    if row.get("seed") is not None:
        return int(row["seed"])
    for ov in row.get("overrides") or []:
        key, _, val = str(ov).partition("=")
        if key.strip() == "seed" and val.strip().lstrip("-").isdigit():
            return int(val)
    return None


CELL_KEY = ("variant", "shape", "illum", "capture", "masks", "budget")  # a cell, whatever its seed


def mean_over_seeds(rows: list[dict]) -> list[dict]:
    """One row per cell (:data:`CELL_KEY`): each metric and ``steps`` averaged over the cell's seeds
    (None where no seed has it; a failed run's inf stays inf), ``seeds`` = how many runs."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault(tuple(r[k] for k in CELL_KEY), []).append(r)
    out = []
    for key, rs in groups.items():
        m = dict(zip(CELL_KEY, key), seeds=len(rs))
        for k in METRICS + ["steps"]:
            vals = [r[k] for r in rs if r.get(k) is not None]
            m[k] = sum(vals) / len(vals) if vals else None
        out.append(m)
    return out


def summarise(rows: list[dict], budgets: list[float]) -> tuple[str, dict]:
    """Markdown tables (one per metric group) and a dict of the target checks; with several seeds
    per cell the grid and the checks use the mean over them, the full table lists every run."""
    for r in rows:
        r.setdefault("variant", "default")
        r.setdefault("capture", "ideal")
        r.setdefault("seed", row_seed(r))

    def order(r: dict) -> tuple:
        return tuple(r[k] for k in CELL_KEY) + (-1 if r.get("seed") is None else r["seed"],)

    runs = sorted(rows, key=order)
    seeded = len({r["seed"] for r in runs}) > 1
    multi = len({r["variant"] for r in rows}) > 1
    lead = (["variant"] if multi else []) + ["shape", "illum"] + \
        (["capture"] if len({r["capture"] for r in rows}) > 1 else []) + ["masks"]
    full = md_table([{**r, **{SHORT.get(k, k): r.get(k) for k in METRICS}} for r in runs],
                    lead + ["budget"] + (["seed"] if seeded else []) + ["steps"] + [SHORT[k] for k in METRICS])
    rows = sorted(mean_over_seeds(runs), key=order)
    # symmetric Chamfer as a compact grid: one row per (shape, illum, masks), one column per budget
    grid_rows = {}
    for r in rows:
        key = (r["variant"], r["shape"], r["illum"], r["capture"], r["masks"])
        g = grid_rows.setdefault(key, {"variant": key[0], "shape": key[1], "illum": key[2], "capture": key[3],
                                       "masks": key[4]})
        g[f"{r['budget']:g} s"] = r.get("chamfer_sym_mm")
        g[f"F {r['budget']:g} s"] = r.get("fscore")
    bcols = [f"{b:g} s" for b in budgets] + [f"F {b:g} s" for b in budgets]
    grid = md_table(list(grid_rows.values()), lead + bcols)
    if seeded:
        grid = f"(mean over the seeds {', '.join(str(x) for x in sorted({r['seed'] for r in runs if r['seed'] is not None}))})\n\n" + grid
    checks = {}
    by = {(r["variant"], r["shape"], r["illum"], r["capture"], r["masks"], r["budget"]): r for r in rows}
    ratios_floater, ratios_nomask, ratios_real = [], [], []
    for (v, s, il, cp, mk, b), r in by.items():
        ideal = by.get((v, s, il, "ideal", mk, b))
        if cp.startswith("realistic") and ideal and ideal.get("chamfer_sym_mm") and r.get("chamfer_sym_mm"):
            ratios_real.append(r["chamfer_sym_mm"] / ideal["chamfer_sym_mm"])
        if mk == "off" and r.get("chamfer_gt2rec_mm"):
            ratios_floater.append(r["chamfer_rec2gt_mm"] / r["chamfer_gt2rec_mm"])
            on = by.get((v, s, il, cp, "on", b))
            if on and on.get("chamfer_sym_mm"):
                ratios_nomask.append(r["chamfer_sym_mm"] / on["chamfer_sym_mm"])
    if ratios_floater:
        checks["no-mask rec->GT / GT->rec (max, median)"] = (max(ratios_floater), median(ratios_floater))
    if ratios_nomask:
        checks["no-mask sym / masked sym (max, median)"] = (max(ratios_nomask), median(ratios_nomask))
    if ratios_real:
        checks["realistic sym / ideal sym (max, median)"] = (max(ratios_real), median(ratios_real))
    mono = []
    for key in {(r["variant"], r["shape"], r["illum"], r["capture"], r["masks"]) for r in rows}:
        seq = [by[key + (b,)]["chamfer_sym_mm"] for b in budgets if key + (b,) in by]
        mono.append(all(seq[i + 1] <= seq[i] * 1.0001 for i in range(len(seq) - 1)))
    checks["cells with sym Chamfer non-increasing over budgets"] = f"{sum(mono)}/{len(mono)}"
    return f"Symmetric Chamfer (mm) and F-score by budget:\n\n{grid}\nAll metrics:\n\n{full}", checks


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--shapes", default="bunny,rock,toy,bear")
    ap.add_argument("--illums", default="normal,dark")
    ap.add_argument("--masks", default="on,off")
    ap.add_argument("--captures", default="ideal",
                    help="ideal, realistic (synth --realistic), realistic:KEY=VALUE[:...] (the realistic mix with "
                         "synth capture options changed, e.g. realistic:blur=0 for a sharp lens); comma-separated")
    ap.add_argument("--budgets", default=None, help="seconds (default 5,10,20,60 on GPU, 30,60,120 on CPU)")
    ap.add_argument("--size", type=int, default=200)
    ap.add_argument("--views", type=int, default=20)
    ap.add_argument("--assets", default=str(ASSETS))
    ap.add_argument("--cache", default="/tmp/fastneus-quality-scenes")
    ap.add_argument("--out", default="/tmp/fastneus-quality")
    ap.add_argument("--tag", default=None, help="name of this matrix (default: the device kind)")
    ap.add_argument("--threads", type=int, default=None,
                    help="CPU threads for the kernels and torch (the config key threads; default: every CPU)")
    ap.add_argument("--report-from", default=None, help="only tabulate these JSONL files (comma-separated)")
    ap.add_argument("--no-md", action="store_true", help="do not update docs/benchmarks/quality-matrix.md")
    ap.add_argument("--variants", default=None, help='named override sets: "name:k=v k=v;name2:k=v"')
    ap.add_argument("--isolate", choices=("auto", "on", "off"), default="auto",
                    help="each cell in its own process (auto: on a GPU, so each cell's steps per second are its "
                         "own: a later cell in one process runs with warm caches; one process trains scene after "
                         "scene correctly since the geometry warm-up fix, docs/perf-notes/2026-11-26-geometry-warmup.md)")
    ap.add_argument("--seeds", default=None, help="training seeds, comma-separated: every cell once per seed "
                    "(seed=S; the tables use the mean over them)")
    ap.add_argument("--cell", default=None, help=argparse.SUPPRESS)  # internal: run one cell, print its row
    ap.add_argument("overrides", nargs="*", help="key=value applied to every cell (tuning only)")
    args = ap.parse_args()
    if args.cell:
        run_one_cell(args.device, json.loads(args.cell))
        return
    for cap in args.captures.split(","):  # a bad capture stops here, not after the cells before it ran
        parse_capture(cap)
    seeds = parse_seeds(args.seeds)

    gpu = args.device.startswith("cuda")
    isolate = args.isolate == "on" or (args.isolate == "auto" and gpu)
    kind = "cuda" if gpu else "cpu"
    tag = args.tag or kind
    budgets = [float(b) for b in (args.budgets or ("5,10,20,60" if gpu else "30,60,120")).split(",")]
    if args.threads:
        args.overrides = list(args.overrides) + [f"threads={args.threads}"]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    jsonl = out / f"quality-{tag}.jsonl"

    if args.report_from:
        rows = [json.loads(line) for f in args.report_from.split(",") for line in Path(f).read_text().splitlines()
                if line.strip()]
    else:
        variants = {"default": []}
        if args.variants:
            variants = {}
            for part in args.variants.split(";"):
                name, _, ov = part.partition(":")
                variants[name.strip()] = ov.split()
        done = set()
        if jsonl.is_file():
            for line in jsonl.read_text().splitlines():
                r = json.loads(line)
                done.add((r.get("variant", "default"), r["shape"], r["illum"], r.get("capture", "ideal"), r["masks"],
                          r["budget"], row_seed(r)))
        for shape in args.shapes.split(","):
            for illum in args.illums.split(","):
                for cap in args.captures.split(","):
                    scene = make_scene(Path(args.cache), shape, illum, args.views, args.size, args.device,
                                       Path(args.assets), cap)
                    for masks in args.masks.split(","):
                        for b in budgets:
                            for (vname, vov), seed in itertools.product(variants.items(), seeds):
                                ov = list(args.overrides) + vov + ([] if seed is None else [f"seed={seed}"])
                                seed = row_seed({"overrides": ov})  # also a seed=S among the overrides
                                if (vname, shape, illum, cap, masks, b, seed) in done:
                                    continue
                                cname = "" if cap == "ideal" else f"-{cap}"
                                sname = "" if seed is None else f"-s{seed}"
                                run = out / "runs" / f"{tag}-{vname}-{shape}-{illum}{cname}-m{masks}-{b:g}s{sname}"
                                if isolate:
                                    r = run_cell_isolated(scene, args.device, b, masks, ov, run)
                                    if r is None:
                                        continue
                                else:
                                    r = run_cell(scene, args.device, b, masks, ov, run)
                                r.update(variant=vname, shape=shape, illum=illum, capture=cap, masks=masks, budget=b,
                                         seed=seed, overrides=ov)
                                print(json.dumps(r), flush=True)
                                with open(jsonl, "a") as f:
                                    f.write(json.dumps(r) + "\n")
        if not jsonl.is_file():
            raise SystemExit(f"{jsonl}: no cell finished")
        rows = [json.loads(line) for line in jsonl.read_text().splitlines() if line.strip()]
    budgets_seen = sorted({r["budget"] for r in rows})
    text, checks = summarise(rows, budgets_seen)
    print(text)
    for k, v in checks.items():
        print(f"{k}: {v}")
    cmd = command_line("quality.py")
    write_results(out, f"quality-{tag}", {"rows": rows, "checks": {k: str(v) for k, v in checks.items()}}, text,
                  args.device, cmd)
    if not args.no_md:
        head = (f"### Quality matrix on {kind.upper()} ({tag})\n\n{provenance_line(args.device, cmd)} (scenes: {args.views} views "
                f"{args.size}x{args.size}, 4 cross-laser projectors, object ~2 m across; default preset, "
                f"`time_budget` per column; 'off' = masks hidden from the run). One run per cell.\n\n")
        chk = "".join(f"- {k}: {v}\n" for k, v in checks.items())
        update_section(ROOT / "docs" / "benchmarks" / "quality-matrix.md", f"quality-matrix-{tag}", head + text + "\n" + chk)


if __name__ == "__main__":
    main()
