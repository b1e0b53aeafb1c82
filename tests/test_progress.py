"""Progress while training (fastneus.train.progress): validation renders in the run folder every N
seconds or steps, TensorBoard event files only when the package is installed; driven by a tiny real
Trainer on CPU."""
from __future__ import annotations

import importlib.util
import os
import sys

import cv2
import numpy as np
import pytest
import torch

from conftest import SMALL_RUN
from fastneus.errors import FastneusError
from fastneus.train import progress as pg
from fastneus.train.progress import CAPTION_PX, ProgressWriter, held_frame


def _trainer(scene_dir, out, extra=()):
    from fastneus.config import load_config
    from fastneus.data import Scene
    from fastneus.train.trainer import Trainer

    return Trainer(Scene.load(scene_dir), load_config("cpu-quick", SMALL_RUN + list(extra)), out, "cpu")


@pytest.fixture
def no_tensorboard(monkeypatch):
    """As on a machine without the tensorboard package."""
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "tensorboard" else real(name, *a))


def test_validation_every_n_steps_writes_photo_render_depth(small_scene, tmp_path, no_tensorboard):
    tr = _trainer(small_scene, tmp_path / "run")
    pw = ProgressWriter(tr, every_s=0, every_steps=2)
    assert pw.tb is None and pw.frame == 0  # every frame is trained on: the first one
    written = []
    for _ in range(4):
        tr.train_step()
        written.append(pw.maybe_validate(tr.step, tr.elapsed))
    pw.close()
    run = tmp_path / "run"
    assert written == [None, run / "validation" / "step_000002.png", None, run / "validation" / "step_000004.png"]
    assert sorted(p.name for p in (run / "validation").iterdir()) == ["step_000002.png", "step_000004.png"]
    assert not (run / "tensorboard").exists()
    img = cv2.imread(str(written[-1]))[..., ::-1]
    photo = tr.scene.image(0)  # 24x24: smaller than the panel size, so not resized
    h, w = photo.shape[:2]
    assert img.shape == (CAPTION_PX + h, 3 * w + 4, 3)
    assert np.array_equal(img[CAPTION_PX:, :w], photo)  # the photo panel is the photo
    render = img[CAPTION_PX:, w + 2:2 * w + 2].astype(int)
    assert render.std() > 0 and not np.array_equal(render, photo)
    assert img[:CAPTION_PX].min() < 128  # the caption is written


def test_time_trigger_and_force(small_scene, tmp_path, no_tensorboard):
    """Every ``every_s`` seconds of training (the caller's clock, so no timing here), plus a forced last one."""
    tr = _trainer(small_scene, tmp_path / "run")
    pw = ProgressWriter(tr, every_s=10.0, size=16)
    got = [pw.maybe_validate(s, t) is not None for s, t in [(1, 5.0), (2, 10.0), (3, 15.0), (4, 20.5), (5, 21.0)]]
    assert got == [False, True, False, True, False]
    assert pw.maybe_validate(6, 21.5, force=True).name == "step_000006.png"
    img = cv2.imread(str(pw.written[-1]))
    assert img.shape == (CAPTION_PX + 16, 3 * 16 + 4, 3)  # 24x24 shrunk to 16x16 panels
    assert pw.finish(6, 21.5) is None  # the last one is already at this step
    assert pw.finish(7, 22.0).name == "step_000007.png"
    off = ProgressWriter(tr, every_s=0, every_steps=0)
    assert off.maybe_validate(100, 1e6) is None and off.finish(100, 1e6) is None and not off.enabled


def test_intervals_count_from_where_a_resumed_run_stands(small_scene, tmp_path, no_tensorboard):
    tr = _trainer(small_scene, tmp_path / "run")
    tr.step, tr.elapsed = 100, 500.0  # as after --resume from a checkpoint
    pw = ProgressWriter(tr, every_s=60.0, every_steps=0, size=16)
    assert pw.maybe_validate(101, 505.0) is None
    assert pw.maybe_validate(102, 560.5).name == "step_000102.png"
    ps = ProgressWriter(tr, every_s=0, every_steps=10, size=16)
    assert ps.maybe_validate(105, 501.0) is None and ps.maybe_validate(110, 502.0) is not None


def test_validation_does_not_change_training(small_scene, tmp_path, no_tensorboard):
    """The same run with a validation render after every step ends with bit-identical parameters."""
    a = _trainer(small_scene, tmp_path / "a")
    for _ in range(4):  # one run after the other: a step draws from torch's global generator too
        a.train_step()
    b = _trainer(small_scene, tmp_path / "b")
    pw = ProgressWriter(b, every_s=0, every_steps=1)
    for _ in range(4):
        b.train_step()
        rng = torch.get_rng_state()
        assert pw.maybe_validate(b.step, b.elapsed) is not None
        assert torch.equal(rng, torch.get_rng_state())  # validation draws no random numbers
    for (name, pa), pb in zip(a.field.state_dict().items(), b.field.state_dict().values()):
        assert torch.equal(pa, pb), name
    assert torch.equal(a.log_ir, b.log_ir) and torch.equal(a.log_ib, b.log_ib)
    assert torch.equal(a.gen.get_state(), b.gen.get_state())


def test_held_out_frame_is_rendered(small_scene, tmp_path, no_tensorboard):
    tr = _trainer(small_scene, tmp_path / "run", ["frames=[1,2]"])
    assert held_frame(tr.scene, [1, 2]) == 0 and held_frame(tr.scene, [0, 1, 2]) == 0
    assert held_frame(tr.scene, [0, 2]) == 1
    pw = ProgressWriter(tr, every_s=0, every_steps=1)
    tr.train_step()
    img = cv2.imread(str(pw.maybe_validate(tr.step, tr.elapsed)))[..., ::-1]
    assert np.array_equal(img[CAPTION_PX:, :24], tr.scene.image(0))
    with pytest.raises(FastneusError, match="out of range"):
        ProgressWriter(tr, frame=3)


def test_no_write_through_a_link(small_scene, tmp_path, no_tensorboard):
    """A symbolic link planted as RUN/validation is refused; nothing lands where it points."""
    tr = _trainer(small_scene, tmp_path / "run")
    (tmp_path / "run").mkdir(exist_ok=True)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    os.symlink(elsewhere, tmp_path / "run" / "validation")
    pw = ProgressWriter(tr, every_s=0, every_steps=1)
    tr.train_step()
    with pytest.raises(FastneusError, match="symbolic link"):
        pw.maybe_validate(tr.step, tr.elapsed)
    assert list(elsewhere.iterdir()) == []


def test_bad_settings_are_one_line(small_scene, tmp_path, no_tensorboard):
    tr = _trainer(small_scene, tmp_path / "run")
    for kw in ({"every_s": -1.0}, {"every_s": float("nan")}, {"every_steps": -2}, {"size": 2}):
        with pytest.raises(FastneusError, match="bad validation setting"):
            ProgressWriter(tr, **kw)
    with pytest.raises(FastneusError, match="auto, on or off"):
        ProgressWriter(tr, tensorboard="yes")
    with pytest.raises(FastneusError, match=r"pip install 'fastneus\[tensorboard\]'"):
        ProgressWriter(tr, tensorboard="on")


def test_without_tensorboard_nothing_is_imported(small_scene, tmp_path, no_tensorboard):
    """No package: on_log is a no-op and neither tensorboard nor torch.utils.tensorboard gets imported."""
    before = {m for m in sys.modules if m.startswith(("tensorboard", "torch.utils.tensorboard"))}
    tr = _trainer(small_scene, tmp_path / "run")
    pw = ProgressWriter(tr, every_s=0, every_steps=1)
    pw.on_log(1, {"step": 1, "loss": 0.5, "psnr": 20.0})
    tr.train_step()
    pw.maybe_validate(tr.step, tr.elapsed)
    pw.close()
    after = {m for m in sys.modules if m.startswith(("tensorboard", "torch.utils.tensorboard"))}
    assert after == before and not (tmp_path / "run" / "tensorboard").exists()
    assert not pg.tensorboard_available()


def test_tensorboard_scalars_and_images(small_scene, tmp_path):
    """With the package installed: the log records' numbers as train/<key> scalars, the panels as images."""
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    tr = _trainer(small_scene, tmp_path / "run")
    pw = ProgressWriter(tr, every_s=0, every_steps=2)
    assert pw.tb is None  # opened by the first validation render (or after TB_OPEN_AFTER_S, or at close)
    for _ in range(4):
        tr.train_step()
        pw.on_log(tr.step, {"step": tr.step, "time": 0.1 * tr.step, "loss": 1.0 / tr.step, "psnr": 10.0 + tr.step,
                            "levels": 4, "note": "text is skipped", "bad": float("nan"), "flag": True})
        pw.maybe_validate(tr.step, tr.elapsed)
    pw.close()
    ea = EventAccumulator(str(tmp_path / "run" / "tensorboard"), size_guidance={"images": 0, "scalars": 0})
    ea.Reload()
    tags = ea.Tags()
    assert {"train/loss", "train/psnr", "train/levels", "train/seconds", "validation/psnr"} <= set(tags["scalars"])
    assert not {"train/note", "train/bad", "train/flag", "train/step"} & set(tags["scalars"])
    assert [(e.step, round(e.value, 6)) for e in ea.Scalars("train/loss")] == [(1, 1.0), (2, 0.5), (3, 0.333333),
                                                                             (4, 0.25)]
    assert [e.step for e in ea.Images("validation/photo_render_depth")] == [2, 4]


class _FakeWriter:
    """Stands in for torch's SummaryWriter: records what is written."""

    def __init__(self):
        self.scalars, self.closed = [], False

    def add_scalar(self, tag, value, step):
        self.scalars.append((tag, step, value))

    def add_image(self, *a, **k):
        pass

    def flush(self):
        pass

    def close(self):
        self.closed = True


def test_tensorboard_opens_after_the_delay_or_at_the_end(small_scene, tmp_path, monkeypatch):
    """The writer (whose import costs 0.3-1 s) is not opened before TB_OPEN_AFTER_S of training, so
    a short run's mesh.ply does not wait for it; every record logged before then is written when
    it opens, in order; a run shorter than the delay opens it at close (after mesh.ply)."""
    opened = []

    def fake_open(self):
        opened.append(_FakeWriter())
        return opened[-1]

    monkeypatch.setattr(pg, "tensorboard_available", lambda: True)
    monkeypatch.setattr(ProgressWriter, "_open_tensorboard", fake_open)
    tr = _trainer(small_scene, tmp_path / "run")
    t = pg.TB_OPEN_AFTER_S
    # a long run: records wait until the training clock passes the delay, then stream
    pw = ProgressWriter(tr, every_s=0)
    for step, time_s in ((50, 0.3 * t), (100, 0.9 * t)):
        pw.on_log(step, {"step": step, "time": time_s, "loss": 1.0 / step})
    assert pw.tb is None and not opened
    pw.on_log(150, {"step": 150, "time": 1.2 * t, "loss": 1.0 / 150})
    assert len(opened) == 1 and pw.tb is opened[0]
    assert [(s, v) for tag, s, v in opened[0].scalars if tag == "train/loss"] == [(50, 1 / 50), (100, 1 / 100),
                                                                                (150, 1 / 150)]
    pw.on_log(200, {"step": 200, "time": 1.5 * t, "loss": 0.005})
    assert opened[0].scalars[-1][:2] == ("train/seconds", 200)
    pw.close()
    assert opened[0].closed and pw.tb is None
    pw.on_log(250, {"step": 250, "time": 2 * t, "loss": 0.004})  # after close: nothing reopens
    assert len(opened) == 1
    # a short run: nothing opens while training; close writes every record
    pw = ProgressWriter(tr, every_s=0)
    pw.on_log(50, {"step": 50, "time": 0.1 * t, "loss": 0.5})
    assert not opened[1:]
    pw.finish(60, 0.2 * t)
    assert len(opened) == 2 and opened[1].closed
    assert ("train/loss", 50, 0.5) in opened[1].scalars
    # off: never opened
    pw = ProgressWriter(tr, every_s=0, tensorboard="off")
    pw.on_log(50, {"step": 50, "time": 2 * t, "loss": 0.5})
    pw.close()
    assert len(opened) == 2


def test_tensorboard_folder_link_refused_early_and_late(small_scene, tmp_path, monkeypatch):
    """A link as RUN/tensorboard is refused when the writer is set up (before training) and, since
    the writer opens late, also when it is planted after that: nothing lands where it points."""
    monkeypatch.setattr(pg, "tensorboard_available", lambda: True)
    tr = _trainer(small_scene, tmp_path / "run")
    (tmp_path / "run").mkdir(exist_ok=True)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    os.symlink(elsewhere, tmp_path / "run" / "tensorboard")
    with pytest.raises(FastneusError, match="symbolic link"):
        ProgressWriter(tr, every_s=0)
    os.unlink(tmp_path / "run" / "tensorboard")
    pw = ProgressWriter(tr, every_s=0)  # no link now: set up
    pw.on_log(50, {"step": 50, "time": 1.0, "loss": 0.5})
    os.symlink(elsewhere, tmp_path / "run" / "tensorboard")  # planted before the writer opens
    with pytest.raises(FastneusError, match="symbolic link"):
        pw.on_log(100, {"step": 100, "time": 2 * pg.TB_OPEN_AFTER_S, "loss": 0.4})
    assert list(elsewhere.iterdir()) == []
