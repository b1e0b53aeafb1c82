"""The pattern study: one-projector rig in synth, captured Gray-code decoding, the classical
baseline (decode + triangulate) and the visible-surface depth metric."""
from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from fastneus.classical.graycode import graycode_baseline, graycode_depth
from fastneus.eval.depth import baseline_depth_metrics
from fastneus.cli import main
from fastneus.data import Scene, look_at
from fastneus.eval.depth import DepthPool, depth_errors, lit_pixels, mesh_depth, view_depth_metrics
from fastneus.light.patterns import decode_graycode_captured, make_pattern
from fastneus.geometry.projection import project_points
from fastneus.synth.render import synthesize


# --------------------------------------------------------------------------- decoding
@pytest.mark.parametrize("size", [(64, 48), (100, 37)])
def test_captured_graycode_round_trip_with_shading(size):
    """Photos = D (1 + i_r bit) + i_b bit with a random surface colour D per pixel: decoded exactly."""
    w, h = size
    rng = np.random.default_rng()
    planes = make_pattern("graycode", w, h)
    D = rng.uniform(0.1, 0.6, (h, w, 1))
    photos = [np.clip(D * (1 + 0.4 * (p / 255.0)) + 0.1 * (p / 255.0), 0, 1) for p in planes]
    photos = [np.round(p * 255).astype(np.uint8) for p in photos]
    col, row, valid = decode_graycode_captured(photos, w, h)
    jj, ii = np.meshgrid(np.arange(w), np.arange(h))
    bits = np.stack([p[:, :, 0] > 0 for p in planes])
    valid_expect = bits.any(0) & ~bits.all(0)  # never lit or always lit: no contrast, rejected
    assert valid_expect.mean() > 0.99
    np.testing.assert_array_equal(valid, valid_expect)
    np.testing.assert_array_equal(col[valid], jj[valid])
    np.testing.assert_array_equal(row[valid], ii[valid])
    # a global threshold cannot do this: half the max brightness misreads dark-surface pixels
    from fastneus.light.patterns import decode_graycode

    gcol, _ = decode_graycode(photos, w, h)
    assert (gcol != jj).mean() > 0.05


@pytest.fixture(scope="module")
def gray_scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("gray") / "toy"
    return synthesize(out, shape="toy", views=2, size=(56, 56), pattern="graycode", seed=3, progress=False)


def test_synth_graycode_decodes_to_the_true_projector_column(gray_scene):
    """Decoding the synthetic photos gives the column the GT surface point projects to."""
    s = gray_scene
    assert len(s.projectors) == 1 and len(s.frames) == 40 and sorted(s.views()) == [0, 1]
    pj = s.projectors["proj0"]
    assert abs(pj.proj_to_cam[0, 3] - 0.6) < 1e-12  # the paper's 60 cm baseline
    idx = s.views()[0]
    col, row, valid = decode_graycode_captured([s.image(i) for i in idx], pj.width, pj.height)
    depth = s.gt_depth(0)
    v, u = np.nonzero(valid & (depth > 0))
    assert v.size > 100
    K = s.frame_camera(0).K
    xc = (np.linalg.inv(K) @ np.stack([u + 0.5, v + 0.5, np.ones(u.size)])) * depth[v, u]
    c2w = s.cam_to_world(0)
    world = (c2w[:3, :3] @ xc + c2w[:3, 3:4]).T
    px, _ = project_points(torch.tensor(world), pj.K, s.world_to_proj(0, "proj0"))
    px = px.numpy()
    ok_col = np.abs(col[v, u] + 0.5 - px[:, 0]) <= 1.0
    ok_row = np.abs(row[v, u] + 0.5 - px[:, 1]) <= 1.0
    assert ok_col.mean() > 0.95 and ok_row.mean() > 0.95


def test_graycode_baseline_accuracy_and_errors(gray_scene):
    s = gray_scene
    depths, sec = graycode_baseline(s)
    assert sorted(depths) == [0, 20] and sec > 0
    m = baseline_depth_metrics(s, depths)
    # column quantisation alone is ~0.2% of depth at this rig; decoding errors would be far larger
    assert m["depth_err_pct"] < 0.5 and m["depth_coverage"] > 0.8 and m["depth_within_1pct"] > 0.75
    from fastneus.errors import FastneusError

    with pytest.raises(FastneusError, match="planes"):
        graycode_depth(s, s.views()[0][:-1])


# --------------------------------------------------------------------------- the depth metric
def _sphere_gt(radius: float, dist: float, size: int):
    """Analytic z-depth of a sphere of ``radius`` at ``dist`` in front of a camera."""
    f = size * 1.2
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]])
    v, u = np.mgrid[0:size, 0:size]
    d = np.linalg.inv(K) @ np.stack([u.ravel() + 0.5, v.ravel() + 0.5, np.ones(size * size)])  # z = 1
    c = np.array([0, 0, dist])
    # |t d - c|^2 = r^2
    a, b, cc = (d * d).sum(0), -2 * (d * c[:, None]).sum(0), c @ c - radius ** 2
    disc = b * b - 4 * a * cc
    t = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), 0.0)
    return K, t.reshape(size, size)


def test_depth_metric_on_an_analytic_sphere():
    K, gt = _sphere_gt(0.5, 3.0, 64)
    assert (gt > 0).mean() > 0.1
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.5)
    sphere.apply_translation([0, 0, 3.0])
    pred = mesh_depth(sphere.vertices, sphere.faces, K, np.eye(4), 64, 64)
    m = depth_errors(pred, gt)
    assert m["depth_err_pct"] < 0.02 and m["depth_err_mm"] < 0.5
    assert m["depth_coverage"] > 0.97 and m["depth_within_1pct"] > 0.97
    # known errors come out as such
    m = depth_errors(gt * 1.02, gt)
    assert m["depth_err_pct"] == pytest.approx(2.0) and m["depth_within_1pct"] == 0.0
    assert m["depth_median_pct"] == pytest.approx(2.0)
    assert m["depth_err_mm"] == pytest.approx(1000 * 0.02 * gt[gt > 0].mean())
    holes = gt.copy()
    holes[:, :32] = np.nan
    m = depth_errors(holes * 1.005, gt)
    cov = (gt[:, 32:] > 0).sum() / (gt > 0).sum()
    assert m["depth_coverage"] == pytest.approx(cov) and m["depth_within_1pct"] == pytest.approx(cov)
    assert m["depth_err_pct"] == pytest.approx(0.5)
    # pooling weighs pixels, not views
    p = DepthPool()
    p.add(gt * 1.01, gt)
    p.add(gt * 1.03, gt, select=np.zeros_like(gt, dtype=bool))
    assert p.metrics()["depth_err_pct"] == pytest.approx(1.0)
    # the median ignores a few far-off pixels that move the mean
    few = gt * 1.002
    few[gt > 0] = np.where(np.arange(int((gt > 0).sum())) < 20, gt[gt > 0] * 1.5, few[gt > 0])
    m = depth_errors(few, gt)
    assert m["depth_median_pct"] == pytest.approx(0.2, abs=1e-6) and m["depth_err_pct"] > 0.3


def test_view_depth_metrics_gt_mesh_and_lit_split(tmp_path):
    s = synthesize(tmp_path / "cl", shape="toy", views=1, size=(48, 48), pattern="crosslaser", illum="dark",
                   baselines=(0.6, -0.6), seed=1, progress=False)
    gt_mesh = trimesh.load(s.path(s.gt_mesh), force="mesh", process=False)
    m = view_depth_metrics(gt_mesh, s, [0])
    assert m["depth_views"] == 1 and m["depth_err_pct"] < 1e-3 and m["depth_coverage"] > 0.99
    lit = lit_pixels(s.image(0), s.gt_clean(0))
    assert 0 < m["depth_lit_pixels"] == int((lit & (s.gt_depth(0) > 0)).sum())
    assert m["depth_lit_pixels"] + m["depth_unlit_pixels"] == m["depth_pixels"]
    shifted = gt_mesh.copy()
    shifted.apply_translation(-0.04 * s.cam_to_world(0)[:3, 2])  # 4 cm toward the camera
    m2 = view_depth_metrics(shifted, s, [0])
    assert 35 < m2["depth_err_mm"] < 45


# --------------------------------------------------------------------------- synth CLI: the rig
def test_cli_synth_one_projector_rig(tmp_path, capsys):
    out = tmp_path / "c"
    rc = main(["synth", "--shape", "sphere", "--views", "3", "--size", "24x24", "--pattern", "colorline",
               "--baselines", "0.6", "--device", "cpu", "--no-contact-sheet", "--out", str(out)])
    assert rc == 0
    s = Scene.load(out)
    assert list(s.projectors) == ["proj0"] and len(s.frames) == 3 and s.meta["baselines"] == [0.6]
    rc = main(["synth", "--shape", "sphere", "--views", "1", "--size", "24x24", "--baselines", "0,0.2",
               "--device", "cpu", "--out", str(tmp_path / "bad")])
    assert rc == 2 and "--baselines" in capsys.readouterr().err
