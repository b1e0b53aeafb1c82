"""The camera's blur: synth forms blurred pixels as a lens + sensor, the model takes the blur on its
patterns (fastneus.train.camblur), and camera_blur=auto estimates it by rendering."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fastneus.synth.capture import Capture, make_capture, sensor_pixels
from fastneus.train.camblur import blur_pattern, projector_scale


def _line_image(h: int, w: int, x0: float, width: float, sigma: float, sub: int = 8) -> np.ndarray:
    """[h, w] a vertical line of ``width`` px at ``x0`` through a lens (sigma) and a sensor (sub)."""
    xs = (np.arange(w * sub) + 0.5) / sub
    fine = ((xs > x0 - width / 2) & (xs < x0 + width / 2)).astype(np.float32)
    img = torch.from_numpy(np.repeat(np.repeat(fine[None, :, None], h * sub, 0), 3, 2))
    return sensor_pixels(img, sigma, sub)[..., 0].numpy()


def _moment(profile: np.ndarray) -> float:
    k = np.arange(profile.size, dtype=np.float64)
    mu = (k * profile).sum() / profile.sum()
    return float(((k - mu) ** 2 * profile).sum() / profile.sum())


@pytest.mark.parametrize("sigma", [0.7, 1.2])
def test_sensor_pixels_integrate_the_pixel_and_the_lens(sigma):
    # a 5/8-px line: the pixel values keep its energy, spread as lens * box (var sigma^2 + 1/12 + w^2/12)
    w = 5 / 8
    img = _line_image(4, 24, 11.3, w, sigma)
    prof = img[2]
    assert prof.sum() == pytest.approx(w, rel=1e-3)
    assert _moment(prof) == pytest.approx(sigma ** 2 + 1 / 12 + w ** 2 / 12, abs=0.05)
    assert prof.max() < w + 1e-3  # never the aliased full-height spike of a point sample


def test_make_capture_supersamples_a_blurred_capture_only():
    assert make_capture({"blur": 0.7}).supersample == 4
    assert make_capture({"blur": 0.7, "supersample": 2}).supersample == 2
    assert make_capture({"speckle": 0.3}).supersample == 4  # stored, used only when blur > 0
    assert Capture().supersample == 1


def test_blur_pattern_keeps_the_light_and_widens_the_line():
    pat = np.zeros((40, 60, 3), np.uint8)
    pat[:, 29:32] = 255
    out = blur_pattern(pat, 2.0)
    prof = out[20, :, 0].astype(np.float64)
    assert prof.sum() == pytest.approx(3 * 255, rel=0.03)
    assert _moment(prof) == pytest.approx(4.0 + 8 / 12, abs=0.2)  # sigma^2 + the 3-px line's own
    assert blur_pattern(pat, 0.0) is pat


def _devices():
    return ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.mark.parametrize("device", _devices())
@pytest.mark.parametrize("sigma", [0.3, 0.76, 2.5])
def test_blur_pattern_torch_twin_matches_opencv(device, sigma):
    """The device path of the blur (the in-run estimate's candidates on a GPU) gives OpenCV's
    values: fresh random patterns with lines, edges and a border; at most one code apart where
    float32 sums fall on either side of a rounding tie."""
    from fastneus.train.camblur import blur_pattern_torch

    rng = np.random.default_rng()
    seed = int(rng.integers(2**31))
    rng = np.random.default_rng(seed)
    pat = (rng.random((37, 53, 3)) < 0.2).astype(np.uint8) * rng.integers(0, 256, (37, 53, 3)).astype(np.uint8)
    pat[:, 20:22] = 255
    pat[:, -1] = 200  # light at the border: zeros outside on both paths
    ref = blur_pattern(pat, sigma)
    out = blur_pattern(torch.from_numpy(pat).to(device), sigma)
    assert out.dtype == torch.uint8 and out.device.type == device and tuple(out.shape) == pat.shape
    diff = np.abs(out.cpu().numpy().astype(int) - ref.astype(int))
    assert diff.max() <= 1 and (diff > 0).mean() < 0.01, f"seed {seed}"
    assert blur_pattern_torch(out, 0.0) is out


def test_projection_from_pre_read_patterns_is_the_same(tmp_path):
    """``build_projection(..., patterns=pattern_images(...))`` (read once, the blur estimate's
    candidates) packs the same store as reading the scene each time."""
    from fastneus.synth.render import synthesize
    from fastneus.train.rays import build_projection, pattern_images

    scene = synthesize(tmp_path / "s", shape="sphere", views=2, size=(64, 64), device="cpu", noise=0.0,
                       proj_size=(128, 96), progress=False, contact_sheet=False)
    pats = pattern_images(scene, [0, 1], "cpu")
    assert pats and all(isinstance(v, np.ndarray) for v in pats.values())
    for s in (0.0, 0.7):
        a = build_projection(scene, [0, 1], "cpu", camera_blur=s)
        b = build_projection(scene, [0, 1], "cpu", camera_blur=s, patterns=pats)
        assert torch.equal(a.store.buffer, b.store.buffer) and torch.equal(a.store.meta, b.store.meta)
    # tensors (the GPU's form) take the torch blur: within one code of OpenCV's
    tens = {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in pats.items()}
    c = build_projection(scene, [0, 1], "cpu", camera_blur=0.7, patterns=tens)
    a = build_projection(scene, [0, 1], "cpu", camera_blur=0.7)
    assert (c.store.buffer.int() - a.store.buffer.int()).abs().max() <= 1


def test_projector_scale_on_the_synthetic_rig(tmp_path):
    from fastneus.synth.render import synthesize

    scene = synthesize(tmp_path / "s", shape="sphere", views=2, size=(64, 64), device="cpu", noise=0.0,
                       proj_size=(128, 96), progress=False, contact_sheet=False)
    p = scene.projectors["proj0"]
    cam = scene.frame_camera(0)
    s = projector_scale(scene, [0, 1], "proj0")
    ratio = float(p.K[0, 0]) / float(cam.K[0, 0])
    assert s == pytest.approx(ratio, rel=0.05)  # projectors on the camera's rig: about the focal ratio


def test_camera_blur_on_the_patterns_changes_only_the_patterns(tmp_path):
    from fastneus.synth.render import synthesize
    from fastneus.train.rays import build_projection

    scene = synthesize(tmp_path / "s", shape="sphere", views=1, size=(64, 64), device="cpu", noise=0.0,
                       proj_size=(128, 96), progress=False, contact_sheet=False)
    a = build_projection(scene, [0], "cpu")
    b = build_projection(scene, [0], "cpu", camera_blur=0.7)
    assert torch.equal(a.W, b.W) and torch.equal(a.pattern, b.pattern)
    sa, sb = a.store.buffer.double(), b.store.buffer.double()
    assert not torch.equal(sa, sb)
    assert float(sb.sum()) == pytest.approx(float(sa.sum()), rel=0.05)  # the light is spread, not lost
    assert float(sb.max()) < float(sa.max())


# --------------------------------------------------------------------------- camera_blur=auto
def test_fit_illumination_recovers_the_light_despite_outliers():
    from fastneus.train.blurfit import fit_illumination

    rng = np.random.default_rng(0)
    n = 4000
    c0 = rng.uniform(0.05, 0.3, n)
    a = rng.uniform(0.0, 1.0, n) * (rng.uniform(size=n) < 0.3)  # the projected light: lines on some pixels
    b = a * c0 * rng.uniform(2, 4, n)
    y = c0 + 0.1 * a + 0.4 * b + rng.normal(0, 0.002, n)
    y[rng.choice(n, 200, replace=False)] += 0.3  # e.g. specular glints: an L1 fit ignores them
    i_r, i_b, res = fit_illumination(y, c0, a, b)
    assert i_r == pytest.approx(0.4, abs=0.01) and i_b == pytest.approx(0.1, abs=0.01)
    assert res < 0.02


def test_pick_sigma_refines_the_grid_minimum():
    from fastneus.train.blurfit import AUTO_SIGMAS, pick_sigma

    s = np.asarray(AUTO_SIGMAS)
    assert pick_sigma(s, (s - 0.62) ** 2 + 1.0) == pytest.approx(0.62, abs=1e-6)
    assert pick_sigma(s, s + 1.0) == 0.0  # the sharpest candidate at the edge: no extrapolation
    assert pick_sigma(s, -s) == 1.5


@pytest.mark.parametrize("true_sigma", [0.0, 0.6])
def test_auto_blur_recovers_a_known_blur_with_a_fixed_field(tmp_path, true_sigma):
    """camera_blur=auto's estimate on a fixed field: the photos are the field's own render with the
    patterns blurred by a known sigma (i_r 0.4, i_b 0.1); the estimate picks that sigma back, 0
    for sharp photos, and recovers the light in closed form."""
    import dataclasses

    from fastneus.config import load_config
    from fastneus.field.renderer import march_samples, shade_samples
    from fastneus.synth.render import synthesize
    from fastneus.train.blurfit import estimate_blur_by_render
    from fastneus.train.rays import build_projection
    from fastneus.train.trainer import Trainer

    scene = synthesize(tmp_path / "s", shape="sphere", views=2, size=(48, 48), pattern="crosslaser",
                       device="cpu", noise=0.0, proj_size=(128, 96), progress=False, contact_sheet=False)
    cfg = load_config("cpu-quick", ["threads=1", "camera_blur=0", "occ_resolution=16", "log2_table=12",
                                    "levels=4", "finest_res=64"])
    tr = Trainer(scene, cfg, tmp_path / "r", "cpu")
    tr.update_grid(0.0)  # warm-up grid: every cell occupied, the field's initial sphere is the surface
    store = build_projection(scene, tr.frames, "cpu", camera_blur=true_sigma).store
    photo_proj = dataclasses.replace(tr.proj, store=store)
    sample = tr.bank.sample

    def photos(n, gen, **kw):  # the "camera": the field rendered through the blurred patterns
        b = sample(n, gen, **kw)
        smp = march_samples(tr.grid.bits, tr.grid.resolution, b["origins"], b["dirs"], cfg, jitter=False)
        with torch.no_grad():
            out = shade_samples(tr.field, smp, photo_proj, b["origins"], b["dirs"], b["fidx"], cfg,
                                i_r=torch.tensor([0.4]), i_b=torch.tensor([0.1]), cos_anneal=tr.cos_anneal())
        b["rgb"] = tr.rig.composite(out["color"], out, cfg.rays.background).clamp(max=1.0)
        b["sat"] = torch.zeros_like(b["rgb"], dtype=torch.bool)
        return b

    tr.bank.sample = photos
    info = estimate_blur_by_render(tr, n_rays=1024)
    assert 256 <= info["rays"] <= 1024 and len(info["residuals"]) == len(info["sigmas"])  # capped in samples
    assert info["sigma"] == pytest.approx(true_sigma, abs=0.12)
    assert info["fit_i_r"] == pytest.approx(0.4, abs=0.05) and info["fit_i_b"] == pytest.approx(0.1, abs=0.03)


def test_auto_blur_is_decided_once_saved_and_restored(tmp_path):
    """camera_blur=auto (the default): decided at blur_at_frac of the run, in the checkpoint, and a
    trainer that loads that checkpoint uses the same blur without estimating again; a number
    keeps today's fixed blur."""
    from conftest import SMALL_RUN

    from fastneus.config import load_config
    from fastneus.synth.render import synthesize
    from fastneus.train.trainer import Trainer

    scene = synthesize(tmp_path / "s", shape="sphere", views=2, size=(24, 24), pattern="crosslaser",
                       device="cpu", noise=0.0, proj_size=(64, 48), progress=False, contact_sheet=False)
    assert load_config("cpu-quick").rays.camera_blur == "auto"  # the default (docs/benchmarks/illum-realistic-gpu.md)
    cfg = load_config("cpu-quick", SMALL_RUN + ["threads=1", "steps=10", "camera_blur=auto"])
    assert cfg.rays.camera_blur == "auto"
    tr = Trainer(scene, cfg, tmp_path / "a", "cpu")
    assert tr.blur_pending and tr.camera_blur == 0.0 and "auto" in tr.blur_note()
    calls = []
    orig = tr.decide_camera_blur
    tr.decide_camera_blur = lambda: calls.append(tr.step) or orig()
    for _ in range(10):
        tr.train_step()
    assert calls == [3, 5]  # steps=10: at blur_at_frac 0.3, again at blur_refine_frac 0.5
    d = tr.blur_decision
    assert d["mode"] == "auto" and d["sigma"] is not None and d["sigma"] >= 0 and d["seconds"] >= 0
    assert len(d["rounds"]) == 2 and d["sigma"] == d["rounds"][-1]["sigma"] and not tr.blur_pending
    assert tr.camera_blur == d["sigma"] and "->" in tr.blur_note()
    st = tr.state()
    assert st["camera_blur"]["sigma"] == d["sigma"]
    tr.apply_camera_blur(0.7)  # pretend the estimate said 0.7: a restored run blurs by it
    st["camera_blur"]["sigma"] = 0.7
    again = Trainer(scene, cfg, tmp_path / "b", "cpu")
    again.load_state(st)
    assert not again.blur_pending and again.camera_blur == 0.7
    half = Trainer(scene, cfg, tmp_path / "h", "cpu")  # a checkpoint between the two estimates
    half.load_state(dict(st, camera_blur=dict(st["camera_blur"], rounds=st["camera_blur"]["rounds"][:1])))
    assert half.blur_due == [0.5] and half.camera_blur == 0.7
    assert torch.equal(again.proj.store.buffer, tr.proj.store.buffer)
    fixed = Trainer(scene, load_config("cpu-quick", SMALL_RUN + ["threads=1", "camera_blur=0.5"]), tmp_path / "c", "cpu")
    assert not fixed.blur_pending and fixed.camera_blur == 0.5 and fixed.blur_decision == {"mode": "set", "sigma": 0.5, "halo_px": 0}  # masks: no halo band


def test_camera_blur_config_values():
    from fastneus.config import camera_blur_sigma, load_config
    from fastneus.errors import FastneusError

    assert camera_blur_sigma(load_config("cpu-quick").rays.camera_blur) is None  # auto by default
    assert camera_blur_sigma(load_config("cpu-quick", ["camera_blur=0.76"]).rays.camera_blur) == 0.76
    assert camera_blur_sigma("auto") is None and camera_blur_sigma(0) == 0.0
    for bad in (["camera_blur=-0.1"], ["camera_blur=11"], ["camera_blur=sharp"], ["camera_blur=nan"],
                ["camera_blur=auto", "blur_via=rays"], ["blur_at_frac=1.5"]):
        with pytest.raises(FastneusError):
            load_config("cpu-quick", bad)
    assert load_config("cpu-quick", ["camera_blur=0.7", "blur_via=rays"]).rays.blur_via == "rays"


def _blur_trainer(tmp_path, device):
    from conftest import SMALL_RUN

    from fastneus.config import load_config
    from fastneus.synth.render import synthesize
    from fastneus.train.trainer import Trainer

    scene = synthesize(tmp_path / "s", shape="sphere", views=2, size=(24, 24), pattern="crosslaser",
                       device=device, noise=0.0, proj_size=(64, 48), progress=False, contact_sheet=False)
    cfg = load_config("cpu-quick", SMALL_RUN + ["threads=1", "steps=10", "camera_blur=auto", "cuda_graph=off"])
    return scene, Trainer(scene, cfg, tmp_path / "r", device)


def _check_blurred_stores(tmp_path, device):
    from fastneus.train.blurfit import AUTO_SIGMAS
    from fastneus.train.rays import build_projection

    scene, tr = _blur_trainer(tmp_path, device)
    tr.prime()
    kept = dict(tr._blurred)
    assert len(kept) == (len(AUTO_SIGMAS) if device == "cuda" else 0)  # the CPU keeps nothing
    for s in AUTO_SIGMAS:
        fresh = build_projection(scene, tr.frames, device, camera_blur=s, patterns=tr.pattern_images()).store
        got = tr.blurred_store(s)
        assert torch.equal(got.buffer, fresh.buffer) and torch.equal(got.meta, fresh.meta)
        if device == "cuda":
            assert got is kept[round(s, 6)]  # built once, before the clock
    for _ in range(10):  # both estimates (30 and 50 % of the run) use them, then they go
        tr.train_step()
    assert not tr.blur_pending and tr._blurred == {}
    if tr.camera_blur > 0:
        assert torch.equal(tr.proj.store.buffer, build_projection(scene, tr.frames, device, camera_blur=tr.camera_blur,
                                                                  patterns=tr.pattern_images()).store.buffer)


def test_blur_candidates_are_the_built_patterns(tmp_path):
    _check_blurred_stores(tmp_path, "cpu")


@pytest.mark.parametrize("cap", ["default", "zero"])
def test_cpu_blur_estimates_read_and_blur_the_patterns_once(tmp_path, monkeypatch, cap):
    """On the CPU the two blur estimates read each pattern image once and blur each candidate once
    (they were read again for every candidate of every round: ~1 s of a 30-s run), the kept
    stores go after the last estimate, and patterns over the host-memory cap are read again
    instead of kept."""
    from fastneus.data.scene import Scene
    from fastneus.train import blurfit
    from fastneus.train import trainer as T

    if cap == "zero":
        monkeypatch.setattr(T, "HOST_PATTERN_CACHE", 0)
    scene, tr = _blur_trainer(tmp_path, "cpu")
    reads, builds = [], []
    real_read, real_build = Scene.pattern_image, T.build_projection
    monkeypatch.setattr(Scene, "pattern_image", lambda self, pid: reads.append(pid) or real_read(self, pid))
    monkeypatch.setattr(T, "build_projection", lambda *a, **k: builds.append(k.get("camera_blur")) or real_build(*a, **k))
    tr.prime()
    for _ in range(10):  # both estimates (30 and 50 % of the run)
        tr.train_step()
    assert not tr.blur_pending and len(tr.blur_decision["rounds"]) == 2
    n_pat = len({fp.pattern for i in tr.frames for fp in scene.frames[i].projectors.values()})
    n_cand = len(blurfit.AUTO_SIGMAS)
    if cap == "default":
        assert len(reads) == n_pat  # once per run
        # each grid candidate built once for both rounds (plus a round's refined pick, if any)
        assert all(builds.count(s) == 1 for s in blurfit.AUTO_SIGMAS) and len(builds) < 2 * n_cand
    else:  # nothing kept: read and built per candidate and round (the old behaviour)
        assert len(reads) >= 2 * n_cand * n_pat and len(builds) >= 2 * n_cand
    assert tr._blurred == {} and tr._patterns is None  # dropped after the last estimate


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_blur_candidates_are_built_before_the_clock_and_dropped_after(tmp_path):
    _check_blurred_stores(tmp_path, "cuda")
