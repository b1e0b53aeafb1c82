"""illum.level and illum.black: a dim capture is trained brighter (the priors' thresholds were set on
captures of a normal level) and everything reported is divided back into the photos' own units; a
raw camera's black level is taken off before training."""
from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest

from fastneus.config import load_config
from fastneus.data import Scene
from fastneus.synth.render import synthesize
from fastneus.train.rays import (LEVEL_LOW, LEVEL_MAX_GAIN, LEVEL_REF, black_level, level_gain, photo_histogram,
                                 photo_level)

KW = dict(shape="torus", views=3, size=(40, 40), pattern="crosslaser", illum="dark", seed=0, device="cpu",
          progress=False, contact_sheet=False)
TINY = ["steps=40", "log_every=10", "mesh_resolution=40", "occ_resolution=32", "target_samples=4096",
        "init_rays=256", "max_rays=512", "render_frames=[0]"]


def test_level_gain_rule():
    assert level_gain(LEVEL_LOW) == 1.0 and level_gain(0.9) == 1.0 and level_gain(0.0) == 1.0
    assert level_gain(LEVEL_LOW * (1 - 1e-6)) == pytest.approx(1.0, abs=1e-4)  # continuous at LEVEL_LOW
    rng = np.random.default_rng()
    x = float(rng.uniform(LEVEL_REF / LEVEL_MAX_GAIN + 1e-3, 0.5 * LEVEL_LOW))
    assert level_gain(x) == pytest.approx(LEVEL_REF / x)  # dim: trained at LEVEL_REF
    ls = np.sort(rng.uniform(0.5 * LEVEL_LOW, LEVEL_LOW, 20))
    trained = [level_gain(v) * v for v in ls]  # between: from LEVEL_REF down to LEVEL_LOW
    assert all(LEVEL_LOW - 1e-9 <= t <= LEVEL_REF + 1e-9 for t in trained) and np.all(np.diff(trained) <= 1e-12)
    assert level_gain(1e-4) == LEVEL_MAX_GAIN


def test_black_level_rule():
    """A pedestal (most pixels on one dark value, none below half of it) is found; a dark surface
    with darker pixels around it, a black backdrop at 0 and a grey backdrop are not."""
    rng = np.random.default_rng()
    lut = (np.arange(256) / 255.0).astype(np.float32)
    c = int(rng.integers(3, 18))  # a pedestal of 1-7 % of full scale
    hist = np.zeros(256, np.int64)
    hist[c] = 6000
    hist[c + 1] = 1500
    hist[c + 2:200] = 10  # the object and its lines above it
    assert black_level(hist, lut) == pytest.approx(c / 255.0)
    shadow = hist.copy()
    shadow[1:c // 2 + 1] += 100  # darker pixels under it: a dark surface, not a pedestal
    assert black_level(shadow, lut) == 0.0
    zero = hist.copy()
    zero[0] = 9000
    assert black_level(zero, lut) == 0.0  # the backdrop already at 0
    grey = np.zeros(256, np.int64)
    grey[80] = 6000
    grey[81:200] = 10
    assert black_level(grey, lut) == 0.0  # a grey backdrop (0.31) is no black level
    assert black_level(hist, lut ** 2.2) == pytest.approx(float((c / 255.0) ** 2.2))  # through a response


def test_pedestal_is_taken_off(bright_dim, tmp_path):
    """A copy of the capture with a camera's black level (every value + 8 codes): training sees the
    pedestal removed (the backdrop at 0 again), the renders compared with the photos get it back."""
    from fastneus.train.trainer import Trainer

    bright, _ = bright_dim
    ped = tmp_path / "ped"
    shutil.copytree(bright.root, ped)
    for p in (ped / "images").glob("*.png"):
        im = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        assert cv2.imwrite(str(p), np.minimum(im.astype(np.int32) + 8, 255).astype(np.uint8))
    nomask = TINY + ["masks=off"]  # the background prior looks for the backdrop
    t = Trainer(Scene.load(ped), load_config("cpu-quick", nomask), tmp_path / "r", "cpu")
    assert t.photo_black == pytest.approx(8 / 255.0) and "black level" in t.level_note
    assert float(t.bank.lut[8]) == 0.0 and float(t.bank.lut[9]) > 0.0
    ref = Trainer(bright, load_config("cpu-quick", nomask), tmp_path / "b", "cpu")
    assert ref.photo_black == 0.0 and ref.bank.bg_fraction > 0.5
    assert t.bank.bg_fraction == pytest.approx(ref.bank.bg_fraction, abs=0.02)  # the backdrop found again
    off = Trainer(Scene.load(ped), load_config("cpu-quick", nomask + ["illum.black=off"]), tmp_path / "o", "cpu")
    assert off.photo_black == 0.0 and off.bank.bg_fraction < 0.05  # over the pedestal: no backdrop at 0


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
    hb, hd = photo_histogram(bright, frames), photo_histogram(dim, frames)
    lb, ld = photo_level(hb, None), photo_level(hd, None)
    assert lb >= LEVEL_LOW and ld < LEVEL_LOW
    assert ld == pytest.approx(0.2 * lb, abs=1.5 / 255)
    lut = (np.arange(256) / 255.0) ** 2.2  # through a response
    assert photo_level(hd, lut) == pytest.approx(lut[int(round(ld * 255))])


def test_dim_capture_trains_scaled_and_reports_in_its_units(bright_dim, tmp_path):
    from fastneus.pipeline import train_scene

    bright, dim = bright_dim
    trainer, m = train_scene(dim, load_config("cpu-quick", TINY), tmp_path / "run", "cpu")
    g = trainer.photo_gain
    frames = list(range(len(dim.frames)))
    assert g == pytest.approx(level_gain(photo_level(photo_histogram(dim, frames), None)))
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
