"""What machine-vision cameras write. Grey photos (a monochrome camera): synth writes them
(capture ``mono``), a scene of them loads as three equal channels with the projectors' light made
grey to match, a mix with colour photos is one line, the thin-line one-shot labelling is not used
on them, the run says so, and a run trains. 10-14-bit sensor values right-aligned in 16-bit files
are read at full range (``sensor_bits``, stated or decided)."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from fastneus.data import Scene
from fastneus.data.model import LaserPlane, Projector
from fastneus.errors import FastneusError
from fastneus.light import grey_rgb, greyed
from fastneus.synth.render import synthesize

SMALL = dict(shape="torus", views=3, size=(48, 48), pattern="crosslaser", seed=0, device="cpu", noise=0.0,
             proj_size=(128, 96), progress=False, contact_sheet=False, illum="normal")


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """The same capture by a colour and a monochrome camera (linear, no noise)."""
    root = tmp_path_factory.mktemp("grey")
    colour = synthesize(root / "colour", capture={"response": "linear"}, **SMALL)
    grey = synthesize(root / "grey", capture={"response": "linear", "mono": 1}, **SMALL)
    return colour, grey


def test_mono_capture_records_the_mean_light(pair):
    import cv2

    colour, grey = pair
    raw = cv2.imread(str(grey.root / grey.frames[0].image), cv2.IMREAD_UNCHANGED)
    assert raw.ndim == 2 and raw.dtype == np.uint8  # a grey PNG on disk
    assert grey.grey and not colour.grey and grey.meta["capture"]["mono"] == 1
    for i in range(len(grey.frames)):
        g = grey.image(i)
        assert g.shape == colour.image(i).shape and (g == g[..., :1]).all()  # three equal channels
        # each pixel the mean of the colour camera's light (both rounded to 8 bits once), where no
        # colour channel clipped (a mono pixel sums the light before it saturates)
        c = colour.image(i).astype(np.float64)
        ok = c.max(-1) < 250
        assert ok.mean() > 0.9 and (c[ok].max(-1) > 20).any()
        assert np.abs(g[..., 0][ok] - c[ok].mean(-1)).max() <= 1.0
        assert (g[..., 0][~ok] >= np.floor(c[~ok].mean(-1))).all()  # brighter where colour clipped
        clean = grey.gt_clean(i)
        assert (clean == clean[..., :1]).all()


def test_grey_scene_sees_the_patterns_grey(pair):
    colour, grey = pair
    pid = grey.frames[0].projectors["proj0"].pattern
    pc, pg = colour.pattern_image(pid), grey.pattern_image(pid)
    assert (pc[..., 1] != pc[..., 0]).any()  # red and green lines: a coloured pattern
    assert (pg == pg[..., :1]).all()
    assert np.array_equal(pg[..., 0], np.round(pc.astype(np.float64).mean(-1)).astype(np.uint8))


def test_grey_rgb_and_greyed_lasers():
    rng = np.random.default_rng()
    im = rng.integers(0, 256, (5, 7, 3), dtype=np.uint8)
    g = grey_rgb(im)
    assert g.dtype == np.uint8 and g.shape == im.shape
    assert np.abs(g[..., 0] - im.astype(np.float64).mean(-1)).max() <= 0.5
    white = np.full((2, 2, 3), 200, np.uint8)
    assert np.array_equal(grey_rgb(white), white)  # white light is what it was
    plane = LaserPlane(normal=np.array([1.0, 0, 0]), offset=0.0, colour=np.array([0.9, 0.0, 0.3]), width=0.01,
                       fan_deg=60.0)
    laser = Projector(id="l", K=np.eye(3), width=1, height=1, planes=[plane])
    out = greyed(laser)
    assert np.allclose(out.planes[0].colour, [0.4, 0.4, 0.4])
    assert np.allclose(laser.planes[0].colour, [0.9, 0.0, 0.3])  # the scene's own projector untouched
    image_proj = Projector(id="p", K=np.eye(3), width=4, height=3)
    assert greyed(image_proj) is image_proj


def test_grey_among_colour_is_one_line(pair, tmp_path):
    colour, grey = pair
    d = tmp_path / "mixed"
    shutil.copytree(colour.root, d)
    shutil.copy(grey.root / grey.frames[1].image, d / colour.frames[1].image)
    with pytest.raises(FastneusError) as e:
        Scene.load(d)
    msg = str(e.value)
    assert "frames[1].image" in msg and "grey" in msg and "\n" not in msg


def test_grey_scene_trains(pair, tmp_path):
    from fastneus.config import load_config
    from fastneus.pipeline import train_scene

    _, grey = pair
    cfg = load_config("cpu-quick", ["steps=60", "log_every=20", "mesh_resolution=40", "occ_resolution=32",
                                    "target_samples=4096", "init_rays=256", "max_rays=512", "render_frames=[0]"])
    trainer, metrics = train_scene(grey, cfg, tmp_path / "run", "cpu")
    assert (tmp_path / "run" / "mesh.ply").is_file()
    assert np.isfinite(metrics["chamfer_gt2rec_mm"]) and np.isfinite(metrics["i_r"])
    log = [json.loads(x) for x in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert log[-1]["loss"] < log[0]["loss"]


def test_grey_line_frames_start_from_the_sphere(tmp_path):
    """The one-shot thin-line labelling needs the lines' colours (fastneus.classical.laserlines):
    on a monochrome camera's photos of the same capture it is not used."""
    from fastneus.classical.laserlines import sparse_line_frame
    from fastneus.train.geometry_init import MIN_LINE_VIEWS, line_frames

    kw = dict(shape="sphere", views=MIN_LINE_VIEWS, size=(48, 48), pattern="crosslaser", illum="dark", seed=0,
              progress=False, contact_sheet=False)
    colour = synthesize(tmp_path / "c", capture={"response": "linear"}, **kw)
    grey = synthesize(tmp_path / "g", capture={"response": "linear", "mono": 1}, **kw)
    views = list(range(MIN_LINE_VIEWS))
    assert sparse_line_frame(colour, 0) and line_frames(colour, views) == views
    assert not sparse_line_frame(grey, 0) and line_frames(grey, views) is None


def test_the_run_says_grey_and_warns_of_a_colour_code(pair, tmp_path):
    """The summary names grey photos; a one-shot of a colour-coded pattern on them is warned of,
    a grey one or a multi-view capture is not."""
    from fastneus.train.geometry_init import grey_photos_note

    colour, grey = pair
    assert grey_photos_note(colour, [0, 1, 2]) is None
    assert "grey" in grey_photos_note(grey, [0, 1, 2])
    from fastneus.train.geometry_init import MAX_SWEEP_VIEWS

    kw = dict(shape="sphere", views=1, size=(32, 32), seed=0, progress=False, contact_sheet=False,
              capture={"response": "linear", "mono": 1})
    many = synthesize(tmp_path / "m", pattern="colorline", **(kw | {"views": MAX_SWEEP_VIEWS + 1}))
    assert "warning" not in grey_photos_note(many, list(range(len(many.frames))))  # multi-view: no sweep
    coded = synthesize(tmp_path / "c", pattern="colorline", **kw)
    note = grey_photos_note(coded, [0])
    assert "warning" in note and "coded by colour" in note and "\n" not in note
    plain = synthesize(tmp_path / "g", pattern="phaseshift", **kw)
    assert "warning" not in (grey_photos_note(plain, list(range(len(plain.frames)))) or "")


def test_grey_survives_conversion_and_sixteen_bits(pair, tmp_path):
    """Converted to our format and to NeRF transforms the photos stay grey; 16-bit grey photos load
    as 8-bit sRGB codes of their light in three equal channels."""
    from fastneus.cli import main
    from fastneus.formats.detect import load_scene

    _, grey = pair
    for to in ("fastneus", "nerf"):
        assert main(["convert", str(grey.root), "--to", to, "--out", str(tmp_path / to)]) == 0
        back = load_scene(tmp_path / to)
        assert back.grey and np.array_equal(back.image(0), grey.image(0))
    deep = synthesize(tmp_path / "g16", capture={"response": "linear", "mono": 1, "bits": 16}, **SMALL)
    assert deep.grey and deep.photo_bits == 16
    im = deep.image(0)
    assert im.dtype == np.uint8 and (im == im[..., :1]).all() and im.max() > 0


def _right_aligned(src, dst, shift: int):
    """A copy of scene ``src`` whose 16-bit photos hold ``16 - shift``-bit values, right-aligned."""
    import cv2

    shutil.copytree(src, dst)
    for p in (dst / "images").glob("*.png"):
        im = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        assert cv2.imwrite(str(p), (im.astype(np.uint32) >> shift).astype(np.uint16))


@pytest.fixture(scope="module")
def deep_pair(tmp_path_factory):
    root = tmp_path_factory.mktemp("deep")
    full = synthesize(root / "d16", capture={"response": "linear", "bits": 16}, **SMALL)
    _right_aligned(full.root, root / "d12", 4)
    return full, root / "d12"


def test_twelve_bit_values_in_sixteen_bit_files_are_full_range(deep_pair):
    """A 12-bit camera's right-aligned values (Mono12 saved by OpenCV or an SDK) are taken as
    12-bit: the photos read as the full-range capture's (within a code), the decision said."""
    full, d12 = deep_pair
    s12 = Scene.load(d12)
    f16, why16 = full.photo_full_scale()
    f12, why12 = s12.photo_full_scale()
    assert (f16, f12) == (65535, 4095) and "12-bit" in why12 and "brightest" in why12
    for i in range(len(full.frames)):
        assert np.abs(s12.image(i).astype(int) - full.image(i).astype(int)).max() <= 1
    from fastneus.data.response import resolve_response

    assert "12-bit values" in resolve_response(s12, [0], "auto")[1]


def test_stated_sensor_bits_and_their_errors(deep_pair, tmp_path):
    full, d12 = deep_pair
    d = json.loads((d12 / "scene.json").read_text())
    for bad in (7, 17, 12.5, True, "12"):
        with pytest.raises(FastneusError) as e:
            Scene.from_dict(d | {"sensor_bits": bad}, d12)
        assert "sensor_bits" in str(e.value) and "\n" not in str(e.value)
    s = Scene.from_dict(d | {"sensor_bits": 16}, d12)  # stated: no guess (the photos stay dim)
    assert s.photo_full_scale()[0] == 65535 and s.image(0).max() < full.image(0).max()
    s = Scene.from_dict(d | {"sensor_bits": 12}, d12)
    assert s.photo_full_scale() == (4095, "12-bit values, scene.json's sensor_bits")
    assert s.to_dict()["sensor_bits"] == 12
    too_few = Scene.from_dict(d | {"sensor_bits": 8}, d12)  # values above 255: one line naming the frame
    with pytest.raises(FastneusError) as e:
        too_few.image(0)
    assert "frames[0].image" in str(e.value) and "sensor_bits" in str(e.value)
    eight = tmp_path / "e"
    synthesize(eight, capture={"response": "linear"}, **SMALL)
    with pytest.raises(FastneusError) as e:
        Scene.from_dict(json.loads((eight / "scene.json").read_text()) | {"sensor_bits": 12}, eight)
    assert "8-bit" in str(e.value)
