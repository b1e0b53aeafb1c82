"""The README's picture of report.html: a headless-Chromium screenshot of a real report.

    fastneus demo --device cpu --out fastneus-demo
    python scripts/report_screenshot.py fastneus-demo/run/report.html --out docs/report.png

The report is opened from a temporary copy (with a small script that waits for the 3D view's
``load`` event and reports any console error), in Debian's chromium (``apt-get install chromium``)
with a fresh profile and no network use; the PNG is reduced to a palette image so that it stays
under ``--max-kb``. Nothing is written but ``--out``.
"""
from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from fastneus.eval.viewer import HEADLESS_CHROMIUM_FLAGS as FLAGS

PROBE = """<script>
(() => {
  const log = console.log.bind(console), err = console.error.bind(console);
  console.error = (...a) => { log("SHOT-ERROR " + a.map(String).join(" ")); err(...a); };
  addEventListener("error", e => log("SHOT-ERROR uncaught: " + (e.message || e.type)));
  addEventListener("DOMContentLoaded", () => {
    const mv = document.getElementById("mesh-view");
    if (mv) mv.addEventListener("load", () => log("SHOT-LOADED"));
  });
})();
</script>"""


def browser() -> str:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    sys.exit("no chromium on PATH: apt-get install chromium")


def screenshot(report: Path, out: Path, width: int, height: int, max_kb: int) -> int:
    """Write the screenshot of ``report`` to ``out``; returns its size in bytes."""
    from PIL import Image

    text = report.read_text(encoding="utf-8")
    if "<head>" not in text:
        sys.exit(f"{report}: not a fastneus report (no <head>)")
    with tempfile.TemporaryDirectory() as tmp:
        page = Path(tmp) / "report.html"
        page.write_text(text.replace("<head>", "<head>" + PROBE, 1), encoding="utf-8")
        shot = Path(tmp) / "shot.png"
        r = subprocess.run([browser(), *FLAGS, f"--user-data-dir={Path(tmp) / 'profile'}",
                            f"--window-size={width},{height}", "--virtual-time-budget=20000",
                            f"--screenshot={shot}", page.as_uri()], capture_output=True, text=True, timeout=300)
        log = r.stderr.splitlines()
        errors = [x for x in log if "SHOT-ERROR" in x]
        if errors or not shot.is_file():
            sys.exit("chromium: " + ("; ".join(errors) or r.stderr[-1000:]))
        if not any("SHOT-LOADED" in x for x in log):
            sys.exit("the 3D view never loaded its mesh (no load event); not writing a picture without it")
        img = Image.open(shot).convert("RGB")
        # a palette PNG: text, tables and the shaded mesh keep their look at a fraction of the bytes
        small = img.quantize(colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
        tmp_out = Path(tmp) / "out.png"
        small.save(tmp_out, optimize=True)
        size = tmp_out.stat().st_size
        if size > max_kb * 1024:
            sys.exit(f"{size // 1024} kB is more than --max-kb {max_kb}; try a smaller --width/--height")
        out.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(tmp_out, out)
    return size


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("report", type=Path, help="a report.html (e.g. fastneus-demo/run/report.html)")
    ap.add_argument("--out", type=Path, default=Path("docs/report.png"), help="PNG to write (default docs/report.png)")
    ap.add_argument("--width", type=int, default=1100, help="window width in pixels (default 1100)")
    ap.add_argument("--height", type=int, default=760, help="window height in pixels (default 760)")
    ap.add_argument("--max-kb", type=int, default=300, help="refuse a picture larger than this (default 300)")
    args = ap.parse_args()
    size = screenshot(args.report, args.out, args.width, args.height, args.max_kb)
    print(f"{args.out}: {size // 1024} kB")


if __name__ == "__main__":
    main()
