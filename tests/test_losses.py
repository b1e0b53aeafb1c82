"""Each loss term on hand-made tensors: known values, zero weight, gradients flow, fixed sum order."""
from __future__ import annotations

import math

import numpy as np

import pytest
import torch

from fastneus.train import losses


def test_photometric_is_mean_l1():
    pred = torch.tensor([[0.5, 0.5, 0.5], [1.0, 0.0, 0.2]], requires_grad=True)
    t = losses.photometric(pred, torch.tensor([[0.25, 0.5, 1.0], [1.0, 0.5, 0.2]]))
    assert t["rgb"].item() == pytest.approx((0.25 + 0 + 0.5 + 0 + 0.5 + 0) / 6)
    t["rgb"].backward()
    assert pred.grad.abs().sum() > 0


def test_eikonal_zero_on_unit_gradients_and_weighted():
    g = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.6, 0.8]])
    assert losses.eikonal(g, 0.1)["eikonal"].item() == pytest.approx(0.0, abs=1e-12)
    g2 = torch.tensor([[2.0, 0.0, 0.0]], requires_grad=True)
    t = losses.eikonal(g2, 0.1)
    assert t["eik"].item() == pytest.approx(1.0) and t["eikonal"].item() == pytest.approx(0.1)
    assert not t["eik"].requires_grad  # the log value is not a second path into the graph
    t["eikonal"].backward()
    assert g2.grad[0, 0].item() == pytest.approx(0.1 * 2 * (2 - 1))


def test_mask_bce_matches_the_formula_and_clamps():
    op = torch.tensor([0.9, 0.0])
    m = torch.tensor([1.0, 0.0])
    expect = -(math.log(0.9) + math.log(1 - 1e-3)) / 2
    assert losses.mask_bce(op, m, 2.0)["mask"].item() == pytest.approx(2.0 * expect, rel=1e-5)


DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("backend", ["warp", "torch"])
@pytest.mark.parametrize("n", [300, 6000])  # 6000 rays (~24 k samples): the CPU launch is split in chunks
def test_ray_min_matches_a_loop_and_leaves_out_the_padding(device, backend, n):
    """renderer.ray_min (the ray_argmin op of either backend, then a gather) against a per-ray
    loop on fresh random rays (some without samples, some with equal values), with padding
    samples past every ray whose stale ray index points at real rays and whose value is below
    all others; a random upstream gradient reaches exactly each ray's minimum sample (the first
    of equals)."""
    from fastneus.field.renderer import ray_min
    from fastneus.kernels import get_op

    g = torch.Generator().manual_seed(int(torch.randint(0, 2**31 - 1, (1,))))
    counts = torch.randint(0, 9, (n,), generator=g, dtype=torch.int32)
    offsets = (torch.cumsum(counts, 0) - counts).to(torch.int32)
    live = int(counts.sum())
    pad = 17
    ri = torch.cat([torch.repeat_interleave(torch.arange(n), counts.long()),
                    torch.randint(0, n, (pad,), generator=g)]).to(torch.int32)
    v = torch.cat([torch.randint(-20, 20, (live,), generator=g).float() / 4, torch.full((pad,), -50.0)])
    args = (ri.to(device), offsets.to(device), counts.to(device))
    vd = v.to(device, copy=True).requires_grad_()
    m, has = ray_min(vd, *args, backend=backend)
    # a gather, not an indexing: on CUDA the indexing's backward walks the empty rays' repeated
    # index serially (perf note 32: 1.4 ms of a 5-ms step)
    assert [type(f).__name__ for f, _ in m.grad_fn.next_functions if f is not None] == ["GatherBackward0"]
    up = torch.randn(n, generator=g)
    m.backward(up.to(device))
    m = m.detach().cpu()
    want_grad = torch.zeros(live + pad)
    for r in range(n):
        a, c = int(offsets[r]), int(counts[r])
        if c == 0:
            assert float(m[r]) == 0.0 and float(has[r]) == 0.0
            continue
        seg = v[a:a + c]
        assert float(m[r]) == float(seg.min()) and float(has[r]) == 1.0
        want_grad[a + int((seg == seg.min()).nonzero()[0])] = up[r]
    assert torch.equal(vd.grad.cpu(), want_grad)
    # the two backends' indices agree exactly
    assert torch.equal(get_op("ray_argmin", "warp")(v.to(device), *args),
                       get_op("ray_argmin", "torch")(v.to(device), *args))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("shots", [None, 3])
def test_exposure_gain_per_ray_and_its_gradient(device, shots):
    """Each ray's gain is its frame's exp(log gain) (the first frame's 1), shaped [B, 1] or
    [B, K, 1]; under a random upstream gradient each learned log gain gets the sum over its
    frame's rays of gain * upstream (against a per-frame loop), by a selection whose backward
    adds (not the indexing's serial walk over repeats on CUDA, perf note 32)."""
    g0 = torch.Generator().manual_seed(int(torch.randint(0, 2**31 - 1, (1,))))
    lg = (torch.randn(5, generator=g0) * 0.2).to(device).requires_grad_()
    shape = (4000,) if shots is None else (4000, shots)
    fidx = torch.randint(0, 6, shape, generator=g0).to(device, torch.int32)
    up = torch.randn(*shape, 1, generator=g0).to(device)
    gain = losses.exposure_gain(lg, fidx)
    assert gain.shape == (*shape, 1)
    full = torch.cat([torch.zeros(1), lg.detach().cpu()]).exp()
    assert torch.allclose(gain.detach().cpu(), full[fidx.cpu().long()].unsqueeze(-1))
    (gain * up).sum().backward()
    fc, uc = fidx.cpu().long(), up.cpu().squeeze(-1)
    want = torch.stack([(uc[fc == f]).sum() * full[f] for f in range(1, 6)])
    torch.testing.assert_close(lg.grad.cpu(), want, rtol=1e-4, atol=1e-4)


def test_mask_silhouette_pulls_only_rays_on_the_wrong_side():
    """sdf: a mask ray that enters the object and a background ray that does not cost nothing;
    the others cost inv_s * |min sdf| (mean over rays, weighted), with the gradient pushing
    the mask ray's minimum down and the background ray's up; rays without samples cost nothing.
    mixed: background pixels by the BCE on the opacity instead."""
    m = torch.tensor([-0.1, 0.2, 0.3, -0.4, 0.5], requires_grad=True)
    has = torch.tensor([1.0, 1.0, 1.0, 1.0, 0.0])
    mask = torch.tensor([1.0, 1.0, 0.0, 0.0, 1.0])
    op = torch.tensor([0.9, 0.1, 0.2, 0.5, 0.0], requires_grad=True)
    s = torch.tensor([10.0], requires_grad=True)
    t = losses.mask_silhouette(m, has, op, mask, 0.5, s, "sdf")["mask"]
    assert t.item() == pytest.approx(0.5 * 10.0 * (0.2 + 0.4) / 5)
    t.backward()
    assert m.grad.tolist() == pytest.approx([0.0, 1.0, 0.0, -1.0, 0.0])
    assert op.grad is None and s.grad is None  # the sharpness scales, it is not trained by the mask
    m.grad = None
    t = losses.mask_silhouette(m, has, op, mask, 0.5, s, "mixed")["mask"]
    want = 0.5 * (10.0 * 0.2 / 5 - (math.log(1 - 0.2) + math.log(1 - 0.5)) / 5)
    assert t.item() == pytest.approx(want)
    t.backward()
    assert m.grad.tolist() == pytest.approx([0.0, 1.0, 0.0, 0.0, 0.0])
    assert op.grad[2] > 0 and op.grad[3] > 0 and op.grad[0] == 0 and op.grad[1] == 0


def test_mask_silhouette_core_pixels_are_held_by_opacity():
    """With a core flag: a core mask pixel costs -log(opacity) and never the hinge (even with a
    positive minimum SDF); a rim mask pixel keeps the hinge; background pixels are unchanged."""
    m = torch.tensor([0.3, 0.2, 0.3, -0.4], requires_grad=True)
    has = torch.ones(4)
    mask = torch.tensor([1.0, 1.0, 0.0, 0.0])
    core = torch.tensor([1.0, 0.0, 0.0, 0.0])
    op = torch.tensor([0.25, 0.1, 0.2, 0.5], requires_grad=True)
    s = torch.tensor(10.0)
    t = losses.mask_silhouette(m, has, op, mask, 0.5, s, "mixed", core)["mask"]
    want = 0.5 * (10.0 * 0.2 / 4 - (math.log(1 - 0.2) + math.log(1 - 0.5)) / 4 - math.log(0.25) / 4)
    assert t.item() == pytest.approx(want)
    t.backward()
    assert m.grad.tolist() == pytest.approx([0.0, 0.5 * 10.0 / 4, 0.0, 0.0])
    assert op.grad[0].item() == pytest.approx(-0.5 / (4 * 0.25)) and op.grad[1] == 0
    # no core pixel: the same as without the flag
    a = losses.mask_silhouette(m, has, op, mask, 0.5, s, "sdf", torch.zeros(4))["mask"]
    b = losses.mask_silhouette(m, has, op, mask, 0.5, s, "sdf")["mask"]
    assert a.item() == pytest.approx(b.item())


def test_mask_core_erodes_each_frame_on_its_own():
    """The core is the mask eroded by px (a square), per frame, the image border not eroding."""
    from fastneus.train.rays import mask_core

    a = np.zeros((6, 8), np.uint8)
    a[1:6, 2:7] = 255                      # a 5 x 5 block touching the bottom border
    b = np.full((4, 5), 255, np.uint8)     # a frame all mask
    flat = torch.from_numpy(np.concatenate([a.reshape(-1), b.reshape(-1)]))
    core = mask_core(flat, torch.tensor([[8, 6], [5, 4]]), 0.1)  # 1 px on both frames (0.8 and 0.5 round up to 1)
    ca, cb = core[:48].view(6, 8).numpy(), core[48:].view(4, 5).numpy()
    want = np.zeros((6, 8), bool)
    want[2:6, 3:6] = True                  # eroded on three sides, not at the border
    assert (ca == want).all() and cb.all()
    assert not mask_core(flat, torch.tensor([[8, 6], [5, 4]]), 0.375)[:48].any()  # 3 px on the 8-px frame


def test_mask_thin_adds_the_parts_narrower_than_the_square():
    """thin: the mask minus its opening joins the core (a 1-px leg off a block); the block's rim,
    which lies beside its core, stays out."""
    from fastneus.train.rays import mask_core

    a = np.zeros((9, 12), np.uint8)
    a[1:8, 1:6] = 255                      # a 7 x 5 block
    a[4, 6:11] = 255                       # a 1-px leg off its right side
    flat, wh = torch.from_numpy(a.reshape(-1)), torch.tensor([[12, 9]])
    core = mask_core(flat, wh, 1 / 12).view(9, 12).numpy()           # r = 1
    both = mask_core(flat, wh, 1 / 12, thin=True).view(9, 12).numpy()
    want = np.zeros((9, 12), bool)
    want[2:7, 2:5] = True
    assert (core == want).all()
    want[4, 6:11] = True                   # the leg; the block's rim (in its opening) is not added
    assert (both == want).all()


def test_mask_core_matches_a_min_filter_reference():
    """OpenCV's rectangle morphology against a plain torch min/max filter (max_pool2d, which ignores
    its padding as the border rule says) on random blobs, frames of two sizes, radii 1-3, with and
    without the thin parts."""
    from fastneus.train.rays import core_radius, mask_core

    pool = torch.nn.functional.max_pool2d
    gen = torch.Generator().manual_seed(3)
    for frac in (0.05, 0.1, 0.15):
        sizes = [(20, 14), (17, 23)]
        blobs = [(pool(torch.rand(1, 1, h, w, generator=gen), 3, 1, 1) > 0.75).to(torch.uint8) * 255 for w, h in sizes]
        flat = torch.cat([b.reshape(-1) for b in blobs])
        wh = torch.tensor(sizes)
        for thin in (False, True):
            got, want = mask_core(flat, wh, frac, thin), []
            for b, (w, h) in zip(blobs, sizes):
                r, m = core_radius(frac, w, h), (b > 127).float()
                core = -pool(-m, 2 * r + 1, 1, r)
                if thin:
                    core = torch.maximum(core, m - pool(core, 2 * r + 1, 1, r))
                want.append(core.reshape(-1) > 0.5)
            assert torch.equal(got, torch.cat(want))


def test_core_radius_scales_with_the_image():
    """The core's radius is a fraction of the image's larger side, at least one pixel."""
    from fastneus.train.rays import core_radius

    assert core_radius(0.02, 200, 200) == 4 and core_radius(0.02, 800, 600) == 16
    assert core_radius(0.02, 20, 10) == 1 and core_radius(0.001, 200, 200) == 1


def test_background_only_pushes_background_pixels():
    op = torch.tensor([0.5, 0.5], requires_grad=True)
    t = losses.background_free_space(op, torch.tensor([1.0, 0.0]), 0.1)
    assert t["background"].item() == pytest.approx(-0.1 * math.log(0.5) / 2, rel=1e-6)
    t["background"].backward()
    assert op.grad[0] > 0 and op.grad[1] == 0  # lower opacity on background pixels only


def test_curvature_and_prior_are_weighted():
    assert losses.curvature(torch.tensor([1.0, -3.0]), 0.5)["curvature"].item() == pytest.approx(1.0)
    assert losses.surface_prior(torch.tensor(2.0), 3.0)["prior"].item() == pytest.approx(6.0)


def test_total_sums_terms_in_a_fixed_order_and_skips_log_values():
    terms = {"curvature": torch.tensor(1e-8), "rgb": torch.tensor(1.0), "eik": torch.tensor(100.0),
             "eikonal": torch.tensor(0.5)}
    assert losses.total(terms).item() == pytest.approx(1.5 + 1e-8)
    reordered = dict(reversed(list(terms.items())))
    assert torch.equal(losses.total(terms), losses.total(reordered))
    with pytest.raises(ValueError):
        losses.total({"eik": torch.tensor(1.0)})


def test_zero_weight_gives_zero_and_no_gradient():
    op = torch.tensor([0.3, 0.7], requires_grad=True)
    curv = torch.tensor([0.5, -1.0], requires_grad=True)
    g = torch.tensor([[2.0, 0.0, 0.0]], requires_grad=True)
    terms = (losses.mask_bce(op, torch.tensor([1.0, 0.0]), 0.0) | losses.background_free_space(op, torch.tensor([1.0, 1.0]), 0.0)
             | losses.curvature(curv, 0.0) | losses.eikonal(g, 0.0) | losses.surface_prior(op.sum(), 0.0))
    for name in ("mask", "background", "curvature", "eikonal", "prior"):
        assert terms[name].item() == 0.0, name
    losses.total(terms).backward()
    assert op.grad.abs().sum() == 0 and curv.grad.abs().sum() == 0 and g.grad.abs().sum() == 0
    assert terms["eik"].item() == pytest.approx(1.0)  # the log value does not depend on the weight


def test_gradients_flow_through_every_weighted_term():
    op = torch.tensor([0.4, 0.6], requires_grad=True)
    curv = torch.tensor([0.5, -1.0], requires_grad=True)
    v = torch.tensor(2.0, requires_grad=True)
    losses.mask_bce(op, torch.tensor([1.0, 0.0]), 1.0)["mask"].backward()
    assert op.grad[0] < 0 < op.grad[1]  # opacity pulled toward the mask
    losses.curvature(curv, 0.5)["curvature"].backward()
    assert curv.grad.tolist() == pytest.approx([0.25, -0.25])
    losses.surface_prior(v, 3.0)["prior"].backward()
    assert v.grad.item() == pytest.approx(3.0)


def test_schedules_ramp_in_and_fade_out():
    assert losses.background_ramp(0.2, 0.2) == 0.0
    assert losses.background_ramp(0.3, 0.2) == pytest.approx(0.5)
    assert losses.background_ramp(0.9, 0.2) == 1.0 and losses.background_ramp(0.0, 0.0) == 1.0
    assert losses.prior_fade(0.0, 3.0, 2.0) == 3.0
    assert losses.prior_fade(0.5, 3.0, 2.0) == pytest.approx(2.25)
    assert losses.prior_fade(2.0, 3.0, 2.0) == 0.0


def test_mask_weight_falls_from_its_start_to_the_weight_over_a_fraction_of_the_run():
    """``loss.mask_weight_start`` holds thin parts while the shape forms: linear to
    ``mask_weight`` at ``mask_start_frac``, then constant; off: the weight is constant."""
    from fastneus.config import load_config
    from fastneus.train.trainer import Trainer

    tr = object.__new__(Trainer)  # mask_weight_at reads the config and the decision only
    tr.cfg = load_config("fewview", ["mask_weight=0.1", "mask_weight_start=0.5", "mask_start_frac=0.4"])
    tr.mask_start_used = True
    seen = [tr.mask_weight_at(p) for p in (0.0, 0.1, 0.2, 0.4, 0.7, 1.0)]
    assert seen == pytest.approx([0.5, 0.4, 0.3, 0.1, 0.1, 0.1])
    tr.mask_start_used = False
    assert {tr.mask_weight_at(p) for p in (0.0, 0.2, 1.0)} == {0.1}


@pytest.fixture(scope="module")
def lit_and_dark(small_scene, tmp_path_factory):
    """conftest's lit sphere (3 views of 24 px with masks) and the same in a dark room."""
    from fastneus.synth.render import synthesize

    d = tmp_path_factory.mktemp("dark")
    synthesize(d, shape="sphere", views=3, size=(24, 24), illum="dark", seed=0, device="cpu",
               contact_sheet=False, progress=False)
    return {True: small_scene, False: d}


@pytest.mark.parametrize("lit, extra, used", [(True, [], True), (False, [], False), (False, ["mask_start=on"], True),
                                              (True, ["mask_start=off"], False),
                                              (True, ["mask_weight_start=0.1"], False)])
def test_mask_start_is_chosen_in_a_lit_room_printed_and_saved(tmp_path, lit_and_dark, lit, extra, used):
    """``mask_start=auto`` strengthens the masks early only where the object is lit (ambient light,
    not lasers in a dark room, where it lost the realistic ant's legs), and says so in the run's
    masks note (printed and written to run.json)."""
    from fastneus.config import load_config
    from fastneus.data import Scene
    from fastneus.train.trainer import Trainer

    cfg = load_config("cpu-quick", ["steps=4", "camera_blur=0", "mask_weight=0.1", "threads=1"] + extra)
    tr = Trainer(Scene.load(lit_and_dark[lit]), cfg, tmp_path / "r", "cpu")
    assert tr.masks_used and tr.mask_start_used is used
    assert ("(mask_start)" in tr.masks_note) is used
    assert tr.mask_weight_at(0.0) == pytest.approx(0.3 if used else 0.1)


@pytest.mark.parametrize("extra, note", [([], None), (["mask_loss=mixed"], "(mask_loss=mixed, background pixels by opacity)"),
                                         (["mask_loss=sdf"], "negative SDF (mask_loss=sdf)"),
                                         (["mask_loss=mixed", "mask_core=0.05"], "px or more inside the outline by opacity (mask_core 0.05")])
def test_the_mask_terms_form_is_in_the_masks_note(tmp_path, lit_and_dark, extra, note):
    """A silhouette form of the mask term is printed and saved with the masks' decision."""
    from fastneus.config import load_config
    from fastneus.data import Scene
    from fastneus.train.trainer import Trainer

    cfg = load_config("cpu-quick", ["steps=4", "camera_blur=0", "threads=1"] + extra)
    tr = Trainer(Scene.load(lit_and_dark[False]), cfg, tmp_path / "r", "cpu")
    assert tr.masks_used
    assert ("negative SDF" in tr.masks_note) is (note is not None)
    assert note is None or note in tr.masks_note
    core = tr.bank.mask_core  # flagged only for a silhouette form with a core radius
    assert (core is not None) is ("mask_core=0.05" in extra)
    if core is not None:
        inside = tr.bank.mask > 127
        assert bool(core.any()) and not bool((core & ~inside).any()) and int(core.sum()) < int(inside.sum())


def test_pixel_min_sdf_takes_the_smallest_of_a_pixels_rays():
    """With blur_sub rays per pixel: the pixel's minimum over its rays that have samples; a
    pixel none of whose rays has samples gets 0 and no samples."""
    from types import SimpleNamespace

    from fastneus.train.trainer import Trainer

    out = {"min_sdf": torch.tensor([0.3, -0.1, 0.0, 0.2, 0.0, 0.0]),
           "has_samples": torch.tensor([1.0, 1.0, 0.0, 1.0, 0.0, 0.0])}
    m, has = Trainer._pixel_min_sdf(SimpleNamespace(blur_sub=2), out)
    assert m.tolist() == pytest.approx([-0.1, 0.2, 0.0]) and has.tolist() == [1.0, 1.0, 0.0]
    m1, has1 = Trainer._pixel_min_sdf(SimpleNamespace(blur_sub=1), out)
    assert m1 is out["min_sdf"] and has1 is out["has_samples"]
