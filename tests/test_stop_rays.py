"""Training rays end deep inside the object (``occupancy.stop_rays``, fastneus/train/trainer.py).

The decision (auto: with masks in a dark room), its note, the grid's stop cells after an update and
the march of a training step reading them; the march itself against its twin is in
tests/test_occupancy.py.
"""
from __future__ import annotations

import pytest
import torch

from conftest import SMALL_RUN
from fastneus.config import load_config
from fastneus.data import Scene


def _trainer(scene_dir, tmp_path, extra=()):
    from fastneus.train.trainer import Trainer

    cfg = load_config("cpu-quick", SMALL_RUN + ["threads=1", "init_geometry=sphere", "occ_warmup_frac=0"] + list(extra))
    return Trainer(Scene.load(scene_dir), cfg, tmp_path / "run", "cpu")


@pytest.mark.parametrize("extra,used", [([], False), (["stop_rays=on"], True), (["masks=off", "stop_rays=on"], True)])
def test_lit_room_decision(small_scene, tmp_path, extra, used):
    """The sphere scene is lit (its masked pixels' median brightness is over LIT_ROOM): auto is off."""
    tr = _trainer(small_scene, tmp_path, extra)
    assert tr.stop_used is used
    assert ("rays end 3 grid cells inside the object" in tr.masks_note) is used


def test_dark_room_with_masks_turns_it_on(small_scene, tmp_path, monkeypatch):
    from fastneus.train import rays

    tr = _trainer(small_scene, tmp_path)
    assert not tr.bank.dark_object()
    monkeypatch.setattr(rays, "LIT_ROOM", 2.0)  # every masked pixel now counts as dark
    tr = _trainer(small_scene, tmp_path / "dark")
    assert tr.bank.dark_object() and tr.stop_used
    assert "dark room: rays end 3 grid cells inside the object (stop_rays)" in tr.masks_note
    assert not _trainer(small_scene, tmp_path / "nomask", ["masks=off"]).stop_used  # no masks: auto is off
    assert not _trainer(small_scene, tmp_path / "off", ["stop_rays=off"]).stop_used
    # the same dark room keeps the masks' hull occupied (cpu-quick: occupancy.hull_keep=auto)
    assert tr.hull_in is not None and "dark room: its cells stay occupied for the whole run (hull_keep)" in tr.hull_note
    assert _trainer(small_scene, tmp_path / "nokeep", ["hull_keep=off"]).hull_in is None


def test_a_step_marches_with_the_grids_stop_cells(small_scene, tmp_path, monkeypatch):
    import fastneus.train.trainer as trainer_mod

    tr = _trainer(small_scene, tmp_path, ["stop_rays=on"])
    seen = []
    march = trainer_mod.march_samples

    def spy(*a, **k):
        seen.append(k.get("stop"))
        return march(*a, **k)

    monkeypatch.setattr(trainer_mod, "march_samples", spy)
    with torch.no_grad():  # a field that is a sphere of radius 0.6: its centre is deep inside
        tr.grid.update(lambda x: x.norm(dim=-1) - 0.6, 100.0, tr.cfg.rays.march_step,
                       inside=tr.cfg.occupancy.stop_inside * 2.0 / tr.grid.resolution)
    assert tr.grid.stop is not None and int(tr.grid.stop.sum()) > 0
    tr.step = 1  # no grid update at this step: the march reads the stop cells set above
    tr.train_step()
    assert seen and seen[-1] is tr.grid.stop
    kept = tr.grid.stop.clone()
    tr.update_grid(1.0)  # step 1: no update is due, the stop cells stay
    assert torch.equal(tr.grid.stop, kept)
    tr.step = 0
    tr.update_grid(0.5)  # a due update derives them again, from the trainer's field (a smaller sphere)
    assert tr.grid.stop is not None and not torch.equal(tr.grid.stop, kept)
    off = _trainer(small_scene, tmp_path / "off")
    off.step = 0
    off.update_grid(0.5)
    assert off.grid.stop is None
