"""scripts/floaters.py: a run's surface far from the ground truth, split into located pieces."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))


def test_a_detached_blob_is_one_free_piece_outside_and_a_pocket_one_inside(tmp_path):
    from floaters import pieces

    from fastneus.data import Scene
    from fastneus.synth.render import synthesize

    synthesize(tmp_path / "sc", shape="sphere", views=3, size=(24, 24), pattern="crosslaser", illum="normal", seed=0,
               device="cpu", proj_size=(64, 48), progress=False, contact_sheet=False)
    scene = Scene.load(tmp_path / "sc")
    gt = trimesh.load(scene.path(scene.gt_mesh), force="mesh", process=False)
    centre, size = gt.bounds.mean(0), float(np.linalg.norm(gt.bounds[1] - gt.bounds[0]))
    blob = trimesh.creation.icosphere(subdivisions=2, radius=0.04 * size)
    toward = scene.cam_to_world(0)[:3, 3] - centre  # between the sphere and the first camera: in view
    at = centre + 0.4 * size * toward / np.linalg.norm(toward)
    blob.apply_translation(at)
    run = tmp_path / "run"
    run.mkdir()
    trimesh.util.concatenate([gt, blob]).export(run / "mesh.ply")
    res = pieces(tmp_path / "sc", run)
    assert len(res["pieces"]) == 1, res["pieces"]
    p = res["pieces"][0]
    assert not p["attached"] and abs(p["error_share"] - res["far_error_share"]) < 1e-9
    assert np.allclose(p["centroid_m"], at, atol=0.01 * size)
    assert p["faces"] == len(blob.faces) and p["masks_seeing"] >= 1
    assert 0 < res["far_area_share"] < 0.1
    assert p["inside_share"] == 0.0 and res["far_inside_error_share"] == 0.0  # in front of the object
    # a closed surface inside the GT solid (an empty pocket the field grew inside the object, its wall
    # facing into the void as marching cubes writes it): far, and all of its error inside
    pocket = trimesh.creation.icosphere(subdivisions=2, radius=0.08 * size)
    pocket.invert()
    pocket.apply_translation(centre)
    trimesh.util.concatenate([gt, pocket]).export(run / "mesh.ply")
    res = pieces(tmp_path / "sc", run)
    assert len(res["pieces"]) == 1 and res["pieces"][0]["inside_share"] == 1.0 and not res["pieces"][0]["attached"]
    assert res["far_inside_error_share"] == 1.0 and res["inside_sampled"] == len(pocket.faces)
    # the GT alone: nothing far
    trimesh.util.concatenate([gt]).export(run / "mesh.ply")
    assert pieces(tmp_path / "sc", run)["pieces"] == []


def test_winding_number_is_one_inside_and_zero_outside():
    from floaters import winding_number

    ball = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    rng = np.random.default_rng(0)
    d = rng.normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = rng.uniform(0.0, 0.95, 200)[:, None]
    w_in = winding_number(ball, d * r)
    w_out = winding_number(ball, d * (1.05 + 3.0 * rng.uniform(size=(200, 1))))
    assert np.allclose(w_in, 1.0, atol=1e-6) and np.allclose(w_out, 0.0, atol=1e-6)
    # the same in small batches (the chunking does not change a value)
    assert np.allclose(winding_number(ball, d * r, chunk=len(ball.faces) * 3), w_in)
    # an inward-facing (flipped) surface counts -1: the sign follows the faces' orientation
    flipped = trimesh.Trimesh(ball.vertices, ball.faces[:, ::-1], process=False)
    assert np.allclose(winding_number(flipped, np.zeros((1, 3))), -1.0, atol=1e-6)

