"""The learning-rate schedule: each group's warm-up starts where the group starts learning."""
import math

import pytest

from conftest import SMALL_RUN
from fastneus.config import load_config
from fastneus.data import Scene
from fastneus.train.trainer import Trainer, lr_warmup


def test_lr_warmup_ramps_from_its_start():
    assert lr_warmup(0.0, 0.0, 0.1, 0.7) == pytest.approx(0.1)
    assert lr_warmup(0.05, 0.0, 0.1, 0.7) == pytest.approx(0.55)
    assert lr_warmup(0.1, 0.0, 0.1, 0.7) == 0.7  # the ramp ends at the decay's value
    # a group that starts at 0.2 ramps over [0.2, 0.3]; before its start the factor stays 0.1
    assert lr_warmup(0.1, 0.2, 0.1, 0.7) == pytest.approx(0.1)
    assert lr_warmup(0.25, 0.2, 0.1, 0.7) == pytest.approx(0.55)
    assert lr_warmup(0.35, 0.2, 0.1, 0.7) == 0.7
    assert lr_warmup(0.0, 0.0, 0.0, 0.7) == 0.7  # no warm-up


def test_geometry_warms_up_after_the_colour_warmup(small_scene, tmp_path):
    """The geometry is frozen during the colour warm-up, then ramps in from 0.1 of its rate
    (it used to start at the full rate: Adam's first steps broke the surface up)."""
    cfg = load_config("cpu-quick", SMALL_RUN + ["threads=1", "warmup_frac=0.05", "color_warmup_frac=0.05",
                                                "decay_to=1.0"])
    tr = Trainer(Scene.load(small_scene), cfg, tmp_path / "run", "cpu")
    lr = lambda p, name: (tr._set_lr(p), next(g["lr"] for g in tr.opt.param_groups if g["name"] == name))[1]  # noqa: E731
    base = {g["name"]: g["base_lr"] for g in tr.opt.param_groups}
    assert lr(0.04, "geometry") == 0.0 and lr(0.04, "variance") == 0.0
    assert lr(0.04, "color") == pytest.approx(base["color"] * (0.1 + 0.9 * 0.04 / 0.05))
    assert lr(0.05, "geometry") == pytest.approx(0.1 * base["geometry"])
    assert lr(0.075, "geometry") == pytest.approx(0.55 * base["geometry"])
    assert lr(0.075, "variance") == pytest.approx(0.55 * base["variance"])
    assert lr(0.075, "color") == pytest.approx(base["color"])  # its own ramp ended at 0.05
    assert lr(0.2, "geometry") == pytest.approx(base["geometry"])
    assert math.isfinite(lr(1.0, "geometry"))
