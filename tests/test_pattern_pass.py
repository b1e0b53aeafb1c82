"""The projected light sampled in its own per-sample pass (``pattern_pass=split``, the CUDA
default) renders the same colours and gradients as the render kernel's fused per-ray sampling."""
from __future__ import annotations

import dataclasses

import pytest
import torch

from fastneus.config import load_config
from fastneus.field.renderer import pattern_pass_split, render_rays
from fastneus.train.trainer import Trainer
from test_formats import make_scene

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def test_auto_splits_on_cuda_only():
    cfg = load_config("cpu-quick", [])
    assert cfg.run.pattern_pass == "auto"
    assert pattern_pass_split(cfg, "cuda") and not pattern_pass_split(cfg, "cpu")
    assert pattern_pass_split(cfg.replace(pattern_pass="split"), "cpu")
    assert not pattern_pass_split(cfg.replace(pattern_pass="fused"), "cuda")


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("backend", ["warp", "torch"])
@pytest.mark.parametrize("pose", [False, True])
def test_split_matches_fused(tmp_path, device, backend, pose):
    scene = make_scene(tmp_path / "s", n=3, n_proj=2, seed=int(torch.randint(0, 1 << 30, (1,))), size=(32, 24))
    keys = [f"backend={backend}", "log_every=1000000", "save_every=100000000"] + (["pose_refine=true"] if pose else [])
    tr = Trainer(scene, load_config("cpu-quick", keys), tmp_path / "run", device)
    with torch.no_grad():  # a non-trivial field and pose corrections (the projector W gets gradients)
        tr.field.table.normal_(0, 0.05)
        if pose:
            tr.rig.cam_xi.normal_(0, 1e-2)
            tr.rig.proj_xi.normal_(0, 1e-2)
    raw = tr.bank.sample(96, torch.Generator(device=device).manual_seed(1))
    params = [p for p in tr.field.parameters() if p.requires_grad] + ([tr.rig.cam_xi, tr.rig.proj_xi] if pose else [])
    res = {}
    for mode in ("fused", "split"):
        cfg = tr.cfg.replace(pattern_pass=mode)
        batch, (i_r, i_b) = tr.rig.rays(raw), tr.illumination()  # fresh graphs per mode
        torch.manual_seed(7)  # same jitter
        out = render_rays(tr.field, tr.grid.bits, tr.grid.resolution, tr.rig.projection(), batch["origins"],
                          batch["dirs"], batch["fidx"], cfg, i_r=i_r, i_b=i_b, cos_anneal=0.5, jitter=True)
        g_up = torch.Generator(device=device).manual_seed(3)
        up = torch.randn(out["color"].shape, device=device, generator=g_up)
        loss = (out["color"] * up).sum() + out["opacity"].sum()
        grads = torch.autograd.grad(loss, params, allow_unused=True)
        res[mode] = (out["color"].detach(), [torch.zeros_like(p) if g is None else g for p, g in zip(params, grads)])
    assert out["n_samples"] > 100
    assert float(res["fused"][0].abs().max()) > 0.05  # lit: the pattern term is there
    torch.testing.assert_close(res["split"][0], res["fused"][0], atol=2e-5, rtol=1e-4)
    for gs, gf, p in zip(res["split"][1], res["fused"][1], params):
        scale = float(gf.abs().max()) + 1e-6
        torch.testing.assert_close(gs / scale, gf / scale, atol=2e-4, rtol=0)
    if pose:
        assert float(res["split"][1][-1].abs().max()) > 0  # the projector corrections get gradients
