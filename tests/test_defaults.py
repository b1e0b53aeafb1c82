"""The default path (issue 9): schedules as fractions of the run, masks when present, the
background prior and the seen-volume limit against floaters, and the shapes of the matrix."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from conftest import SMALL_RUN
from fastneus.config import Config, load_config
from fastneus.data import Scene
from fastneus.errors import FastneusError


# ---------------------------------------------------------------- schedules are fractions
def test_fractions_validated_and_legacy_steps_converted(tmp_path, capsys):
    with pytest.raises(FastneusError, match="c2f_frac"):
        load_config(None, ["c2f_frac=1.5"])
    # a run saved by an earlier version (steps) keeps its meaning as a share of its own length
    from fastneus.config import config_from_dict

    cfg = config_from_dict({"steps": 1000, "occ_warmup_steps": 250, "warmup_steps": 50, "c2f_start_levels": 4,
                            "levels": 16, "c2f_steps_per_level": 25}, "old/config.yaml")
    assert cfg.occupancy.occ_warmup_frac == pytest.approx(0.25) and cfg.optim.warmup_frac == pytest.approx(0.05)
    assert cfg.hashgrid.c2f_frac == pytest.approx(12 * 25 / 1000)
    assert not hasattr(cfg, "occ_warmup_steps")
    # a hand-written YAML with an old key loads translated, with one line naming the new key
    f = tmp_path / "old.yaml"
    f.write_text("occ_warmup_steps: 250\n")
    assert load_config(str(f)).occupancy.occ_warmup_frac == pytest.approx(250 / 3000)
    assert "occupancy.occ_warmup_frac" in capsys.readouterr().err


@pytest.mark.parametrize("preset", ["fewview", "cpu-quick", "oneshot", "paper"])
def test_presets_have_no_step_schedules(preset):
    cfg = load_config(preset)
    for k in ("occ_warmup_frac", "c2f_frac", "warmup_frac", "color_warmup_frac", "cos_anneal_frac",
              "illum_warmup_frac", "inv_s_floor_frac", "bg_start_frac", "mask_start_frac"):
        assert 0.0 <= cfg.flat()[k] <= 1.0, k


def test_coarse_to_fine_and_floor_follow_progress_not_steps():
    from fastneus.field.model import SDFField

    cfg = load_config("cpu-quick", ["c2f_start_levels=3", "levels=8", "c2f_frac=0.4"])
    field = SDFField(cfg.hashgrid, cfg.network, "cpu", backend=cfg.run.backend)
    seen = []
    for p in (0.0, 0.1, 0.2, 0.39, 0.4, 1.0):
        field.set_progress(p)
        seen.append((field.active_levels, field.inv_s_floor))
    levels = [s[0] for s in seen]
    floors = [s[1] for s in seen]
    assert levels[0] == 3 and levels[-2] == 8 and levels[-1] == 8
    assert levels == sorted(levels) and 3 < levels[2] < 8
    assert floors == sorted(floors) and floors[0] == pytest.approx(cfg.network.inv_s_floor_start)


def test_same_stages_at_any_budget(tmp_path):
    """Progress is the share of time_budget when one is set, so stages do not depend on speed."""
    from fastneus.train.trainer import Trainer

    class _T:  # Trainer.progress/finished read only cfg, step and elapsed
        progress = Trainer.progress
        finished = Trainer.finished
        stop_signal = None

    t = _T()
    t.cfg = Config().replace(steps=1000, time_budget=10.0)
    t.step, t.elapsed = 5, 5.0
    assert t.progress() == pytest.approx(0.5) and not t.finished()
    t.elapsed = 10.0
    assert t.progress() == 1.0 and t.finished()
    # a budget spent before the first step (a slow machine's setup) still trains one step
    t.step, t.elapsed = 0, 12.0
    assert not t.finished()
    t.step = 1
    assert t.finished()
    t.cfg = Config().replace(steps=200, time_budget=0.0)
    t.step = 50
    assert t.progress() == pytest.approx(0.25) and not t.finished()


def test_floor_end_follows_the_runs_length_when_asked():
    """inv_s_floor_per_step caps the sharpness floor's end at that many times the run's steps (set,
    or expected from the rate so far under a time budget), never below the floor's start; at 0 the
    end is inv_s_floor_end whatever the length."""
    from fastneus.field.model import SDFField
    from fastneus.train.trainer import Trainer

    cfg = load_config("cpu-quick", ["inv_s_floor_end=1000", "inv_s_floor_per_step=0.5", "inv_s_floor_start=20"])
    field = SDFField(cfg.hashgrid, cfg.network, "cpu", backend=cfg.run.backend)
    assert field.floor_end(1050) == pytest.approx(525) and field.floor_end(4400) == 1000
    assert field.floor_end(10) == 20 and field.floor_end(None) == 1000
    field.set_progress(1.0, 1050)
    assert field.inv_s_floor == pytest.approx(525)
    field.set_progress(0.3, 1050)  # half-way up the ramp (frac 0.6): the geometric mean of 20 and 525
    assert field.inv_s_floor == pytest.approx((20 * 525) ** 0.5)
    off = SDFField(cfg.hashgrid, load_config("cpu-quick", ["inv_s_floor_end=1000"]).network, "cpu",
                   backend=cfg.run.backend)
    off.set_progress(1.0, 1050)
    assert off.inv_s_floor == pytest.approx(1000)

    class _T:  # steps_expected reads cfg, step and elapsed through progress
        progress = Trainer.progress
        steps_expected = Trainer.steps_expected

    t = _T()
    t.cfg = Config().replace(steps=1000, time_budget=5.0)
    t.step, t.elapsed = 0, 0.0
    assert t.steps_expected() is None
    t.step, t.elapsed = 420, 2.0
    assert t.steps_expected() == pytest.approx(1050)
    t.cfg = Config().replace(steps=600, time_budget=0.0)
    assert t.steps_expected() == 600


def test_table_size_follows_the_photos_pixels():
    """hashgrid.pixels_per_entry: the largest power of two at most pixels / k, never below 2^17 (the
    smallest measured) nor above 2^log2_table; off (0) or with a smaller log2_table: log2_table. The
    GPU preset gives 20 views of 200 px 2^17 and keeps 2^19 from ~3.2 M pixels."""
    from fastneus.field.model import table_log2

    fv = load_config("fewview").hashgrid
    assert table_log2(fv, 20 * 200 * 200) == 17 and table_log2(fv, 20 * 300 * 300) == 18
    assert table_log2(fv, 20 * 400 * 400) == 19 and table_log2(fv, 100 * 800 * 800) == 19
    assert table_log2(fv, 3 * 24 * 24) == 17  # tiny data: the floor
    assert table_log2(load_config("fewview", ["pixels_per_entry=0"]).hashgrid, 800_000) == 19
    assert table_log2(load_config("fewview", ["log2_table=15"]).hashgrid, 10 ** 9) == 15


def test_trainer_prints_and_saves_the_table_it_chose(small_scene, tmp_path):
    """The table the trainer builds is the rule's, and its line names the pixels and the rule; a
    multi-shot view's frames count once (view_pixels)."""
    from fastneus.train.trainer import Trainer, view_pixels

    scene = Scene.load(small_scene)
    assert view_pixels(scene, [0, 1, 2]) == (3 * 24 * 24, 3)
    scene2 = Scene.load(small_scene)
    for f in scene2.frames:
        f.view = 0  # one viewpoint photographed three times
    assert view_pixels(scene2, [0, 1, 2]) == (24 * 24, 1)
    cfg = load_config("cpu-quick", SMALL_RUN + ["threads=1", "init_geometry=sphere", "log2_table=17",
                                                "pixels_per_entry=0.001"])
    tr = Trainer(scene, cfg, tmp_path / "run", "cpu")
    assert tr.field.grid_cfg.log2_table == 17 and tr.field.table.shape[1] == 1 << 17
    assert "2^17 entries per level" in tr.table_note and "0.00 M pixels in 3 viewpoints" in tr.table_note
    off = Trainer(scene, load_config("cpu-quick", SMALL_RUN + ["threads=1", "init_geometry=sphere"]), tmp_path / "r2",
                  "cpu")
    assert off.table_note == "hash table: 2^12 entries per level"


# ---------------------------------------------------------------- masks and background
class _Frame:
    def __init__(self, mask):
        self.mask = mask


class _Scene:
    def __init__(self, masks):
        self.frames = [_Frame(m) for m in masks]


def test_masks_auto_on_only_when_every_frame_has_one():
    from fastneus.train.trainer import resolve_masks

    all_m, some_m = _Scene(["a.png", "b.png"]), _Scene(["a.png", None])
    used, note = resolve_masks(all_m, [0, 1], Config())
    assert used and "auto -> on" in note
    used, note = resolve_masks(some_m, [0, 1], Config())
    assert not used and "1/2" in note
    assert not resolve_masks(all_m, [0, 1], Config().replace(masks="off"))[0]
    assert not resolve_masks(all_m, [0, 1], Config().replace(mask_weight=0.0))[0]
    with pytest.raises(FastneusError, match="masks"):
        resolve_masks(some_m, [0, 1], Config().replace(masks="on"))


def test_background_prior_auto():
    from fastneus.train.trainer import resolve_bg_prior

    assert not resolve_bg_prior(Config(), True, 0.9)[0]           # masks win
    assert resolve_bg_prior(Config(), False, 0.4)[0]               # a dark room
    assert not resolve_bg_prior(Config(), False, 0.01)[0]          # a real backdrop
    assert resolve_bg_prior(Config().replace(bg_prior="on"), False, 0.0)[0]
    assert not resolve_bg_prior(Config().replace(bg_prior="off"), False, 0.9)[0]


# ---------------------------------------------------------------- seen volume
class _Cam:
    def __init__(self, f):
        self.K = np.array([[f, 0, 16.0], [0, f, 16.0], [0, 0, 1]])
        self.width = self.height = 32


class _RigScene:
    """Narrow cameras at x = -0.3 and x = +0.3 on z = -3, looking along +z (world = normalised)."""

    def __init__(self, xs=(-0.3, 0.3), f=100.0):
        from types import SimpleNamespace

        self.xs, self.cam = xs, _Cam(f)
        self.frames = [SimpleNamespace(view=i) for i in range(len(xs))]
        self.bounds = SimpleNamespace(radius=1.0)

    def normalisation(self):
        return np.eye(4)

    def frame_camera(self, i):
        return self.cam

    def world_to_cam(self, i):
        m = np.eye(4)
        m[:3, 3] = [-self.xs[i], 0.0, 3.0]
        return m


def test_seen_cells_need_two_views():
    from fastneus.train.visibility import seen_cells, seen_fraction

    scene, r = _RigScene(), 16
    one = seen_cells(scene, [0], r, "cpu", min_views=2)            # a single viewpoint: one camera suffices
    two = seen_cells(scene, [0, 1], r, "cpu", min_views=2)
    any_ = seen_cells(scene, [0, 1], r, "cpu", min_views=1)
    assert one.dtype == torch.bool and one.numel() == r ** 3
    assert bool(two.le(any_).all()) and seen_fraction(two) < seen_fraction(any_) < 1.0

    def cell(x, y, z):
        i = [min(r - 1, int((v + 1) * r / 2)) for v in (x, y, z)]
        return i[0] + r * (i[1] + r * i[2])

    assert bool(two[cell(0, 0, 0)])                                 # both cameras see the centre
    assert not bool(two[cell(0.6, 0, 0)]) and bool(any_[cell(0.6, 0, 0)])   # only the right one
    assert not bool(any_[cell(0, 0.95, -0.9)])                      # outside both frustums
    # frames of one viewpoint count once
    scene.frames[1].view = 0
    assert torch.equal(seen_cells(scene, [0, 1], r, "cpu", min_views=2), seen_cells(scene, [0], r, "cpu"))


def test_grid_never_occupies_unseen_cells():
    from fastneus.kernels.occupancy import OccupancyGrid

    g = OccupancyGrid(8, "cpu")
    allowed = torch.rand(8 ** 3, generator=torch.Generator().manual_seed(1)) > 0.5
    g.set_allowed(allowed)
    assert not bool(g.bits.bool()[~allowed].any()) and bool(g.bits.bool()[allowed].all())
    g.update(lambda x: torch.zeros(x.shape[0]), 0.0, 0.01, warmup=True)     # warm-up: all allowed cells
    assert torch.equal(g.bits.bool(), allowed)
    g.update(lambda x: torch.zeros(x.shape[0]), 50.0, 0.01, threshold=0.0, backend="torch")
    assert not bool(g.bits.bool()[~allowed].any())


def test_mesh_has_no_surface_outside_allowed():
    from fastneus.export.mesh import mesh_from_grid, sdf_grid

    class Ball:  # a sphere of radius 0.5 plus a floater at x = 0.8
        def sdf(self, x):
            return torch.minimum(x.norm(dim=-1) - 0.5, (x - torch.tensor([0.8, 0.0, 0.0])).norm(dim=-1) - 0.1)

    r = 8
    lin = (torch.arange(r) + 0.5) * (2.0 / r) - 1.0
    z, y, x = torch.meshgrid(lin, lin, lin, indexing="ij")
    allowed = (x < 0.6).reshape(-1)                                # the floater's cells are unseen
    full = mesh_from_grid(sdf_grid(Ball(), 48, "cpu"), np.zeros(3), 1.0, keep_fraction=0)
    cut = mesh_from_grid(sdf_grid(Ball(), 48, "cpu", allowed=allowed), np.zeros(3), 1.0, keep_fraction=0)
    assert full.vertices[:, 0].max() > 0.85
    assert cut.vertices[:, 0].max() < 0.6 and len(cut.faces) > 100


# ---------------------------------------------------------------- shapes
def test_rock_is_a_closed_irregular_surface():
    from fastneus.synth.shapes import SHAPES, make_shape

    assert "rock" in SHAPES
    m = make_shape("rock")
    assert m.is_watertight and len(m.faces) > 1000
    r = np.linalg.norm(m.vertices - m.vertices.mean(0), axis=1)
    assert r.std() / r.mean() > 0.05                               # not a sphere
