"""The lens's halo left out of the foreground flags in a dark room without masks (``loss.fg_halo``,
cpu-quick's choice): the rule on a drawn image, the bank's trim and restore, and the trainer's
timing (from ``fg_halo_frac``, only with a known blur, only in a dark room, printed and saved)."""
from __future__ import annotations

import torch

from conftest import SMALL_RUN
from fastneus.config import load_config
from fastneus.data import Scene
from fastneus.train.rays import _brightness, trim_halo


def _bar(h: int = 12, w: int = 12):
    """A 2-px bright bar (columns 5-6, rows 2-9) with a dim 1-px ring flagged foreground on its
    sides (columns 4 and 7: the blurred lens's halo), on a flagged backdrop."""
    bright = torch.zeros(h, w)
    bright[2:10, 5:7] = 1.0
    bright[5, 6] = 0.8      # a dimmer pixel of the object: still above 0.7 of its brightest neighbour
    bright[2:10, 4] = 0.3   # the halo
    bright[2:10, 7] = 0.3
    fg = bright > 0.2
    bg = ~fg
    return fg, bg, bright


def test_trim_halo_drops_the_dim_ring_beside_the_backdrop_and_keeps_the_part():
    fg, bg, bright = _bar()
    out = trim_halo(fg.reshape(-1), bg.reshape(-1), bright.reshape(-1), [(12, 12)], 0.7).reshape(12, 12)
    assert not out[2:10, 4].any() and not out[2:10, 7].any()      # the ring: beside the backdrop, 0.3 < 0.7
    assert out[2:10, 5:7].all()                                   # the bar, its dim pixel and its ends kept
    assert not (out & ~fg).any()                                  # nothing gains a flag
    # share > 1: every flagged pixel beside the backdrop, the bar's ends (rows 2 and 9) too
    whole = trim_halo(fg.reshape(-1), bg.reshape(-1), bright.reshape(-1), [(12, 12)], 1.5).reshape(12, 12)
    assert not whole[2, 5:7].any() and not whole[9, 5:7].any() and whole[3:9, 5:7].all()
    # frames are separate: a second frame's flags are trimmed on their own
    two = trim_halo(torch.cat([fg.reshape(-1), fg.reshape(-1)]), torch.cat([bg.reshape(-1), bg.reshape(-1)]),
                    torch.cat([bright.reshape(-1), bright.reshape(-1)]), [(12, 12), (12, 12)], 0.7)
    assert torch.equal(two[:144], out.reshape(-1)) and torch.equal(two[144:], out.reshape(-1))


def _dark_trainer(small_scene, tmp_path, extra=(), console=None):
    from fastneus.train.trainer import Trainer

    run = SMALL_RUN + ["threads=1", "masks=off", "bg_prior=on", "fg_prior=on", "steps=10", "camera_blur=0.7",
                       "fg_halo=0.7", "fg_halo_frac=0.5"] + list(extra)
    tr = Trainer(Scene.load(small_scene), load_config("cpu-quick", run), tmp_path / "r", "cpu", console=console)
    tr.bank.__dict__["lit_room"] = False  # the sphere scene is lit: the rule is for a dark room
    return tr


def test_the_trainer_trims_the_flags_from_fg_halo_frac_in_a_dark_room(small_scene, tmp_path):
    import io

    from rich.console import Console

    said = io.StringIO()
    tr = _dark_trainer(small_scene, tmp_path, console=Console(file=said, width=200))
    assert tr.fg_used and tr.bank.fg is not None
    loaded = tr.bank.fg
    while tr.progress() < 0.5:
        tr.train_step()
        assert tr.bank.fg is loaded and not tr.blur_decision.get("fg_halo")  # waits for half the run
    tr.train_step()
    assert tr.blur_decision["fg_halo"] == 0.7 and tr.bank.fg is not loaded
    assert "the lens's halo left out from step 5 (fg_halo 0.7)" in said.getvalue()
    assert bool((tr.bank.fg <= loaded).all()) and "fg_halo" in tr.blur_note()
    b = tr.bank
    want = trim_halo(loaded, b.bg, _brightness(b.rgb, b.lut, b._background), b._room[1], 0.7)
    assert torch.equal(tr.bank.fg, want)
    again = tr.bank.fg
    tr.update_fg_halo()  # a later blur decision: the same share, the flags left as they are
    assert tr.bank.fg is again
    tr.bank.set_fg_halo(0.0)  # put back
    assert torch.equal(tr.bank.fg, loaded) and tr.bank.fg is not loaded


def test_no_trim_in_a_lit_room_without_blur_or_with_masks(small_scene, tmp_path):
    from fastneus.train.trainer import Trainer

    lit = _dark_trainer(small_scene, tmp_path / "lit")
    lit.bank.__dict__["lit_room"] = True
    sharp = _dark_trainer(small_scene, tmp_path / "sharp", ["camera_blur=0"])
    for tr in (lit, sharp):
        loaded = tr.bank.fg
        while tr.progress() < 0.6:
            tr.train_step()
        assert tr.bank.fg is loaded and not tr.blur_decision.get("fg_halo")
    masked = Trainer(Scene.load(small_scene), load_config("cpu-quick", SMALL_RUN + ["threads=1", "camera_blur=0.7",
                                                                                   "fg_halo=0.7", "fg_halo_frac=0"]),
                     tmp_path / "m", "cpu")
    assert masked.masks_used and not masked.fg_used and not masked.blur_decision.get("fg_halo")


def test_both_presets_trim_late_with_the_photos_hull():
    """The trim was measured together with the photos' hull: every preset that trims also builds
    that hull; the GPU keeps no masked hull occupied (worse on the realistic rock); the one-shot,
    paper and passive presets do not trim (not measured there)."""
    for name, hull in (("cpu-quick", "auto"), ("fewview", "dark")):
        c = load_config(name)
        assert c.loss.fg_halo == 0.7 and c.loss.fg_halo_frac == 0.7
        assert c.occupancy.photo_hull == hull
    assert load_config("fewview").occupancy.hull_keep == "off"
    for name in ("paper", "oneshot", "passive"):
        assert load_config(name).loss.fg_halo == 0.0
