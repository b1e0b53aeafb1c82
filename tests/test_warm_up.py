"""Trainer.warm_up (run by Trainer.prime before the clock on CUDA) changes nothing.

It runs the first step's loss and backward once so that CUDA's lazy module loading, cuBLAS and
autograd set themselves up outside a time budget. A run with it must train exactly as one
without: the same parameters, no gradients left behind, the optimizer's state, the occupancy grid,
the run's generator and torch's global random stream untouched, and the next steps identical.
"""
from __future__ import annotations

import pytest
import torch

from conftest import SMALL_RUN, scene_on
from fastneus.config import load_config
from fastneus.data import Scene

def _trainers(scene_dir, tmp_path, device):
    from fastneus.train.trainer import Trainer

    cfg = load_config("cpu-quick", SMALL_RUN + ["threads=1", "cuda_graph=off", "curvature_weight=0.001"])
    sc = Scene.load(scene_dir)
    a, b = Trainer(sc, cfg, tmp_path / "a", device), Trainer(sc, cfg, tmp_path / "b", device)
    b.field.load_state_dict(a.field.state_dict())
    b.gen.set_state(a.gen.get_state())
    return a, b


def _snapshot(tr):
    params = [q.detach().clone() for g in tr.opt.param_groups for q in g["params"]]
    grads = [q.grad for g in tr.opt.param_groups for q in g["params"]]
    state = {k: {n: (v.clone() if torch.is_tensor(v) else v) for n, v in st.items()}
             for k, st in tr.opt.state.items()} if hasattr(tr.opt, "state") else {}
    return params, grads, state, tr.gen.get_state().clone(), tr.grid.bits.clone(), tr.n_rays, tr.step


def test_warm_up_changes_nothing_and_the_run_trains_the_same(small_scene, tmp_path):
    _check(small_scene, tmp_path, "cpu")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_warm_up_changes_nothing_and_the_run_trains_the_same(tmp_path):
    _check(scene_on(None, tmp_path, "cuda"), tmp_path, "cuda")


def _check(scene_dir, tmp_path, device):
    a, b = _trainers(scene_dir, tmp_path, device)
    before = _snapshot(a)
    torch.manual_seed(123)
    cpu_rng = torch.get_rng_state()
    cuda_rng = torch.cuda.get_rng_state(a.device) if device == "cuda" else None
    a.warm_up()
    after = _snapshot(a)
    for x, y in zip(before[0], after[0]):
        assert torch.equal(x, y), "warm_up moved a parameter"
    assert all(g is None for g in after[1]), "warm_up left a gradient behind"
    assert before[2].keys() == after[2].keys()
    for k in before[2]:
        for n, v in before[2][k].items():
            w = after[2][k][n]
            assert torch.equal(v, w) if torch.is_tensor(v) else v == w, f"optimizer state {n} changed"
    assert torch.equal(before[3], after[3]), "warm_up drew from the run's generator"
    assert torch.equal(before[4], after[4]) and before[5:] == after[5:]
    assert torch.equal(cpu_rng, torch.get_rng_state()), "warm_up drew from torch's global stream"
    if cuda_rng is not None:
        assert torch.equal(cuda_rng, torch.cuda.get_rng_state(a.device))

    # the next steps: the same losses and parameters as a trainer that never warmed up
    losses = {}
    for name, tr in (("a", a), ("b", b)):
        torch.manual_seed(7)  # the march's jitter draws from torch's global stream
        losses[name] = [float(r["loss"]) for r in (tr.train_step() for _ in range(3)) if r is not None]
    assert len(losses["a"]) == 3
    if device == "cpu":
        assert losses["a"] == losses["b"]
        for x, y in zip(_snapshot(a)[0], _snapshot(b)[0]):
            assert torch.equal(x, y)
    else:  # CUDA's float atomics sum in a different order on every run
        torch.testing.assert_close(torch.tensor(losses["a"]), torch.tensor(losses["b"]), rtol=1e-4, atol=1e-6)


def test_prime_skips_the_warm_up_on_the_cpu(small_scene, tmp_path, monkeypatch):
    """On the CPU there is no lazy loading to move out of the budget: prime does not warm up."""
    from fastneus.train.trainer import Trainer

    a, _ = _trainers(small_scene, tmp_path, "cpu")
    called = []
    monkeypatch.setattr(Trainer, "warm_up", lambda self: called.append(1))
    a.prime()
    assert called == []
