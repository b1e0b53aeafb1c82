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
    bank.use_floor_background()
    assert bank.bg_tolerance == 0.008 and torch.equal(bank.bg, floor.bg)
    # a dark room: a dim leg next to a bright line keeps its flags (no relative test)
    v = np.zeros((10, 10), np.float32)
    v[:, 4] = 0.6
    v[:, 5] = 0.05
    v[0:8, 0:3] = 0.04
    codes = torch.from_numpy(np.repeat(np.round(v * 255).astype(np.uint8)[..., None], 3, -1).reshape(-1, 3))
    fg = foreground_flags(codes, None, 0.0, 0.02, 0.5, [(10, 10)]).reshape(10, 10).numpy()
    assert fg[:, 5].all() and fg[0:8, 0:3].all()
