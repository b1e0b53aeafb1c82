"""Wall-clock phases from process start, peak memory, mesh first, lazy verb imports."""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

from fastneus import timing

ROOT = Path(__file__).resolve().parents[1]


def test_run_clock_phases_marks_and_table():
    c = timing.RunClock(time.perf_counter() - 1.0, "process start")
    with c.phase("scene_load"):
        time.sleep(0.02)
    with c.phase("mesh"):
        time.sleep(0.01)
    with c.phase("mesh"):                     # accumulates
        time.sleep(0.01)
    c.add("kernels", 0.5)
    at = c.mark("mesh_ready")
    c.notes["kernels_compiled"] = ["hashgrid"]
    s = c.summary()
    assert s["origin"] == "process start" and s["startup"] >= 0.99
    assert s["scene_load"] >= 0.02 and s["mesh"] >= 0.02 and s["kernels"] == 0.5
    assert s["mesh_ready_at"] == round(at, 3) <= s["total"]
    assert s["notes"] == {"kernels_compiled": ["hashgrid"]} and s["other"] >= 0
    text = timing.table(s)
    assert "scene_load" in text and "mesh_ready at" in text and text.index("startup") < text.index("mesh ")


def test_process_age_and_cli_clock():
    age = timing.process_age()
    if sys.platform.startswith("linux"):
        assert age is not None and 0 <= age < 3600
    timing.begin_cli_run(from_process_start=True)
    c = timing.take_clock()
    assert c.source == "process start" and c.now() >= (age or 0) - 0.05
    assert timing.take_clock().source == "run start"   # taken once; then a fresh clock
    timing.begin_cli_run(from_process_start=False)
    assert timing.take_clock().now() < 1.0


def test_peak_memory_on_cpu():
    m = timing.peak_memory("cpu")
    assert m["peak_rss_mb"] > 10 and "peak_gpu_mb" not in m


def test_verb_table_matches_the_registered_verbs():
    from fastneus.cli import VERBS, build_parser

    p = build_parser()
    sub = next(a for a in p._actions if a.__class__.__name__ == "_SubParsersAction")
    assert set(sub.choices) == set(VERBS)
    for verb in VERBS:
        one = build_parser([verb, "--help"])
        s1 = next(a for a in one._actions if a.__class__.__name__ == "_SubParsersAction")
        assert verb in s1.choices


def test_parsing_train_imports_nothing_heavy():
    code = ("import sys; from fastneus.cli import build_parser; build_parser(['train', 'x']); "
            "print(sorted(m for m in ('torch', 'trimesh', 'scipy', 'warp', 'skimage') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_cli_train_times_each_phase_from_process_start(small_scene, tmp_path):
    from conftest import SMALL_RUN

    run = tmp_path / "run"
    # record what is imported when mesh.ply is written: no evaluation module, trimesh or scipy KD-tree yet
    code = (
        "import sys\n"
        "import fastneus.export.mesh as M\n"
        "orig = M.save_mesh\n"
        "def spy(mesh, path):\n"
        "    seen = sorted(m for m in ('fastneus.eval.metrics', 'fastneus.eval.report', 'trimesh', "
        "'scipy.spatial') if m in sys.modules)\n"
        "    print('AT_MESH', seen)\n"
        "    return orig(mesh, path)\n"
        "M.save_mesh = spy\n"
        "from fastneus.cli import main\n"
        "sys.exit(main())\n")
    cmd = [sys.executable, "-c", code, "train", str(small_scene), "--out", str(run), "--device", "cpu"] + SMALL_RUN
    env = dict(os.environ, COLUMNS="200")
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    line = next(x for x in r.stdout.splitlines() if x.startswith("AT_MESH"))
    assert line == "AT_MESH []", line
    assert "wall clock from process start: mesh.ply at" in r.stdout and "peak RSS" in r.stdout
    m = json.loads((run / "metrics.json").read_text())
    t = m["timing"]
    assert t["origin"] == "process start"
    for k in ("startup", "scene_load", "imports", "setup", "kernels", "train", "checkpoint", "mesh", "renders",
              "eval", "report", "other", "total", "mesh_ready_at"):
        assert k in t and t[k] >= 0, k
    assert t["startup"] > 0.05 and t["mesh_ready_at"] <= t["total"]
    parts = sum(v for k, v in t.items() if isinstance(v, float) and not k.endswith("_at") and k != "total")
    assert abs(parts - t["total"]) < 0.05 * t["total"] + 0.05
    assert isinstance(t["notes"]["kernels_compiled"], list) and t["notes"]["mesh"]["points"] > 0
    assert m["peak_rss_mb"] > 100
    meta = json.loads((run / "run.json").read_text())
    assert meta["timing"]["total"] == t["total"] and meta["peak_rss_mb"] == m["peak_rss_mb"]
    assert meta["scene"] and meta["preset"]                          # what train_scene wrote first is kept
    renders = sorted((run / "renders").glob("*.png"))
    assert renders and (run / "mesh.ply").stat().st_mtime <= min(p.stat().st_mtime for p in renders)
    assert (run / "checkpoint.pt").is_file()
    page = (run / "report.html").read_text()
    assert "Wall clock (seconds from process start)" in page and "mesh_ready_at" in page and "{&#x27;" not in page


def _spin_after_import(env_extra: dict) -> str:
    env = {k: v for k, v in os.environ.items() if k not in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY")}
    env.update(env_extra)
    code = "import os, fastneus, sys; print(os.environ.get('GOMP_SPINCOUNT'), 'torch' in sys.modules)"
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                          env=env).stdout.split()


def test_import_shortens_openmp_spin_before_torch_loads():
    # torch's libgomp reads GOMP_SPINCOUNT when it loads: fastneus must set it on import, while
    # torch is not loaded yet, and leave a user's own OpenMP settings alone
    assert _spin_after_import({}) == ["30000", "False"]
    assert _spin_after_import({"GOMP_SPINCOUNT": "7"})[0] == "7"
    assert _spin_after_import({"OMP_WAIT_POLICY": "ACTIVE"})[0] == "None"


def test_scripts_import_fastneus_before_torch():
    # a benchmark that loads torch first runs its CPU ops with libgomp's long default spin, which
    # holds the core the Warp kernels' second thread needs: its thread numbers would not be the
    # product's (2026-11-28: step_profile, speed_compare and quality.py all did)
    import ast

    scripts = Path(__file__).resolve().parents[1] / "scripts"
    late = []
    for p in sorted(scripts.glob("*.py")):
        first = {}
        for node in ast.parse(p.read_text()).body:  # module-level imports, in order
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            for n in names:
                root = n.split(".")[0]
                if root in ("torch", "fastneus", "benchutil"):
                    first.setdefault(root, node.lineno)
        fast = min((first[k] for k in ("fastneus", "benchutil") if k in first), default=None)
        if "torch" in first and (fast is None or fast > first["torch"]) and p.name != "benchutil.py":
            late.append(p.name)
        if p.name == "benchutil.py" and "torch" in first and first.get("fastneus", 10**9) > first["torch"]:
            late.append(p.name)
    assert not late, f"import fastneus before torch in: {late}"


def _simulated_run(budget: float, host: float, device: float, log_every: int, predict: bool):
    """The fit loop's clock against a device that runs ``device`` s per step while the host
    enqueues in ``host`` s: a sync waits for the queue. Returns (steps, host elapsed at the end,
    the time the device finishes its queue)."""
    from fastneus.train.trainer import BudgetSync

    sync_ctl = BudgetSync(budget)
    wall = dev_done = elapsed = 0.0
    step = 0
    sync_ctl.synced(step, elapsed)
    while elapsed < budget:
        t0 = wall
        wall += host
        dev_done = max(dev_done, t0) + device     # the step runs once the device is free
        step += 1
        sync = step % log_every == 0 or (predict and sync_ctl.due(step))
        if sync:
            wall = max(wall, dev_done)
        elapsed += wall - t0
        if sync:
            sync_ctl.synced(step, elapsed)
    return step, elapsed, dev_done


def test_budget_sync_ends_a_budgeted_run_on_the_device_not_the_host():
    """Between syncs the host runs ahead of the device; a budget checked on the host alone lets
    the device run up to log_every steps past it (before mesh.ply). BudgetSync's prediction
    syncs as the budget nears, so the device stops within about a step of it."""
    from fastneus.train.trainer import BudgetSync

    host, device = 0.001, 0.006
    for budget, log_every in ((3.13, 50), (5.0, 37), (2.93, 50)):
        _, _, late = _simulated_run(budget, host, device, log_every, predict=False)
        steps, elapsed, on_time = _simulated_run(budget, host, device, log_every, predict=True)
        assert late - budget > 0.05                  # the old loop: tens of queued steps past the budget
        assert on_time - budget <= device + 1e-9     # at most the one step that crosses it
        assert abs(elapsed - on_time) < 1e-9         # the run's clock is the device's at the end
        assert steps == math.ceil(budget / device - 1e-9)
    b = BudgetSync(2.0)
    assert not b.due(10**6)                          # no rate yet: only the log syncs
    b.synced(0, 0.0)
    b.synced(50, 1.0)                                # 0.02 s per step
    assert not b.due(99) and b.due(100)
    assert not BudgetSync(0.0).due(10**6)            # a step-count run never syncs for it
