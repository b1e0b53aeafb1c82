"""report.html of a run: the mesh in 3D, headline metrics, per-view images, charts, timing, config.

One self-contained file that works offline: the 3D viewer (vendored ``<model-viewer>``, see
``fastneus/eval/viewer.py``) and the mesh (a decimated GLB) are inlined, images and charts are
data URIs; it also links the full-size files of the run folder (mesh.ply, renders/*.png).
Written after mesh.ply; matplotlib and OpenCV are imported inside the functions.
"""
from __future__ import annotations

import html
import json
import math
from pathlib import Path

from fastneus.io import atomic_write_image, atomic_write_text

# (metric key, plain name, unit) of the headline table, in order; absent keys are left out
HEADLINE = [
    ("chamfer_gt2rec_mm", "Chamfer distance, ground truth → reconstruction (mean)", "mm"),
    ("chamfer_gt2rec_filtered_mm", "the same with the 1-σ outlier filter (the paper's value)", "mm"),
    ("chamfer_rec2gt_mm", "Chamfer distance, reconstruction → ground truth (mean)", "mm"),
    ("chamfer_sym_mm", "symmetric Chamfer distance (mean of both directions)", "mm"),
    ("fscore", "F-score", "%"),
    ("visible_gt2rec_mm", "Chamfer on the ground truth seen by the training cameras", "mm"),
    ("depth_err_mm", "depth error of the mesh on the training views", "mm"),
    ("depth_mae_mm", "depth error of the renders on the report's frames", "mm"),
    ("psnr_pattern", "PSNR, render with pattern vs photo", "dB"),
    ("psnr_texture", "PSNR, pattern-free render vs ground-truth pattern-free image", "dB"),
    ("mask_iou", "silhouette IoU vs the masks", "%"),
    ("i_r", "i_r, projector (pattern) light: learned", ""),
    ("i_b", "i_b, ambient light: learned", ""),
]
_CHART_TRUTH = ("i_r", "i_b")


def read_log(path: Path) -> list[dict]:
    """The records of a run's ``log.jsonl`` that are whole; a line cut short (kill -9 or a full
    disk mid-append) or not a training record is dropped with a one-line warning."""
    import sys

    keys = ("step", "loss", "psnr", "i_r", "i_b")
    log, bad = [], 0
    if not path.is_file():
        return log
    for line in path.read_text(errors="replace").splitlines():
        if not line.strip():
            continue
        try:
            r = json.loads(line)
        except (ValueError, RecursionError):
            r = None
        if isinstance(r, dict) and all(isinstance(r.get(k), (int, float)) for k in keys):
            log.append(r)
        else:
            bad += 1
    if bad:
        print(f"warning: {path}: dropped {bad} unreadable line{'s' * (bad > 1)} (a write cut short, e.g. by "
              "kill -9 or a full disk)", file=sys.stderr)
    return log


def _fmt(v, unit: str = "") -> str:
    """A metric value for people: 3-4 significant digits, % for fractions, — for none/inf."""
    if isinstance(v, bool) or v is None:
        return "—" if v is None else ("yes" if v else "no")
    if isinstance(v, int):
        return f"{v:,}"
    if isinstance(v, float):
        if not math.isfinite(v):
            return "—"
        if unit == "%":
            return f"{100 * v:.1f} %"
        return f"{v:.4g}" + (f" {unit}" if unit else "")
    return str(v)


def _unit_of(key: str) -> str:
    """The unit of a metrics.json key, from its name (for the full table)."""
    k = key.lower()
    for suffix, unit in (("_mm", "mm"), ("_pct", "% of depth"), ("_mb", "MiB"), ("_seconds", "s"), ("_s", "s")):
        if k.endswith(suffix):
            return unit
    if k.startswith("psnr"):
        return "dB"
    return ""


def headline_rows(metrics: dict) -> list[tuple[str, str, str]]:
    """(plain name, value with unit, note) of the headline metrics present in ``metrics``."""
    m = metrics
    rows = []
    for key, name, unit in HEADLINE:
        v = m.get(key)
        if not isinstance(v, (int, float)) or isinstance(v, bool):
            continue
        note = ""
        if key == "fscore" and "fscore_tau_mm" in m:
            name = f"F-score at τ = {_fmt(m['fscore_tau_mm'])} mm (1% of the ground truth's box diagonal)"
            if "precision" in m and "recall" in m:
                note = f"precision {_fmt(m['precision'], '%')}, recall {_fmt(m['recall'], '%')}"
        elif key == "depth_err_mm":
            parts = [f"{_fmt(m[k])} % of depth" for k in ("depth_err_pct",) if k in m]
            parts += [f"median {_fmt(m['depth_median_pct'])} %"] if "depth_median_pct" in m else []
            parts += [f"{_fmt(m['depth_within_1pct'], '%')} of pixels within 1 %"] if "depth_within_1pct" in m else []
            parts += [f"coverage {_fmt(m['depth_coverage'], '%')}"] if "depth_coverage" in m else []
            parts += [f"{m['depth_views']} views"] if "depth_views" in m else []
            note = ", ".join(parts)
        elif key == "chamfer_gt2rec_mm":
            note = "the paper's headline metric"
        elif key in ("i_r", "i_b"):
            if f"{key}_gt" in m:
                name = name.replace("learned", "learned vs truth")
                note = f"truth {_fmt(m[key + '_gt'])}, error {_fmt(m.get(key + '_err'))}"
        elif key == "depth_mae_mm":
            note = "volume-rendered depth where opacity > 0.5"
        rows.append((name, _fmt(v, unit), note))
    if "mesh_vertices" in m:
        rows.append(("mesh (mesh.ply)", f"{_fmt(m['mesh_vertices'])} vertices, {_fmt(m.get('mesh_faces'))} faces", ""))
    if "steps" in m:
        extra = f" in {_fmt(float(m['train_seconds']))} s" if isinstance(m.get("train_seconds"), (int, float)) else ""
        rows.append(("training", f"{_fmt(m['steps'])} steps{extra}",
                     f"{m['train_frames']} frames" if "train_frames" in m else ""))
    return rows


def _table(rows, head=None, cls: str = "") -> str:
    th = "".join(f"<th>{html.escape(h)}</th>" for h in head) if head else ""
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in r) + "</tr>" for r in rows)
    return f'<table class="{cls}">' + (f"<thead><tr>{th}</tr></thead>" if th else "") + f"<tbody>{body}</tbody></table>"


def _flat_metrics(metrics: dict) -> list[tuple[str, str, str]]:
    out = []
    for k, v in metrics.items():
        if isinstance(v, dict) or isinstance(v, list):
            continue
        out.append((k, _fmt(v) if not isinstance(v, float) else (f"{v:.6g}" if math.isfinite(v) else "—"),
                    _unit_of(k)))
    return out


def timing_html(tm: dict) -> str:
    """The wall-clock table: seconds per phase in run order, bars to scale, then the marks."""
    from fastneus.timing import PHASE_ORDER

    if not tm:
        return ""
    total = tm.get("total") if isinstance(tm.get("total"), (int, float)) else None
    num = {k: v for k, v in tm.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
    phases = [k for k in PHASE_ORDER if k in num and k != "total"]
    phases += [k for k in num if k not in phases and k != "total" and not k.endswith("_at")]
    rows = []
    for k in phases:
        w = 100 * num[k] / total if total else 0
        rows.append(f'<tr><td>{html.escape(k)}</td><td class="num">{num[k]:.2f} s</td>'
                    f'<td><div class="tbar" style="width:{max(0.0, min(100.0, w)):.1f}%"></div></td></tr>')
    if "report" not in num:
        rows.append('<tr><td>report</td><td class="num">…</td><td>this page (being written when the clock was read)</td></tr>')
    if total is not None:
        rows.append(f'<tr class="total"><td>total</td><td class="num">{total:.2f} s</td><td></td></tr>')
    marks = "".join(f'<tr><td>{html.escape(k)}</td><td class="num">{num[k]:.2f} s</td><td>'
                    f'{"mesh.ply written" if k == "mesh_ready_at" else html.escape(k[:-3])}, seconds from '
                    f'{html.escape(str(tm.get("origin", "start")))}</td></tr>' for k in num if k.endswith("_at"))
    return (f"<h2>Wall clock (seconds from {html.escape(str(tm.get('origin', 'start')))})</h2>"
            f'<table class="timing"><tbody>{"".join(rows)}{marks}</tbody></table>')


def decisions_html(run: Path) -> str:
    """What the run decided from the data: the lines it printed and saved in run.json (masks, the
    background prior, the photos' response, the camera blur, the per-photo exposure)."""
    import json

    try:
        info = json.loads((Path(run) / "run.json").read_text())
    except (OSError, ValueError):
        return ""
    if not isinstance(info, dict):
        return ""
    keys = (("masks", "masks"), ("background_prior", "background prior"), ("response", "photo response"),
            ("camera_blur_note", "camera blur"), ("exposure_note", "exposure"))
    rows = [(name, info[key]) for key, name in keys if isinstance(info.get(key), str)]
    if not rows:
        return ""
    body = "".join(f"<tr><td>{html.escape(k)}</td><td>{html.escape(v)}</td></tr>" for k, v in rows)
    return f'<h2 id="decisions">Decisions from the data</h2><table class="decisions"><tr><th>what</th><th>decided</th></tr>{body}</table>'


def config_html(config: dict) -> str:
    """The resolved config with the values that differ from its preset (else the defaults) marked."""
    from fastneus.config import Config, load_config, preset_names

    preset = str((config.get("run") or {}).get("preset", ""))
    try:
        ref, label = ((load_config(preset).to_dict(), f"preset {preset}") if preset in preset_names()
                      else (Config().to_dict(), "the defaults"))
    except Exception:  # noqa: BLE001 - a preset that no longer loads: compare with the defaults
        ref, label = Config().to_dict(), "the defaults"

    def show(v) -> str:
        return json.dumps(v) if not isinstance(v, str) else v

    changed, rows = [], []
    for sec, values in config.items():
        if not isinstance(values, dict):
            continue
        rows.append(f'<tr class="section"><td colspan="3">{html.escape(sec)}</td></tr>')
        for k, v in values.items():
            key = f"{sec}.{k}"
            base = (ref.get(sec) or {}).get(k, None)
            diff = k != "preset" and base != v
            cell = f"{label.split(' ')[0]}: {show(base)}" if diff else ""
            tr = (f'<tr class="{"changed" if diff else "same"}" data-key="{html.escape(key)}"><td>{html.escape(key)}'
                  f'</td><td>{html.escape(show(v))}</td><td>{html.escape(cell)}</td></tr>')
            rows.append(tr)
            if diff:
                changed.append(tr)
    head = f"<h2>Config: {len(changed)} value{'s' * (len(changed) != 1)} differ from {html.escape(label)}</h2>"
    diff_table = (f'<table class="config">{"".join(changed)}</table>' if changed else
                  f"<p>none: the run used {html.escape(label)} as is.</p>")
    return (head + diff_table + '<details><summary>the whole resolved config (changed values marked)</summary>'
            f'<table class="config">{"".join(rows)}</table></details>')


def views_html(run: Path, render_paths: dict[int, dict[str, str]], renders: dict | None, scene) -> str:
    """Per frame: photo, renders, coloured depth with its scale, normals, depth error vs ground truth.

    Full-size coloured depth and error maps are written next to the other renders
    (``renders/NNN_depth_color.png``, ``NNN_depth_error.png``); the page embeds reduced copies.
    """
    import numpy as np

    from fastneus.eval.depth import depth_image, error_map
    from fastneus.eval.figures import colormap_stops, data_uri, nice_ceiling, read_rgb, scale_bar

    units = getattr(scene, "units", "m") if scene is not None else "m"
    scale, unit = (1000.0, "mm") if units == "m" else (1.0, str(units))
    labels = [("photo", "photo (input)", "jpeg"), ("color", "render with pattern", "jpeg"),
              ("texture", "pattern-free texture (i_r = 0)", "jpeg"), ("clean", "ground truth, pattern-free", "jpeg")]
    out = []
    for i, paths in render_paths.items():
        cells = []

        def fig(uri: str, cap: str, href: str | None, extra: str = "") -> str:
            img = f'<img src="{uri}" alt="{html.escape(cap)}">'
            if href:
                img = f'<a href="{html.escape(href)}">{img}</a>'
            return f'<figure>{img}<figcaption>{html.escape(cap)}</figcaption>{extra}</figure>'

        for k, cap, fmt in labels:
            if k in paths and (img := read_rgb(run / paths[k])) is not None:
                cells.append(fig(data_uri(img, fmt), cap, paths[k]))
        r = (renders or {}).get(i)
        gt = scene.gt_depth(i) if scene is not None and r is not None else None
        if r is not None:
            z = np.where(r["opacity"] > 0.5, r["depth"], np.nan).astype(np.float64)
            ok = np.isfinite(z) & (z > 0)
            ref = np.concatenate([z[ok], gt[gt > 0]]) if gt is not None else z[ok]
            if ref.size:
                lo, hi = (float(x) for x in np.percentile(ref, [1, 99]))
                hi = max(hi, lo + 1e-6)
                img = depth_image(z, lo, hi)
                rel = f"renders/{i:03d}_depth_color.png"
                atomic_write_image(run / rel, img)
                bar = scale_bar(colormap_stops("viridis", reverse=True), f"{lo * scale:.4g}", f"{hi * scale:.4g}",
                                f"depth ({unit})")
                cells.append(fig(data_uri(img), "depth (near bright, far dark)", rel, bar))
        elif "depth" in paths and (img := read_rgb(run / paths["depth"])) is not None:
            cells.append(fig(data_uri(img), "depth", paths["depth"]))
        if "normal" in paths and (img := read_rgb(run / paths["normal"])) is not None:
            cells.append(fig(data_uri(img), "normals (x, y, z as r, g, b)", paths["normal"]))
        if r is not None and gt is not None and (gt > 0).any():
            has = gt > 0
            good = has & np.isfinite(z) & (z > 0)
            relerr = np.abs(z[good] - gt[good]) / gt[good] * 100.0
            top = nice_ceiling(float(np.percentile(relerr, 90))) if relerr.size else 1.0
            top = max(top, 1.0)
            img = error_map(z, gt, max_pct=top)
            rel = f"renders/{i:03d}_depth_error.png"
            atomic_write_image(run / rel, img)
            mean = (f"mean {np.abs(z[good] - gt[good]).mean() * scale:.3g} {unit} "
                    f"({relerr.mean():.2f} %), missing {100 * (1 - good.sum() / has.sum()):.0f} %") if relerr.size \
                else "no surface rendered"
            bar = scale_bar(colormap_stops("turbo"), "0", f"{top:g} %", "|Δz| / z",
                            '<div class="ends"><span><i class="swatch" style="background:#f0f"></i> missed</span>'
                            '<span><i class="swatch" style="background:#000"></i> background</span></div>')
            cells.append(fig(data_uri(img), f"depth error of the render vs ground truth: {mean}", rel, bar))
        out.append(f'<h3>frame {i}</h3><div class="row views">{"".join(cells)}</div>')
    return "".join(out)


def mesh_view_html(run: Path, mesh, scene, frame: int | None) -> str:
    """The 3D view of ``mesh`` (MeshArrays or trimesh; None: read run/mesh.ply), seen first from
    ``frame``'s camera."""
    from fastneus.eval.viewer import VIEWER_VERSION, view_rotation, viewer_html

    if mesh is None:
        import trimesh

        if not (run / "mesh.ply").is_file():
            return "<p>no mesh.ply in this run.</p>"
        mesh = trimesh.load(run / "mesh.ply", force="mesh", process=False)
    v, f = mesh.vertices, mesh.faces
    normals = getattr(mesh, "normals", None)
    colors = getattr(mesh, "colors", None)
    if normals is None and hasattr(mesh, "vertex_normals"):  # a trimesh: the file's normals, else computed
        normals = mesh.vertex_normals
    vis = getattr(mesh, "visual", None)
    if colors is None and getattr(vis, "kind", None) == "vertex":
        colors = vis.vertex_colors[:, :3]
    if len(f) == 0:
        return "<p>the mesh is empty: nothing to show.</p>"
    rot = None
    if scene is not None and frame is not None:
        try:
            rot = view_rotation(scene.cam_to_world(frame))
        except Exception:  # noqa: BLE001 - a view without a pose: the mesh as it is
            rot = None
    body, facts = viewer_html(v, f, normals, colors, rot)
    note = (f"{facts['faces']:,} faces shown (decimated from {facts['faces_full']:,} for this page; mesh.ply has "
            f"them all)" if facts["decimated"] else f"{facts['faces']:,} faces")
    first = f"; opens as seen by frame {frame}'s camera" if rot is not None else ""
    return (f'<div class="viewer">{body}<p class="hint">drag to orbit, scroll or pinch to zoom, right-drag to pan'
            f'{first}; {"vertex colours: the learned pattern-free colour" if colors is not None else "no vertex colours"}'
            f'. {note}. Viewer: {html.escape(VIEWER_VERSION)}, inlined.</p></div>')


CSS = """body{font-family:system-ui,sans-serif;margin:20px;color:#222;max-width:1500px}
h1{margin-bottom:4px} h2{margin-top:28px;border-bottom:1px solid #ddd} .sub{color:#666;margin-top:0}
.row{display:flex;flex-wrap:wrap;gap:8px} .top{display:flex;flex-wrap:wrap;gap:20px;align-items:flex-start}
.viewer{flex:3 1 520px;min-width:320px} .headline{flex:2 1 380px}
figure{margin:0;width:240px} figure img{width:240px;image-rendering:pixelated;border:1px solid #ccc;display:block}
figcaption{font-size:12px;text-align:center} .hint{font-size:12px;color:#555}
table{border-collapse:collapse} td,th{border:1px solid #ddd;padding:3px 8px;font-size:13px;text-align:left}
table.headline td:nth-child(2){font-weight:600;white-space:nowrap} td.num{text-align:right;white-space:nowrap}
.tbar{height:10px;background:#1f77b4;min-width:1px} tr.total td{font-weight:600}
.scale{font-size:11px;margin-top:2px} .bar{height:10px;border:1px solid #999}
.ends{display:flex;justify-content:space-between} .swatch{display:inline-block;width:9px;height:9px;vertical-align:middle}
tr.changed td{background:#fff3c4} tr.changed td:first-child{font-weight:600} tr.section td{background:#f0f0f0;font-weight:600}
.charts img{width:440px;border:1px solid #eee} details{margin-top:8px} summary{cursor:pointer;color:#1f4e99}"""


def write_report(run: Path, metrics: dict, render_paths: dict[int, dict[str, str]], config: dict,
                 title: str = "fastneus run", *, renders: dict | None = None, scene=None, mesh=None,
                 timing: dict | None = None) -> Path:
    """Write ``run/report.html``: one self-contained page (see the module docstring).

    Args:
        metrics: metrics.json's content; render_paths: {frame: {kind: path relative to run}}.
        config: ``cfg.to_dict()`` (nested); its values that differ from the preset are marked.
        renders: the numpy renders (``render_frames``) for coloured depth and the error maps.
        scene: the scene (ground-truth depth, units, the first frame's camera for the 3D view).
        mesh: the mesh (MeshArrays or trimesh); None reads run/mesh.ply.
        timing: ``clock.summary()`` read after the eval phase (default: ``metrics["timing"]``).
    """
    run = Path(run)
    from fastneus.eval.figures import training_charts

    log = read_log(run / "log.jsonl")
    truth = {k: metrics[f"{k}_gt"] for k in _CHART_TRUTH if isinstance(metrics.get(f"{k}_gt"), (int, float))}
    charts = training_charts(log, truth)
    chart_html = ("".join(f'<img class="chart" src="{uri}" alt="{html.escape(t)}">' for t, uri in charts)
                  if charts else "<p>no training curves (fewer than two log records, or matplotlib missing).</p>")
    head = headline_rows(metrics)
    head_html = _table(head, ("metric", "value", "details"), "headline")
    full = _flat_metrics(metrics)
    first = next(iter(render_paths), None)
    view = mesh_view_html(run, mesh, scene, first)
    tm = timing if timing is not None else (metrics.get("timing") or {})
    sub = []
    if "steps" in metrics:
        sub.append(f"{metrics['steps']} steps")
    preset = (config.get("run") or {}).get("preset")
    if preset:
        sub.append(f"preset {preset}")
    page = f"""<!doctype html><html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width,initial-scale=1"><title>{html.escape(title)}</title>
<style>{CSS}</style></head><body>
<h1>{html.escape(title)}</h1><p class="sub">{html.escape(' · '.join(sub))}</p>
<div class="top">{view}
<div class="headline"><h2 id="headline">Headline metrics</h2>{head_html}
<details id="all-metrics"><summary>all {len(full)} metrics (metrics.json)</summary>
{_table(full, ("key", "value", "unit"), "metrics")}</details></div></div>
<h2>Views</h2>
{views_html(run, render_paths, renders, scene)}
<h2>Training</h2><div class="row charts">{chart_html}</div>
{timing_html(tm)}
{decisions_html(run)}
{config_html(config)}
<h2>Files</h2><p><a href="mesh.ply">mesh.ply</a> (full resolution, world units) · <a href="metrics.json">metrics.json</a> ·
<a href="illumination.json">illumination.json</a> · <a href="log.jsonl">log.jsonl</a> · <a href="renders/">renders/</a></p>
</body></html>"""
    path = run / "report.html"
    atomic_write_text(path, page)
    return path
