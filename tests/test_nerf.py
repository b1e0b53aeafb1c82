"""NeRF / nerfstudio transforms.json: axes, intrinsics variants, projector block, round trips, errors."""
from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from fastneus.cli import main
from fastneus.data import Scene
from fastneus.errors import FastneusError
from fastneus.formats.detect import detect_format, load_scene
from fastneus.formats.nerf import GL_TO_CV, read_nerf, write_nerf
from fastneus.geometry.projection import project_points
from test_formats import make_scene


def _same_scene(a: Scene, b: Scene) -> None:
    assert len(a.frames) == len(b.frames)
    for i in range(len(a.frames)):
        ca, cb = a.frame_camera(i), b.frame_camera(i)
        assert np.allclose(ca.K, cb.K, atol=1e-9) and (ca.width, ca.height) == (cb.width, cb.height)
        assert np.allclose(ca.dist, cb.dist)
        assert np.allclose(a.cam_to_world(i), b.cam_to_world(i), atol=1e-9)
        assert np.array_equal(a.image(i), b.image(i))
        ma, mb = a.mask(i), b.mask(i)
        assert (ma is None) == (mb is None) and (ma is None or np.array_equal(ma, mb))
        pa = sorted(p for p, _ in a.active_projectors(i))
        assert pa == sorted(p for p, _ in b.active_projectors(i))
        for (pid, qa), (_, qb) in zip(sorted(a.active_projectors(i)), sorted(b.active_projectors(i))):
            assert np.allclose(a.proj_to_world(i, pid), b.proj_to_world(i, pid), atol=1e-9)
            assert np.array_equal(a.pattern_image(qa), b.pattern_image(qb))
    for pid in a.projectors:
        assert np.allclose(a.projectors[pid].K, b.projectors[pid].K)
    assert np.allclose(a.bounds.center, b.bounds.center) and math.isclose(a.bounds.radius, b.bounds.radius)


def test_round_trip_rigged_projectors(tmp_path):
    src = make_scene(tmp_path / "src", n=3, n_proj=2, seed=3)
    path = write_nerf(src, tmp_path / "nerf")
    assert detect_format(tmp_path / "nerf") == "nerf"
    back = load_scene(tmp_path / "nerf")
    _same_scene(src, back)
    # and back again through fastneus -> transforms.json gives the same numbers
    d1 = json.loads(path.read_text())
    write_nerf(back, tmp_path / "nerf2")
    d2 = json.loads((tmp_path / "nerf2" / "transforms.json").read_text())
    assert np.allclose(d1["frames"][1]["transform_matrix"], d2["frames"][1]["transform_matrix"], atol=1e-12)
    assert d1["projectors"]["p1"]["proj_to_cam"] == d2["projectors"]["p1"]["proj_to_cam"]


def test_round_trip_free_projector_two_cameras_and_off_frames(tmp_path):
    src = make_scene(tmp_path / "src", n=3, n_proj=1, seed=5, masks=False)
    d = json.loads((tmp_path / "src" / "scene.json").read_text())
    rng = np.random.default_rng(1)
    p2w = d["frames"][0]["cam_to_world"]
    d["projectors"]["p0"]["proj_to_cam"] = None
    for i, f in enumerate(d["frames"]):
        f["projectors"]["p0"] = {"pattern": None if i == 1 else "q0", "proj_to_world": p2w}
    d["cameras"]["c2"] = {"K": [[50.0 + rng.random(), 0, 11.0], [0, 52.0, 9.0], [0, 0, 1]], "width": 24, "height": 16,
                          "dist": [0.01, -0.002, 0.0, 0.0, 0.0]}
    d["frames"][2]["camera"] = "c2"
    (tmp_path / "src" / "scene.json").write_text(json.dumps(d))
    src = Scene.load(tmp_path / "src")
    write_nerf(src, tmp_path / "nerf")
    out = json.loads((tmp_path / "nerf" / "transforms.json").read_text())
    assert "fl_x" not in out and "fl_x" in out["frames"][0]  # two cameras: per-frame intrinsics
    assert "transform_matrix" in out["projectors"]["p0"] and out["frames"][1]["projectors"]["p0"] is None
    back = read_nerf(tmp_path / "nerf")
    _same_scene(src, back)
    assert back.frames[1].projectors["p0"].pattern is None


def _write_png(path: Path, h=20, w=30, seed=0):
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8))


def test_nerf_synthetic_layout_axes_and_focal(tmp_path):
    """camera_angle_x only, extension-less paths, OpenGL axes: a point up and right in the
    world lands up and right in the image, at the pinhole's exact pixel."""
    _write_png(tmp_path / "train" / "r_0.png")
    _write_png(tmp_path / "pat.png", 24, 32, 1)
    T = np.eye(4)
    T[:3, 3] = (0.0, 0.0, 4.0)  # OpenGL camera at +z looking down -z, y up
    ang = 0.7
    d = {"camera_angle_x": ang, "frames": [{"file_path": "./train/r_0", "transform_matrix": T.tolist()}],
         "projectors": {"lamp": {"camera_angle_x": 1.0, "w": 32, "h": 24, "proj_to_cam": np.eye(4).tolist(),
                                 "pattern": "pat.png"}}}
    (tmp_path / "transforms.json").write_text(json.dumps(d))
    s = load_scene(tmp_path)
    K = s.cameras["cam0"].K
    f = 0.5 * 30 / math.tan(0.35)
    assert np.allclose(K, [[f, 0, 15], [0, f, 10], [0, 0, 1]])
    assert np.allclose(s.cam_to_world(0), T @ GL_TO_CV)
    X = torch.tensor([[0.1, 0.2, 0.0]], dtype=torch.float64)
    px, z = project_points(X, K, s.world_to_cam(0))
    assert float(z) == pytest.approx(4.0)
    assert px[0, 0].item() == pytest.approx(15 + f * 0.1 / 4) and px[0, 1].item() == pytest.approx(10 - f * 0.2 / 4)
    assert s.active_projectors(0) == [("lamp", "q000")]
    assert s.projectors["lamp"].K[0, 0] == pytest.approx(16 / math.tan(0.5))
    # bounds default: where the axes meet (the origin), half the camera distance
    assert np.allclose(s.bounds.center, 0, atol=1e-9) and s.bounds.radius == pytest.approx(2.0)


def test_nerfstudio_per_frame_intrinsics_and_distortion(tmp_path):
    for i in range(2):
        _write_png(tmp_path / "images" / f"frame_{i:05d}.jpg", seed=i)
    frames = []
    for i in range(2):
        T = np.eye(4)
        T[:3, 3] = (i * 0.5, 0, 3.0)
        frames.append({"file_path": f"images/frame_{i:05d}.jpg", "transform_matrix": T.tolist(),
                       "fl_x": 40.0 + i, "fl_y": 41.0, "cx": 14.5, "cy": 10.25})
    d = {"camera_model": "OPENCV", "w": 30, "h": 20, "k1": 0.01, "k2": -0.001, "p1": 0.0, "p2": 0.0,
         "frames": frames, "bounds": {"center": [0, 0, 0], "radius": 1.0}}
    (tmp_path / "transforms.json").write_text(json.dumps(d))
    s = read_nerf(tmp_path / "transforms.json")
    assert len(s.cameras) == 2 and s.frame_camera(1).K[0, 0] == 41.0 and s.frame_camera(1).K[0, 2] == 14.5
    assert np.allclose(s.frame_camera(0).dist, [0.01, -0.001, 0, 0, 0]) and s.projectors == {}
    assert s.bounds.radius == 1.0


@pytest.mark.parametrize("edit, field", [
    (lambda d: d["frames"][0].pop("file_path"), "frames[0].file_path"),
    (lambda d: d["frames"][0].__setitem__("transform_matrix", (2 * np.eye(4)).tolist()), "frames[0].transform_matrix"),
    (lambda d: d.__setitem__("camera_model", "OPENCV_FISHEYE"), "camera_model"),
    (lambda d: d.pop("camera_angle_x"), "frames[0]"),
    (lambda d: d["projectors"]["lamp"].__setitem__("transform_matrix", np.eye(4).tolist()), "projectors.lamp"),
    (lambda d: d["frames"][0].__setitem__("projectors", {"other": "pat.png"}), "frames[0].projectors"),
    (lambda d: d["frames"][0].__setitem__("file_path", "nope.png"), "frames[0].file_path"),
])
def test_bad_input_names_file_and_field(tmp_path, edit, field):
    _write_png(tmp_path / "a.png")
    _write_png(tmp_path / "pat.png", 24, 32, 1)
    T = np.eye(4)
    T[2, 3] = 3
    d = {"camera_angle_x": 0.7, "frames": [{"file_path": "a.png", "transform_matrix": T.tolist()}],
         "projectors": {"lamp": {"fl_x": 30.0, "w": 32, "h": 24, "proj_to_cam": np.eye(4).tolist(),
                                 "pattern": "pat.png"}}}
    edit(d)
    (tmp_path / "transforms.json").write_text(json.dumps(d))
    with pytest.raises(FastneusError) as e:
        read_nerf(tmp_path)
    assert "transforms.json" in str(e.value) and e.value.field == field, str(e.value)


def test_convert_cli_to_nerf(tmp_path, capsys):
    make_scene(tmp_path / "src", n=2, n_proj=1, seed=2)
    assert main(["convert", str(tmp_path / "src"), "--to", "nerf", "--out", str(tmp_path / "n")]) == 0
    assert main(["convert", str(tmp_path / "n"), "--to", "fastneus", "--out", str(tmp_path / "f")]) == 0
    _same_scene(Scene.load(tmp_path / "src"), Scene.load(tmp_path / "f"))


def test_round_trip_keeps_underwater_ports(tmp_path):
    from fastneus.synth.render import synthesize

    s = synthesize(tmp_path / "w", shape="sphere", views=2, size=(16, 16), seed=0, device="cpu", progress=False,
                   contact_sheet=False, proj_size=(32, 24), medium="water")
    write_nerf(s, tmp_path / "n")
    d = json.loads((tmp_path / "n" / "transforms.json").read_text())
    assert d["port"]["thickness"] == pytest.approx(0.01) and "port" in d["projectors"]["proj0"]
    back = read_nerf(tmp_path / "n")
    assert back.cameras["cam0"].port.distance == pytest.approx(0.03)
    assert back.projectors["proj2"].port.n_water == pytest.approx(1.333)
    d["port"]["normal"] = [0, 0, -1]
    (tmp_path / "n" / "transforms.json").write_text(json.dumps(d))
    with pytest.raises(FastneusError) as e:
        read_nerf(tmp_path / "n")
    assert e.value.field == "port.normal"
