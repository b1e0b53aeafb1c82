"""Multi-shot batching: one ray per viewpoint pixel carries all (or a sample of) its shots."""
from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from fastneus.config import load_config
from fastneus.errors import FastneusError
from fastneus.field.model import SDFField
from fastneus.field.renderer import render_rays
from fastneus.train.multishot import ShotBank, group_views, is_multishot, make_bank
from fastneus.train.rays import RayBank, build_projection
from fastneus.synth.render import synthesize


@pytest.fixture(scope="module")
def gray(tmp_path_factory):
    """2 viewpoints x 20 Gray-code shots, 24x20 px (projector 64x48: 6 + 6 bits -> 12 shots)."""
    out = tmp_path_factory.mktemp("ms") / "g"
    return synthesize(out, shape="torus", views=2, size=(24, 20), pattern="graycode", proj_size=(64, 48),
                      seed=2, progress=False)


def test_groups_and_sampling_all_shots(gray):
    frames = list(range(len(gray.frames)))
    assert is_multishot(gray, frames) and not is_multishot(gray, [0, 12])
    assert group_views(gray, frames) == [list(range(12)), list(range(12, 24))]
    bank = ShotBank(gray, frames, "cpu", shots=0, background=0.0)
    ref = RayBank(gray, frames, "cpu")
    assert bank.k == 12 and bank.rgb.shape == (2 * 24 * 20, 12, 3) and bank.rgb.dtype == torch.uint8
    g = torch.Generator().manual_seed(int(np.random.default_rng().integers(1 << 30)))
    b = bank.sample(300, g)
    view = b["pix"] // (24 * 20)
    assert b["fidx"].shape == (300, 12) and b["rgb"].shape == (300, 12, 3)
    torch.testing.assert_close(b["fidx"].long(), view[:, None] * 12 + torch.arange(12))
    # each shot's colour is that frame's pixel, and the ray is that frame's ray
    local = b["pix"] % (24 * 20)
    for k in (0, 5, 11):
        flat = ref.offset[b["fidx"][:, k].long()] + local
        torch.testing.assert_close(b["rgb"][:, k], ref.rgb[flat].float() / 255)
    o, d = ref.rays(b["fidx"][:, 3].long(), (local % 24).float() + 0.5, (local // 24).float() + 0.5)
    torch.testing.assert_close(b["origins"], o)
    torch.testing.assert_close(b["dirs"], d)
    # background = background in every shot; memory per view pixel, not per shot
    assert b["bg"].shape == (300,)
    every = torch.stack([ref.rgb[ref.offset[a]:ref.offset[a] + 480].amax(1) <= 2 for a in range(12)]).all(0)
    torch.testing.assert_close(bank.bg[:480], every)
    torch.testing.assert_close(bank.mean_rgb(), ref.mean_rgb())


def test_sampled_subset_of_shots(gray):
    frames = [j for j in range(len(gray.frames)) if j not in (3, 4)]  # view 0 keeps 10 shots, view 1 all 12
    bank = ShotBank(gray, frames, "cpu", shots=3, brightness_cdf=True)
    assert bank.k == 3 and bank.cdf.shape == (2 * 480,)
    g = torch.Generator().manual_seed(int(np.random.default_rng().integers(1 << 30)))
    b = bank.sample(2000, g, bright_fraction=0.5)
    view = (b["pix"] // 480)
    rows = b["fidx"].long()
    assert ((rows < 10) == (view[:, None] == 0)).all()   # a ray's shots are its own view's
    assert len(torch.unique(rows[view == 0])) == 10 and len(torch.unique(rows[view == 1])) == 12
    ref = RayBank(gray, frames, "cpu")
    flat = ref.offset[rows] + (b["pix"] % 480)[:, None]
    torch.testing.assert_close(b["rgb"], ref.rgb[flat].float() / 255)


def test_view_sharing_needs_one_pose(gray):
    bad = copy.copy(gray)
    bad.frames = [copy.deepcopy(f) for f in gray.frames]
    bad.frames[1].cam_to_world = bad.frames[12].cam_to_world
    with pytest.raises(FastneusError, match="share view"):
        group_views(bad, list(range(len(bad.frames))))


@pytest.mark.parametrize("backend", ["warp", "torch"])
def test_grouped_render_equals_per_shot_renders(gray, backend):
    """Rendering K shots over shared samples = K separate renders, in value and in gradient."""
    cfg = load_config("cpu-quick", [f"backend={backend}", "levels=4", "log2_table=12", "finest_res=64"])
    torch.manual_seed(int(np.random.default_rng().integers(1 << 30)))
    field = SDFField(cfg.hashgrid, cfg.network, "cpu", backend=cfg.run.backend)
    with torch.no_grad():
        field.table.normal_(0, 0.05)
    frames = list(range(len(gray.frames)))
    proj = build_projection(gray, frames, "cpu")
    bank = ShotBank(gray, frames, "cpu", shots=0)
    b = bank.sample(64, torch.Generator().manual_seed(0))
    bits = torch.ones(32 ** 3, dtype=torch.uint8)
    ir, ib = torch.tensor([0.4]), torch.tensor([0.1])
    kw = dict(i_r=ir, i_b=ib, cos_anneal=0.5, jitter=False)
    fid = b["fidx"][:, :5]
    out = render_rays(field, bits, 32, proj, b["origins"], b["dirs"], fid, cfg, **kw)
    assert out["color"].shape == (64, 5, 3) and out["n_samples"] > 0
    w = torch.rand(64, 5, 3)
    (out["color"] * w).sum().backward()
    g_grouped = field.table.grad.clone()
    field.zero_grad()
    total = 0.0
    for k in range(5):
        o = render_rays(field, bits, 32, proj, b["origins"], b["dirs"], fid[:, k].contiguous(), cfg, **kw)
        torch.testing.assert_close(o["color"], out["color"][:, k], rtol=1e-5, atol=1e-6)
        total = total + (o["color"] * w[:, k]).sum()
    total.backward()
    torch.testing.assert_close(field.table.grad, g_grouped, rtol=1e-4, atol=1e-6)
    # the shots differ: a Gray-code sequence lights different pixels
    assert (out["color"][:, 0] - out["color"][:, 4]).abs().max() > 1e-3


@pytest.mark.parametrize("mask_loss", ["bce", "mixed", "mixed mask_core=0.05"])  # mixed: each ray's minimum SDF under several shots
def test_trainer_uses_shot_bank_and_trains(gray, tmp_path, mask_loss):
    from fastneus.train.trainer import Trainer

    cfg = load_config("cpu-quick", ["steps=6", "occ_resolution=16", "target_samples=2048", "init_rays=64",
                                    "min_rays=32", "levels=4", "log2_table=12", "finest_res=64",
                                    *f"mask_loss={mask_loss}".split()])
    tr = Trainer(gray, cfg, tmp_path / "r", "cpu")
    assert isinstance(tr.bank, ShotBank) and tr.bank.k == 4
    assert tr.masks_used
    core = tr.bank.mask_core  # one flag per viewpoint pixel, like the mask
    assert (core is not None) is ("core" in mask_loss)
    assert core is None or (core.shape == tr.bank.mask.shape and bool(core.any()))
    for _ in range(6):
        tr.train_step()
    assert tr.step == 6 and tr.skipped == 0
    # the exposure estimate on rays that carry several shots: one value row per (ray, shot), every
    # photo's gain relative to the first
    from fastneus.train.exposure import estimate_exposure

    e = estimate_exposure(tr)
    assert len(e["log_gains"]) == len(tr.frames) and e["log_gains"][0] == 0.0 and e["rays"] > 0
    assert e["spread"] >= 0.0 and np.isfinite(e["log_gains"]).all()
    flat = load_config("cpu-quick", ["group_shots=false"])
    assert isinstance(make_bank(gray, [0, 1, 12], "cpu", flat), RayBank)
    # pose refinement indexes per-frame camera tables: it takes the per-frame bank
    assert isinstance(make_bank(gray, [0, 1, 12], "cpu", load_config("cpu-quick", ["pose_refine=true"])), RayBank)
    assert isinstance(make_bank(gray, [0, 1, 12], "cpu", load_config("cpu-quick")), ShotBank)
    with pytest.raises(FastneusError, match="shots_per_ray"):
        load_config("cpu-quick", ["shots_per_ray=-1"])


def test_geometry_init_from_decoded_gray_code(tmp_path):
    """init_geometry=auto on a one-view Gray-code scene: the SDF starts at the decoded surface."""
    from fastneus.train.geometry_init import decodable_views, decoded_points, initialise_geometry
    from fastneus.train.trainer import Trainer

    s = synthesize(tmp_path / "g1", shape="toy", views=1, size=(48, 48), pattern="graycode", seed=4, progress=False)
    assert decodable_views(s, list(range(20))) == [list(range(20))]
    assert decodable_views(s, list(range(19))) is None
    cfg = load_config("cpu-quick", ["levels=8", "log2_table=14", "init_geometry_steps=80"])
    tr = Trainer(s, cfg, tmp_path / "r", "cpu")
    dec = decoded_points(s, [list(range(20))])
    b = s.bounds
    P = torch.tensor((dec["points"] - b.center) / b.radius, dtype=torch.float32)
    D = torch.tensor(dec["dirs"], dtype=torch.float32)
    with torch.no_grad():
        before = tr.field.sdf(P).abs().mean()
    note = initialise_geometry(tr)
    assert note and "decoded Gray code" in note and tr.field.active_levels == cfg.hashgrid.levels
    with torch.no_grad():
        f0 = tr.field.sdf(P)
        f_front = tr.field.sdf(P - 0.03 * D)
    assert f0.abs().mean() < 0.25 * before and f0.abs().mean() < 0.01
    assert (f_front > 0).float().mean() > 0.9
    sphere = Trainer(s, load_config("cpu-quick", ["init_geometry=sphere"]), tmp_path / "r2", "cpu")
    assert initialise_geometry(sphere) is None
    with pytest.raises(FastneusError, match="init_geometry=decode"):
        initialise_geometry(Trainer(s, load_config("cpu-quick", ["init_geometry=decode", "frames=[0, 1]"]),
                                    tmp_path / "r3", "cpu"))
