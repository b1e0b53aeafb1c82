"""scripts/speed_compare.py end to end on CPU: a tiny sphere, 1-2 s budgets, small models.

No timing assertions: only that every method ran, was evaluated at every point and that the
JSON, Markdown table and plot were written.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    from fastneus.synth.render import synthesize

    out = tmp_path_factory.mktemp("scene") / "sphere3"
    synthesize(out, shape="sphere", views=3, size=(32, 32), seed=0, device="cpu", progress=False)
    return out


def test_speed_compare_cpu_end_to_end(tiny_scene, tmp_path):
    out = tmp_path / "sc"
    cmd = [sys.executable, str(ROOT / "scripts" / "speed_compare.py"), str(tiny_scene), "--device", "cpu",
           "--budgets", "1,2", "--out", str(out), "--no-md", "--no-isolate", "--threads", "1",
           "--mesh-res", "24", "--points", "2000", "--psnr-pixels", "64", "--extra-points", "1",
           "--breakdown", "--breakdown-steps", "3",
           "--set", "occ_resolution=32", "target_samples=4096", "init_rays=256", "max_rays=1024",
           "--baseline-set", "n_rays=64", "sdf_hidden=64", "color_hidden=64", "feature_dim=64",
           "n_samples=16", "n_importance=16"]
    env = dict(os.environ, PYTHONPATH=str(ROOT / "scripts") + os.pathsep + os.environ.get("PYTHONPATH", ""))
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    data = json.loads((out / "speed-compare-cpu.json").read_text())
    assert [x["method"] for x in data["results"]] == ["warp", "torch", "baseline"]
    for res in data["results"]:
        ts = [p["t_target"] for p in res["points"]]
        assert ts == [0.0, 1.0, 2.0]
        last = res["points"][-1]
        assert last["steps"] >= 1 and last["t"] >= 2.0 and last["peak_mem_mb"] > 0
        assert last["psnr"] > 0
        if res["method"] != "baseline":
            phases = {p["phase"] for p in res["breakdown"]["phases"]}
            assert {"marching", "hash encoding", "MLPs", "rendering", "optimiser"} <= phases
    assert len(data["rows"]) == 6 and data["target_chamfer_mm"] is not None
    md = (out / "speed-compare-cpu.md").read_text()
    assert "| method | budget_s |" in md and "ActiveNeuS baseline" in md
    assert (out / "chamfer-vs-time-cpu.png").stat().st_size > 1000


def test_speed_compare_wallclock_cpu(tiny_scene, tmp_path):
    """--wallclock: one `fastneus train` process per budget; the per-phase table from its metrics.json."""
    out = tmp_path / "wall"
    cmd = [sys.executable, str(ROOT / "scripts" / "speed_compare.py"), str(tiny_scene), "--device", "cpu",
           "--wallclock", "--budgets", "1", "--out", str(out), "--no-md", "--mesh-res", "24",
           "--set", "occ_resolution=32", "target_samples=4096", "init_rays=256", "max_rays=1024",
           "render_frames=[0]"]
    env = dict(os.environ, PYTHONPATH=str(ROOT / "scripts") + os.pathsep + os.environ.get("PYTHONPATH", ""))
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    data = json.loads((out / "wallclock-cpu.json").read_text())
    (row,) = data["rows"]
    # steps may be 0 on a loaded machine: the geometry init counts against the 1-s budget
    assert row["budget_s"] == 1.0 and row["preset"] == "cpu-quick" and isinstance(row["steps"], int)
    for k in ("startup", "scene_load", "imports", "setup", "kernels", "train", "mesh", "renders", "eval", "total"):
        assert row[k] >= 0, k
    assert 1.0 <= row["mesh_ready_s"] <= row["total"] <= row["process_s"]
    assert row["over_budget_s"] == pytest.approx(row["mesh_ready_s"] - 1.0, abs=1e-3)
    assert row["peak_rss_mb"] > 100 and row["mesh_detail"]["resolution"] == 24
    md = (out / "wallclock-cpu.md").read_text()
    assert "| phase | 1 s #0 |" in md and "**mesh_ready_s**" in md and "Mesh extraction detail" in md


@pytest.mark.parametrize("mode", ["fd", "analytic"])
def test_step_phases_time_the_real_step(tiny_scene, tmp_path, mode):
    """The breakdown wraps the real Trainer.train_step's parts: the step's result is unchanged
    (same loss and parameters as an untimed twin), every phase is seen, and the wrappers go."""
    import torch

    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        import benchutil
    finally:
        sys.path.pop(0)
    import fastneus.field.renderer as renderer
    from fastneus.data import Scene

    scene = Scene.load(tiny_scene)
    ov = ["backend=torch", f"sdf_grad={mode}", "occ_resolution=32", "init_rays=128", "steps=4", "occ_warmup_frac=0"]
    a = benchutil.make_trainer(scene, "cpu", ov, tmp_path / "a")
    b = benchutil.make_trainer(scene, "cpu", ov, tmp_path / "b")
    get_op, encode = renderer.get_op, b.field.encode
    for i in range(2):
        torch.manual_seed(i)  # the ray jitter draws from the global generator
        ra = a.train_step()
        torch.manual_seed(i)
        with benchutil.StepPhases(b) as sp:
            ms, wall, rb = sp.step()
        assert float(ra["loss"]) == pytest.approx(float(rb["loss"]), rel=1e-5)
    for pa, pb in zip(a.field.parameters(), b.field.parameters()):
        assert torch.allclose(pa, pb, rtol=1e-5, atol=1e-6)
    assert set(ms) == set(benchutil.PHASES) and wall > 0
    for p in ("ray generation", "marching", "hash encoding", "MLPs", "rendering", "loss + backward", "optimiser"):
        assert ms[p] > 0, p
    assert sum(ms.values()) == pytest.approx(wall, rel=1e-6)
    assert renderer.get_op is get_op and b.field.encode is encode and "sdf_and_grad" not in vars(b.field)
    res = benchutil.phase_breakdown({"b": b}, steps=2, warmup=0)["b"]
    assert [p["phase"] for p in res["phases"]] == list(benchutil.PHASES) and res["total_ms"] > 0
