"""Scene model: scene.json round trip, accessors, and one-line validation errors."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from fastneus.data import Scene, look_at
from fastneus.errors import FastneusError

CAM_W, CAM_H = 32, 24
PROJ_W, PROJ_H = 40, 30


def _write_scene(root, n_frames=3, free=False):
    """A small valid scene on disk; returns its scene.json dict."""
    (root / "images").mkdir(parents=True, exist_ok=True)
    (root / "masks").mkdir(exist_ok=True)
    (root / "patterns").mkdir(exist_ok=True)
    rng = np.random.default_rng(0)
    pat = rng.integers(0, 256, (PROJ_H, PROJ_W, 3), dtype=np.uint8)
    cv2.imwrite(str(root / "patterns/p0.png"), pat)
    frames = []
    for i in range(n_frames):
        im = rng.integers(0, 256, (CAM_H, CAM_W, 3), dtype=np.uint8)
        cv2.imwrite(str(root / f"images/{i:03d}.png"), im)
        cv2.imwrite(str(root / f"masks/{i:03d}.png"), np.full((CAM_H, CAM_W), 255, np.uint8))
        ang = 2 * np.pi * i / n_frames
        c2w = look_at([4 * np.cos(ang), 4 * np.sin(ang), 1.0], [0, 0, 0])
        fp = {"pattern": "p0"}
        if free:
            fp["proj_to_world"] = (c2w @ _p2c()).tolist()
        frames.append({"image": f"images/{i:03d}.png", "camera": "cam0", "cam_to_world": c2w.tolist(),
                       "view": i // 2, "mask": f"masks/{i:03d}.png", "projectors": {"proj0": fp}})
    K = [[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]]
    KP = [[35.0, 0, 20], [0, 35.0, 15], [0, 0, 1]]
    d = {
        "format": "fastneus-scene", "version": 1, "units": "m", "name": "test",
        "bounds": {"center": [0.1, 0.0, -0.2], "radius": 1.5},
        "cameras": {"cam0": {"K": K, "width": CAM_W, "height": CAM_H, "dist": [0, 0, 0, 0, 0]}},
        "projectors": {"proj0": {"K": KP, "width": PROJ_W, "height": PROJ_H,
                                 "proj_to_cam": None if free else _p2c().tolist()}},
        "patterns": {"p0": {"file": "patterns/p0.png"}},
        "frames": frames,
        "illumination": {"i_r": 0.4, "i_b": 0.1, "ambient": 1.0, "known": True},
        "gt": {"mesh": None},
    }
    (root / "scene.json").write_text(json.dumps(d))
    return d


def _p2c():
    T = np.eye(4)
    a = np.deg2rad(5)
    T[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    T[0, 3] = 0.2
    return T


def test_round_trip(tmp_path):
    d = _write_scene(tmp_path)
    s = Scene.load(tmp_path)
    assert len(s.frames) == 3 and s.name == "test"
    s.save(tmp_path / "copy")
    s2 = Scene.load(tmp_path / "copy" / "scene.json")
    # paths are rewritten relative to the new folder but point to the same files
    assert s2.path(s2.frames[0].image).resolve() == s.path(s.frames[0].image).resolve()
    s.save()
    s3 = Scene.load(tmp_path)
    assert s3.to_dict() == s.to_dict()
    assert json.loads((tmp_path / "scene.json").read_text())["frames"][1]["cam_to_world"] == d["frames"][1]["cam_to_world"]
    np.testing.assert_array_equal(s2.image(1), s.image(1))


def test_accessors(tmp_path):
    _write_scene(tmp_path, n_frames=4)
    s = Scene.load(tmp_path)
    im = s.image(0)
    assert im.dtype == np.uint8 and im.shape == (CAM_H, CAM_W, 3)
    bgr = cv2.imread(str(tmp_path / "images/000.png"))
    np.testing.assert_array_equal(im, bgr[:, :, ::-1])
    m = s.mask(0)
    assert m.dtype == np.float32 and m.shape == (CAM_H, CAM_W) and m.max() == 1.0
    assert s.pattern_image("p0").shape == (PROJ_H, PROJ_W, 3)
    np.testing.assert_allclose(s.proj_to_world(1, "proj0"), s.cam_to_world(1) @ _p2c())
    np.testing.assert_allclose(s.world_to_proj(1, "proj0") @ s.proj_to_world(1, "proj0"), np.eye(4), atol=1e-12)
    S = s.normalisation()
    np.testing.assert_allclose(S @ [0, 0, 0, 1], [0.1, 0, -0.2, 1])
    np.testing.assert_allclose(S @ [1, 0, 0, 1], [1.6, 0, -0.2, 1])
    assert s.views() == {0: [0, 1], 1: [2, 3]}
    sub = s.subset([3, 1])
    assert len(sub.frames) == 2 and sub.frames[0].image == "images/003.png" and len(s.frames) == 4
    assert s.gt_depth(0) is None and s.gt_clean(0) is None


def test_free_projector(tmp_path):
    _write_scene(tmp_path, free=True)
    s = Scene.load(tmp_path)
    np.testing.assert_allclose(s.proj_to_world(2, "proj0"), s.cam_to_world(2) @ _p2c(), atol=1e-12)


def test_undistort(tmp_path):
    d = _write_scene(tmp_path, n_frames=1)
    d["cameras"]["cam0"]["dist"] = [0.1, 0, 0, 0, 0]
    (tmp_path / "scene.json").write_text(json.dumps(d))
    s = Scene.load(tmp_path)
    raw = cv2.imread(str(tmp_path / "images/000.png"))[:, :, ::-1]
    assert s.image(0).shape == raw.shape and not np.array_equal(s.image(0), raw)


def _mutate_and_load(tmp_path, fn):
    d = _write_scene(tmp_path)
    fn(d, tmp_path)
    (tmp_path / "scene.json").write_text(json.dumps(d))
    with pytest.raises(FastneusError) as ei:
        Scene.load(tmp_path)
    msg = str(ei.value)
    assert "\n" not in msg and "scene.json" in msg
    return msg


def _set_pose(i, T):
    def fn(d, root):
        d["frames"][i]["cam_to_world"] = T
    return fn


def _nonrigid():
    T = np.eye(4)
    T[0, 0] = 1.1
    return T.tolist()


def _reflection():
    T = np.eye(4)
    T[0, 0] = -1
    return T.tolist()


def _nan_pose():
    T = np.eye(4).tolist()
    T[0][3] = float("nan")
    return T


def _bad_image(d, root):
    (root / "images/001.png").write_bytes(b"not an image at all, just text")


def _wrong_size(d, root):
    cv2.imwrite(str(root / "images/002.png"), np.zeros((CAM_H + 1, CAM_W, 3), np.uint8))


def _wrong_pattern_size(d, root):
    cv2.imwrite(str(root / "patterns/p0.png"), np.zeros((PROJ_H, PROJ_W + 2, 3), np.uint8))


CASES = {
    "missing image": (lambda d, r: (r / "images/001.png").unlink(), "frames[1].image"),
    "unreadable image": (_bad_image, "frames[1].image"),
    "wrong image size": (_wrong_size, "frames[2].image"),
    "missing mask": (lambda d, r: (r / "masks/000.png").unlink(), "frames[0].mask"),
    "missing pattern file": (lambda d, r: (r / "patterns/p0.png").unlink(), "patterns.p0.file"),
    "non-finite pose": (_set_pose(1, _nan_pose()), "frames[1].cam_to_world"),
    "non-rigid pose": (_set_pose(0, _nonrigid()), "frames[0].cam_to_world"),
    "reflection pose": (_set_pose(0, _reflection()), "frames[0].cam_to_world"),
    "bad last row": (_set_pose(0, (np.eye(4) + np.diag([0, 0, 0, 1.0])).tolist()), "frames[0].cam_to_world"),
    "pose shape": (_set_pose(2, np.eye(3).tolist()), "frames[2].cam_to_world"),
    "unknown camera": (lambda d, r: d["frames"][2].update(camera="nope"), "frames[2].camera"),
    "unknown projector": (lambda d, r: d["frames"][0]["projectors"].update(projX={"pattern": "p0"}),
                          "frames[0].projectors.projX"),
    "unknown pattern": (lambda d, r: d["frames"][1]["projectors"]["proj0"].update(pattern="zz"),
                        "frames[1].projectors.proj0.pattern"),
    "pattern size mismatch": (_wrong_pattern_size, "frames[0].projectors.proj0.pattern"),
    "empty frames": (lambda d, r: d.update(frames=[]), "frames"),
    "K not 3x3": (lambda d, r: d["cameras"]["cam0"].update(K=[[1, 0], [0, 1]]), "cameras.cam0.K"),
    "bad width": (lambda d, r: d["cameras"]["cam0"].update(width="32"), "cameras.cam0.width"),
    "dist shape": (lambda d, r: d["cameras"]["cam0"].update(dist=[0, 0]), "cameras.cam0.dist"),
    "proj_to_cam non-rigid": (lambda d, r: d["projectors"]["proj0"].update(proj_to_cam=_nonrigid()),
                              "projectors.proj0.proj_to_cam"),
    "unknown format": (lambda d, r: d.update(format="nerf"), "format"),
    "unknown version": (lambda d, r: d.update(version=7), "version"),
    "missing bounds": (lambda d, r: d.pop("bounds"), "bounds"),
    "bad radius": (lambda d, r: d["bounds"].update(radius=-1), "bounds.radius"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_validation(tmp_path, case):
    fn, fld = CASES[case]
    msg = _mutate_and_load(tmp_path, fn)
    assert fld in msg, msg


def test_free_projector_needs_pose(tmp_path):
    def fn(d, root):
        d["projectors"]["proj0"]["proj_to_cam"] = None
    msg = _mutate_and_load(tmp_path, fn)
    assert "frames[0].projectors.proj0.proj_to_world" in msg


def test_invalid_json(tmp_path):
    (tmp_path / "scene.json").write_text("{not json")
    with pytest.raises(FastneusError, match="invalid JSON"):
        Scene.load(tmp_path)
    with pytest.raises(FastneusError, match="not found"):
        Scene.load(tmp_path / "nowhere")
