"""Camera response, per-photo exposure and saturated pixels in training (issue 23)."""
from __future__ import annotations

import struct
import zlib
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch

from fastneus.config import load_config
from fastneus.data.response import decode, decode_lut, encode, encode_u8, parse_response, png_tags, resolve_response
from fastneus.errors import FastneusError
from fastneus.train import losses

from conftest import SMALL_RUN, one_line_error


# --------------------------------------------------------------------------- the response itself
@pytest.mark.parametrize("resp", ["linear", "srgb", "gamma=2.2", "gamma=1.8"])
def test_round_trip_within_quantisation(resp):
    x = np.linspace(0, 1, 2001)
    lut = decode_lut(resp)
    back = lut[encode_u8(x, resp)]
    # the error is at most half a code step, measured in linear units around the code
    k = np.round(encode(x, resp) * 255)
    mid = decode(k / 255, resp)
    half = np.maximum(decode(np.clip((k + 0.5) / 255, 0, 1), resp) - mid, mid - decode(np.clip((k - 0.5) / 255, 0, 1), resp))
    assert np.all(np.abs(back - x) <= half + 1e-6)
    codes = np.arange(256) / 255.0
    np.testing.assert_allclose(encode(decode(codes, resp), resp), codes, atol=1e-6)  # exact inverses
    assert lut[0] == 0 and lut[255] == pytest.approx(1.0)


def test_srgb_values_and_torch_numpy_agree():
    assert float(decode(np.array(0.5), "srgb")) == pytest.approx(0.21404, abs=1e-4)
    t = torch.linspace(0, 1, 11)
    np.testing.assert_allclose(encode(t, "srgb").numpy(), encode(t.numpy(), "srgb"), atol=1e-6)
    assert str(parse_response("GAMMA=2.2")) == "gamma=2.2" and str(parse_response("gamma=1")) == "linear"


@pytest.mark.parametrize("bad", ["srgbx", "gamma=", "gamma=0.1", "gamma=9", "", None, 2.2])
def test_bad_response_value(bad):
    with pytest.raises(FastneusError) as e:
        parse_response(bad, file="scene.json")
    assert e.value.field == "response" and "\n" not in str(e.value)


@pytest.mark.parametrize("bad", ["sRGBish", "gamma=0", "gamma=x", "log"])
def test_bad_response_knob_is_one_line(bad, small_scene, tmp_path, capsys):
    from fastneus.cli import main

    assert main(["train", str(small_scene), "--out", str(tmp_path / "r"), "--device", "cpu",
                 f"response={bad}"] + SMALL_RUN) != 0
    one_line_error(capsys, "illum.response")


def test_scene_json_response_is_parsed_and_checked(small_scene, tmp_path):
    import json
    import shutil

    from fastneus.data import Scene

    d = tmp_path / "s"
    shutil.copytree(small_scene, d)
    data = json.loads((d / "scene.json").read_text())
    data["response"] = "Gamma=2.2"
    (d / "scene.json").write_text(json.dumps(data))
    assert Scene.load(d).response == "gamma=2.2"
    data["response"] = "banana"
    (d / "scene.json").write_text(json.dumps(data))
    with pytest.raises(FastneusError) as e:
        Scene.load(d)
    assert e.value.field == "response" and str(e.value.file).endswith("scene.json")


# --------------------------------------------------------------------------- the auto decision
def _png(path, chunk: bytes | None = None, data: bytes = b""):
    cv2.imwrite(str(path), np.zeros((4, 4, 3), np.uint8))
    if chunk is not None:  # insert a colour chunk right after IHDR (8 + 25 bytes)
        raw = path.read_bytes()
        c = struct.pack(">I", len(data)) + chunk + data + struct.pack(">I", zlib.crc32(chunk + data) & 0xFFFFFFFF)
        path.write_bytes(raw[:33] + c + raw[33:])
    return path


def _fake_scene(tmp_path, image="a.png", response=None, meta=None):
    return SimpleNamespace(response=response, meta=meta or {}, frames=[SimpleNamespace(image=image)],
                           path=lambda rel: tmp_path / rel)


def test_auto_decision(tmp_path):
    _png(tmp_path / "plain.png")
    _png(tmp_path / "srgb.png", b"sRGB", b"\x00")
    _png(tmp_path / "lin.png", b"gAMA", struct.pack(">I", 100000))
    _png(tmp_path / "g18.png", b"gAMA", struct.pack(">I", 55556))
    assert png_tags(tmp_path / "srgb.png") == {"srgb": True} and png_tags(tmp_path / "plain.png") == {}
    cases = [(dict(response="gamma=2"), "gamma=2", "scene.json states"),
             (dict(meta={"generator": "fastneus synth"}), "linear", "synthetic"),
             (dict(meta={"source_format": "activeneus"}), "linear", "activeneus"),
             (dict(image="srgb.png"), "srgb", "sRGB chunk"),
             (dict(image="lin.png"), "linear", "gAMA"),
             (dict(image="g18.png"), "gamma=1.8", "gAMA"),
             (dict(image="plain.png", meta={"source_format": "nerf-transforms"}), "srgb", "state no encoding")]
    for kw, want, why in cases:
        r, note = resolve_response(_fake_scene(tmp_path, **kw), [0], "auto")
        assert str(r) == want and why in note and note.startswith("response: auto -> "), (kw, note)
    r, note = resolve_response(_fake_scene(tmp_path, response="srgb"), [0], "linear")  # the knob wins
    assert str(r) == "linear" and "asked for" in note


# --------------------------------------------------------------------------- the bank and the loss
def test_bank_decodes_through_the_lut(small_scene):
    from fastneus.data import Scene
    from fastneus.train.rays import RayBank

    scene = Scene.load(small_scene)
    lut = decode_lut("srgb")
    plain = RayBank(scene, [0, 1], "cpu")
    bank = RayBank(scene, [0, 1], "cpu", lut=lut, background=0.0, bg_tolerance=0.008)
    g = torch.Generator().manual_seed(0)
    b = bank.sample(256, g)
    u8 = bank.rgb[b["pix"]]
    np.testing.assert_allclose(b["rgb"].numpy(), lut[u8.numpy()])
    assert torch.equal(b["sat"], u8 >= 254)
    want = lut[plain.rgb.numpy()].mean(0)
    np.testing.assert_allclose(bank.mean_rgb().numpy(), want, rtol=1e-5)
    # the background flags of linear tolerance 0.008: codes up to 23 in sRGB (0.0080 linear)
    assert torch.equal(bank.bg, (bank.rgb <= 23).all(1))


def test_saturated_channels_onesided_and_mask():
    target = torch.tensor([[1.0, 0.5, 0.5], [0.5, 0.5, 0.5]])
    sat = torch.tensor([[True, False, False], [False, False, False]])
    brighter = torch.tensor([[1.0, 0.5, 0.5], [0.5, 0.5, 0.5]]) + torch.tensor([[0.0, 0.0, 0.0], [0, 0, 0]])
    brighter[0, 0] = 1.0
    target2 = target.clone()
    target2[0, 0] = 254 / 255  # a clipped channel just below 1
    off = losses.photometric(brighter, target2)["rgb"]
    one = losses.photometric(brighter, target2, sat=sat, saturated="onesided")["rgb"]
    assert float(off) > 0 and float(one) == 0.0  # rendering brighter than a clipped channel is no error
    darker = brighter.clone()
    darker[0, 0] = 0.5
    assert float(losses.photometric(darker, target2, sat=sat, saturated="onesided")["rgb"]) > 0
    # mask: the pixel with a saturated channel is left out; the others count as usual
    pred = torch.tensor([[0.0, 0.0, 0.0], [0.4, 0.5, 0.5]])
    m = losses.photometric(pred, target, sat=sat, saturated="mask")["rgb"]
    assert float(m) == pytest.approx(0.1 / 3)


@pytest.mark.parametrize("robust", ["l1", "charbonnier", "huber", "cauchy"])
def test_robust_penalties(robust):
    e = torch.tensor([0.0, 0.001, 0.1, 1.0])
    p = losses.penalty(e, robust, 0.01)
    assert float(p[0]) == 0 and torch.all(p[1:] > 0) and torch.all(p[1:] <= e[1:] + 1e-7)
    if robust in ("charbonnier", "huber"):  # L1 slope for large errors
        assert float(p[3] - p[2]) == pytest.approx(0.9, abs=1e-3)
    if robust == "cauchy":  # sub-linear: a large residual pulls far less than L1
        assert float(p[3]) < 0.1


# --------------------------------------------------------------------------- exposure in training
def test_exposure_gains_checkpointed_and_old_checkpoints_load(small_scene, tmp_path):
    from fastneus.data import Scene
    from fastneus.train.trainer import Trainer

    scene = Scene.load(small_scene)
    cfg = load_config("cpu-quick", SMALL_RUN + ["threads=1", "exposure=true"])
    tr = Trainer(scene, cfg, tmp_path / "a", "cpu")
    assert tr.log_gain is not None and tr.log_gain.shape == (2,)
    assert "exposure" in [g["name"] for g in tr.opt.param_groups]
    for _ in range(3):
        tr.train_step()
    with torch.no_grad():
        tr.log_gain.copy_(torch.tensor([0.1, -0.2]))
    st = tr.state()
    tr2 = Trainer(scene, cfg, tmp_path / "b", "cpu")
    tr2.load_state(st)
    assert torch.equal(tr2.log_gain, tr.log_gain)
    # a checkpoint written without exposure (older versions): loads, gains stay 1
    old = Trainer(scene, cfg.replace(exposure=False), tmp_path / "c", "cpu")
    old.train_step()
    tr3 = Trainer(scene, cfg, tmp_path / "d", "cpu")
    tr3.load_state(old.state())
    assert torch.equal(tr3.log_gain, torch.zeros(2)) and len(tr3.opt.param_groups) == len(tr.opt.param_groups)
    assert Trainer(scene, cfg.replace(exposure=False), tmp_path / "e", "cpu").log_gain is None


def test_exposure_recovered_on_a_tiny_scene(tmp_path):
    """Frames with known gains (synth exposure only): the learned gains move toward the truth.

    Measured (docs/benchmarks/realistic-cpu.md): on a tiny CPU scene the gains are recovered only
    in part (the view-dependent colour network explains some of a frame's brightness), so the
    check is that they beat "no exposure model" (all gains 1), not a tight tolerance."""
    from fastneus.pipeline import train_scene
    from fastneus.synth.render import synthesize

    scene = synthesize(tmp_path / "s", shape="sphere", views=6, size=(64, 64), seed=1, device="cpu",
                       proj_size=(128, 96), progress=False, contact_sheet=False, capture={"exposure": 0.3})
    scene.gt_mesh = None
    scene.save()
    true = np.log(np.asarray(scene.meta["capture"]["gains"]))
    assert np.abs(true).max() > 0.1  # the test needs gains that differ
    # the mask weight of the GPU preset: on this 6-view sphere cpu-quick's 0.3 recovers the gains
    # less well (0.74-0.88 of "no model" over 3 seeds, against 0.48-0.82 at 0.1), while on the
    # 20-view realistic scenes it recovers them better (docs/benchmarks/mask-weight.md); this test
    # is about the exposure model, not the mask weight
    cfg = load_config("cpu-quick", ["steps=400", "threads=1", "log_every=50", "save_every=1000",
                                    "mesh_resolution=16", "exposure=true", "mask_weight=0.1"])
    tr, m = train_scene(scene, cfg, tmp_path / "run", "cpu")
    learned = np.log(np.asarray(m["exposure_gains"]))
    assert learned[0] == 0.0  # the anchor
    assert np.abs(learned - true).mean() < 0.85 * np.abs(true).mean(), (learned, true)
    assert m["exposure_err"] == pytest.approx(np.abs(np.exp(learned - true) - 1).max(), abs=1e-3)


# --------------------------------------------------------------------------- 16-bit photos
def _deep_copy_of(small_scene, dst, response=None, bits_of=None):
    """``small_scene`` with its (linear, 8-bit) photos rewritten as 16-bit PNGs (code x 257: the
    same light), scene.json's response set to ``response`` (None: not stated) and the synth mark
    dropped (so nothing else says linear); ``bits_of``: frame indices to rewrite (default all)."""
    import json
    import shutil

    shutil.copytree(small_scene, dst)
    d = json.loads((dst / "scene.json").read_text())
    d.pop("response", None)
    (d.get("meta") or {}).pop("generator", None)
    if response is not None:
        d["response"] = response
    (dst / "scene.json").write_text(json.dumps(d))
    for i, f in enumerate(d["frames"]):
        if bits_of is None or i in bits_of:
            p = dst / f["image"]
            cv2.imwrite(str(p), cv2.imread(str(p), cv2.IMREAD_UNCHANGED).astype(np.uint16) * 257)
    return dst


def test_sixteen_bit_photos_become_srgb_codes_of_their_light(small_scene, tmp_path):
    """A 16-bit photo set (a machine-vision camera's) loads; untagged it is linear light, kept as
    8-bit sRGB codes (finer than 8-bit linear in the dark), and training decodes those as sRGB;
    stated as sRGB it is the same codes; the illum.response knob is refused for it in one line."""
    from fastneus.data import Scene

    ref = Scene.load(small_scene)
    sc = Scene.load(_deep_copy_of(small_scene, tmp_path / "lin16"))
    assert ref.photo_bits == 8 and sc.photo_bits == 16
    for i in range(len(sc.frames)):
        got, want = sc.image(i), encode_u8(ref.image(i) / 255.0, "srgb")
        assert got.dtype == np.uint8 and np.abs(got.astype(int) - want.astype(int)).max() <= 1
    # the light comes back: decoding the codes as sRGB gives the 8-bit linear photo within its step
    lin = decode(sc.image(0) / 255.0, "srgb")
    assert np.abs(lin - ref.image(0) / 255.0).max() < 0.5 / 255 + 0.01 * lin.max()
    r, note = resolve_response(sc, [0], "auto")
    assert str(r) == "srgb" and "16-bit photos, linear" in note and "no colour tag" in note
    with pytest.raises(FastneusError) as e:
        resolve_response(sc, [0], "linear")
    assert e.value.field == "illum.response" and "scene.json" in str(e.value)
    stated = Scene.load(_deep_copy_of(small_scene, tmp_path / "srgb16", response="srgb"))
    assert np.array_equal(stated.image(1), ref.image(1))  # v * 257 / 65535 = v / 255: the same codes
    assert "16-bit photos, srgb: scene.json states it" in resolve_response(stated, [0], "auto")[1]


def test_mixed_bit_depths_are_one_line(small_scene, tmp_path, capsys):
    from fastneus.cli import main

    d = _deep_copy_of(small_scene, tmp_path / "mixed", bits_of={1})
    assert main(["train", str(d), "--device", "cpu", "--out", str(tmp_path / "run"), "steps=1"]) == 2
    one_line_error(capsys, "frames[1].image", "16-bit", "8-bit")


def test_training_on_sixteen_bit_photos(small_scene, tmp_path):
    """The 16-bit set trains like the 8-bit one it was made from (same light, finer codes in the
    dark); the decision is printed and saved."""
    import json

    from fastneus.data import Scene
    from fastneus.pipeline import train_scene

    cfg = load_config("cpu-quick", SMALL_RUN + ["steps=30"])
    d = _deep_copy_of(small_scene, tmp_path / "lin16")
    train_scene(Scene.load(d), cfg, tmp_path / "run16", "cpu", finish=False)
    run = json.loads((tmp_path / "run16" / "run.json").read_text())
    assert run["response"].startswith("response: auto -> srgb (16-bit photos, linear")
