"""scripts/budget_timeline.py: the split of a budgeted run's step time into steady steps and the
excess of slow ones by cause (no timing assertions: synthetic step times in, sums out), and a CPU
run end to end."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))


def test_summarise_splits_steady_and_excess_by_cause():
    from budget_timeline import summarise

    # 20 replays of 4 ms, every 8th (a grid update) 6 ms; step 10 an estimate of 504 ms, step 3 a
    # capture of 44 ms, step 5 counted (a sync) at 5 ms
    rows = [{"step": s, "s": 0.006 if s % 8 == 0 else 0.004, "kind": "replay", "rays": 64} for s in range(20)]
    rows[10]["s"] = 0.504
    rows[3].update(s=0.044, kind="capture")
    rows[5].update(s=0.005, kind="counted")
    r = summarise(rows, 20, 8, {"blur estimate": [10]}, top=2)
    assert r["calls"] == 20
    assert abs(r["median_ms"] - 4.0) < 1e-9  # of the plain replays only
    assert abs(r["steady_s"] - 0.080) < 1e-12
    assert abs(r["excess_s"] - (3 * 0.002 + 0.5 + 0.04 + 0.001)) < 1e-12
    by = r["by_cause"]
    assert by["grid update"]["calls"] == 3 and abs(by["grid update"]["excess_s"] - 0.006) < 1e-12  # 0, 8, 16
    assert by["blur estimate"]["calls"] == 1 and abs(by["blur estimate"]["excess_s"] - 0.5) < 1e-12
    assert abs(by["capture"]["excess_s"] - 0.04) < 1e-12 and abs(by["counted"]["excess_s"] - 0.001) < 1e-12
    assert by["other"]["calls"] == 20 - 3 - 1 - 1 - 1
    assert list(by)[0] == "blur estimate"  # largest first
    assert [s["step"] for s in r["slowest"]] == [10, 3]
    assert r["slowest"][0]["frac"] == 0.5 and r["slowest"][1]["kind"] == "capture"


def test_cpu_run_end_to_end(tmp_path):
    from fastneus.synth.render import synthesize

    scene = tmp_path / "scene"
    synthesize(scene, shape="sphere", views=3, size=(32, 32), proj_size=(64, 48), contact_sheet=False, progress=False)
    out = tmp_path / "bt"
    subprocess.run([sys.executable, str(ROOT / "scripts" / "budget_timeline.py"), str(scene), "--device", "cpu",
                    "--budget", "1", "--out", str(out), "hashgrid.log2_table=12", "hashgrid.finest_res=32"],
                   check=True, capture_output=True, text=True, timeout=300)
    res = json.loads((out / "budget-timeline.json").read_text())
    assert res["steps"] == res["calls"] == len(res["rows"]) > 0
    assert {r["kind"] for r in res["rows"]} == {"cpu"}
    assert abs(sum(v["calls"] for v in res["by_cause"].values()) - res["calls"]) == 0
    assert (out / "budget-timeline.md").is_file()
