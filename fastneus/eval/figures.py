"""Pictures for report.html: training charts (matplotlib, Agg, no pyplot), per-view images as data
URIs, and colour scale bars.

Everything heavy (matplotlib, OpenCV) is imported inside the functions: the report is written
after mesh.ply, and importing this module costs nothing before that.
"""
from __future__ import annotations

import base64
import html
import io
import math
from pathlib import Path

import numpy as np

MAX_SIDE = 480  # pixels: the longest side of a picture embedded in the page (the PNG on disk keeps its size)


def data_uri(rgb: np.ndarray, fmt: str = "png", max_side: int = MAX_SIDE) -> str:
    """An RGB uint8 image [H, W, 3] as a ``data:`` URI, shrunk to ``max_side`` (area filter).

    Args:
        fmt: ``png`` (maps, exact colours) or ``jpeg`` (photographs, ~10x smaller).
    """
    import cv2

    img = np.asarray(rgb)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    h, w = img.shape[:2]
    s = max_side / max(h, w)
    if s < 1:
        img = cv2.resize(img, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA)
    ext, params = (".jpg", [cv2.IMWRITE_JPEG_QUALITY, 88]) if fmt == "jpeg" else (".png", [])
    ok, buf = cv2.imencode(ext, np.ascontiguousarray(img[..., :3][..., ::-1]), params)
    if not ok:
        raise ValueError("cannot encode image")
    mime = "image/jpeg" if fmt == "jpeg" else "image/png"
    return f"data:{mime};base64,{base64.b64encode(buf.tobytes()).decode('ascii')}"


def read_rgb(path: Path) -> np.ndarray | None:
    """An image file as RGB uint8 [H, W, 3], or None when missing or unreadable."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    return None if img is None else img[..., ::-1]


def colormap_stops(name: str, n: int = 9, reverse: bool = False) -> list[str]:
    """``n`` CSS colours sampled evenly from an OpenCV colour map (``turbo`` or ``viridis``)."""
    import cv2

    cmap = {"turbo": cv2.COLORMAP_TURBO, "viridis": cv2.COLORMAP_VIRIDIS}[name]
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cmap)[:, 0, ::-1]
    idx = np.linspace(0, 255, n).round().astype(int)
    if reverse:
        idx = idx[::-1]
    return [f"rgb({r},{g},{b})" for r, g, b in lut[idx]]


def scale_bar(stops: list[str], lo: str, hi: str, label: str, extra: str = "") -> str:
    """HTML colour bar: a gradient with its end values and what it measures."""
    grad = ",".join(stops)
    return (f'<div class="scale"><div class="bar" style="background:linear-gradient(to right,{grad})"></div>'
            f'<div class="ends"><span>{html.escape(lo)}</span><span>{html.escape(label)}</span>'
            f'<span>{html.escape(hi)}</span></div>{extra}</div>')


def nice_ceiling(x: float) -> float:
    """The smallest of 1, 2, 5 x 10^k that is >= x (x > 0)."""
    if not (x > 0 and math.isfinite(x)):
        return 1.0
    e = math.floor(math.log10(x))
    for m in (1, 2, 5, 10):
        if m * 10 ** e >= x * (1 - 1e-9):
            return float(m * 10 ** e)
    return float(10 ** (e + 1))


def _png(fig) -> str:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def training_charts(log: list[dict], truth: dict[str, float] | None = None) -> list[tuple[str, str]]:
    """(title, PNG data URI) of the loss, PSNR, i_r and i_b curves over the training steps.

    Axes are labelled, with ticks and a grid; ``truth`` (e.g. ``{"i_r": 0.5}``) draws the true
    value as a dashed line. Empty when matplotlib is missing or the log has fewer than 2 records.
    """
    try:
        from matplotlib.figure import Figure  # Agg canvas, no pyplot: the process's backend is left alone
        from matplotlib.ticker import FuncFormatter, MaxNLocator, NullFormatter
    except ImportError:
        return []
    if len(log) < 2:
        return []
    truth = truth or {}
    steps = np.array([r["step"] for r in log], dtype=float)
    specs = [("loss", "training loss", "loss (log scale)", True),
             ("psnr", "training PSNR", "PSNR (dB)", False),
             ("i_r", "i_r: projector (pattern) light", "i_r", False),
             ("i_b", "i_b: ambient light", "i_b", False)]
    out = []
    for key, title, ylabel, log_y in specs:
        y = np.array([r.get(key, np.nan) for r in log], dtype=float)
        ok = np.isfinite(y) & ((y > 0) if log_y else True)
        if ok.sum() < 2:
            continue
        fig = Figure(figsize=(4.4, 2.9))
        ax = fig.add_subplot(1, 1, 1)
        ax.plot(steps[ok], y[ok], color="#1f77b4", lw=1.4, label="learned" if key in truth else None)
        if log_y:
            ax.set_yscale("log")
            ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:.3g}"))
            span = np.nanmax(y[ok]) / np.nanmin(y[ok])
            ax.yaxis.set_minor_formatter(FuncFormatter(lambda v, _: f"{v:.2g}") if span < 20 else NullFormatter())
        ax.xaxis.set_major_locator(MaxNLocator(nbins=6, integer=True))
        if key in truth and truth[key] is not None and math.isfinite(truth[key]):
            ax.axhline(truth[key], color="#d62728", ls="--", lw=1.2, label=f"truth {truth[key]:.3g}")
            ax.legend(loc="best", fontsize=8, frameon=False)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("step", fontsize=9)
        ax.set_ylabel(ylabel, fontsize=9)
        ax.tick_params(labelsize=8)
        ax.grid(True, which="major", alpha=0.3)
        fig.tight_layout()
        out.append((title, _png(fig)))
    return out
