"""scripts/step_profile.py: the interval union it reports GPU busy time with, and a CPU run end
to end (no timing assertions: only that the steps were profiled and the files written)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))


def test_union_of_intervals():
    from step_profile import _union_ms

    assert _union_ms([]) == 0.0
    # overlapping, nested, touching and disjoint intervals (microseconds in, milliseconds out)
    iv = [(0, 1000), (500, 1500), (600, 700), (1500, 2000), (3000, 3500)]
    assert abs(_union_ms(iv) - 2.5) < 1e-12
    assert abs(_union_ms(list(reversed(iv))) - 2.5) < 1e-12


def test_sync_site_names_the_innermost_own_frame():
    import traceback

    from step_profile import sync_site

    def fs(path, line, name):
        return traceback.FrameSummary(path, line, name)

    stack = [fs("/x/scripts/step_profile.py", 5, "main"), fs("/r/fastneus/train/trainer.py", 10, "train_step"),
             fs("/r/fastneus/train/occupancy.py", 355, "march_rays"), fs("/site/torch/_tensor.py", 99, "item")]
    assert sync_site(stack, "/site/torch/_tensor.py", 99) == "occupancy.py:355 in march_rays"
    stack[2] = fs("/r/kernels/march.py", 7, "count")
    assert sync_site(stack, "/site/torch/_tensor.py", 99) == "march.py:7 in count"
    # a user's folder called my_fastneus_runs is not fastneus' code
    other = [fs("/home/u/my_fastneus_runs/x.py", 1, "f"), fs("/site/torch/autograd/__init__.py", 1270, "backward")]
    assert sync_site(other, "/site/torch/autograd/__init__.py", 1270) == "__init__.py:1270 (outside fastneus)"


def test_sync_sites_counts_the_warnings_per_step(monkeypatch):
    import warnings

    import torch
    from step_profile import sync_sites

    modes = []
    monkeypatch.setattr(torch.cuda, "set_sync_debug_mode", modes.append)  # no CUDA here: the warnings by hand

    class Stepper:
        def train_step(self):
            for _ in range(2):
                warnings.warn("called a synchronizing CUDA operation")
            warnings.warn("something else")  # not a sync: not counted

    before = warnings.showwarning
    sites = sync_sites(Stepper(), 4)
    assert modes == ["warn", "default"] and warnings.showwarning is before
    # this test file is not fastneus' code: the site is the warning's own file and line
    assert len(sites) == 1 and sites[0]["per_step"] == 2.0 and sites[0]["site"].startswith("test_step_profile.py:")


def test_step_profile_cpu_end_to_end(tmp_path):
    from fastneus.synth.render import synthesize

    scene = tmp_path / "s"
    synthesize(scene, shape="sphere", views=2, size=(24, 24), seed=1, device="cpu", progress=False,
               contact_sheet=False)
    out = tmp_path / "sp"
    r = subprocess.run([sys.executable, str(ROOT / "scripts" / "step_profile.py"), str(scene), "--device", "cpu",
                        "--warm-steps", "2", "--steps", "2", "--out", str(out), "pattern_pass=split"],
                       capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    data = json.loads((out / "step-profile.json").read_text())
    assert data["steps"] == 2 and data["preset"] == "cpu-quick"
    assert data["args"]["overrides"] == ["pattern_pass=split"]
    m = data["median"]
    assert m["wall_ms"] > 0 and m["samples"] > 0 and m["kernels"] == 0  # no GPU: no device kernels
    assert "| wall_ms |" in (out / "step-profile.md").read_text()


def test_device_gaps_sum_idle_per_neighbour_pair():
    """Gaps between device ops are attributed to the ops either side; overlaps count as busy; gaps
    at most min_gap_us are only summed."""
    from step_profile import device_gaps

    ops = [(0.0, 10.0, "a"), (5.0, 12.0, "b"),        # overlap: busy 0-12
           (112.0, 120.0, "c"),                       # 100 us after b
           (123.0, 130.0, "a"),                       # 3 us: a small gap
           (230.0, 240.0, "b"), (340.0, 350.0, "c")]  # 100 us after a, then 100 us after b
    g = device_gaps(list(reversed(ops)), min_gap_us=5.0)
    assert abs(g["span_ms"] - 0.350) < 1e-9 and abs(g["busy_ms"] - 0.047) < 1e-9
    assert abs(g["idle_ms"] - 0.303) < 1e-9 and abs(g["small_gaps_ms"] - 0.003) < 1e-9 and g["n_gaps"] == 4
    by = {(r["after"], r["before"]): (r["count"], r["ms"]) for r in g["gaps"]}
    assert by == {("b", "c"): (2, 0.2), ("a", "b"): (1, 0.1)}
    assert device_gaps([])["span_ms"] == 0.0


def test_scoped_parts_show_in_the_profile_and_are_undone(tmp_path):
    """--trace names the host parts of a step in the profile; afterwards the trainer is as it was
    (no wrapper left on the instance, the module's march_samples restored)."""
    from benchutil import make_trainer
    from step_profile import _scoped, _unscope
    from torch.profiler import ProfilerActivity, profile

    from fastneus.data import Scene
    from fastneus.synth.render import synthesize
    from fastneus.train import trainer as trainer_mod

    scene = tmp_path / "s"
    synthesize(scene, shape="sphere", views=2, size=(24, 24), seed=1, device="cpu", progress=False,
               contact_sheet=False)
    tr = make_trainer(Scene.load(scene), "cpu", ["threads=1"], tmp_path / "run", "cpu-quick")
    march, sample = trainer_mod.march_samples, tr.bank.sample
    undo = _scoped(tr)
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        tr.train_step()
    _unscope(undo)
    names = {e.name for e in prof.events()}
    assert {"fastneus.march_samples", "fastneus.sample", "fastneus.compute", "fastneus.update_grid"} <= names
    assert trainer_mod.march_samples is march and "sample" not in vars(tr.bank) and "compute" not in vars(tr)
    assert tr.bank.sample == sample
    tr.train_step()


def test_gaps_by_scope_names_the_launching_part():
    """Each gap goes to the innermost annotated range around the launch of the op ending it;
    late_ms counts only the part of the gap after which the op was still not launched."""
    from step_profile import gaps_by_scope

    ev = [{"cat": "user_annotation", "name": "fastneus.step", "ts": 0, "dur": 1000, "tid": 1},
          {"cat": "user_annotation", "name": "fastneus.load", "ts": 100, "dur": 50, "tid": 1},
          {"cat": "kernel", "name": "k1", "ts": 0, "dur": 10, "args": {"correlation": 1}},
          {"cat": "cuda_runtime", "name": "cudaLaunchKernel", "ts": 0, "dur": 2, "tid": 1, "args": {"correlation": 1}},
          # launched inside load at 120 (+5 us of launch): the device idled from 10 to 130
          {"cat": "cuda_runtime", "name": "cudaMemcpyAsync", "ts": 120, "dur": 5, "tid": 1, "args": {"correlation": 2}},
          {"cat": "gpu_memcpy", "name": "Memcpy DtoD", "ts": 130, "dur": 10, "args": {"correlation": 2}},
          # launched early (at 50) but started late: a gap the host did not cause
          {"cat": "cuda_runtime", "name": "cudaLaunchKernel", "ts": 50, "dur": 2, "tid": 1, "args": {"correlation": 3}},
          {"cat": "kernel", "name": "k3", "ts": 200, "dur": 10, "args": {"correlation": 3}},
          {"cat": "kernel", "name": "k4", "ts": 212, "dur": 10, "args": {"correlation": 9}}]  # 2 us: not a gap
    rows = {r["scope"]: r for r in gaps_by_scope(ev, 5.0)}
    assert set(rows) == {"fastneus.load", "fastneus.step"}
    assert rows["fastneus.load"]["count"] == 1 and abs(rows["fastneus.load"]["ms"] - 0.120) < 1e-9
    assert abs(rows["fastneus.load"]["late_ms"] - 0.115) < 1e-9
    assert abs(rows["fastneus.step"]["ms"] - 0.060) < 1e-9 and rows["fastneus.step"]["late_ms"] == 0.0


def test_gemm_kernel_names():
    """--gemm-ops keeps cuBLAS / CUTLASS products (the names the H200 profiles show) and nothing else."""
    from step_profile import is_gemm_kernel

    for name in ("void cutlass::Kernel2<cutlass_80_simt_sgemm_64x64_8x5_nt_align1>(cutlass_80_simt_sgemm_64x",
                 "sm80_xmma_gemm_f32f32_f32f32_f32_tn_n_tilesize64x64x8_stage3_warpsize1x4x1_ffma_aligna4",
                 "std::enable_if<!(false), void>::type internal::gemvx::kernel<int, int, float, float>"):
        assert is_gemm_kernel(name)
    for name in ("_hash_jac_bwd_kernel_3a82b8dd_cuda_kernel_forward", "Memcpy DtoD (Device -> Device)",
                 "void at::native::vectorized_elementwise_kernel<4, at::native::sigmoid>"):
        assert not is_gemm_kernel(name)
