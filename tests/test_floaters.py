"""scripts/floaters.py: a run's surface far from the ground truth, split into located pieces."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))


def test_a_detached_blob_is_one_free_piece_with_all_the_far_error(tmp_path):
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
    # the GT alone: nothing far
    trimesh.util.concatenate([gt]).export(run / "mesh.ply")
    assert pieces(tmp_path / "sc", run)["pieces"] == []
