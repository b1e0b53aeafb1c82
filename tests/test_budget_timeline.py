"""scripts/budget_timeline.py: the split of a budgeted run's step time into steady steps and the
excess of slow ones (no timing assertions: synthetic step times in, sums out)."""
from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))


def test_summarise_splits_steady_and_excess():
    from budget_timeline import summarise

    # 20 steps of 4 ms, every 8th (a grid update) 6 ms, step 10 an estimate of 504 ms
    rows = [(s, 0.006 if s % 8 == 0 else 0.004) for s in range(20)]
    rows[10] = (10, 0.504)
    r = summarise(rows, 20, {"grid update": 8}, top=2)
    assert r["calls"] == 20
    assert abs(r["median_ms"] - 4.0) < 1e-9
    assert abs(r["steady_s"] - 0.080) < 1e-12
    assert abs(r["total_s"] - (17 * 0.004 + 3 * 0.006 + 0.5)) < 1e-12
    assert abs(r["excess_s"] - (3 * 0.002 + 0.5)) < 1e-12
    assert r["by_period"]["grid update"]["calls"] == 3  # steps 0, 8, 16
    assert abs(r["by_period"]["grid update"]["excess_s"] - 0.006) < 1e-12
    assert abs(r["by_period"]["other"]["excess_s"] - 0.5) < 1e-12
    assert [s["step"] for s in r["slowest"]] == [10, 0]
    assert r["slowest"][0]["frac"] == 0.5
