"""illum.level: a dim capture is trained brighter (the priors' thresholds were set on captures of a
normal level) and everything reported is divided back into the photos' own units."""
from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest

from fastneus.config import load_config
from fastneus.data import Scene
from fastneus.synth.render import synthesize
from fastneus.train.rays import LEVEL_LOW, LEVEL_MAX_GAIN, LEVEL_REF, level_gain, photo_level

KW = dict(shape="torus", views=3, size=(40, 40), pattern="crosslaser", illum="dark", seed=0, device="cpu",
          progress=False, contact_sheet=False)
TINY = ["steps=40", "log_every=10", "mesh_resolution=40", "occ_resolution=32", "target_samples=4096",
        "init_rays=256", "max_rays=512", "render_frames=[0]"]


def test_level_gain_rule():
    assert level_gain(LEVEL_LOW) == 1.0 and level_gain(0.9) == 1.0 and level_gain(0.0) == 1.0
    x = float(np.random.default_rng().uniform(LEVEL_REF / LEVEL_MAX_GAIN + 1e-3, LEVEL_LOW - 1e-3))
    assert level_gain(x) == pytest.approx(LEVEL_REF / x)
    assert level_gain(1e-4) == LEVEL_MAX_GAIN


@pytest.fixture(scope="module")
def bright_dim(tmp_path_factory):
    """A linear capture and a copy of it a fifth as bright (an underexposed camera)."""
    root = tmp_path_factory.mktemp("lvl")
    bright = synthesize(root / "bright", **KW)
    dim = root / "dim"
    shutil.copytree(bright.root, dim)
    for p in (dim / "images").glob("*.png"):
        im = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        assert cv2.imwrite(str(p), np.round(im * 0.2).astype(np.uint8))
    d = json.loads((dim / "scene.json").read_text())
    d["illumination"]["i_b"] *= 0.2  # i_b is light: a fifth in the dim photos' units; i_r is a ratio
    (dim / "scene.json").write_text(json.dumps(d))
    return bright, Scene.load(dim)


def test_photo_level_reads_the_bright_end(bright_dim):
    bright, dim = bright_dim
    frames = list(range(len(bright.frames)))
    lb, ld = photo_level(bright, frames, None), photo_level(dim, frames, None)
    assert lb >= LEVEL_LOW and ld < LEVEL_LOW
    assert ld == pytest.approx(0.2 * lb, abs=1.5 / 255)
    lut = (np.arange(256) / 255.0) ** 2.2  # through a response
    assert photo_level(dim, frames, lut) == pytest.approx(lut[int(round(ld * 255))])


def test_dim_capture_trains_scaled_and_reports_in_its_units(bright_dim, tmp_path):
    from fastneus.pipeline import train_scene

    bright, dim = bright_dim
    trainer, m = train_scene(dim, load_config("cpu-quick", TINY), tmp_path / "run", "cpu")
    g = trainer.photo_gain
    frames = list(range(len(dim.frames)))
    assert g == pytest.approx(level_gain(photo_level(dim, frames, None)))
    assert g > 1.0 and trainer.level_note and "brighter" in trainer.level_note
    run = json.loads((tmp_path / "run" / "run.json").read_text())
    assert run["photo_gain"] == pytest.approx(g) and "photo_level" in run
    # the bank's targets are the photos times g (clipped at 1); i_b comes back divided by g
    assert float(trainer.bank.lut[10]) == pytest.approx(min(1.0, 10 / 255 * g), rel=1e-5)
    i_r, i_b = (float(x.detach()) for x in trainer.illumination())
    assert m["i_r"] == pytest.approx(i_r) and m["i_b"] == pytest.approx(i_b / g)
    assert m["i_b_gt"] == pytest.approx(0.2 * bright.illumination.i_b)
    # the training started from the scene's i_b in the trained units
    ill = json.loads((tmp_path / "run" / "illumination.json").read_text())
    assert ill["i_b"] == pytest.approx(m["i_b"])


def test_level_off_and_bright_captures_keep_the_photos(bright_dim, tmp_path):
    from fastneus.train.trainer import Trainer

    bright, dim = bright_dim
    t = Trainer(bright, load_config("cpu-quick", TINY), tmp_path / "b", "cpu")
    assert t.photo_gain == 1.0 and t.level_note is None and t.bank.lut is None  # linear, untouched
    t = Trainer(dim, load_config("cpu-quick", TINY + ["illum.level=off"]), tmp_path / "d", "cpu")
    assert t.photo_gain == 1.0 and t.bank.lut is None


def test_mesh_colours_are_scaled_back(bright_dim, tmp_path):
    """shade_mesh's scale multiplies the model's colour before encoding (a trained-brighter run's
    colours come back in the photos' units)."""
    import torch

    from fastneus.export.mesh import MeshArrays, shade_mesh
    from fastneus.field.model import SDFField

    bright, _ = bright_dim
    cfg = load_config("cpu-quick", TINY)
    torch.manual_seed(0)
    field = SDFField(cfg.hashgrid, cfg.network, "cpu")
    field.init_color_bias(torch.tensor([0.6, 0.5, 0.4]))
    v = np.random.default_rng().normal(size=(50, 3)) * 0.3
    mesh = MeshArrays(vertices=v.astype(np.float64), faces=np.zeros((0, 3), np.int64))
    full = shade_mesh(field, bright, mesh, "cpu").colors.astype(float)
    half = shade_mesh(field, bright, mesh, "cpu", scale=0.5).colors.astype(float)
    assert np.abs(half - 0.5 * full).max() <= 1.0
