"""scripts/split_overhead.py: arguments and the result file (no timing asserted)."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))


def test_bad_arguments_are_one_line():
    from split_overhead import main

    with pytest.raises(SystemExit, match="--sizes"):
        main(["--sizes", "many"])
    with pytest.raises(SystemExit, match="--sizes"):
        main(["--sizes", "0,64"])
    with pytest.raises(SystemExit, match="--threads"):
        main(["--threads", "1"])


def test_writes_rows_for_every_size_with_provenance(tmp_path):
    from split_overhead import main

    res = main(["--sizes", "64,256", "--repeat", "1", "--out", str(tmp_path)])
    assert [r["points"] for r in res["rows"]] == [64, 256]
    saved = json.loads((tmp_path / "split-overhead.json").read_text())
    assert {"machine", "git", "command", "pool_round_trip_ms", "rows"} <= set(saved)
    assert saved["rows"][1]["hash 2 threads ms"] > 0 and saved["rows"][1]["exp speed-up"] > 0
    assert "split_overhead.py" in saved["command"]
    assert (tmp_path / "split-overhead.md").read_text().startswith("# What one split CPU launch costs")
