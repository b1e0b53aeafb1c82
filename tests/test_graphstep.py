"""The captured training step (fastneus/train/graphstep.py) against the eager reference.

CPU (always): the padded fixed-capacity inputs with the 0/1 ``valid`` vector, the device-side
schedule of the field (all hash levels evaluated, the inactive ones multiplied by 0; the floor
of inv_s from a tensor) and the captured Adam update give the same loss and parameters as the
eager step on the unpadded inputs. CUDA (where available): a replayed graph gives the same
loss and parameters as the eager step on the same inputs, step after step.
"""
from __future__ import annotations

import math

import pytest
import torch

from conftest import SMALL_RUN, scene_on
from fastneus.config import load_config
from fastneus.data import Scene
from fastneus.field.renderer import march_samples, march_samples_capped
from fastneus.train.graphstep import _Entry, ray_bucket, sample_bucket



class _KeyTrainer:
    """What StepGraphs' key and capacity planning read of a trainer (a stand-in: no scene)."""

    def __init__(self):
        self.cfg = load_config("cpu-quick")

    @staticmethod
    def photo_priors(p):
        return False, False

    @staticmethod
    def prior_on(p):
        return False

def test_buckets_hold_the_count_and_are_few():
    for n in list(range(8, 3000, 7)) + [65536, 100_003]:
        r = ray_bucket(n)
        assert abs(r - n) <= 0.07 * n + 1, (n, r)
    for s in list(range(1, 5000, 3)) + [262_144, 300_001]:
        c = sample_bucket(s)
        assert s <= c <= max(16, s * 1.07 + 1), (s, c)
    # a few percent of jitter around a count lands on at most 3 capacities
    assert len({sample_bucket(s) for s in range(250_000, 262_000, 97)}) <= 3
    assert len({ray_bucket(n) for n in range(730, 790)}) <= 2


def test_the_presets_mask_forms():
    """The GPU preset states the mask as where rays cross the surface; the CPU preset keeps the BCE."""
    assert load_config("fewview").loss.mask_loss == "mixed"
    assert load_config("fewview").loss.mask_core == 0.02
    assert load_config("cpu-quick").loss.mask_loss == "bce"


def test_ray_count_and_capacity_stay_put_under_jitter():
    """The adaptive ray count and the march's sample count jitter by a few % per step: the
    captured step's ray count and sample capacity must not hop between graphs with them."""
    from fastneus.train.graphstep import StepGraphs

    g = StepGraphs.__new__(StepGraphs)  # the bookkeeping only (no CUDA stream)
    g.cache = {}
    seen = {g.ray_count(n) for n in (760, 745, 790, 770, 801, 735)}
    assert len(seen) == 1
    assert g.ray_count(1000) != g.ray_count(760) or g.ray_count(1000) == ray_bucket(1000)

    _T = _KeyTrainer()
    batch = {"origins": torch.zeros(768, 3), "dirs": torch.zeros(768, 3)}
    cap = g._capacity(_T, batch, 250_000, 0.5)
    assert cap >= 250_000 * 1.05
    g.cache[g._key(_T, batch, cap, 0.5)] = None
    for s in (240_000, 251_000, 258_000, 235_000):  # within 20 % padding: the same capacity
        assert g._capacity(_T, batch, s, 0.5) == cap
    assert g._capacity(_T, batch, cap + 1, 0.5) > cap  # too many samples: a larger one
    assert g._capacity(_T, batch, 150_000, 0.5) < cap  # far fewer: a smaller one


def _pair(scene_dir, tmp_path, device, extra=()):
    """Two trainers with the same parameters; ``a`` on the device-side schedule and guard."""
    from fastneus.train.trainer import Trainer

    cfg = load_config("cpu-quick", SMALL_RUN + ["threads=1", "init_geometry=sphere", "levels=6",
                                                 "c2f_start_levels=2", "cuda_graph=off"] + list(extra))
    sc = Scene.load(scene_dir)
    a, b = Trainer(sc, cfg, tmp_path / "a", device), Trainer(sc, cfg, tmp_path / "b", device)
    b.field.load_state_dict(a.field.state_dict())
    for tr in (a, b):
        tr._skipped_dev = torch.zeros((), dtype=torch.int64, device=tr.device)  # the device guard on both
    a.field.enable_device_schedule()
    return a, b


def _inputs(tr, p: float):
    """One step's host part (as Trainer.train_step does it), at progress ``p``."""
    c = tr.cfg
    tr.field.set_progress(p)
    tr._set_lr(p)
    n = ray_bucket(tr.n_rays)
    batch = tr.rig.rays(tr.bank.sample(n, tr.gen, bright_fraction=c.rays.bright_fraction))
    xr = torch.rand(max(256, n // 4), 3, device=tr.device, generator=tr.gen) * 2 - 1
    if tr.device.type == "cuda":  # the march's jitter comes from the default CUDA generator
        tr.rng_before_march = torch.cuda.get_rng_state(tr.device)
    return batch, xr, march_samples(tr.grid.bits, tr.grid.resolution, batch["origins"], batch["dirs"], c)


def _sphere_prior(device):
    """A SurfacePrior of 400 points on a sphere of radius 0.5 seen from a camera at z = -3, with
    100 background rays (a stand-in for a one-shot's plane sweep)."""
    from fastneus.train.geometry_init import SurfacePrior

    g = torch.Generator().manual_seed(11)
    pts = torch.nn.functional.normalize(torch.randn(400, 3, generator=g), dim=-1) * 0.5
    cam = torch.tensor([0.0, 0.0, -3.0]).expand(400, 3)
    dirs = torch.nn.functional.normalize(pts - cam, dim=-1)
    bg_dirs = torch.nn.functional.normalize(torch.tensor([0.45, 0.0, 1.0]) + 0.05 * torch.randn(100, 3, generator=g), dim=-1)
    return SurfacePrior(pts.to(device), dirs.to(device), cam.contiguous().to(device),
                        bg_origins=cam[:100].contiguous().to(device), bg_dirs=bg_dirs.to(device))


def _params(tr):
    return [q.detach().clone() for g in tr.opt.param_groups for q in g["params"]]


def _close(a, b, what):
    # Adam's step is ~lr whatever the gradient's size, so table entries whose gradient is at
    # rounding level (levels just opened, curvature taps) may move differently by a fraction
    # of lr; the losses above are compared tightly
    for x, y in zip(_params(a), _params(b)):
        if x.is_cuda:
            # CUDA's float atomics sum the hash-table gradients in a different order on every
            # run (eager against eager too): Adam turns a rounding-level gradient into a step of
            # ~lr of either sign, so a few entries may differ by up to 2 lr per step; the rest agree
            close = torch.isclose(x, y, rtol=1e-3, atol=1e-4)
            assert float(close.float().mean()) >= 0.99, (what, float(close.float().mean()))
            assert float((x - y).abs().max()) <= 0.1, (what, float((x - y).abs().max()))
        else:
            torch.testing.assert_close(x, y, rtol=1e-3, atol=1e-4, msg=what)


def _in_place(e, smp, gen):
    """``smp`` as the march leaves it when it writes into ``e``'s buffers (``march_out``): its
    samples first, then stale but finite samples of earlier steps in the padding."""
    s, n = smp["n_samples"], smp["offsets"].shape[0]
    t0, t1, ri = e.buffers()
    t0.copy_(torch.rand(t0.shape, generator=gen) * 1.5)
    t1.copy_(t0 + 0.01)
    ri.copy_(torch.randint(0, n, ri.shape, generator=gen, dtype=torch.int32))
    for k, buf in zip(("t0", "t1", "ray_index"), (t0, t1, ri)):
        buf[:s].copy_(smp[k])
    return {**smp, "t0": t0[:s], "t1": t1[:s], "ray_index": ri[:s]}


@pytest.mark.parametrize("extra", [[], ["curvature_weight=0.001"], ["hull=loss", "init_radius=0.95"], "in-place",
                                   ["mask_loss=mixed"], "in-place mask_loss=sdf", "in-place network.highlight=true",
                                   ["mask_loss=mixed", "mask_core=0.05"]])
def test_padded_device_schedule_step_matches_the_eager_step(small_scene, tmp_path, extra):
    """The padded step against the eager one; ``in-place``: the samples written into the
    entry's buffers with earlier steps' samples left in the padding (not copied, not zeroed)."""
    in_place = isinstance(extra, str)  # the padding's stale ray indices must not reach a ray's min SDF
    a, b = _pair(small_scene, tmp_path, "cpu", extra.split()[1:] if in_place else extra)
    assert a.masks_used
    a.opt._scal = torch.zeros(len(a.opt.param_groups), 2)
    gen = torch.Generator().manual_seed(5)
    for p in (0.1, 0.2, 0.5):  # coarse-to-fine still opening levels at the first two
        batch, xr, smp = _inputs(b, p)
        a.field.set_progress(p)
        a._set_lr(p)
        assert a.field.active_levels == b.field.active_levels
        rb = b.compute(batch, xr, smp, p)
        e = _Entry(batch, xr, sample_bucket(smp["n_samples"]) + 37)  # padding on purpose
        e.load(batch, xr, _in_place(e, smp, gen) if in_place else smp)
        if in_place:  # nothing copied over the stale padding
            assert float(e.smp["t0"][smp["n_samples"]:].abs().sum()) > 0
        e.mark_live()
        assert int(e.valid[:e.capacity].sum()) == smp["n_samples"] and bool(e.valid[e.capacity:].all())
        a.opt.prepare_device_step()
        ra = a.compute(e.batch, e.xr, e.smp, p, valid=e.valid, device_adam=True)
        torch.testing.assert_close(ra["loss"], rb["loss"], rtol=1e-5, atol=1e-7)
        torch.testing.assert_close(ra["eik"], rb["eik"], rtol=1e-5, atol=1e-7)
        _close(a, b, f"p={p}")
        torch.testing.assert_close(a.field.inv_s(), b.field.inv_s())


def test_device_schedule_gives_the_same_field_and_table_gradients(small_scene, tmp_path):
    a, b = _pair(small_scene, tmp_path, "cpu")
    with torch.no_grad():
        a.field.table.normal_(0, 1e-2)
        b.field.table.copy_(a.field.table)
    x = torch.rand(500, 3) * 2 - 1
    for p in (0.05, 1.0):
        for f in (a.field, b.field):
            f.set_progress(p)
            f.zero_grad()
        oa, ga = a.field.geometry_and_grad(x.clone().requires_grad_())
        ob, gb = b.field.geometry_and_grad(x.clone().requires_grad_())
        torch.testing.assert_close(oa, ob)
        torch.testing.assert_close(ga, gb)
        up = torch.randn_like(oa)
        (oa * up).sum().backward()
        (ob * up).sum().backward()
        torch.testing.assert_close(a.field.table.grad, b.field.table.grad, rtol=1e-5, atol=1e-8)
        if p < 0.1:  # inactive levels: exactly no gradient
            L0 = a.field.active_levels
            T = a.field.table.grad.reshape(a.field.hashgrid.levels, -1)
            assert float(T[L0:].abs().max()) == 0.0


def test_shared_inputs_are_fixed_per_layout_and_not_copied_again():
    """StepGraphs.inputs: one set of fixed buffers per batch layout, refilled each step (before
    the march); an entry made from them keeps them (no clone) and its load copies nothing."""
    from fastneus.train.graphstep import StepGraphs

    g = object.__new__(StepGraphs)
    g._inputs = {}
    gen = torch.Generator().manual_seed(3)

    def batch(n):
        return {"origins": torch.rand(n, 3, generator=gen), "dirs": torch.rand(n, 3, generator=gen),
                "rgb": torch.rand(n, 3, generator=gen)}

    b1, x1 = g.inputs(batch(64), torch.rand(256, 3, generator=gen))
    src, xs = batch(64), torch.rand(256, 3, generator=gen)
    b2, x2 = g.inputs(src, xs)
    assert all(b1[k].data_ptr() == b2[k].data_ptr() for k in b1) and x1.data_ptr() == x2.data_ptr()
    assert all(torch.equal(b2[k], src[k]) for k in src) and torch.equal(x2, xs)
    b3, _ = g.inputs(batch(72), torch.rand(256, 3, generator=gen))  # another ray count: its own set
    assert b3["origins"].data_ptr() != b1["origins"].data_ptr() and len(g._inputs) == 2
    smp = march_samples(torch.ones(8 ** 3, dtype=torch.uint8), 8, b2["origins"] * 0.2,
                        torch.nn.functional.normalize(b2["dirs"] - 0.5, dim=-1), load_config("cpu-quick"))
    assert g._from_inputs(b2) and g._from_inputs(b3) and not g._from_inputs(batch(64))
    e = _Entry(b2, x2, sample_bucket(smp["n_samples"]), shared=g._from_inputs(b2))
    assert e.batch["rgb"].data_ptr() == b2["rgb"].data_ptr() and e.xr.data_ptr() == x2.data_ptr()
    e.load(b2, x2, smp)
    assert torch.equal(e.batch["rgb"], src["rgb"])
    own = _Entry(batch(64), x1, 4096)  # not shared: its own copies
    assert own.xr.data_ptr() != x1.data_ptr()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device")
@pytest.mark.parametrize("extra", [[], ["hull=bound"], ["mask_start=on", "mask_weight_start=0.8", "mask_start_frac=0.3"],
                                   ["mask_loss=mixed"], "train-step path", ["masks=off", "bg_prior=on"],
                                   "surface prior", ["network.highlight=true"], ["mask_loss=mixed", "mask_core=0.05"],
                                   "second key"])
def test_cuda_replayed_graph_matches_the_eager_step(tmp_path, extra):
    """Graph steps (first: eager on the side stream + capture; then replays) against eager
    steps on the same inputs: the same loss and parameters after every step. ``second key``: the
    ray count doubles half-way, so a second graph is captured the way every capture after the
    run's first is (recorded, then replayed for that step's update: no eager pass). The scene is
    rendered on the GPU (no small_scene: a GPU machine may have no CPU compiler for Warp).
    With a falling mask weight the replayed graph reads each step's weight from the device.
    ``train-step path``: as Trainer.train_step feeds it: the inputs in the shared fixed buffers
    before the march, and the march writing into the graph's sample buffers (march_out)."""
    from fastneus.train.graphstep import StepGraphs

    path = extra == "train-step path"
    prior = extra == "surface prior"  # a one-shot's: faded weight and drawn points inside the graph; off past 0.45
    a, b = _pair(scene_on(None, tmp_path, "cuda"), tmp_path, "cuda",
                 ["prior_frac=0.45"] if prior else extra if isinstance(extra, list) else [])
    if prior:
        a.prior = b.prior = _sphere_prior("cuda")
    a.field._dev_sched = False  # StepGraphs switches it on
    graphs = StepGraphs(a)
    # coarse-to-fine still opening levels (the kernels read the count at replay), then over; the
    # first steps are in the NeuS cos-anneal ramp (its ratio read from the device, changing per
    # step): one graph replays through both
    ramp = isinstance(extra, list) and "masks=off" in extra  # through the background prior's ramp-in
    if ramp:
        assert a.bg_used and a.photo_priors(0.25)[0]
    # with the prior: more steps per phase, so that both keys (prior on, then off) replay although a
    # sample count past its capacity now and then costs a step a new key
    progress = ([0.22, 0.25, 0.28, 0.31, 0.34, 0.37, 0.5, 0.5] if ramp else
                [0.02, 0.03, 0.04, 0.05, 0.06, 0.07, 0.08] + [0.5] * 7 if prior else [0.02, 0.04, 0.06, 0.08] + [0.5] * 4)
    replays = {}  # prior on / off -> replayed steps
    for i, p in enumerate(progress):
        before = graphs.replayed
        if extra == "second key" and i == 4:
            a.n_rays = b.n_rays = 2 * b.n_rays
        batch, xr, smp = _inputs(b, p)
        a.field.set_progress(p)
        a._set_lr(p)
        if prior:  # the eager steps draw the prior's points from the run's generator, a replay from the default one
            st = torch.cuda.get_rng_state(a.device)
            a.gen.set_state(st)
            b.gen.set_state(st)
        rb = b.compute(batch, xr, smp, p)
        ra = None
        if path:  # the same rays, the same march jitter, through the train-step route
            batch, xr = graphs.inputs(batch, xr)
            plan = graphs.capped(a, batch, xr, p)
            if plan is not None:  # no host sync: the march into the planned graph's buffers
                torch.cuda.set_rng_state(b.rng_before_march, b.device)
                march_samples_capped(a.grid.bits, a.grid.resolution, batch["origins"], batch["dirs"], a.cfg,
                                     plan[1].capped_buffers())
                if int(plan[1].total) <= plan[1].capacity:  # (past it the step would be skipped: not this test's)
                    assert int(plan[1].smp["counts"].sum()) == smp["n_samples"]
                    ra = graphs.run_capped(a, *plan, p)
            if ra is None:
                torch.cuda.set_rng_state(b.rng_before_march, b.device)
                smp2 = march_samples(a.grid.bits, a.grid.resolution, batch["origins"], batch["dirs"], a.cfg,
                                     out=graphs.march_out(a, batch, xr, p))
                assert smp2["n_samples"] == smp["n_samples"] and torch.equal(smp2["t0"], smp["t0"])
                smp = smp2
        if ra is None:
            ra = graphs.step(a, batch, xr, smp, p)
        torch.testing.assert_close(ra["loss"], rb["loss"], rtol=1e-4, atol=1e-6)
        _close(a, b, f"step {i}")
        assert float(a.mask_w_dev) == pytest.approx(a.mask_weight_at(p))
        assert not prior or float(a.prior_w_dev) == pytest.approx(a.prior_weight_at(p))
        replays[a.prior_on(p)] = replays.get(a.prior_on(p), 0) + graphs.replayed - before
        if ramp:  # the ramp's steps, past the cos-anneal and coarse-to-fine ramps
            assert float(a.bg_w_dev) == pytest.approx(a.background_weight_at(p))
            assert p == 0.5 or 0.0 < a.background_weight_at(p) < a.bg_weight
            continue
        assert p == 0.5 or (float(a.cos_dev) == pytest.approx(a.cos_anneal(p)) and a.cos_anneal(p) < 1.0)
        assert (a.field.active_levels < a.field.hashgrid.levels) == (p < 0.1)
        assert int(a.field._levels_t[0]) == a.field.active_levels
    if extra == "second key":  # both captures' steps were compared above: the run's first and a later one
        assert graphs.captured == 2 and graphs.replayed >= 2, graphs.summary()
    else:
        assert graphs.captured >= 1 and graphs.replayed >= 4, graphs.summary()
    assert not prior or (replays.get(True, 0) >= 1 and replays.get(False, 0) >= 1), (replays, graphs.summary())
    assert graphs.enabled
    assert not path or graphs.unsynced >= 2, graphs.summary()
    assert int(a._overflow_dev) == 0


def test_graphs_make_room_drops_the_least_recent_while_memory_is_short(monkeypatch):
    """Before a new capture, cached graphs (each holding its activations) go, oldest first,
    until MIN_FREE of the GPU memory is free (eight filled an 80-GB H100)."""
    import collections

    from fastneus.train import graphstep

    g = object.__new__(graphstep.StepGraphs)  # no CUDA stream needed for the bookkeeping
    g.cache, g.evicted, g.device = collections.OrderedDict((k, object()) for k in "abcd"), 0, "cpu"
    frees = iter([0.10, 0.20, 0.5])
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda d: (int(next(frees) * 100), 100))
    monkeypatch.setattr(torch.cuda, "empty_cache", lambda: None)
    g._make_room()
    assert list(g.cache) == ["c", "d"] and g.evicted == 2


def test_graphs_released_at_the_end_of_training(monkeypatch):
    """The end of a fit drops every captured graph and hands its pool back (a second scene in
    the same process found the GPU full otherwise); the counts stay for the summary."""
    import collections

    from fastneus.train import graphstep

    g = object.__new__(graphstep.StepGraphs)
    g.cache, g.device = collections.OrderedDict((k, object()) for k in "ab"), "cpu"
    g.captured, g.replayed, g.eager, g.evicted, g.eager_reasons = 2, 10, 3, 0, {}
    g.captures = [{"step": 1, "rays": 64, "capacity": 1024, "seconds": 0.05}] * 2
    calls = []
    monkeypatch.setattr(torch.cuda, "synchronize", lambda d=None: calls.append("sync"))
    monkeypatch.setattr(torch.cuda, "empty_cache", lambda: calls.append("empty"))
    g.release()
    assert not g.cache and calls == ["sync", "empty"]
    assert g.summary() == {"graphs": 0, "captured": 2, "replayed": 10, "eager": 3, "eager_reasons": {}, "evicted": 0, "unsynced": 0, "drawn": 0,
                           "captures": g.captures}
    g.release()  # nothing cached: nothing to hand back
    assert calls == ["sync", "empty"]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device")
def test_a_finished_fit_holds_no_graph_memory(tmp_path):
    from fastneus.train.trainer import Trainer

    scene = Scene.load(scene_on(None, tmp_path, "cuda"))
    cfg = load_config("fewview", SMALL_RUN + ["steps=40", "camera_blur=0"])
    tr = Trainer(scene, cfg, tmp_path / "r", "cuda")
    tr.fit(final_save=False)
    assert tr.graphs is not None and tr.graphs.captured >= 1 and not tr.graphs.cache


def test_a_key_is_captured_only_when_the_next_step_repeats_it():
    """While the ray count settles (after the occupancy grid's first update it climbs through
    ~8 buckets in as many steps) each new key runs one eager step on the unpadded inputs and
    records nothing: a graph captured for one step costs 30-50 ms of host time and is never
    replayed. The capacity of that pending key is reused like a cached one's."""
    import collections

    from fastneus.train import graphstep

    g = object.__new__(graphstep.StepGraphs)  # the bookkeeping only (no CUDA stream)
    g.cache, g.enabled, g._pending, g.eager, g.eager_reasons = collections.OrderedDict(), True, None, 0, {}
    calls = []

    class _Eager(_KeyTrainer):
        @staticmethod
        def fill_step_scalars(p):
            pass

        @staticmethod
        def compute(batch, xr, smp, p, valid=None, device_adam=False):
            calls.append((batch["origins"].shape[0], smp["n_samples"], valid, device_adam))
            return {"loss": torch.zeros(())}

    _T = _Eager()

    xr = torch.zeros(256, 3)
    for n, s in ((1536, 60_000), (2560, 100_000), (3328, 140_000)):  # a new key every step
        batch = {"origins": torch.zeros(n, 3), "dirs": torch.zeros(n, 3)}
        g.step(_T, batch, xr, {"n_samples": s}, 0.5)
    assert calls == [(1536, 60_000, None, False), (2560, 100_000, None, False), (3328, 140_000, None, False)]
    assert not g.cache and g.eager == 3
    pending = g._pending
    assert pending[0] == 3328 and pending[1] >= 140_000 * 1.05
    batch = {"origins": torch.zeros(3328, 3), "dirs": torch.zeros(3328, 3)}
    # a few % more samples on the next step: the pending key's capacity still holds them
    assert g._capacity(_T, batch, 143_000, 0.5) == pending[1]


def test_capped_plan_uses_a_captured_graph_with_room_for_the_estimate():
    """StepGraphs.capped: the last known count, scaled to this step's rays and CAP_MARGIN above,
    picks a key whose graph exists; none without a known count, without a graph, or once the
    count outgrew every capacity (the step then counts on the host)."""
    import collections

    from fastneus.train import graphstep

    g = object.__new__(graphstep.StepGraphs)
    g.cache, g._pending = collections.OrderedDict(), None

    _T = _KeyTrainer()
    batch = {"origins": torch.zeros(1024, 3), "dirs": torch.zeros(1024, 3)}
    assert g.capped(_T, batch, None, 0.5) is None  # nothing known yet
    g._last = (100_000, 1024)
    cap = g._capacity(_T, batch, int(100_000 * 1.05) + 1, 0.5)  # what a counted step would make
    key = g._key(_T, batch, cap, 0.5)
    e = type("E", (), {"graph": None})()
    g.cache[key] = e
    assert g.capped(_T, batch, None, 0.5) is None  # no graph yet
    e.graph = object()
    assert g.capped(_T, batch, None, 0.5) == (key, e)
    assert g.samples_estimate(2048) == 200_000
    g._last = (int(cap / graphstep.CAP_MARGIN) + 50, 1024)  # grown past the room: count on the host
    assert g.capped(_T, batch, None, 0.5) is None


def test_a_step_that_does_not_fit_is_not_applied(small_scene, tmp_path):
    """fits False (a capped march past its buffers): the guarded update leaves every parameter
    as it was and counts the step as overflowed, not as non-finite; fits True: a normal step."""
    a, b = _pair(small_scene, tmp_path, "cpu")
    a.opt._scal = torch.zeros(len(a.opt.param_groups), 2)
    batch, xr, smp = _inputs(b, 0.5)
    a.field.set_progress(0.5)
    a._set_lr(0.5)
    e = _Entry(batch, xr, sample_bucket(smp["n_samples"]))
    e.load(batch, xr, smp)
    e.total.fill_(e.capacity + 1)
    e.mark_live()
    assert not bool(e.fits)
    before = _params(a)
    a.opt.prepare_device_step()
    a.compute(e.batch, e.xr, e.smp, 0.5, valid=e.valid, device_adam=True, fits=e.fits)
    assert all(torch.equal(x, y) for x, y in zip(before, _params(a)))
    assert int(a._overflow_dev) == 1 and a.skipped == 0
    e.total.fill_(e.capacity)
    e.mark_live()
    a.opt.prepare_device_step()
    a.compute(e.batch, e.xr, e.smp, 0.5, valid=e.valid, device_adam=True, fits=e.fits)
    assert not all(torch.equal(x, y) for x, y in zip(before, _params(a)))
    assert int(a._overflow_dev) == 1


def test_train_step_wires_a_capped_step(small_scene, tmp_path):
    """Trainer.train_step with graphs that plan a capped step (CPU, a stand-in for StepGraphs):
    the batch goes through inputs(), the capped march fills the planned entry's buffers, the
    replay is asked for that (key, entry), and the step's record carries the estimated count;
    with no plan the step counts on the host and goes to graphs.step."""
    from fastneus.config import load_config
    from fastneus.train.trainer import Trainer

    cfg = load_config("cpu-quick", SMALL_RUN + ["threads=1", "cuda_graph=off"])
    tr = Trainer(Scene.load(small_scene), cfg, tmp_path / "r", "cpu")
    calls = []

    class _G:
        plan = True
        replay_draw = False

        def eligible(self, t, p):
            return True

        def ray_count(self, n):
            return ray_bucket(n)

        def drawn(self, t, n, p):
            calls.append(("drawn", n))
            return ("drawn key", self.e) if self.replay_draw else None

        @staticmethod
        def draw_token(t):
            return ("token",)

        def inputs(self, batch, xr, drawn=None):
            calls.append(("inputs", drawn[1]))
            return batch, xr

        def capped(self, t, batch, xr, p):
            if not self.plan:
                return None
            n, cap = batch["origins"].shape[0], 4096
            self.e = _Entry(batch, xr, cap)
            return ("key", self.e)

        def samples_estimate(self, n):
            return 1234

        def run_capped(self, t, key, e, p):
            calls.append(("run_capped", key, e is self.e))
            return {"loss": torch.zeros(())}

        def march_out(self, t, batch, xr, p):
            return None

        def step(self, t, batch, xr, smp, p):
            calls.append(("step", smp["n_samples"]))
            return {"loss": torch.zeros(())}

    g = tr.graphs = _G()
    tr.update_grid(0.0)
    rec = tr.train_step()
    n = calls[0][1]
    assert calls == [("drawn", n), ("inputs", ("token",)), ("run_capped", "key", True)]
    assert rec["samples"] == 1234 and tr.step == 1
    e = g.e
    assert int(e.total) > 0 and int(e.smp["counts"].sum()) == min(int(e.total), e.capacity)
    # a replayed draw graph: no eager draw, no inputs, no march on the host; the replay and the estimate
    g.replay_draw, calls[:] = True, []
    e.total.fill_(-7)  # the capped march did not run again
    rec = tr.train_step()
    assert calls == [("drawn", calls[0][1]), ("run_capped", "drawn key", True)]
    assert rec["samples"] == 1234 and int(e.total) == -7 and tr.step == 2
    g.replay_draw, g.plan, calls[:] = False, False, []
    tr.train_step()
    assert calls[1][0] == "inputs" and calls[2][0] == "step" and calls[2][1] > 0 and tr.step == 3


def test_eager_steps_are_counted_by_reason():
    """run.json's cuda_graphs.eager_reasons says why steps ran eagerly (what to capture next)."""
    from types import SimpleNamespace

    from fastneus.train.graphstep import StepGraphs
    from fastneus.train.rays import RayBank

    g = StepGraphs.__new__(StepGraphs)  # the bookkeeping only (no CUDA stream)
    g.enabled, g.eager, g.eager_reasons = True, 0, {}
    cfg = load_config("fewview")
    opt = SimpleNamespace(uniform_steps=lambda: True)
    field = SimpleNamespace(active_levels=16, hashgrid=SimpleNamespace(levels=16), sdf_grad="analytic")
    tr = SimpleNamespace(cfg=cfg, rig=SimpleNamespace(active=False), bank=RayBank.__new__(RayBank), prior=None,
                         opt=opt, field=field, photo_priors=lambda p: (True, False))
    start = cfg.loss.bg_start_frac
    assert g.eligible(tr, start * 1.5)  # inside the background prior's ramp: its weight is on the device
    tr.prior = object()
    assert g.eligible(tr, 0.9)  # the surface prior's weight and draws are in the graph too
    tr.prior, tr.rig.active = None, True
    assert not g.eligible(tr, 0.9)
    tr.rig.active, tr.field.active_levels, tr.field.sdf_grad = False, 8, "fd"
    assert not g.eligible(tr, 0.2)
    assert g.eager == 2 and g.eager_reasons == {"rig corrections": 1, "coarse-to-fine taps": 1}
    g.enabled = False
    assert g.ineligible(tr, 0.9) == "capture failed"


def test_device_scalars_give_the_eager_loss_through_the_background_ramp(small_scene, tmp_path, monkeypatch):
    """No masks: the loss a captured step records (its schedule values read from the device
    scalars ``fill_step_scalars`` wrote) equals the eager loss at every progress through the
    background prior's ramp-in and after it (a scalar last filled inside the ramp must not keep
    that value). On the CPU, by letting ``step_loss`` take its capturing branch."""
    a, b = _pair(small_scene, tmp_path, "cpu", ["masks=off", "bg_prior=on"])
    assert a.bg_used and not a.masks_used
    a.cos_dev = torch.ones((1,))
    a.mask_w_dev = torch.full((), a.mask_weight_at(0.0))
    a.bg_w_dev = torch.full((), a.bg_weight)
    start = a.cfg.loss.bg_start_frac
    seen = []
    for p in (start * 1.1, start * 1.5, start * 1.9, start * 2.5, 0.9):
        batch, xr, smp = _inputs(b, p)
        a.field.set_progress(p)
        a._set_lr(p)
        a.fill_step_scalars(p)
        assert float(a.bg_w_dev) == pytest.approx(a.background_weight_at(p))
        seen.append(float(a.bg_w_dev))
        with torch.no_grad():
            lb, tb = b.step_loss(batch, xr, smp, p)
            monkeypatch.setattr(torch.cuda, "is_current_stream_capturing", lambda: True)
            la, ta = a.step_loss(batch, xr, smp, p)
            monkeypatch.undo()
        torch.testing.assert_close(ta["background"], tb["background"], rtol=1e-5, atol=1e-8)
        torch.testing.assert_close(la, lb, rtol=1e-5, atol=1e-7)
    assert seen[0] < seen[1] < seen[2] < seen[3] == pytest.approx(a.bg_weight) == seen[4]


def test_a_draw_graph_replays_only_the_draw_it_was_recorded_for(small_scene, tmp_path):
    """StepGraphs.drawn (CPU, the recording stood in for): a capped step replays a draw graph
    only after an eager draw of its ray count into the graphs' buffers, for an entry with a
    captured compute graph on those buffers, while nothing the draw reads was replaced; it is
    recorded once and again after such a replacement; draws off: never."""
    import collections

    from fastneus.train.graphstep import StepGraphs
    from fastneus.train.trainer import Trainer

    cfg = load_config("cpu-quick", SMALL_RUN + ["threads=1", "cuda_graph=off"])
    tr = Trainer(Scene.load(small_scene), cfg, tmp_path / "r", "cpu")
    tr.update_grid(0.0)
    g = StepGraphs.__new__(StepGraphs)
    g.cache, g._inputs, g._drawn, g.captures = collections.OrderedDict(), {}, {}, []
    recorded = []

    class _Graph:
        replays = 0

        def replay(self):
            _Graph.replays += 1

    g._record_draw = lambda t, n, e: recorded.append((n, e)) or _Graph()
    n, p = 96, 0.5
    assert g.drawn(tr, n, p) is None  # no eager draw of 96 rays yet
    b, x = g.inputs(*tr.draw(n, tr.gen), drawn=(n, g.draw_token(tr)))
    g._last = (40 * n, n)  # the last count read back: 40 samples per ray
    assert g.drawn(tr, n, p) is None  # no captured compute graph for the key
    est = g._estimate(n)
    key = g._key(tr, b, g._capacity(tr, b, est, p), p)
    e = g.cache[key] = _Entry(b, x, key[1], shared=True)
    assert g.drawn(tr, n, p) is None and not recorded  # captured? not yet
    e.graph = object()
    assert g.drawn(tr, n, p) == (key, e) and recorded == [(n, e)] and _Graph.replays == 1
    assert g.drawn(tr, n, p) == (key, e) and len(recorded) == 1 and _Graph.replays == 2 and g.drawn_steps == 2
    assert g.drawn(tr, 2 * n, p) is None  # another ray count: its own eager draw first
    tr.bank.rgb = tr.bank.rgb.clone()  # the same values in other memory: the graph would read the old
    assert g.drawn(tr, n, p) is None
    g.inputs(*tr.draw(n, tr.gen), drawn=(n, g.draw_token(tr)))
    assert g.drawn(tr, n, p) == (key, e) and len(recorded) == 2  # recorded again for the new tensors
    tr.grid.stop = torch.zeros_like(tr.grid.bits)  # the march's stop cells appear: a new token
    assert g.drawn(tr, n, p) is None
    g.inputs(*tr.draw(n, tr.gen), drawn=(n, g.draw_token(tr)))
    g._last = (80 * n, n)  # the count doubled: past the entry's capacity, no graph for it
    assert g.drawn(tr, n, p) is None
    g._last = (40 * n, n)
    g.draws_on = False
    assert g.drawn(tr, n, p) is None and len(recorded) == 2  # off: nothing recorded or replayed
    assert StepGraphs.same_draw((tr.bank.rgb, 1.0), (tr.bank.rgb, 1.0))
    assert not StepGraphs.same_draw((tr.bank.rgb, 1.0), (tr.bank.rgb.clone(), 1.0))
    assert not StepGraphs.same_draw((None, 1.0), (None, 0.5)) and not StepGraphs.same_draw((None,), (tr.bank.rgb,))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device")
def test_cuda_drawn_graph_matches_the_eager_draw(tmp_path):
    """A replayed draw graph (the rays, the uniform points and the capped march) writes what the
    eager draw and march write from the same default-generator state, bit for bit; training
    steps use it (drawn_steps > 0) and their loss stays finite."""
    from fastneus.train.trainer import Trainer

    scene = Scene.load(scene_on(None, tmp_path, "cuda"))
    cfg = load_config("fewview", SMALL_RUN + ["steps=80", "camera_blur=0"])
    tr = Trainer(scene, cfg, tmp_path / "r", "cuda")
    g = tr.graphs
    assert g is not None
    drawn, seen = g.drawn, []

    def spy(t, n, p):  # the first replayed draw, with the generator state before it and the grid it read
        state = torch.cuda.get_rng_state(t.device)
        got = drawn(t, n, p)
        if got is not None and not seen:
            e = got[1]
            stop = None if t.grid.stop is None else t.grid.stop.clone()
            seen.append((n, state, t.grid.bits.clone(), stop, {k: v.clone() for k, v in e.batch.items()},
                         e.xr.clone(), [b.clone() for b in e.capped_buffers()], e.capacity))
        return got

    g.drawn = spy
    losses = []
    for _ in range(60):
        rec = tr.train_step()
        if rec is not None:
            losses.append(float(rec["loss"]))
    assert g.drawn_steps > 0 and seen, g.summary()
    assert all(math.isfinite(v) for v in losses)
    n, state, bits, stop, rb, rxr, rsmp, cap = seen[0]
    torch.cuda.set_rng_state(state, tr.device)
    batch, xr = tr.draw(n, None)
    out = tuple(torch.empty_like(t) for t in rsmp)
    march_samples_capped(bits, tr.grid.resolution, batch["origins"], batch["dirs"], tr.cfg, out, stop=stop)
    assert set(batch) == set(rb)
    for k, v in batch.items():
        assert torch.equal(rb[k], v), k
    assert torch.equal(rxr, xr)
    for name, a, b in zip(("offsets", "counts", "total"), rsmp[:3], out[:3]):
        assert torch.equal(a, b), name
    live = min(int(out[2]), cap)
    for name, a, b in zip(("t0", "t1", "ray_index"), rsmp[3:], out[3:]):
        assert torch.equal(a[:live], b[:live]), name


def test_device_scalars_give_the_eager_loss_with_the_surface_prior(small_scene, tmp_path, monkeypatch):
    """A one-shot's fading surface prior in a captured step: the weight read from the device scalar
    ``fill_step_scalars`` wrote and the points drawn from the default generator give the eager
    loss (the run's generator in the same state); past ``init.prior_frac`` the term is off, its
    weight 0, and the step's graph key says so. On the CPU, by letting ``step_loss`` take its
    capturing branch."""
    from fastneus.train.graphstep import StepGraphs

    a, b = _pair(small_scene, tmp_path, "cpu", ["prior_frac=0.6"])
    a.prior = b.prior = _sphere_prior("cpu")
    a.cos_dev = torch.ones((1,))
    a.mask_w_dev = torch.full((), a.mask_weight_at(0.0))
    a.prior_w_dev = torch.zeros(())
    keys = set()
    for p in (0.1, 0.3, 0.55, 0.7):
        batch, xr, smp = _inputs(b, p)
        a.field.set_progress(p)
        a._set_lr(p)
        a.fill_step_scalars(p)
        assert float(a.prior_w_dev) == pytest.approx(a.prior_weight_at(p))
        assert (a.prior_weight_at(p) > 0) == a.prior_on(p) == (p < 0.6)
        keys.add(StepGraphs._key(None, a, batch, 4096, p))
        with torch.no_grad():
            torch.manual_seed(17)
            b.gen.manual_seed(17)
            lb, tb = b.step_loss(batch, xr, smp, p)
            monkeypatch.setattr(torch.cuda, "is_current_stream_capturing", lambda: True)
            la, ta = a.step_loss(batch, xr, smp, p)
            monkeypatch.undo()
        assert ("prior" in ta) == ("prior" in tb) == (p < 0.6)
        if p < 0.6:
            assert float(ta["prior"]) > 0
            torch.testing.assert_close(ta["prior"], tb["prior"], rtol=1e-5, atol=1e-8)
        torch.testing.assert_close(la, lb, rtol=1e-5, atol=1e-7)
    assert len(keys) == 2  # with the prior, and without it past prior_frac


@pytest.mark.parametrize("extra", [[], ["masks=off", "bg_prior=on"]])
def test_the_draw_token_covers_every_tensor_a_draw_reads(small_scene, tmp_path, extra):
    """A recorded draw graph reads the bank's tensors where they were when it was recorded, and
    StepGraphs.draw_token retires it when one of DRAW_FIELDS is replaced. Every tensor attribute
    the draw reads (RayBank.sample and the methods it calls, traced through a proxy) must be one
    of them, or replacing it would leave a graph reading stale memory."""
    import types

    from fastneus.train.graphstep import DRAW_FIELDS
    from fastneus.train.rays import RayBank
    from fastneus.train.trainer import Trainer

    cfg = load_config("cpu-quick", SMALL_RUN + ["threads=1", "bright_fraction=0.3"] + extra)
    tr = Trainer(Scene.load(small_scene), cfg, tmp_path / "r", "cpu")
    bank = tr.bank
    if "masks=off" in extra:
        bank.set_halo(1, 0.5)  # the halo's weights too (bg_soft)
        assert bank.fg is not None and bank.bg is not None and bank.bg_soft is not None
    assert bank.cdf is not None

    class Spy:
        def __init__(self):
            object.__setattr__(self, "seen", set())

        def __getattr__(self, k):
            v = getattr(bank, k)
            if isinstance(v, torch.Tensor):
                self.seen.add(k)
            elif callable(v) and callable(getattr(RayBank, k, None)):
                return types.MethodType(getattr(RayBank, k), self)  # its reads through the spy too
            return v

    spy = Spy()
    out = RayBank.sample(spy, 64, tr.gen, bright_fraction=0.3)
    assert out["origins"].shape == (64, 3)
    assert {"rgb", "offset", "wh", "kinv", "rot", "origin"} <= spy.seen
    assert spy.seen <= set(DRAW_FIELDS), spy.seen - set(DRAW_FIELDS)


def test_ray_count_jumps_to_a_far_target_only_with_graphs():
    """After the occupancy grid's first update the samples per ray fall several-fold: with CUDA
    graphs the ray count goes straight to its new target (each bucket passed on the way would be an
    eager step and a capture); near the target, and without graphs, it keeps its running mean."""
    from fastneus.train.trainer import RAY_JUMP, Trainer

    t = object.__new__(Trainer)
    t.cfg = load_config("fewview", ["target_samples=262144", "min_rays=256", "max_rays=65536"])
    for graphs in (None, object()):
        t.graphs = graphs
        t.n_rays = 1536
        # 1536 rays gave 1536 * 30 samples: the target is 262144 / 30 = 8738 rays
        n = t._next_ray_count(1536, 1536 * 30)
        assert n == (8738 if graphs is not None else int(0.8 * 1536 + 0.2 * 262144 / 30))
        t.n_rays = 8000  # within RAY_JUMP of the target: the running mean either way
        assert 8738 / RAY_JUMP < 8000
        assert t._next_ray_count(8000, 8000 * 30) == int(0.8 * 8000 + 0.2 * 262144 / 30)
        t.n_rays = 1536  # an empty step (no samples) never jumps
        assert t._next_ray_count(1536, 0) == int(0.8 * 1536 + 0.2 * 262144)
