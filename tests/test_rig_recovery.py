"""scripts/rig_recovery.py end to end at a toy size (the pose part): rows, JSON and Markdown."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_rig_recovery_pose_part_runs(tmp_path):
    out = tmp_path / "rr"
    cmd = [sys.executable, str(ROOT / "scripts" / "rig_recovery.py"), "--device", "cpu", "--out", str(out),
           "--parts", "pose", "--steps", "4", "--points", "3000", "--size", "16", "--views", "3", "--proj-size", "48x36",
           "mesh_resolution=24", "occ_resolution=16", "target_samples=2048", "init_rays=128", "max_rays=256"]
    env = dict(os.environ, PYTHONPATH=str(ROOT / "scripts") + os.pathsep + os.environ.get("PYTHONPATH", ""))
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    data = json.loads((out / "rig-recovery.json").read_text())
    runs = [row["run"] for row in data["rows"]]
    assert runs == ["exact poses", "perturbed, no refinement", "perturbed, pose_refine"], runs
    given = data["rows"][1]
    assert abs(given["cam_rot_deg_max"] - 0.5) < 1e-6 and abs(given["proj_trans_mm_max"] - 10.0) < 1e-6
    assert data["rows"][0]["cam_rot_deg_max"] == 0.0 and "target_met" in data["rows"][2]
    assert all(row["steps"] == 4 for row in data["rows"])
    md = (out / "rig-recovery.md").read_text()
    assert "| run | chamfer_sym_mm |" in md and "Pose refinement" in md
