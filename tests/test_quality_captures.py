"""scripts/quality.py's capture axis: ``realistic:KEY=VALUE`` changes one part of the realistic mix."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))


def test_capture_specs_parse_and_bad_ones_are_one_line():
    from quality import parse_capture, scene_dir

    assert parse_capture("ideal") is None and parse_capture("realistic") == {}
    assert parse_capture("realistic:blur=0:response=linear") == {"blur": 0.0, "response": "linear"}
    # each capture gets its own cached scene; the plain ones keep their old folders
    dirs = {scene_dir(Path("/c"), "rock", "dark", 20, 200, c)
            for c in ("ideal", "realistic", "realistic:blur=0", "realistic:speckle=0")}
    assert len(dirs) == 4 and Path("/c/rock-dark20-200-realistic") in dirs and Path("/c/rock-dark20-200") in dirs
    for bad, says in (("foo", "unknown capture"), ("realistic:bogus=1", "capture.bogus"),
                      ("realistic:blur", "KEY=VALUE"), ("realistic:blur=99", "capture.blur")):
        with pytest.raises(SystemExit, match=says):
            parse_capture(bad)


def test_a_changed_effect_reaches_the_scene(tmp_path):
    from quality import make_scene

    sc = make_scene(tmp_path, "sphere", "dark", 2, 24, "cpu", tmp_path, capture="realistic:speckle=0")
    cap = sc.meta["capture"]
    assert cap["speckle"] == 0.0 and cap["blur"] == 0.7 and cap["response"] == "srgb"  # the rest of the mix
    assert sc.root.name == "sphere-dark2-24-realistic-speckle-0"
