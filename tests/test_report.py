"""report.html of a tiny CPU run: the mesh in an offline 3D view, headline metrics before the full
table, per-view images, charts, the wall clock with its eval row, the config diff against the preset."""
from __future__ import annotations

import base64
import io
import re
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from conftest import SMALL_RUN


class Page(HTMLParser):
    """Every start tag in order (tag, attrs, position), the text inside scripts, tables' text by class."""

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.tags: list[tuple[str, dict, int]] = []
        self.scripts: list[tuple[dict, str]] = []
        self._script: dict | None = None
        self._stack: list[tuple[str, dict]] = []
        self.text_in: dict[str, list[str]] = {}

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        self.tags.append((tag, a, len(self.tags)))
        if tag == "script":
            self._script = a
            self.scripts.append((a, ""))
        if tag in ("table", "details", "figure", "tr"):
            self._stack.append((tag, a))

    def handle_endtag(self, tag):
        if tag == "script":
            self._script = None
        if self._stack and self._stack[-1][0] == tag:
            self._stack.pop()

    def handle_data(self, data):
        if self._script is not None:
            a, t = self.scripts[-1]
            self.scripts[-1] = (a, t + data)
        for tag, a in self._stack:
            for key in (a.get("class") or "").split() + ([a["id"]] if a.get("id") else []):
                self.text_in.setdefault(f"{tag}.{key}", []).append(data)

    def find(self, tag: str, **attrs) -> list[tuple[dict, int]]:
        return [(a, i) for t, a, i in self.tags if t == tag and all(a.get(k) == v for k, v in attrs.items())]


@pytest.fixture(scope="module")
def report(small_scene, tmp_path_factory):
    from fastneus.cli import main

    run = tmp_path_factory.mktemp("report") / "run"
    assert main(["train", str(small_scene), "--out", str(run), "--device", "cpu"] + SMALL_RUN) == 0
    text = (run / "report.html").read_text()
    page = Page()
    page.feed(text)
    return run, text, page


def test_viewer_is_inlined_and_nothing_is_fetched(report):
    _, text, page = report
    modules = [(a, t) for a, t in page.scripts if a.get("type") == "module"]
    assert len(modules) == 1
    a, src = modules[0]
    assert "src" not in a and len(src) > 500_000 and 'customElements.define("model-viewer"' in src.replace("'", '"')
    for tag, attrs, _ in page.tags:  # no element loads anything from the network
        for k in ("src", "href"):
            assert not str(attrs.get(k, "")).lower().startswith(("http:", "https:", "//")), (tag, attrs.get(k))
    (mv, _), = page.find("model-viewer")
    assert mv["src"].startswith("data:model/gltf-binary;base64,") and "camera-controls" in mv


def test_embedded_glb_is_the_mesh_with_vertex_colours(report):
    import trimesh

    run, _, page = report
    (mv, _), = page.find("model-viewer")
    glb = base64.b64decode(mv["src"].split(",", 1)[1])
    assert glb[:4] == b"glTF" and len(glb) < 4_000_000
    scene = trimesh.load(io.BytesIO(glb), file_type="glb")
    (geom,) = scene.geometry.values()
    ply = trimesh.load(run / "mesh.ply", process=False)
    assert len(geom.faces) == len(ply.faces) > 0  # small: not decimated
    colors = geom.visual.vertex_attributes["color"]
    assert colors.shape == (len(geom.vertices), 4) and colors[:, :3].std() > 0
    # the same surface, turned to face the first camera: same size
    assert np.allclose(np.ptp(np.linalg.norm(geom.vertices - geom.vertices.mean(0), axis=1)),
                       np.ptp(np.linalg.norm(ply.vertices - ply.vertices.mean(0), axis=1)), rtol=1e-3)


def test_headline_metrics_with_units_come_before_the_full_table(report):
    _, _, page = report
    (_, head_at), = page.find("table", **{"class": "headline"})
    (_, details_at), = page.find("details", id="all-metrics")
    assert head_at < details_at
    head = " ".join(page.text_in["table.headline"])
    for needle in ("PSNR, render with pattern vs photo", " dB", " mm", "%", "i_r", "truth 0.4", "i_b"):
        assert needle in head, needle
    assert "depth_unlit_within_1pct" not in head  # raw names only in the folded table
    assert "psnr_pattern" in " ".join(page.text_in["details.all-metrics"])


def test_views_charts_and_wall_clock(report):
    run, text, page = report
    charts = page.find("img", **{"class": "chart"})
    assert len(charts) == 4 and all(a["src"].startswith("data:image/png;base64,") for a, _ in charts)
    imgs = [a for a, _ in page.find("img")]
    alts = [a.get("alt", "") for a in imgs]
    for cap in ("photo (input)", "render with pattern", "pattern-free texture (i_r = 0)", "normals (x, y, z as r, g, b)"):
        assert cap in alts, cap
    assert any(x.startswith("depth error of the render vs ground truth") for x in alts)
    assert (run / "renders" / "000_depth_color.png").is_file() and (run / "renders" / "000_depth_error.png").is_file()
    assert text.count('class="scale"') == 2 and "depth (mm)" in text
    assert "Wall clock (seconds from" in text
    wall = text[text.index("Wall clock"):]
    for phase in ("train", "mesh", "renders", "eval", "total", "mesh_ready_at"):
        assert re.search(rf"<td>{phase}</td><td class=\"num\">[0-9.]+ s</td>", wall), phase


def test_config_diff_marks_the_changed_keys(report):
    _, _, page = report
    changed = {a["data-key"] for a, _ in page.find("tr", **{"class": "changed"})}
    same = {a["data-key"] for a, _ in page.find("tr", **{"class": "same"})}
    assert {"run.steps", "export.mesh_resolution"} <= changed  # SMALL_RUN overrides cpu-quick
    assert "optim.lr" in same and "run.preset" in same


def test_decimation_keeps_surface_and_colours():
    import trimesh

    from fastneus.eval.viewer import decimate, glb_bytes

    m = trimesh.creation.icosphere(6)  # 81,920 faces
    col = np.tile(np.array([[200, 40, 10]], np.uint8), (len(m.vertices), 1))
    v, f, n, c = decimate(m.vertices, m.faces, m.vertex_normals, col, max_faces=5000)
    assert 1000 < len(f) <= 5000 and f.max() < len(v) and len(n) == len(c) == len(v)
    assert np.abs(np.linalg.norm(v, axis=1) - 1).max() < 0.05 and (c == [200, 40, 10]).all()
    assert (np.einsum("ij,ij->i", n, v) > 0.9).all()  # normals still point out
    g = trimesh.load(io.BytesIO(glb_bytes(v, f, n, c)), file_type="glb")
    (geom,) = g.geometry.values()
    assert len(geom.faces) == len(f)


@pytest.mark.skipif(shutil.which("chromium") is None, reason="Debian's chromium is not installed (optional check)")
def test_browser_draws_the_mesh(report, tmp_path):
    """The page's own viewer and GLB, alone in a window: the screenshot shows more than the background."""
    import cv2

    _, text, _ = report
    script = re.search(r'<script type="module"[^>]*>.*?</script>', text, re.S).group(0)
    viewer = re.search(r"<model-viewer .*?</model-viewer>", text, re.S).group(0)
    page = tmp_path / "view.html"
    page.write_text('<!doctype html><html><head><meta charset="utf-8"><style>body{margin:0}model-viewer{width:'
                    f'100vw!important;height:100vh!important}}</style></head><body>{script}{viewer}</body></html>')
    shot = tmp_path / "shot.png"
    r = subprocess.run(["chromium", "--headless", "--no-sandbox", "--use-angle=swiftshader",
                        "--enable-unsafe-swiftshader", "--hide-scrollbars", "--window-size=400,300",
                        "--virtual-time-budget=15000", "--enable-logging=stderr", f"--screenshot={shot}",
                        page.as_uri()], capture_output=True, text=True, timeout=120)
    assert shot.is_file(), r.stderr[-2000:]
    console = [x for x in r.stderr.splitlines() if "CONSOLE" in x]
    assert not [x for x in console if "Uncaught" in x or "Error" in x], console  # e.g. a GLB it cannot parse
    img = cv2.imread(str(shot))[..., ::-1].astype(int)
    background = np.array([0xEE, 0xF0, 0xF3])
    drawn = (np.abs(img - background).sum(-1) > 30).mean()
    assert drawn > 0.03, drawn
