"""scripts/threads_bench.py: the summary of interleaved runs (no timing: made-up step counts)."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))


def test_summary_pairs_rounds_and_takes_the_ratio_of_medians():
    from threads_bench import summarise

    rows = [{"round": 0, "threads": 1, "steps": 400, "chamfer_sym_mm": 10.0},
            {"round": 0, "threads": 2, "steps": 600, "chamfer_sym_mm": 9.0},
            {"round": 1, "threads": 1, "steps": 360, "chamfer_sym_mm": 11.0},
            {"round": 1, "threads": 2, "steps": 450, "chamfer_sym_mm": None},
            {"round": 2, "threads": 1, "steps": 440, "chamfer_sym_mm": 12.0},
            {"round": 2, "threads": 2, "steps": 700, "chamfer_sym_mm": 8.0}]
    one, two = summarise(rows, [1, 2])
    assert one["median steps"] == 400 and one["ratio of medians to 1"] == 1.0
    assert two["steps (per round)"] == "600 / 450 / 700"
    assert two["ratio to 1 (per round)"] == "1.50 / 1.25 / 1.59"      # each round against its own pair
    assert two["ratio of medians to 1"] == 1.5                          # 600 / 400
    assert two["median symmetric mm"] == 8.5                            # a run without metrics is left out


def test_bad_thread_list_is_one_line():
    from threads_bench import main

    with pytest.raises(SystemExit, match="--threads"):
        main(["/nonexistent", "--threads", "two"])
    with pytest.raises(SystemExit, match="--threads"):
        main(["/nonexistent", "--threads", "0,2"])
