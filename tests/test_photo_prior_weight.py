"""The photo priors' weight in a lit room (loss.bg_weight_lit; the CPU preset's 0.3).

Without masks the background and foreground priors read "empty" and "object" off the photos. In a
lit room the CPU preset weighs them 3x (the realistic ant's thin legs survive: 29.0 -> 10.0 mm), in
a dark room not (the rock lost dim surface: 8.7 -> 10.9 mm); docs/benchmarks/mask-weight.md."""
from __future__ import annotations

import torch

from fastneus.config import load_config
from fastneus.train.rays import LIT_ROOM, lit_room


def _frame(h=64, w=64):
    return torch.zeros((h, w, 3), dtype=torch.uint8)


def test_lit_room_needs_bright_and_solid_object_pixels():
    size = [(64, 64)]
    lit = _frame()
    lit[16:48, 16:48] = 110                      # a lit object on a black backdrop
    assert lit_room(lit.reshape(-1, 3), None, 0.0, 0.02, size)
    dim = _frame()
    dim[16:48, 16:48] = 12                       # dark room: a dim ambient-lit object ...
    dim[30, 10:54, 0] = 250                      # ... crossed by a bright laser line
    assert not lit_room(dim.reshape(-1, 3), None, 0.0, 0.02, size)
    lines = _frame()
    lines[20, 8:56, 0] = 250                     # dark room, the object under the threshold: lines only
    lines[8:56, 40, 1] = 250
    assert not lit_room(lines.reshape(-1, 3), None, 0.0, 0.02, size)
    assert 110 / 255 > LIT_ROOM > 12 / 255
    assert not lit_room(_frame().reshape(-1, 3), None, 0.0, 0.02, size)  # nothing above the background


def test_the_trainer_weighs_the_priors_by_the_room(tmp_path):
    from fastneus.synth.render import synthesize
    from fastneus.train.trainer import Trainer

    assert load_config("cpu-quick").loss.bg_weight_lit == 0.3
    assert load_config("fewview").loss.bg_weight_lit == 0.3  # the GPU preset too (H100, mask-weight.md)
    seen = {}
    for illum in ("normal", "dark"):
        # the default projector (1024 x 768): a 64 x 48 one draws lines so wide that a dark scene's
        # photos are mostly laser-lit, bright and solid (what the room test then rightly calls lit)
        scene = synthesize(tmp_path / illum, shape="sphere", views=2, size=(64, 64), illum=illum, device="cpu",
                           noise=0.0, progress=False, contact_sheet=False)
        for preset in ("cpu-quick", "fewview", "zero"):
            over = ["bg_weight_lit=0"] if preset == "zero" else []  # 0: bg_weight in every room
            cfg = load_config("fewview" if preset == "zero" else preset, ["masks=off", "threads=1", *over])
            tr = Trainer(scene, cfg, tmp_path / f"r-{illum}-{preset}", "cpu")
            assert tr.bg_used
            seen[illum, preset] = (tr.bank.lit_room, tr.bg_weight, "lit room" in tr.bg_note)
    assert seen["normal", "cpu-quick"] == (True, 0.3, True)
    assert seen["dark", "cpu-quick"] == (False, 0.1, False)
    assert seen["normal", "fewview"] == (True, 0.3, True)
    assert seen["dark", "fewview"] == (False, 0.1, False)
    assert seen["normal", "zero"] == (True, 0.1, False)
    # with masks the photo priors are off whatever the room
    tr = Trainer(scene, load_config("cpu-quick", ["threads=1"]), tmp_path / "rm", "cpu")
    assert not tr.bg_used and tr.bg_weight == 0.1
