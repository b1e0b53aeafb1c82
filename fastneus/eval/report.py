"""report.html of a run: renders side by side, loss/PSNR curves (inline SVG), metrics."""
from __future__ import annotations

import html
import json
from pathlib import Path

from fastneus.io import atomic_write_text


def _svg_curve(xs: list[float], ys: list[float], title: str, log: bool = False, w: int = 420, h: int = 180) -> str:
    import math

    pts = [(x, math.log10(y) if log else y) for x, y in zip(xs, ys) if y is not None and (not log or y > 0)
           and math.isfinite(y)]
    if len(pts) < 2:
        return f"<div><b>{html.escape(title)}</b>: not enough points</div>"
    x0, x1 = min(p[0] for p in pts), max(p[0] for p in pts)
    y0, y1 = min(p[1] for p in pts), max(p[1] for p in pts)
    sx = lambda x: 40 + (x - x0) / max(x1 - x0, 1e-12) * (w - 50)  # noqa: E731
    sy = lambda y: h - 25 - (y - y0) / max(y1 - y0, 1e-12) * (h - 45)  # noqa: E731
    poly = " ".join(f"{sx(x):.1f},{sy(y):.1f}" for x, y in pts)
    lab = (lambda v: f"{10 ** v:.3g}") if log else (lambda v: f"{v:.3g}")
    return (f'<svg width="{w}" height="{h}" style="background:#fafafa;border:1px solid #ddd">'
            f'<text x="{w / 2}" y="14" text-anchor="middle" font-size="12">{html.escape(title)}</text>'
            f'<polyline fill="none" stroke="#1f77b4" stroke-width="1.5" points="{poly}"/>'
            f'<text x="2" y="{sy(y1) + 4:.0f}" font-size="10">{lab(y1)}</text>'
            f'<text x="2" y="{sy(y0):.0f}" font-size="10">{lab(y0)}</text>'
            f'<text x="40" y="{h - 8}" font-size="10">step {x0:.0f}</text>'
            f'<text x="{w - 10}" y="{h - 8}" font-size="10" text-anchor="end">{x1:.0f}</text></svg>')


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


def write_report(run: Path, metrics: dict, render_paths: dict[int, dict[str, str]], config: dict,
                 title: str = "fastneus run") -> Path:
    """Write ``run/report.html`` (self-contained apart from the PNGs in ``run/renders``)."""
    log = read_log(run / "log.jsonl")
    steps = [r["step"] for r in log]
    curves = "".join([
        _svg_curve(steps, [r["loss"] for r in log], "training loss (log)", log=True),
        _svg_curve(steps, [r["psnr"] for r in log], "training PSNR (dB)"),
        _svg_curve(steps, [r["i_r"] for r in log], "i_r"),
        _svg_curve(steps, [r["i_b"] for r in log], "i_b"),
    ])
    rows = "".join(f"<tr><td>{html.escape(k)}</td><td>{v:.4g}</td></tr>" if isinstance(v, float) else
                   f"<tr><td>{html.escape(k)}</td><td>{html.escape(str(v))}</td></tr>" for k, v in metrics.items()
                   if not isinstance(v, dict))
    tm = metrics.get("timing") or {}
    wall = ""
    if tm:  # seconds per phase so far (the report itself is the last phase)
        trs = "".join(f"<tr><td>{html.escape(k)}</td><td>{v:.2f} s</td></tr>" for k, v in tm.items()
                      if isinstance(v, (int, float)) and not isinstance(v, bool))
        wall = (f"<h2>Wall clock (seconds from {html.escape(str(tm.get('origin', 'start')))})</h2>"
                f"<table>{trs}</table>")
    labels = [("photo", "photo (input)"), ("color", "rendered with pattern"), ("texture", "texture only (i_r=i_b=0)"),
              ("clean", "GT pattern-free"), ("depth", "depth"), ("normal", "normals")]
    figs = []
    for i, p in render_paths.items():
        cells = "".join(f'<figure><img src="{html.escape(p[k])}"><figcaption>{lab}</figcaption></figure>'
                        for k, lab in labels if k in p)
        figs.append(f"<h3>frame {i}</h3><div class='row'>{cells}</div>")
    cfg = html.escape(json.dumps(config, indent=1))
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>body{{font-family:sans-serif;margin:20px}} .row{{display:flex;flex-wrap:wrap;gap:6px}}
figure{{margin:0}} img{{width:220px;image-rendering:pixelated;border:1px solid #ccc}}
figcaption{{font-size:12px;text-align:center}} table{{border-collapse:collapse}}
td{{border:1px solid #ddd;padding:2px 8px;font-size:13px}}</style></head><body>
<h1>{html.escape(title)}</h1>
<h2>Metrics</h2><table>{rows}</table>
{wall}
<h2>Training</h2><div class="row">{curves}</div>
<h2>Renders</h2>{''.join(figs)}
<h2>Resolved config</h2><pre style="font-size:11px">{cfg}</pre>
<p>mesh: <a href="mesh.ply">mesh.ply</a> (world units) · <a href="metrics.json">metrics.json</a> ·
<a href="illumination.json">illumination.json</a> · <a href="log.jsonl">log.jsonl</a></p>
</body></html>"""
    path = run / "report.html"
    atomic_write_text(path, page)
    return path
