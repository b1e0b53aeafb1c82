"""``run.matmul``: the training step's float32 GEMMs in TF32 on CUDA GPUs that have it.

CPU (always): the decision (auto is fp32 without CUDA; an explicit tf32 on the CPU is fp32),
the scoped flag (set inside, restored after, also on an error), and the run's record. CUDA
(where available): one training step's loss and gradients in TF32 against full float32 from
the same state and inputs, and the flag restored around the step.
"""
from __future__ import annotations

import json

import pytest
import torch

from conftest import SMALL_RUN, scene_on
from fastneus.config import load_config
from fastneus.train.precision import matmul_precision, resolve_matmul


def _flag() -> str:
    m = torch.backends.cuda.matmul
    return m.fp32_precision if hasattr(m, "fp32_precision") else str(m.allow_tf32)


def test_auto_is_fp32_without_cuda():
    cpu = torch.device("cpu")
    assert resolve_matmul("auto", cpu) == "fp32"
    assert resolve_matmul("tf32", cpu) == "fp32"  # the CPU has no TF32: asked or not
    assert resolve_matmul("fp32", cpu) == "fp32"
    assert load_config("fewview").run.matmul == "auto"


def test_the_flag_is_scoped_and_restored():
    before = _flag()
    with matmul_precision("tf32"):
        assert _flag() in ("tf32", "True")
        with matmul_precision("fp32"):
            assert _flag() in ("ieee", "False")
        assert _flag() in ("tf32", "True")
    assert _flag() == before
    with pytest.raises(ValueError):
        with matmul_precision("tf32"):
            raise ValueError("a step failed")
    assert _flag() == before  # restored on the way out of an error too


def test_run_json_records_the_decision(small_scene, tmp_path):
    from fastneus.cli import main

    run = tmp_path / "run"
    assert main(["train", str(small_scene), "--out", str(run), "--device", "cpu", "matmul=tf32"] + SMALL_RUN) == 0
    assert json.loads((run / "run.json").read_text())["matmul"] == "fp32"


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_tf32_step_matches_the_fp32_step_on_cuda(tmp_path):
    """Same parameters, same rays and samples: the loss agrees to TF32's rounding, and every
    parameter's gradient points the same way (cosine >= 0.999) at a similar size."""
    from fastneus.data import Scene
    from fastneus.field.renderer import march_samples
    from fastneus.train.trainer import Trainer

    cfg = load_config("fewview", SMALL_RUN + ["init_geometry=sphere", "cuda_graph=off"])
    sc = Scene.load(scene_on(None, tmp_path, "cuda"))  # rendered on the GPU (no CPU compiler needed)
    tr = Trainer(sc, cfg, tmp_path / "a", "cuda")
    gen = torch.Generator(device="cuda")
    gen.manual_seed(3)
    batch = tr.rig.rays(tr.bank.sample(512, gen, bright_fraction=0.5))
    xr = torch.rand(256, 3, device="cuda", generator=gen) * 2 - 1
    smp = march_samples(tr.grid.bits, tr.grid.resolution, batch["origins"], batch["dirs"], cfg)
    assert smp["n_samples"] > 0
    params = [q for g in tr.opt.param_groups for q in g["params"] if q.requires_grad]
    out = {}
    before = _flag()
    for mode in ("fp32", "tf32"):
        with matmul_precision(mode):
            loss, _ = tr.step_loss(batch, xr, smp, 0.5)
            grads = torch.autograd.grad(loss, params, allow_unused=True)
        out[mode] = (float(loss), grads)
    assert _flag() == before
    (l32, g32), (l19, g19) = out["fp32"], out["tf32"]
    assert abs(l19 - l32) <= 2e-3 * abs(l32) + 1e-6, (l32, l19)
    for a, b in zip(g32, g19):
        if a is None or float(a.norm()) == 0.0:
            continue
        cos = float(torch.nn.functional.cosine_similarity(a.flatten(), b.flatten(), dim=0))
        assert cos >= 0.999, cos
        assert 0.98 <= float(b.norm() / a.norm()) <= 1.02


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_a_cuda_train_step_leaves_the_flag_as_it_was(tmp_path):
    from fastneus.data import Scene
    from fastneus.train.trainer import Trainer

    cfg = load_config("fewview", SMALL_RUN + ["init_geometry=sphere"])
    tr = Trainer(Scene.load(scene_on(None, tmp_path, "cuda")), cfg, tmp_path / "a", "cuda")
    assert tr.matmul == ("tf32" if torch.cuda.get_device_capability()[0] >= 8 else "fp32")
    before = _flag()
    for _ in range(3):
        tr.train_step()
    assert _flag() == before
