"""One-shot labelling of thin projected lines (fastneus/classical/laserlines.py) and the geometry
init it feeds: candidates along a ray are the runs of lit samples, a ray inside a sheet says
nothing, labels are right where accepted, and init_geometry=auto uses it only on one-shot runs
lit by thin coloured lines."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fastneus.classical.laserlines import _runs, laser_line_depth, sparse_line_frame
from fastneus.config import load_config
from fastneus.train.geometry_init import MAX_SWEEP_VIEWS, MIN_LINE_VIEWS, line_frames
from fastneus.synth.render import synthesize


def test_runs_are_candidates_and_long_runs_say_nothing():
    rng = np.random.default_rng()
    D = 400
    t = torch.linspace(2.0, 6.0, D, dtype=torch.float64)[None].repeat(3, 1)
    q = torch.zeros(3, D)
    c1, c2 = int(rng.integers(20, 150)), int(rng.integers(220, 380))
    for c in (c1, c2):  # two symmetric bumps on ray 0: centres exact
        q[0, c - 3:c + 4] = torch.tensor([0.2, 0.5, 0.9, 1.0, 0.9, 0.5, 0.2])
    q[1, c1 - 3:c1 + 4] = 1.0  # one flat run on ray 1
    q[2, 50:300] = 1.0  # ray 2 lies in a sheet: lit over most of its chord
    chord = t[:, -1] - t[:, 0]
    cz = _runs(q, t, chord, max_run=0.2)
    assert cz.shape == (3, 8)
    got = cz[0][torch.isfinite(cz[0])]
    assert torch.allclose(got, t[0, [c1, c2]], atol=1e-9), (got, t[0, [c1, c2]])
    assert torch.isfinite(cz[1]).sum() == 1 and math.isclose(float(cz[1, 0]), float(t[1, c1]), abs_tol=1e-9)
    assert not torch.isfinite(cz[2]).any()


@pytest.fixture(scope="module")
def laser_scene(tmp_path_factory):
    # the default rig: 4 cross-laser projectors (red vertical, green horizontal lines), Dark light.
    # A fixed seed: the synthetic albedo's random colours decide how many red pixels the colour test
    # finds (seeds 100-111: 0-1189 labels, 0 when the red channel is skipped as albedo), and a test
    # must not pass or fail by that draw; the spread is in docs/BENCHMARKS.md.
    return synthesize(tmp_path_factory.mktemp("cx") / "s", shape="toy", views=MAX_SWEEP_VIEWS + 1, size=(400, 400),
                      pattern="crosslaser", illum="dark", seed=102,
                      progress=False, contact_sheet=False)


def test_labels_are_right_where_accepted(laser_scene):
    sc = laser_scene
    z, uv, K = laser_line_depth(sc, 0)
    gt = sc.gt_depth(0)
    ok = np.isfinite(z)
    assert not (ok & (gt <= 0)).any()  # nothing on the background
    ph = sc.image(0).astype(np.float32) / 255
    red = (ph[..., 0] > 2.5 * ph.min(2) + 0.02) & (gt > 0)
    assert ok.sum() > 0.3 * red.sum(), (ok.sum(), red.sum())
    # the depth belongs to the ray through the sub-pixel line centre: compare with the GT there
    import cv2

    g = cv2.remap(gt.astype(np.float32), uv[..., 0] - 0.5, uv[..., 1] - 0.5, cv2.INTER_NEAREST)
    keep = ok & (g > 0)
    err = np.abs(z[keep] - g[keep]) / g[keep]
    assert np.median(err) < 0.005, np.median(err)
    assert (err > 0.05).mean() < 0.05, (err > 0.05).mean()  # wrong sheets are rare
    # the horizontal (green) sheets contain the camera centre on this rig: no green-only labels
    green_only = (ph[..., 1] > 2.5 * ph.min(2) + 0.02) & ~red
    assert (ok & green_only).sum() <= 0.02 * ok.sum()


def test_the_auto_rule(laser_scene, tmp_path):
    assert sparse_line_frame(laser_scene, 0)
    assert line_frames(laser_scene, list(range(MIN_LINE_VIEWS - 1))) is None  # one view: too sparse
    assert line_frames(laser_scene, list(range(MAX_SWEEP_VIEWS))) == list(range(MAX_SWEEP_VIEWS))
    assert line_frames(laser_scene, list(range(MAX_SWEEP_VIEWS + 1))) is None  # more views find the surface
    dense = synthesize(tmp_path / "d", shape="sphere", views=1, size=(24, 24), pattern="colorline",
                       progress=False, contact_sheet=False)
    assert not sparse_line_frame(dense, 0) and line_frames(dense, [0]) is None


def test_init_geometry_fits_the_labelled_lines(laser_scene, tmp_path):
    from fastneus.train.geometry_init import initialise_geometry, lined_points
    from fastneus.train.trainer import Trainer

    sc = laser_scene
    frames = list(range(MIN_LINE_VIEWS))
    cfg = load_config("cpu-quick", ["log_every=1000000", "save_every=100000000"], base={"frames": frames})
    tr = Trainer(sc, cfg, tmp_path / "run", "cpu")
    pts = lined_points(sc, frames)
    P = torch.tensor((pts["points"] - sc.bounds.center) / sc.bounds.radius, dtype=torch.float32)
    with torch.no_grad():
        before = float(tr.field.sdf(P).abs().median())
    note = initialise_geometry(tr)
    assert note is not None and "labelled lines" in note
    with torch.no_grad():
        after = float(tr.field.sdf(P).abs().median())
    assert after < 0.25 * before and after < 0.01, (before, after)
    assert tr.prior is not None


def test_a_coloured_surface_is_not_a_line(laser_scene, monkeypatch):
    """A red object under the same lines: red is 'lit' over most of it, which is albedo, not lines;
    the red channel is skipped rather than labelled everywhere (before this guard: ~80 % of the
    labels on a wrong sheet)."""
    sc = laser_scene
    gt = sc.gt_depth(0)
    photo = sc.image(0).astype(np.float32)
    tinted = photo.copy()
    tinted[gt > 0, 0] = np.clip(3.0 * photo[gt > 0, 0] + 6.0, 0, 255)  # red albedo
    monkeypatch.setattr(sc, "image", lambda i: tinted.astype(np.uint8) if i == 0 else photo.astype(np.uint8))
    z, _, _ = laser_line_depth(sc, 0)
    assert not np.isfinite(z).any()
    z, _, _ = laser_line_depth(sc, 0, max_share=1.0)  # the guard is what keeps them out
    assert np.isfinite(z).sum() > 100
