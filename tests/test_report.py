"""report.html of a tiny CPU run: the mesh in an offline 3D view, headline metrics before the full
table, per-view images, charts, the wall clock with its eval row, the config diff against the preset."""
from __future__ import annotations

import base64
import io
import os
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


# Debian's chromium, headless, as root, on a machine without a network (the flags the env notes give):
# no sandbox (root), no GPU (SwiftShader's WebGL draws), nothing fetched in the background, a fresh profile
from fastneus.eval.viewer import HEADLESS_CHROMIUM_FLAGS as CHROMIUM_FLAGS  # noqa: E402
# injected first into a copy of report.html: console errors, uncaught exceptions, rejected promises and the
# viewer's own error event become marked log lines; once the GLB is loaded the viewer's box is logged
PROBE = """<script>
(() => {
  const log = console.log.bind(console), mark = (...a) => log("FASTNEUS-ERROR " + a.map(String).join(" "));
  const err = console.error.bind(console);
  console.error = (...a) => { mark(...a); err(...a); };
  addEventListener("error", e => mark("uncaught:", e.message || e.type));
  addEventListener("unhandledrejection", e => mark("unhandled rejection:", e.reason));
  addEventListener("DOMContentLoaded", () => {
    const mv = document.getElementById("mesh-view");
    if (!mv) { mark("no #mesh-view element"); return; }
    mv.scrollIntoView({block: "center"});
    mv.addEventListener("error", e => mark("model-viewer:", JSON.stringify(e.detail)));
    mv.addEventListener("load", () => requestAnimationFrame(() => requestAnimationFrame(() => {
      const r = mv.getBoundingClientRect();
      log(`FASTNEUS-LOADED ${Math.round(r.left)} ${Math.round(r.top)} ${Math.round(r.width)} ${Math.round(r.height)}`);
    })));
  });
})();
</script>"""


def find_browser() -> str | None:
    """Debian's chromium (or another Chromium build on PATH), or None."""
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    return None


def test_browser_draws_the_mesh(report, tmp_path):
    """report.html in headless Chromium: the viewer loads the embedded GLB, its box on the screenshot shows
    more than the background (the mesh was drawn), and nothing logged an error.

    Skips only where no browser is installed and FASTNEUS_REQUIRE_BROWSER is unset; CI (.ci/run) installs
    Debian's chromium and sets it, so there a missing browser fails."""
    import cv2

    browser = find_browser()
    if browser is None:
        if os.environ.get("FASTNEUS_REQUIRE_BROWSER"):
            pytest.fail("FASTNEUS_REQUIRE_BROWSER is set but no chromium is on PATH "
                        "(.ci/run installs Debian's chromium: did apt-get fail?)")
        pytest.skip("no chromium on PATH (apt-get install chromium); CI sets FASTNEUS_REQUIRE_BROWSER and runs it")
    _, text, _ = report
    assert text.count("<head>") == 1
    page = tmp_path / "report.html"
    page.write_text(text.replace("<head>", "<head>" + PROBE, 1))
    shot = tmp_path / "shot.png"
    w, h = 1000, 900
    r = subprocess.run([browser, *CHROMIUM_FLAGS, f"--user-data-dir={tmp_path / 'profile'}", f"--window-size={w},{h}",
                        "--virtual-time-budget=15000", f"--screenshot={shot}", page.as_uri()],
                       capture_output=True, text=True, timeout=180)
    assert shot.is_file(), r.stderr[-2000:]
    errors = [x for x in r.stderr.splitlines() if "FASTNEUS-ERROR" in x]
    assert errors == [], errors
    loaded = [x for x in r.stderr.splitlines() if "FASTNEUS-LOADED" in x]
    assert loaded, "the viewer never fired its load event: " + r.stderr[-2000:]
    x, y, bw, bh = (int(v) for v in re.search(r"FASTNEUS-LOADED (-?\d+) (-?\d+) (\d+) (\d+)", loaded[-1]).groups())
    img = cv2.imread(str(shot))[..., ::-1].astype(int)
    x0, y0, x1, y1 = max(0, x) + 2, max(0, y) + 2, min(img.shape[1], x + bw) - 2, min(img.shape[0], y + bh) - 2
    assert x1 - x0 > 100 and y1 - y0 > 100, ((x, y, bw, bh), img.shape)  # the viewer is on the screen
    region = img[y0:y1, x0:x1]
    background = np.array([0xEE, 0xF0, 0xF3])
    drawn = (np.abs(region - background).sum(-1) > 30).mean()
    assert drawn > 0.03, drawn


def test_missing_browser_skips_only_where_not_required(monkeypatch, tmp_path):
    """No chromium: a skip with its reason, but a failure where FASTNEUS_REQUIRE_BROWSER is set (CI)."""
    monkeypatch.setattr(shutil, "which", lambda name: None)
    monkeypatch.setenv("FASTNEUS_REQUIRE_BROWSER", "1")
    with pytest.raises(pytest.fail.Exception, match="no chromium"):
        test_browser_draws_the_mesh(None, tmp_path)
    monkeypatch.delenv("FASTNEUS_REQUIRE_BROWSER")
    with pytest.raises(pytest.skip.Exception, match="apt-get install chromium"):
        test_browser_draws_the_mesh(None, tmp_path)


def test_decisions_from_the_data_are_shown(report, tmp_path):
    """The run's automatic choices (run.json) are listed: masks, background prior, response, the
    camera blur and the exposure; a damaged run.json only drops the section."""
    import json

    from fastneus.eval.report import decisions_html

    run, text, page = report
    rows = " ".join(page.text_in.get("table.decisions", []))
    for what in ("masks", "photo response", "camera blur", "exposure"):
        assert what in rows, what
    info = json.loads((run / "run.json").read_text())
    assert info["exposure"]["mode"] == "auto" and info["camera_blur"]["mode"] == "auto"
    assert info["exposure_note"].startswith("exposure: auto -> ") and "camera blur: auto -> " in info["camera_blur_note"]
    assert info["exposure_note"] in rows and info["camera_blur_note"] in rows  # the lines the run printed
    (tmp_path / "run.json").write_text('{"camera_blur_note": {"not": "a line"}, "masks": "<i>m</i>"}')
    html_ = decisions_html(tmp_path)
    assert "<i>" not in html_ and "&lt;i&gt;m&lt;/i&gt;" in html_ and "camera blur" not in html_
    (tmp_path / "run.json").write_text("not json")
    assert decisions_html(tmp_path) == ""
