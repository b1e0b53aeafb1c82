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


def test_seeds_run_each_cell_and_the_tables_use_their_mean():
    from quality import parse_seeds, summarise

    assert parse_seeds(None) == [None] and parse_seeds("0,1, 2") == [0, 1, 2]
    for bad in ("a,b", "1,1", ","):
        with pytest.raises(SystemExit, match="--seeds"):
            parse_seeds(bad)

    def row(sym, capture="ideal", **kw):
        return dict(variant="v", shape="rock", illum="dark", capture=capture, masks="on", budget=10.0, steps=100,
                    chamfer_gt2rec_mm=sym, chamfer_gt2rec_filtered_mm=sym, chamfer_rec2gt_mm=sym, chamfer_sym_mm=sym,
                    fscore=0.9, **kw)
    # seed 1 written by --seeds, seed 0 an older row whose seed is only in its overrides
    rows = [row(8.0, seed=1), row(6.0, overrides=["time_budget=10", "seed=0"]),
            row(4.0, capture="realistic", seed=0), row(6.0, capture="realistic", seed=1)]
    text, checks = summarise(rows, [10.0])
    grid, full = text.split("All metrics:")
    assert "mean over the seeds 0, 1" in grid
    assert "| rock | dark | ideal | on | 7 | 0.9 |" in grid and "| rock | dark | realistic | on | 5 | 0.9 |" in grid
    assert "| budget | seed | steps |" in full and full.count("| rock |") == 4
    assert "| ideal | on | 10 | 0 | 100 | 6 |" in full and "| ideal | on | 10 | 1 | 100 | 8 |" in full
    lo, med = checks["realistic sym / ideal sym (max, median)"]
    assert lo == pytest.approx(5.0 / 7.0) and med == pytest.approx(5.0 / 7.0)  # means, not one seed's pair
