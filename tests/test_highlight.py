"""The projected light's learned highlight (``network.highlight``): the colour MLP's fourth output
e >= 0 at each sample, added to i_b there (c = D + (i_r D + i_b + e) Q), and its L1 penalty on
each ray's rendered highlight (``loss.highlight_weight``). The render kernel's part is tested
in test_render.py (the op against its twin, gradcheck); here: the field, the renderer's
per-ray highlight and what its penalty may move, the trainer's loss term and a checkpoint."""
from __future__ import annotations

import pytest
import torch

from conftest import SMALL_RUN
from fastneus.config import load_config
from fastneus.data import Scene
from fastneus.field.model import HIGHLIGHT_BIAS


def _trainer(scene_dir, tmp_path, extra=()):
    from fastneus.train.trainer import Trainer

    cfg = load_config("cpu-quick", SMALL_RUN + ["threads=1", "init_geometry=sphere", "cuda_graph=off",
                                                "network.highlight=true"] + list(extra))
    return Trainer(Scene.load(scene_dir), cfg, tmp_path / "r", "cpu")


def test_shade_gives_the_colour_and_a_small_non_negative_highlight(small_scene, tmp_path):
    tr = _trainer(small_scene, tmp_path)
    f = tr.field
    gen = torch.Generator().manual_seed(0)
    x = torch.rand(500, 3, generator=gen) - 0.5
    sdf, geo, grad, _ = f.sdf_and_grad(x)
    dirs = torch.nn.functional.normalize(torch.randn(500, 3, generator=gen), dim=-1)
    D, e = f.shade(x, grad, dirs, geo)
    assert D.shape == (500, 3) and e.shape == (500,)
    assert torch.equal(f.color(x, grad, dirs, geo), D)
    # no glint at the start, whatever the colour bias was set to from the photos
    assert float(e.detach().min()) >= 0.0 and float(e.detach().max()) < 0.05
    assert float(f.color_net[-1].bias.detach()[3]) == pytest.approx(HIGHLIGHT_BIAS)
    f.init_color_bias([0.2, 0.5, 0.7])
    assert float(f.color_net[-1].bias.detach()[3]) == pytest.approx(HIGHLIGHT_BIAS)
    # off: the three-channel network and no highlight
    import dataclasses

    from fastneus.field.model import SDFField

    off = SDFField(tr.cfg.hashgrid, dataclasses.replace(tr.cfg.network, highlight=False), "cpu")
    assert off.color_net[-1].out_features == 3 and off.shade(x, grad, dirs, off.sdf_and_grad(x)[1])[1] is None


def test_the_penalty_reaches_the_highlight_but_not_the_geometry(small_scene, tmp_path):
    """Each ray's rendered highlight sum_i w_i e_i, with the weights held: its penalty lowers e,
    it does not make the surface more transparent to hide a glint."""
    from fastneus.field.renderer import march_samples, shade_samples

    tr = _trainer(small_scene, tmp_path)
    batch = tr.rig.rays(tr.bank.sample(128, tr.gen))
    smp = march_samples(tr.grid.bits, tr.grid.resolution, batch["origins"], batch["dirs"], tr.cfg)
    assert smp["n_samples"] > 0
    i_r, i_b = tr.illumination()
    out = shade_samples(tr.field, smp, tr.rig.projection(), batch["origins"], batch["dirs"], batch["fidx"], tr.cfg,
                        i_r=i_r, i_b=i_b, cos_anneal=1.0)
    h = out["highlight"]
    assert h.shape == (128,) and float(h.min()) >= 0.0 and float(h.sum()) > 0.0
    tr.field.zero_grad(set_to_none=True)
    h.mean().backward()
    # the weights are held: nothing reaches the NeuS sharpness, which acts only through them (the
    # surface's normal and features still feed e, as they feed the colour)
    assert tr.field.variance.grad is None or float(tr.field.variance.grad.abs().max()) == 0.0
    assert float(tr.field.color_net[-1].weight.grad[3].abs().sum()) > 0.0
    assert float(tr.field.color_net[-1].weight.grad[:3].abs().sum()) == 0.0  # the colour channels untouched


def test_the_trainer_adds_the_term_and_the_checkpoint_keeps_the_fourth_output(small_scene, tmp_path):
    from fastneus.field.renderer import march_samples

    tr = _trainer(small_scene, tmp_path, ["loss.highlight_weight=0.5"])
    batch = tr.rig.rays(tr.bank.sample(128, tr.gen))
    xr = torch.rand(64, 3, generator=tr.gen) * 2 - 1
    smp = march_samples(tr.grid.bits, tr.grid.resolution, batch["origins"], batch["dirs"], tr.cfg)
    loss, terms = tr.step_loss(batch, xr, smp, 0.5)
    assert "highlight" in terms and float(terms["highlight"]) == pytest.approx(0.5 * float(terms["spec"]), rel=1e-5)
    assert float(terms["spec"]) > 0
    tr0 = _trainer(small_scene, tmp_path / "w0", ["loss.highlight_weight=0"])
    tr0.field.load_state_dict(tr.field.state_dict())
    _, t0 = tr0.step_loss(batch, xr, smp, 0.5)
    assert "highlight" not in t0
    tr.fit()
    from fastneus.train.trainer import trainer_from_run

    back = trainer_from_run(Scene.load(small_scene), tmp_path / "r", "cpu")
    assert back.field.highlight and back.field.color_net[-1].out_features == 4
    for k, v in tr.field.state_dict().items():
        assert torch.equal(v, back.field.state_dict()[k]), k
