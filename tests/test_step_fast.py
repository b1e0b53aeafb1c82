"""The fast paths of the training step against the eager reference, on the same inputs:
the device-gated NaN guard (CUDA's step without a host sync) against the host-checked one,
and the eikonal points evaluated in the same field call as the samples against a separate
call. CPU always; CUDA where available."""
from __future__ import annotations

import copy

import pytest
import torch

from conftest import SMALL_RUN, scene_on
from fastneus.config import load_config
from fastneus.data import Scene

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def _trainer(small_scene, tmp_path, device, name):
    from fastneus.train.trainer import Trainer

    # eager steps: this file checks the guard and the merged pass (test_graphstep.py the graphs)
    cfg = load_config("cpu-quick", SMALL_RUN + ["threads=1", "init_geometry=sphere", "cuda_graph=off"])
    return Trainer(Scene.load(scene_on(small_scene, tmp_path, device)), cfg, tmp_path / name, device)


def _params(tr):
    return [p.detach().clone() for g in tr.opt.param_groups for p in g["params"]]


@pytest.mark.parametrize("device", DEVICES)
def test_gated_guard_matches_the_host_guard(request, tmp_path, device):
    """Three steps with the device-gated guard and three with the host-checked one, from the
    same state and random streams: same losses and parameters (to rounding); then a NaN loss
    is skipped by both without moving a parameter, and counted."""
    small_scene = request.getfixturevalue("small_scene") if device == "cpu" else None
    a = _trainer(small_scene, tmp_path, device, "a")
    b = _trainer(small_scene, tmp_path, device, "b")
    b.field.load_state_dict(a.field.state_dict())
    a._skipped_dev = torch.zeros((), dtype=torch.int64, device=a.device)  # force the gated path
    b._skipped_dev = None
    for tr in (a, b):
        tr.gen.manual_seed(7)
    for _ in range(3):
        torch.manual_seed(11)
        ra = a.train_step()
        torch.manual_seed(11)
        rb = b.train_step()
        torch.testing.assert_close(ra["loss"], rb["loss"], rtol=1e-5, atol=1e-7)
    for x, y in zip(_params(a), _params(b)):
        torch.testing.assert_close(x, y, rtol=1e-4, atol=1e-6)
    assert a.skipped == b.skipped == 0
    for tr in (a, b):  # a NaN anywhere in the loss: no parameter moves, the step is counted
        before = _params(tr)
        tr.field.variance.data.fill_(float("nan"))
        nan_v = tr.field.variance.detach().clone()
        tr.train_step()
        after = _params(tr)
        for x, y in zip(before, after):
            if x.shape == nan_v.shape and torch.isnan(y).all():
                continue
            assert torch.equal(x, y)
        assert tr.skipped == 1


@pytest.mark.parametrize("device", DEVICES)
def test_eikonal_points_in_the_sample_call_match_a_separate_call(request, tmp_path, device):
    from fastneus.field.renderer import render_rays

    small_scene = request.getfixturevalue("small_scene") if device == "cpu" else None
    tr = _trainer(small_scene, tmp_path, device, "e")
    tr.train_step()
    c = tr.cfg
    batch = tr.rig.rays(tr.bank.sample(64, tr.gen))
    xr = torch.rand(300, 3, device=tr.device) * 2 - 1
    i_r, i_b = tr.illumination()
    kw = dict(i_r=i_r, i_b=i_b, cos_anneal=1.0, jitter=False)
    out = render_rays(tr.field, tr.grid.bits, tr.grid.resolution, tr.rig.projection(), batch["origins"],
                      batch["dirs"], batch["fidx"], c, extra_points=xr, **kw)
    ref = render_rays(tr.field, tr.grid.bits, tr.grid.resolution, tr.rig.projection(), batch["origins"],
                      batch["dirs"], batch["fidx"], c, **kw)
    s = out["n_samples"]
    assert s > 0 and out["grad_all"].shape == (s + 300, 3)
    torch.testing.assert_close(out["color"], ref["color"], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(out["grad_all"][:s], ref["grad"], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(out["grad_all"][s:], tr.field.sdf_and_grad(xr)[2], rtol=1e-5, atol=1e-6)
    # gradients reach the table and the MLP through the extra points' share alone
    tr.opt.zero_grad()
    (out["grad_all"][s:].norm(dim=-1) - 1).pow(2).mean().backward()
    assert float(tr.field.sdf_net[0].weight.grad.abs().sum()) > 0


def test_oneshot_is_budgeted_in_time_unless_steps_are_given(capsys):
    """The oneshot preset trains 10 s; ``steps=N`` among the overrides means N steps (the
    preset's budget is switched off and a note says so), from the CLI and the Python API alike
    (the rule is in load_config); an explicit budget stays."""
    cfg = load_config("oneshot")
    assert cfg.run.time_budget == 10
    fixed = load_config("oneshot", ["run.steps=300"])
    assert fixed.run.time_budget == 0 and fixed.run.steps == 300 and "time budget is off" in capsys.readouterr().err
    both = load_config("oneshot", ["steps=300", "time_budget=4"])
    assert both.run.time_budget == 4


def test_camera_blur_rays_average_to_the_blurred_pixel(small_scene, tmp_path):
    """rays.camera_blur: each pixel is blur_rays rays around its centre, spread by the blur, and
    the step compares their mean colour with the photo; 0 keeps one ray through the centre."""
    from fastneus.train.trainer import Trainer

    sc = Scene.load(small_scene)
    cfg = load_config("cpu-quick", SMALL_RUN + ["threads=1", "camera_blur=0.7", "blur_via=rays", "blur_rays=4"])
    tr = Trainer(sc, cfg, tmp_path / "b", "cpu")
    assert tr.blur_sub == 4
    g = torch.Generator().manual_seed(3)
    b = tr.bank.sample(50, g, blur=0.7, sub=4)
    assert b["origins"].shape == (200, 3) and b["rgb"].shape == (50, 3) and b["fidx"].shape == (200,)
    assert torch.equal(b["fidx"].view(50, 4), b["fidx"].view(50, 4)[:, :1].expand(50, 4))  # a pixel's rays: one frame
    g = torch.Generator().manual_seed(3)
    centre = tr.bank.sample(50, g)
    # the rays spread around the centre ray by about the blur (0.7 px of a 24-px image's focal length)
    spread = (b["dirs"].view(50, 4, 3) - centre["dirs"][:, None]).norm(dim=-1)
    fx = float(sc.frame_camera(0).K[0, 0])
    assert 0.1 / fx < float(spread.mean()) < 3.0 / fx
    for _ in range(3):
        rec = tr.train_step()
    assert rec is not None and torch.isfinite(rec["loss"])
    assert Trainer(sc, load_config("cpu-quick", SMALL_RUN), tmp_path / "c", "cpu").blur_sub == 1


def test_camera_blur_on_the_patterns_costs_no_rays_and_trains(small_scene, tmp_path):
    """blur_via=pattern (the default way): one ray per pixel, the trainer's patterns blurred, and a
    step trains; camera_blur=0 leaves the patterns untouched."""
    from fastneus.train.trainer import Trainer

    sc = Scene.load(small_scene)
    tr = Trainer(sc, load_config("cpu-quick", SMALL_RUN + ["threads=1", "camera_blur=0.7"]), tmp_path / "p", "cpu")
    ref = Trainer(sc, load_config("cpu-quick", SMALL_RUN + ["threads=1"]), tmp_path / "q", "cpu")
    assert tr.blur_sub == 1 and tr.pattern_blur == 0.7 and ref.pattern_blur == 0.0
    assert not torch.equal(tr.proj.store.buffer, ref.proj.store.buffer)
    for _ in range(3):
        rec = tr.train_step()
    assert rec is not None and torch.isfinite(rec["loss"])


def test_background_prior_in_a_dark_room_only_where_the_light_reaches(small_scene, tmp_path):
    """bg_lit: auto turns on in a dark room (>= 85 % background pixels) without the foreground
    prior; shade_samples' ``lit``
    is the projected light at each ray's surface (>= 0, zero for rays that miss every lit
    sample), so a black pixel over an unlit surface is not pushed to empty space."""
    from fastneus.field.renderer import march_samples, shade_samples
    from fastneus.train.trainer import Trainer, resolve_bg_lit

    cfg = load_config("cpu-quick").replace(fg_prior="off")  # with the foreground prior, auto keeps bg_lit off
    assert resolve_bg_lit(cfg, 0.94) and not resolve_bg_lit(cfg, 0.6)
    assert resolve_bg_lit(cfg.replace(bg_lit="on"), 0.1) and not resolve_bg_lit(cfg.replace(bg_lit="off"), 0.99)
    tr = Trainer(Scene.load(small_scene), load_config("cpu-quick", SMALL_RUN + ["threads=1"]), tmp_path / "l", "cpu")
    tr.train_step()
    batch = tr.bank.sample(64, tr.gen)
    smp = march_samples(tr.grid.bits, tr.grid.resolution, batch["origins"], batch["dirs"], tr.cfg, jitter=False)
    i_r, i_b = tr.illumination()
    out = shade_samples(tr.field, smp, tr.rig.projection(), batch["origins"], batch["dirs"], batch["fidx"], tr.cfg,
                        i_r=i_r, i_b=i_b, cos_anneal=1.0, lit=True)
    assert out["lit"].shape == (64,) and bool((out["lit"] >= 0).all()) and not out["lit"].requires_grad
    assert float(out["lit"].max()) > 0  # the cross lasers reach some surfaces
    # the light is weighted like the colour: never more than the ray's opacity times the brightest
    # light a sample can get (3 channels of at most 1 per projector)
    n_proj = len(Scene.load(small_scene).projectors)
    assert bool((out["lit"] <= out["opacity"].detach() * 3 * n_proj + 1e-6).all())


def test_foreground_prior_in_a_dark_room_pulls_bright_pixels_to_full_opacity(small_scene, tmp_path):
    """fg_prior: auto is on with the background prior in a dark room (and then the background
    prior carves every black pixel: bg_lit off); its term pulls opacity up only at pixels
    brighter than the backdrop, and a training step with it on logs the term."""
    from fastneus.train import losses
    from fastneus.train.trainer import Trainer, resolve_bg_lit, resolve_fg_prior

    cfg = load_config("cpu-quick")
    assert resolve_fg_prior(cfg, True, 0.94) and not resolve_bg_lit(cfg, 0.94)
    assert not resolve_fg_prior(cfg, True, 0.6) and not resolve_fg_prior(cfg, False, 0.99)  # lit room; masks
    assert resolve_fg_prior(cfg.replace(fg_prior="on"), True, 0.1)
    assert not resolve_fg_prior(cfg.replace(fg_prior="off"), True, 0.99) and resolve_bg_lit(cfg.replace(fg_prior="off"), 0.99)
    op = torch.tensor([0.2, 0.2, 0.9], requires_grad=True)
    losses.foreground_opacity(op, torch.tensor([1.0, 0.0, 1.0]), 0.1)["foreground"].backward()
    assert op.grad[0] < op.grad[2] < 0 and op.grad[1] == 0  # up where foreground, most where least opaque
    run = SMALL_RUN + ["threads=1", "masks=off", "bg_prior=on", "fg_prior=on", "bg_start_frac=0", "log_every=1"]
    tr = Trainer(Scene.load(small_scene), load_config("cpu-quick", run), tmp_path / "f", "cpu")
    assert tr.fg_used and "foreground prior" in tr.bg_note
    out = tr.train_step()
    assert out is not None and float(out["loss"]) > 0
    assert not Trainer(Scene.load(small_scene), load_config("cpu-quick", run[:-3] + ["fg_prior=off"]), tmp_path / "g",
                       "cpu").fg_used


@pytest.mark.parametrize("device", DEVICES)
def test_unused_kernel_arguments_are_cached_per_site_and_never_during_a_capture(device):
    """kernels/_warp.dummy: one zeroed tensor per (site, shape, dtype, device), so a step launches
    no fill for arguments its kernels do not use; two sites never share one (one site's unread
    writes must not reach another's unread input); a tensor made while a CUDA graph is captured is
    not kept (it would live in the graph's pool)."""
    from fastneus.kernels import _warp

    a = _warp.dummy((1, 3), torch.device(device), "test.a")
    assert a.shape == (1, 3) and a.dtype == torch.float32 and not a.any()
    assert _warp.dummy((1, 3), torch.device(device), "test.a") is a
    assert _warp.dummy((1, 3), torch.device(device), "test.b") is not a
    assert _warp.dummy((1,), torch.device(device), "test.a") is not a
    assert _warp.dummy((1, 3), torch.device(device), "test.a", dtype=torch.int32).dtype == torch.int32
    if device == "cuda":
        g = torch.cuda.CUDAGraph()
        side = torch.cuda.Stream()
        with torch.cuda.stream(side):
            with torch.cuda.graph(g):
                inside = _warp.dummy((1, 2), torch.device("cuda"), "test.capture")
        assert inside is not _warp.dummy((1, 2), torch.device("cuda"), "test.capture")


def _split_trainer(small_scene, tmp_path, name, extra=()):
    from fastneus.train.trainer import Trainer

    cfg = load_config("cpu-quick", SMALL_RUN + ["threads=2", "init_geometry=sphere", "steps=12", "split_step=on", *extra])
    return Trainer(Scene.load(small_scene), cfg, tmp_path / name, "cpu")


def test_split_step_on_two_threads_equals_its_halves_in_turn(small_scene, tmp_path):
    """run.split_step: the step's two half batches on two threads give bit for bit the parameters
    of the same halves run one after the other on one thread (two gradients: the same sum in
    either order), and a second run of the same seed repeats it; off (the default) the step is not
    split."""
    import functools

    a = _split_trainer(small_scene, tmp_path, "a")
    b = _split_trainer(small_scene, tmp_path, "b")
    c = _split_trainer(small_scene, tmp_path, "c")
    assert a.split_now(0.5) and b.split_now(0.5)
    b._split_step = functools.partial(b._split_step, threaded=False)
    calls = []
    orig = c._split_step
    c._split_step = lambda *args, **kw: calls.append(1) or orig(*args, **kw)
    recs = []
    for i in range(12):
        rec = []
        for tr in (a, b, c):
            torch.manual_seed(i)  # the march's jitter draws from torch's global generator
            rec.append(tr.train_step())
        recs.append(rec)
    assert len(calls) == 12 and sum(r[0] is not None for r in recs) >= 10
    for ra, rb, _ in recs:
        if ra is not None:
            assert torch.equal(ra["loss"], rb["loss"]) and ra["samples"] == rb["samples"]
    for (na, pa), (_, pb), (_, pc) in zip(a.field.named_parameters(), b.field.named_parameters(),
                                          c.field.named_parameters()):
        assert torch.equal(pa, pb), na  # threads vs in turn
        assert torch.equal(pa, pc), na  # the same seed again
    assert not _split_trainer(small_scene, tmp_path, "off", ["split_step=off"]).split_now(0.5)
    assert load_config("cpu-quick").run.split_step == "off"


def test_split_step_reraises_a_halfs_error(small_scene, tmp_path, monkeypatch):
    """An error in the half run on the second thread reaches the caller (not a silent skip)."""
    import threading

    tr = _split_trainer(small_scene, tmp_path, "err")
    step_loss = tr.step_loss

    def failing(*args, **kw):
        if threading.current_thread().name == "fastneus-half":
            raise RuntimeError("half failed")
        return step_loss(*args, **kw)

    monkeypatch.setattr(tr, "step_loss", failing)
    with pytest.raises(RuntimeError, match="half failed"):
        for _ in range(6):
            tr.train_step()
