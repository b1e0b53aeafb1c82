"""The background tolerance follows the photos' noise floor (loss.bg_noise_k): a real camera's
black is a few thousandths above 0, and a fixed 2/255 tolerance then called a quarter of a
dark room's backdrop 'not background', which turned the foreground prior off (realistic ant,
no masks: legs lost). Ideal captures (black = 0) keep the fixed tolerance bit for bit."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from fastneus.data.response import decode_lut, encode_u8, parse_response
from fastneus.synth.render import synthesize
from fastneus.train.rays import RayBank, backdrop_noise, backdrop_tolerance


def test_tolerance_rule():
    assert backdrop_tolerance(0.008, 3.0, 0.0, 0.02) == 0.008           # ideal black: the floor
    assert backdrop_tolerance(0.008, 3.0, 0.004, 0.02) == pytest.approx(0.012)
    assert backdrop_tolerance(0.008, 3.0, 0.015, 0.02) == 0.02           # capped at the foreground threshold
    assert backdrop_tolerance(0.008, 3.0, 0.3, 0.02) == 0.008            # the median pixel is not backdrop
    assert backdrop_tolerance(0.008, 0.0, 0.004, 0.02) == 0.008          # off


def test_noise_floor_of_srgb_codes():
    srgb = parse_response("srgb")
    lut = torch.as_tensor(decode_lut(srgb))
    rng = np.random.default_rng(0)
    lin = np.clip(rng.normal(0.0, 0.002, (20000, 3)), 0, 1)
    codes = torch.from_numpy(encode_u8(lin, srgb).reshape(-1, 3))
    noise = backdrop_noise(codes, lut, 0.0)
    # median of the largest of three clipped N(0, 0.002) channels, through 8-bit sRGB codes
    ref = np.median(np.clip(rng.normal(0.0, 0.002, (200000, 3)), 0, 1).max(1))
    assert abs(noise - ref) < 0.0006
    assert backdrop_noise(torch.zeros(100, 3, dtype=torch.uint8), lut, 0.0) == 0.0
    assert backdrop_noise(torch.full((10, 3), 255, dtype=torch.uint8), None, 1.0) == 0.0


class _Noisy:
    """A scene whose backdrop (code 0) gets dark sRGB read noise; everything else as the original."""

    def __init__(self, scene, sigma):
        self._s, self._sigma = scene, sigma
        self._srgb = parse_response("srgb")

    def __getattr__(self, k):
        return getattr(self._s, k)

    def image(self, i):
        img = self._s.image(i).copy()
        rng = np.random.default_rng(i)
        back = (img == 0).all(-1)
        lin = np.clip(rng.normal(0.0, self._sigma, (int(back.sum()), 3)), 0, 1)
        img[back] = encode_u8(lin, self._srgb).reshape(-1, 3)
        return img


def test_raybank_widens_the_tolerance_on_a_noisy_backdrop_only(tmp_path):
    scene = synthesize(tmp_path / "s", shape="torus", views=2, size=(32, 28), illum="dark", seed=1, progress=False)
    frames = [0, 1]
    lut = decode_lut(parse_response("srgb"))
    kw = dict(background=0.0, bg_tolerance=0.008, bg_cap=0.02, lut=lut)
    ideal_fixed = RayBank(scene, frames, "cpu", bg_noise_k=0.0, **kw)
    ideal_auto = RayBank(scene, frames, "cpu", bg_noise_k=3.0, **kw)
    assert ideal_auto.bg_tolerance == 0.008 and torch.equal(ideal_auto.bg, ideal_fixed.bg)
    noisy = _Noisy(scene, 0.005)
    fixed = RayBank(noisy, frames, "cpu", bg_noise_k=0.0, **kw)
    auto = RayBank(noisy, frames, "cpu", bg_noise_k=3.0, **kw)
    assert 0.008 < auto.bg_tolerance <= 0.02
    assert fixed.bg_fraction < ideal_fixed.bg_fraction - 0.1        # the fixed tolerance loses the backdrop
    assert auto.bg_fraction > ideal_fixed.bg_fraction - 0.03       # the widened one keeps it
    # what the wider tolerance adds beyond the ideal backdrop: the dimmest object pixels (grazing,
    # ambient-lit), as dark as the camera's noise: a few percent of the frame at most
    assert float((auto.bg & ~ideal_fixed.bg).float().mean()) < 0.02


def test_foreground_flags_drop_the_halo_and_keep_thin_dim_parts():
    from fastneus.train.rays import foreground_flags

    h, w = 20, 30
    v = np.zeros((h, w), np.float32)
    v[5:15, 5:12] = 0.6                      # a bright blob
    v[4, 5:12] = v[15, 5:12] = 0.1          # its 1-px lens halo (1/6 of it)
    v[4:16, 4] = v[4:16, 12] = 0.1
    v[2:18, 20] = 0.04                       # a thin dim leg, 1 px wide
    v[1, 25] = 0.03                          # an isolated dim pixel: its own neighbourhood's max
    codes = torch.from_numpy(np.repeat(np.round(v * 255).astype(np.uint8)[..., None], 3, -1).reshape(-1, 3))
    fg = foreground_flags(codes, None, 0.0, 0.02, 0.5, [(w, h)]).reshape(h, w).numpy()
    assert fg[5:15, 5:12].all() and not fg[4, 5:12].any() and not fg[:, 12].any() and not fg[:, 4].any()
    assert fg[2:18, 20].all() and fg[1, 25]
    plain = foreground_flags(codes, None, 0.0, 0.02, 1e-9, [(w, h)]).reshape(h, w).numpy()
    assert plain[4, 5:12].all()              # threshold only: the halo counts as object


def test_floor_flags_outside_a_dark_room_and_no_halo_test_in_a_dark_one(tmp_path):
    """The wide tolerance's flags go back to the floor's when the trainer finds no dark room;
    in a dark room (dim above-threshold pixels) the foreground flags are the plain threshold."""
    from fastneus.train.rays import foreground_flags

    scene = synthesize(tmp_path / "s", shape="torus", views=2, size=(32, 28), illum="dark", seed=1, progress=False)
    lut = decode_lut(parse_response("srgb"))
    bank = RayBank(_Noisy(scene, 0.005), [0, 1], "cpu", background=0.0, bg_tolerance=0.008, bg_cap=0.02, lut=lut,
                   bg_noise_k=3.0)
    floor = RayBank(_Noisy(scene, 0.005), [0, 1], "cpu", background=0.0, bg_tolerance=0.008, bg_cap=0.02, lut=lut)
    assert bank.bg_tolerance > 0.008 and not torch.equal(bank.bg, floor.bg)
    bank.bg_soft = torch.zeros_like(bank.bg, dtype=torch.uint8)  # weights made from the wide flags
    bank.use_floor_background()
    assert bank.bg_tolerance == 0.008 and torch.equal(bank.bg, floor.bg) and bank.bg_soft is None
    # a dark room: a dim leg next to a bright line keeps its flags (no relative test)
    v = np.zeros((10, 10), np.float32)
    v[:, 4] = 0.6
    v[:, 5] = 0.05
    v[0:8, 0:3] = 0.04
    codes = torch.from_numpy(np.repeat(np.round(v * 255).astype(np.uint8)[..., None], 3, -1).reshape(-1, 3))
    fg = foreground_flags(codes, None, 0.0, 0.02, 0.5, [(10, 10)]).reshape(10, 10).numpy()
    assert fg[:, 5].all() and fg[0:8, 0:3].all()


def _codes(v: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.repeat(np.round(v * 255).astype(np.uint8)[..., None], 3, -1).reshape(-1, 3))


def test_halo_weights_weigh_the_lens_halo_as_background_and_spare_thin_parts():
    """A blurred blob's halo (neither flag) becomes partial background by how far under the
    neighbourhood's brightest pixel it is; the flags' own pixels, a thin part (its own
    neighbourhood's maximum) and pixels away from the backdrop keep their weights."""
    import cv2

    from fastneus.train.rays import foreground_flags, halo_radius, halo_weights

    h, w = 24, 36
    sharp = np.zeros((h, w), np.float32)
    sharp[6:18, 5:15] = 0.6                   # a lit blob
    sharp[3:21, 25] = 0.3                     # a thin leg, 1 px wide
    v = cv2.GaussianBlur(sharp, (0, 0), 0.7)
    codes = _codes(v)
    fg = foreground_flags(codes, None, 0.0, 0.02, 0.5, [(w, h)])
    bg = torch.from_numpy(np.round(v * 255).reshape(-1) <= 2)
    r = halo_radius(0.7)
    assert r == 2 and halo_radius(0.0) == 0 and halo_radius(0.5) == 1
    wt = halo_weights(codes, None, 0.0, fg, bg, [(w, h)], r, 0.35).reshape(h, w).numpy()
    fgi, bgi = fg.reshape(h, w).numpy(), bg.reshape(h, w).numpy()
    assert (wt[bgi] == 255).all() and (wt[fgi] == 0).all()
    ring = ~fgi & ~bgi
    assert ring[5, 6:14].all() and (wt[5, 6:14] > 60).all()     # the blob's halo row: backdrop now
    assert fgi[3:21, 25].all() and (wt[3:21, 25] == 0).all()    # the leg stays free of the prior
    # the rule: weight = 1 - (v / max within 2 px) / share, clamped, on the band's pixels
    y, x = 5, 9
    ratio = np.round(v * 255)[y, x] / np.round(v * 255)[max(0, y - 2):y + 3, x - 2:x + 3].max()
    assert abs(wt[y, x] / 255 - max(0.0, 1 - ratio / 0.35)) < 0.01
    assert torch.equal(halo_weights(codes, None, 0.0, fg, bg, [(w, h)], 0, 0.35), bg.to(torch.uint8) * 255)


def test_trainer_weighs_the_halo_only_for_a_blurred_capture_in_a_lit_room(tmp_path):
    """camera_blur > 0, no masks, a lit room: batches carry fractional background weights and
    the note says so; a sharp capture (camera_blur=0) keeps the 0/1 flags bit for bit."""
    from fastneus.config import load_config
    from fastneus.train.rays import pixel_fields
    from fastneus.train.trainer import Trainer

    scene = synthesize(tmp_path / "s", shape="torus", views=2, size=(40, 36), illum="normal", seed=1,
                       progress=False, realistic=True)
    base = ["steps=4", "masks=off", "bg_prior=on", "fg_prior=on", "exposure=off", "occ_resolution=16"]
    sharp = Trainer(scene, load_config("cpu-quick", base + ["camera_blur=0"]), tmp_path / "a", "cpu")
    blurred = Trainer(scene, load_config("cpu-quick", base + ["camera_blur=0.7"]), tmp_path / "b", "cpu")
    assert sharp.bank.lit_room and blurred.bank.lit_room
    assert sharp.bank.bg_soft is None and sharp.blur_decision["halo_px"] == 0
    assert blurred.blur_decision["halo_px"] == 2 and "halo" in blurred.blur_note()
    flat = torch.arange(blurred.bank.n_pixels)
    soft = pixel_fields(blurred.bank, flat, blurred.bank.rgb)["bg"]
    plain = pixel_fields(sharp.bank, flat, sharp.bank.rgb)["bg"]
    assert torch.equal(plain, sharp.bank.bg.float())
    part = (soft > 0) & (soft < 1)
    assert int(part.sum()) > 0 and not blurred.bank.bg[part].any()        # only unflagged pixels gain weight
    assert torch.equal(soft[blurred.bank.bg], torch.ones(int(blurred.bank.bg.sum())))
    off = Trainer(scene, load_config("cpu-quick", base + ["camera_blur=0.7", "bg_halo=0"]), tmp_path / "c", "cpu")
    assert off.bank.bg_soft is None and off.blur_decision["halo_px"] == 0
    blurred.train_step()  # the fractional weights go through the loss
