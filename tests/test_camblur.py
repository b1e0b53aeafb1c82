"""The camera's blur: synth forms blurred pixels as a lens + sensor, the model takes the blur on its
patterns (fastneus.train.camblur), and the line-profile measure recovers a known blur."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fastneus.synth.capture import Capture, make_capture, sensor_pixels
from fastneus.train.camblur import blur_pattern, projector_scale, ridge_moments


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


@pytest.mark.parametrize("sigma", [0.5, 0.8, 1.2])
def test_ridge_moments_recover_a_known_blur(sigma):
    # untextured lines (several, slanted) through a known lens + sensor: the median moment is
    # sigma^2 + 1/12 + w^2/12, so sigma comes back within 0.1 px
    sub, h, w = 8, 48, 64
    yy, xx = np.meshgrid((np.arange(h * sub) + 0.5) / sub, (np.arange(w * sub) + 0.5) / sub, indexing="ij")
    fine = np.zeros((h * sub, w * sub), np.float32)
    for x0, slope in ((12.2, 0.0), (30.7, 0.3), (47.4, -0.5)):
        d = np.abs((xx - x0 - slope * yy)) / math.sqrt(1 + slope ** 2)
        fine[d < 0.3] = 0.5
    img = sensor_pixels(torch.from_numpy(np.repeat(fine[..., None], 3, 2)), sigma, sub)[..., 0].numpy() + 0.2
    m = ridge_moments(img)
    assert m.size > 50
    est = math.sqrt(max(0.0, float(np.median(m)) - 1 / 12 - 0.6 ** 2 / 12))
    assert est == pytest.approx(sigma, abs=0.1)


def test_blur_pattern_keeps_the_light_and_widens_the_line():
    pat = np.zeros((40, 60, 3), np.uint8)
    pat[:, 29:32] = 255
    out = blur_pattern(pat, 2.0)
    prof = out[20, :, 0].astype(np.float64)
    assert prof.sum() == pytest.approx(3 * 255, rel=0.03)
    assert _moment(prof) == pytest.approx(4.0 + 8 / 12, abs=0.2)  # sigma^2 + the 3-px line's own
    assert blur_pattern(pat, 0.0) is pat


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
