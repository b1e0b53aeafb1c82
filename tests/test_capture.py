"""Realistic captures in synth (fastneus.synth.capture): each effect does what it says, measured
on a small render against the ideal capture of the same scene and seed; ground truth stays linear."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from fastneus.data.response import encode
from fastneus.errors import FastneusError
from fastneus.synth.capture import (REALISTIC, Capture, apply_speckle, blinn_phong, finish, frame_gains,
                                    make_capture, vignette)
from fastneus.synth.render import synthesize
from fastneus.synth.shapes import make_shape

SMALL = dict(shape="sphere", views=2, size=(64, 64), pattern="crosslaser", seed=0, device="cpu", noise=0.0,
             proj_size=(128, 96), progress=False, contact_sheet=False)


def _render(root, name, capture=None, realistic=False):
    scene = synthesize(root / name, capture=capture, realistic=realistic, **SMALL)
    imgs = np.stack([scene.image(i) for i in range(len(scene.frames))]).astype(np.float64) / 255.0
    masks = np.stack([scene.mask(i) > 0.5 for i in range(len(scene.frames))])
    return scene, imgs, masks


@pytest.fixture(scope="module")
def ideal(tmp_path_factory):
    return _render(tmp_path_factory.mktemp("cap"), "ideal")


def test_ideal_states_linear_and_has_no_capture(ideal):
    scene = ideal[0]
    assert scene.response == "linear" and "capture" not in scene.meta
    assert json.loads((scene.root / "scene.json").read_text())["response"] == "linear"


def test_speckle_multiplies_the_projected_light_only(tmp_path, ideal):
    scene, ref, masks = ideal
    _, img, _ = _render(tmp_path, "speckle", {"speckle": 0.3})
    clean = np.stack([scene.gt_clean(i) for i in range(len(scene.frames))]) / 255.0
    unlit = masks & (np.abs(ref - clean).max(-1) == 0)  # no pattern light (the pattern-free image)
    lit = masks & (np.abs(ref - clean).max(-1) > 0.1)
    assert unlit.sum() > 50 and lit.sum() > 50
    np.testing.assert_array_equal(img[unlit], ref[unlit])  # ambient light untouched
    ratio = (img - clean)[lit].sum(-1) / (ref - clean)[lit].sum(-1)  # the projected light's speckle factor
    assert abs(np.median(ratio) - 1) < 0.1 and 0.2 < ratio.std() < 0.4
    q = torch.ones(20000, 3)
    s = apply_speckle(q, 0.3, (0, 1))
    assert abs(float(s.mean()) - 1) < 0.02 and abs(float(s[:, 0].std()) - 0.3) < 0.02
    assert torch.equal(s[:, 0], s[:, 1])  # one speckle grain value for the three channels


def test_specular_adds_highlights(tmp_path, ideal):
    _, ref, masks = ideal
    _, img, _ = _render(tmp_path, "spec", {"specular": 0.5, "shininess": 20})
    d = (img - ref)[masks]
    assert d.min() >= -1.5 / 255  # only adds light (rounding aside)
    assert d.max() > 0.2  # a real highlight somewhere on the sphere
    n = torch.tensor([[0.0, 0.0, 1.0]] * 2)
    lobe = blinn_phong(n, torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]), torch.tensor([0.0, 0.0, 1.0]), 40.0)
    assert float(lobe[0]) == pytest.approx(1.0) and float(lobe[1]) < 0.01


def test_exposure_gains_scale_frames(tmp_path, ideal):
    _, ref, masks = ideal
    scene, img, _ = _render(tmp_path, "exp", {"exposure": 0.25})
    gains = scene.meta["capture"]["gains"]
    assert gains[0] == 1.0 and all(0.8 - 1e-6 <= g <= 1.25 + 1e-6 for g in gains)
    for f, g in enumerate(gains):
        sel = masks[f] & (ref[f].max(-1) > 0.1) & (ref[f].max(-1) * g < 0.95)
        ratio = np.median(img[f][sel].sum(-1) / ref[f][sel].sum(-1))
        assert ratio == pytest.approx(g, abs=0.02)
    g = frame_gains(200, 0.25, 3)
    assert g[0] == 1.0 and g.min() >= 0.8 - 1e-9 and g.max() <= 1.25 + 1e-9 and g.std() > 0.05


def test_white_balance_gains_scale_each_channel(tmp_path, ideal):
    """``white_balance``: every channel of a frame scaled by its own gain (frame 0 by 1), saved."""
    from fastneus.synth.capture import channel_gains

    _, ref, masks = ideal
    scene, img, _ = _render(tmp_path, "wb", {"white_balance": 0.2})
    wb = np.asarray(scene.meta["capture"]["white_balance_gains"])
    assert wb.shape == (len(scene.frames), 3) and np.all(wb[0] == 1.0)
    assert np.all((wb >= 1 / 1.2 - 1e-6) & (wb <= 1.2 + 1e-6)) and wb[1:].std() > 0.02
    for f in range(len(scene.frames)):
        for c in range(3):
            sel = masks[f] & (ref[f][..., c] > 0.1) & (ref[f][..., c] * wb[f, c] < 0.95)
            assert np.median(img[f][..., c][sel] / ref[f][..., c][sel]) == pytest.approx(wb[f, c], abs=0.02)
    assert np.array_equal(channel_gains(5, 0.0, 1), np.ones((5, 3)))


def test_blur_smooths_and_keeps_light(tmp_path, ideal):
    _, ref, _ = ideal
    _, img, _ = _render(tmp_path, "blur", {"blur": 0.7})
    energy = lambda x: (np.diff(x, axis=2) ** 2).mean()  # noqa: E731 (high-frequency energy)
    assert energy(img) < 0.7 * energy(ref)
    assert img.sum() == pytest.approx(ref.sum(), rel=0.02)


def test_vignetting_darkens_corners():
    v = vignette(64, 64, 0.25, "cpu")[..., 0]
    assert float(v[32, 32]) > 0.999 and float(v[0, 0]) == pytest.approx(0.75, abs=0.01)
    img = torch.full((64, 64, 3), 0.5)
    out = finish(img, Capture(vignetting=0.25), 1.0, (0,))
    assert float(out[0, 0, 0]) < float(out[32, 32, 0]) - 0.1


def test_noise_read_and_shot():
    cap = Capture(read_noise=0.01, shot_noise=0.004)
    for level in (0.2, 0.6):
        out = finish(torch.full((200, 200, 3), level), cap, 1.0, (1,))
        assert float(out.std()) == pytest.approx((0.01 ** 2 + 0.004 * level) ** 0.5, rel=0.05)


def test_saturation_and_response():
    img = torch.tensor([[[0.2, 0.9, 3.0]]])
    lin = finish(img, Capture(), 1.2, (0,))
    assert lin.flatten().tolist() == pytest.approx([0.24, 1.0, 1.0])  # gain, then clipped at 1
    srgb = finish(img, Capture(response="srgb"), 1.0, (0,))
    assert float(srgb[0, 0, 0]) == pytest.approx(float(encode(torch.tensor(0.2), "srgb")))
    assert float(srgb[0, 0, 0]) == pytest.approx(0.4845, abs=1e-3)  # sRGB of 0.2


def test_realistic_scene_states_response_and_keeps_linear_truth(tmp_path, ideal):
    scene, img, masks = _render(tmp_path, "real", realistic=True)
    assert scene.response == "srgb"
    assert scene.illumination.i_r == ideal[0].illumination.i_r and scene.illumination.known
    cap = scene.meta["capture"]
    assert {k: cap[k] for k in REALISTIC} == REALISTIC and len(cap["gains"]) == len(scene.frames)
    # the photos are sRGB-encoded: object pixels are much brighter than the linear ones
    assert img[masks].mean() > 1.3 * ideal[1][masks].mean()
    # clean (ground truth, pattern-free) images stay the linear ideal ones
    np.testing.assert_array_equal(scene.gt_clean(0), ideal[0].gt_clean(0))


@pytest.mark.parametrize("opts, field", [({"speckle": -0.1}, "capture.speckle"), ({"blur": float("nan")}, "capture.blur"),
                                         ({"response": "gama=2"}, "capture.response"),
                                         ({"sparkle": 1}, "capture.sparkle"),
                                         ({"interreflection": 5}, "capture.interreflection"),
                                         ({"interreflection": -0.5}, "capture.interreflection"),
                                         ({"bits": 12}, "capture.bits"), ({"bits": 16.5}, "capture.bits")])
def test_bad_capture_options(opts, field):
    with pytest.raises(FastneusError) as e:
        make_capture(opts)
    assert e.value.field == field and "\n" not in str(e.value)


def test_make_capture_defaults():
    assert make_capture(None) is None and make_capture({}) is None
    c = make_capture({"speckle": 0.5}, realistic=True)
    assert c.speckle == 0.5 and c.response == "srgb" and c.blur == REALISTIC["blur"]


@pytest.mark.parametrize("name", ["ant", "airplane", "hexnut"])
def test_thin_shapes_are_closed(name):
    m = make_shape(name)
    assert m.is_watertight and len(m.faces) > 100
    if name == "hexnut":  # one part with a hole through it: genus 1
        assert m.euler_number == 0 and m.is_volume


def test_interreflection_adds_nothing_on_a_convex_shape(tmp_path):
    """A sphere sees no other surface: every bounce ray misses, the photos are unchanged."""
    _, ref, _ = _render(tmp_path, "lin", {"response": "linear"})
    scene, img, _ = _render(tmp_path, "ir", {"response": "linear", "interreflection": 1.0})
    np.testing.assert_array_equal(img, ref)
    assert scene.meta["capture"]["interreflection"] == 1.0


@pytest.mark.parametrize("illum", ["normal", "dark"])
def test_interreflection_lights_the_parts_that_see_each_other(tmp_path, illum):
    """The toy's cup, fin, torus and ball light each other: photos and pattern-free images only get
    brighter, by a visible amount somewhere; in a dark room the lasers' light is bounced too (the
    photos gain more than the pattern-free images)."""
    opts = dict(SMALL, shape="toy", illum=illum)
    out = {}
    for name, ir in (("off", 0.0), ("on", 1.0)):
        sc = synthesize(tmp_path / f"{illum}-{name}", capture={"response": "linear", "interreflection": ir}, **opts)
        imgs = np.stack([sc.image(i) for i in range(len(sc.frames))]).astype(np.float64) / 255.0
        clean = np.stack([sc.gt_clean(i) for i in range(len(sc.frames))]).astype(np.float64) / 255.0
        masks = np.stack([sc.mask(i) > 0.5 for i in range(len(sc.frames))])
        out[name] = (imgs, clean, masks)
    (i0, c0, m), (i1, c1, _) = out["off"], out["on"]
    gain, gain_clean = (i1 - i0)[m], (c1 - c0)[m]
    assert gain.min() >= -1.5 / 255 and gain_clean.min() >= -1.5 / 255  # light is only added
    assert gain.max() > 0.05 and (gain.max(-1) > 2 / 255).mean() > 0.1
    if illum == "dark":
        assert (gain - gain_clean).max() > 0.02  # laser light reflected onto another part
    else:
        assert gain_clean.max() > 0.05  # the room's light bounced: part of the pattern-free truth


def test_interreflection_under_water_is_refused(tmp_path):
    with pytest.raises(FastneusError) as e:
        synthesize(tmp_path / "wet", capture={"interreflection": 1.0}, medium="water", **SMALL)
    assert e.value.field == "capture.interreflection"


def test_synth_command_takes_interreflection(tmp_path, capsys):
    from fastneus.cli import main

    out = tmp_path / "cli"
    assert main(["synth", "--shape", "sphere", "--views", "1", "--size", "32x32", "--device", "cpu",
                 "--response", "linear", "--interreflection", "0.5", "--no-contact-sheet", "--out", str(out)]) == 0
    meta = json.loads((out / "scene.json").read_text())["meta"]["capture"]
    assert meta["interreflection"] == 0.5 and meta["response"] == "linear"
    capsys.readouterr()
    assert main(["synth", "--shape", "sphere", "--views", "1", "--size", "32x32", "--device", "cpu",
                 "--interreflection", "9", "--out", str(tmp_path / "bad")]) == 2
    err = capsys.readouterr().err
    assert "capture.interreflection" in err and "Traceback" not in err


def test_sixteen_bit_photos_hold_the_same_light_finer(tmp_path, ideal):
    """``bits=16`` writes the photos as 16-bit PNGs of the same linear light (a machine-vision
    camera's); loaded, they come as 8-bit sRGB codes whose light is the 16-bit file's to within an
    sRGB code, and finer in the dark than the 8-bit linear capture's codes."""
    import cv2

    lin8, _, _ = _render(tmp_path, "lin8", capture={"response": "linear", "read_noise": 0.0005})
    s16 = synthesize(tmp_path / "lin16", capture={"response": "linear", "read_noise": 0.0005, "bits": 16}, **SMALL)
    raw = cv2.imread(str(s16.root / s16.frames[0].image), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16 and s16.photo_bits == 16 and s16.meta["capture"]["bits"] == 16
    light16 = raw[:, :, ::-1].astype(np.float64) / 65535.0
    # the same light as the 8-bit capture, to within the 8-bit linear step
    assert np.abs(light16 - lin8.image(0) / 255.0).max() <= 0.5 / 255 + 1e-9
    from fastneus.data.response import decode

    back = decode(s16.image(0) / 255.0, "srgb")
    c = s16.image(0).astype(np.float64)
    span = decode(np.minimum(c + 1, 255) / 255.0, "srgb") - decode(np.maximum(c - 1, 0) / 255.0, "srgb")
    assert np.all(np.abs(back - light16) <= 0.5 * span + 1e-12)  # rounded to the nearest sRGB code
    dark = (light16 > 0.0001) & (light16 < 0.01)  # the backdrop under read noise, the shadows
    assert dark.any()
    err16 = np.abs(back - light16)[dark].mean()
    err8 = np.abs(lin8.image(0) / 255.0 - light16)[dark].mean()
    assert err16 < 0.5 * err8                                 # the dark end: sRGB codes are finer
