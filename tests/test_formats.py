"""Scene formats: ActiveNeuS read/write, OpenCV procam calibration, NeuS, COLMAP, convert verb."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from fastneus.cli import main
from fastneus.data import Scene, look_at, rigid_inverse
from fastneus.errors import FastneusError
from fastneus.formats.activeneus import read_activeneus, write_activeneus
from fastneus.formats.detect import load_scene
from fastneus.geometry.projection import pixel_rays, project_points, sample_pattern

SAMPLE = Path(__file__).resolve().parents[2] / "shared" / "data" / "activeneus_sample"
if not SAMPLE.is_dir():
    SAMPLE = Path("/work/shared/data/activeneus_sample")


# --------------------------------------------------------------------------- helpers
def _rot(rng, deg: float) -> np.ndarray:
    return cv2.Rodrigues(rng.normal(size=3) / np.sqrt(3) * np.deg2rad(deg))[0]


def make_scene(root: Path, n: int = 3, n_proj: int = 2, seed: int = 0, size=(24, 16), masks=True) -> Scene:
    """A tiny hand-made scene: random cameras on a sphere, random rig-attached projectors."""
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    w, h = size
    (root / "images").mkdir(exist_ok=True)
    (root / "masks").mkdir(exist_ok=True)
    (root / "patterns").mkdir(exist_ok=True)
    cams = {"c": {"K": [[30.0 + rng.random(), 0, w / 2 + rng.random()], [0, 31.0, h / 2 - rng.random()], [0, 0, 1]],
                  "width": w, "height": h}}
    projs, pats = {}, {}
    for k in range(n_proj):
        T = np.eye(4)
        T[:3, :3] = _rot(rng, 10)
        T[:3, 3] = rng.normal(size=3) * 0.3
        projs[f"p{k}"] = {"K": [[40.0 + k, 0, 16.0], [0, 41.0, 12.0], [0, 0, 1]], "width": 32, "height": 24,
                          "proj_to_cam": T.tolist()}
        pat = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
        cv2.imwrite(str(root / f"patterns/q{k}.png"), pat)
        pats[f"q{k}"] = {"file": f"patterns/q{k}.png"}
    frames = []
    center = np.array([0.1, -0.2, 0.3])
    for i in range(n):
        v = rng.normal(size=3)
        eye = center + 2.5 * v / np.linalg.norm(v)
        c2w = look_at(eye, center)
        cv2.imwrite(str(root / f"images/{i:03d}.png"), rng.integers(0, 256, (h, w, 3), dtype=np.uint8))
        cv2.imwrite(str(root / f"masks/{i:03d}.png"), rng.integers(0, 256, (h, w), dtype=np.uint8))
        fr = {"image": f"images/{i:03d}.png", "camera": "c", "cam_to_world": c2w.tolist(),
              "projectors": {f"p{k}": {"pattern": f"q{k}"} for k in range(n_proj)}}
        if masks:
            fr["mask"] = f"masks/{i:03d}.png"
        frames.append(fr)
    d = {"format": "fastneus-scene", "version": 1, "bounds": {"center": center.tolist(), "radius": 0.8},
         "cameras": cams, "projectors": projs, "patterns": pats, "frames": frames,
         "illumination": {"i_r": 0.3, "i_b": 0.05, "ambient": 1.0},
         "response": "linear"}  # as the format's photos: written back as they are
    (root / "scene.json").write_text(json.dumps(d))
    return Scene.load(root)


def _rays(scene: Scene, i: int) -> tuple[np.ndarray, np.ndarray]:
    cam = scene.frame_camera(i)
    v, u = np.mgrid[0:cam.height, 0:cam.width]
    uv = torch.tensor(np.stack([u.ravel() + 0.5, v.ravel() + 0.5], 1), dtype=torch.float64)
    o, d = pixel_rays(cam.K, scene.cam_to_world(i), uv, scene.normalisation())
    return o.numpy(), d.numpy()


def _proj_pixels(scene: Scene, i: int, pid: str, pts: np.ndarray) -> np.ndarray:
    """Projector pixels of normalised points (the renderer's mapping)."""
    S = scene.normalisation()
    W = scene.world_to_proj(i, pid) @ S
    px, _ = project_points(torch.tensor(pts, dtype=torch.float64), scene.projectors[pid].K, W)
    return px.numpy()


# --------------------------------------------------------------------------- the official sample
@pytest.fixture(scope="module")
def sample():
    if not (SAMPLE / "cameras_sphere.npz").is_file():
        pytest.skip("ActiveNeuS sample not present")
    return read_activeneus(SAMPLE)


def test_sample_values_match_format_page(sample):
    s = sample
    assert len(s.frames) == 40 and list(s.projectors) == ["proj0"] and len(s.patterns) == 1
    cam = s.frame_camera(0)
    assert (cam.width, cam.height) == (800, 800)
    np.testing.assert_allclose(cam.K[:2, 2], [400.5, 400.5])
    # pixel (400, 400): its centre is (400.5, 400.5) in fastneus convention
    o, d = pixel_rays(cam.K, s.cam_to_world(0), torch.tensor([[400.5, 400.5]], dtype=torch.float64),
                      s.normalisation())
    np.testing.assert_allclose(o[0].numpy(), [0, 1.36863, 1.47965], atol=2e-5)
    np.testing.assert_allclose(d[0].numpy(), [0, -0.67903, -0.73411], atol=2e-5)
    # world origin in projector 0
    pj = s.projectors["proj0"]
    px, z = project_points(torch.zeros(1, 3, dtype=torch.float64), pj.K, s.world_to_proj(0, "proj0"))
    np.testing.assert_allclose(px[0].numpy(), [379.0161, 375.6885], atol=2e-4)
    assert abs(z.item() - 4.00113) < 1e-4
    col = sample_pattern(torch.from_numpy(s.pattern_image("p00")), px, z > 1e-6)
    np.testing.assert_allclose(col[0].numpy(), [0, 1, 1])  # BGR (1, 1, 0) read as RGB
    # projector centre radius (normalised). The FORMAT page lists 2.2567, but that value
    # contradicts its own depth / pixel rows: the origin at depth 4.00113 and pixel
    # (379.0161, 375.6885) through K_p lies |X_p| = 4.0466 m = 2.0233 normalised from the
    # projector centre. We check the self-consistent value.
    pc = (s.proj_to_world(0, "proj0")[:3, 3] - s.bounds.center) / s.bounds.radius
    ray = np.linalg.solve(pj.K, [379.0161, 375.6885, 1.0]) * 4.00113
    assert abs(np.linalg.norm(pc) - np.linalg.norm(ray) / 2) < 1e-4
    radii = [np.linalg.norm(s.cam_to_world(i)[:3, 3]) / s.bounds.radius for i in range(40)]
    np.testing.assert_allclose(radii, 2.015564, atol=1e-5)
    assert s.illumination.i_r == 0.4 and s.illumination.i_b == 0.1 and s.illumination.ambient == 1.0
    m = s.mask(0)
    assert m.dtype == np.float32 and 0 < m.mean() < 1
    assert len({f.view for f in s.frames}) == 40


# --------------------------------------------------------------------------- round trips
def test_roundtrip_fastneus_activeneus_fastneus(tmp_path):
    src = make_scene(tmp_path / "src")
    write_activeneus(src, tmp_path / "an")
    back = read_activeneus(tmp_path / "an")
    assert len(back.frames) == len(src.frames) and len(back.projectors) == len(src.projectors)
    np.testing.assert_allclose(back.normalisation(), src.normalisation(), atol=1e-12)
    rng = np.random.default_rng(1)
    for i in range(len(src.frames)):
        o1, d1 = _rays(src, i)
        o2, d2 = _rays(back, i)
        np.testing.assert_allclose(o2, o1, atol=1e-5)
        np.testing.assert_allclose(d2, d1, atol=1e-5)
        pts = rng.uniform(-1, 1, (200, 3))
        for k, (pa, pb) in enumerate(zip(src.projectors, back.projectors)):
            np.testing.assert_allclose(_proj_pixels(back, i, pb, pts), _proj_pixels(src, i, pa, pts), atol=1e-5)
            np.testing.assert_array_equal(back.pattern_image(back.frames[i].projectors[pb].pattern),
                                          src.pattern_image(f"q{k}"))
        np.testing.assert_array_equal(back.image(i), src.image(i))
        np.testing.assert_allclose(back.mask(i), src.mask(i), atol=1 / 255 / 2)
    il = back.illumination
    assert (il.i_r, il.i_b, il.ambient) == (0.3, 0.05, 1.0)
    # raw npz layout
    z = np.load(tmp_path / "an" / "cameras_sphere.npz", allow_pickle=True)
    assert z["proj_mat_0"].shape == (2, 4, 4) and z["cam_proj_pose_2"].shape == (2, 4, 4)
    np.testing.assert_allclose(z["cam_mat_0"][:2, 2], src.cameras["c"].K[:2, 2] - 0.5)
    assert z["illumination_params"].item() == {"ambient": 1.0, "diffuse": 0.3, "emissive": 0.05}
    assert sorted(p.name for p in (tmp_path / "an" / "pattern").iterdir())[:2] == ["000_00.png", "000_01.png"]


def test_sixteen_bit_photos_go_to_activeneus_as_their_linear_light(tmp_path):
    """The format's photos are linear 8-bit: 16-bit (linear) photos are written as their light at
    8 bits, which the format's reader (linear) reads back as the same light, to within one code
    (two roundings: the sRGB code Scene.image keeps, then the linear one)."""
    import json

    src = make_scene(tmp_path / "src")
    d = json.loads((src.root / "scene.json").read_text())
    d["response"] = "linear"
    (src.root / "scene.json").write_text(json.dumps(d))
    lin = {}
    for i, f in enumerate(d["frames"]):
        p = src.root / f["image"]
        lin[i] = cv2.imread(str(p))[:, :, ::-1].astype(np.float64) / 255.0  # the 8-bit photo's light
        cv2.imwrite(str(p), np.round(lin[i][:, :, ::-1] * 65535).astype(np.uint16))
    deep = Scene.load(src.root)
    assert deep.photo_bits == 16
    write_activeneus(deep, tmp_path / "an")
    back = read_activeneus(tmp_path / "an")
    for i in lin:
        err = np.abs(back.image(i) / 255.0 - lin[i])
        assert err.max() <= 1 / 255 + 1e-9 and err.mean() < 0.5 / 255


def test_srgb_photos_go_to_activeneus_as_their_linear_light(tmp_path):
    """An sRGB scene's photos are written as their light (the format's photos are linear)."""
    from fastneus.data.response import decode, encode_u8

    src = make_scene(tmp_path / "src", n=2)
    d = json.loads((src.root / "scene.json").read_text())
    d["response"] = "srgb"
    (src.root / "scene.json").write_text(json.dumps(d))
    srgb = Scene.load(src.root)
    write_activeneus(srgb, tmp_path / "an")
    back = read_activeneus(tmp_path / "an")
    for i in range(2):
        np.testing.assert_array_equal(back.image(i), encode_u8(decode(srgb.image(i) / 255.0, "srgb"), "linear"))


def test_writer_rejects_free_projectors(tmp_path):
    s = make_scene(tmp_path / "src", n=2, n_proj=1)
    for i, f in enumerate(s.frames):
        f.projectors["p0"].proj_to_world = s.proj_to_world(i, "p0")
    s.projectors["p0"].proj_to_cam = None
    with pytest.raises(FastneusError, match="rigidly attached") as e:
        write_activeneus(s, tmp_path / "an")
    assert "proj_to_cam" in str(e.value) and "\n" not in str(e.value)


def test_writer_downscale_keeps_rays(tmp_path):
    src = make_scene(tmp_path / "src", n=1, size=(24, 16))
    write_activeneus(src, tmp_path / "an", downscale=2)
    back = read_activeneus(tmp_path / "an")
    cam = back.frame_camera(0)
    assert (cam.width, cam.height) == (12, 8)
    # pixel (u, v) of the small image covers pixels 2u..2u+1 of the big one: same centre ray
    o, d = pixel_rays(cam.K, back.cam_to_world(0), torch.tensor([[3.5, 2.5]], dtype=torch.float64),
                      back.normalisation())
    o2, d2 = pixel_rays(src.frame_camera(0).K, src.cam_to_world(0), torch.tensor([[7.0, 5.0]], dtype=torch.float64),
                        src.normalisation())
    np.testing.assert_allclose(d.numpy(), d2.numpy(), atol=1e-9)


def test_convert_cli_roundtrip(tmp_path, capsys):
    src = make_scene(tmp_path / "src", n=2)
    assert main(["convert", str(tmp_path / "src"), "--to", "activeneus", "--out", str(tmp_path / "an")]) == 0
    assert main(["convert", str(tmp_path / "an"), "--to", "fastneus", "--out", str(tmp_path / "fn")]) == 0
    back = Scene.load(tmp_path / "fn")
    assert (tmp_path / "fn" / "image" / "000.png").is_file() and back.frames[1].mask == "mask/001.png"
    for i in range(2):
        np.testing.assert_allclose(_rays(back, i)[1], _rays(src, i)[1], atol=1e-5)
        np.testing.assert_array_equal(back.image(i), src.image(i))
    # fastneus -> fastneus copies every file and keeps the pattern sharing
    assert main(["convert", str(tmp_path / "src"), "--to", "fastneus", "--out", str(tmp_path / "fn2")]) == 0
    again = load_scene(tmp_path / "fn2")
    assert len(again.patterns) == 2 and again.frames[0].mask == "mask/000.png"
    # a bad input prints one line and exits 2
    assert main(["convert", str(tmp_path / "nowhere"), "--to", "fastneus", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "scene not found" in err


# --------------------------------------------------------------------------- malformed ActiveNeuS
def _an(tmp_path) -> Path:
    src = make_scene(tmp_path / "src", n=3, n_proj=2)
    write_activeneus(src, tmp_path / "an")
    return tmp_path / "an"


def _edit_npz(folder: Path, fn) -> None:
    p = folder / "cameras_sphere.npz"
    d = dict(np.load(p, allow_pickle=True))
    fn(d)
    np.savez(p, **d)


def _one_line(e, *words):
    msg = str(e.value)
    assert "\n" not in msg
    for w in words:
        assert w in msg, msg


def test_malformed_missing_key(tmp_path):
    an = _an(tmp_path)
    _edit_npz(an, lambda d: d.pop("cam_pose_1"))
    with pytest.raises(FastneusError) as e:
        read_activeneus(an)
    _one_line(e, "cameras_sphere.npz", "cam_pose_1", "missing")


def test_malformed_wrong_shape(tmp_path):
    an = _an(tmp_path)
    _edit_npz(an, lambda d: d.__setitem__("cam_mat_2", np.eye(3)))
    with pytest.raises(FastneusError) as e:
        read_activeneus(an)
    _one_line(e, "cameras_sphere.npz", "cam_mat_2", "shape")
    _edit_npz(an, lambda d: (d.__setitem__("cam_mat_2", np.eye(4)), d.__setitem__("proj_mat_1", np.eye(4))))
    with pytest.raises(FastneusError) as e:
        read_activeneus(an)
    _one_line(e, "proj_mat_1", "shape")


def test_malformed_non_finite(tmp_path):
    an = _an(tmp_path)

    def bad(d):
        d["cam_proj_pose_0"] = d["cam_proj_pose_0"].copy()
        d["cam_proj_pose_0"][1, 0, 3] = np.nan
    _edit_npz(an, bad)
    with pytest.raises(FastneusError) as e:
        read_activeneus(an)
    _one_line(e, "cameras_sphere.npz", "cam_proj_pose_0", "non-finite")


def test_malformed_inconsistent_pattern_counts(tmp_path):
    an = _an(tmp_path)
    (an / "pattern" / "001_01.png").unlink()
    with pytest.raises(FastneusError) as e:
        read_activeneus(an)
    _one_line(e, "pattern", "001", "pattern counts")


def test_malformed_missing_pattern_files(tmp_path):
    an = _an(tmp_path)
    for p in (an / "pattern").glob("002_*.png"):
        p.unlink()
    with pytest.raises(FastneusError) as e:
        read_activeneus(an)
    _one_line(e, "002_00.png", "proj_mat_2", "missing pattern")
    shutil.rmtree(an / "pattern")
    with pytest.raises(FastneusError) as e:
        read_activeneus(an)
    _one_line(e, "pattern", "proj_mat_0", "missing pattern")


def test_malformed_missing_images_and_bad_pose(tmp_path):
    an = _an(tmp_path)
    _edit_npz(an, lambda d: d.__setitem__("cam_pose_0", np.diag([1.0, 1.0, 2.0, 1.0])))
    with pytest.raises(FastneusError) as e:
        read_activeneus(an)
    _one_line(e, "cam_pose_0", "orthonormal")
    shutil.rmtree(an / "image")
    with pytest.raises(FastneusError) as e:
        read_activeneus(an)
    _one_line(e, "image", "no images")


def test_per_frame_patterns_kept(tmp_path):
    an = _an(tmp_path)
    cv2.imwrite(str(an / "pattern" / "001_00.png"), np.full((24, 32, 3), 7, np.uint8))
    s = read_activeneus(an)
    pats = [s.frames[i].projectors["proj0"].pattern for i in range(3)]
    assert len(set(pats)) == 3 and s.pattern_image(pats[1])[0, 0, 0] == 7


# --------------------------------------------------------------------------- OpenCV calibration
def _write_fs(path: Path, items: dict) -> None:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for k, v in items.items():
        fs.write(k, v)
    fs.release()


@pytest.fixture
def rig():
    rng = np.random.default_rng(3)
    Kc = np.array([[1200.0, 0, 639.5], [0, 1190.0, 479.5], [0, 0, 1]])
    Kp = np.array([[1500.0, 0, 511.5], [0, 1500.0, 383.5], [0, 0, 1]])
    R = _rot(rng, 15)
    T = np.array([[-210.0], [15.0], [30.0]])  # mm
    dc = np.array([[0.1, -0.05, 0.001, -0.002, 0.01]])
    return Kc, Kp, R, T, dc


@pytest.mark.parametrize("layout", ["moreno-taubin", "opencv-stereo", "kamino410"])
@pytest.mark.parametrize("ext", ["yml", "xml"])
def test_calibration_layouts_give_same_rig(tmp_path, rig, layout, ext):
    from fastneus.formats.opencv_calib import read_procam_calibration

    Kc, Kp, R, T, dc = rig
    dp = np.zeros((1, 5))
    if layout == "moreno-taubin":
        items = {"cam_K": Kc, "cam_kc": dc, "proj_K": Kp, "proj_kc": dp, "R": R, "T": T,
                 "cam_width": 1280, "cam_height": 960, "proj_width": 1024, "proj_height": 768}
    elif layout == "opencv-stereo":
        items = {"M1": Kc, "D1": dc, "M2": Kp, "D2": dp, "R": R, "T": T}
    else:
        items = {"img_shape": np.array([[960.0], [1280.0]]), "rms": 0.4, "cam_int": Kc, "cam_dist": dc,
                 "proj_int": Kp, "proj_dist": dp, "roration": R, "translation": T}
    f = tmp_path / f"calib.{ext}"
    _write_fs(f, items)
    cam, proj = read_procam_calibration(f, proj_size="1024x768", units="mm", cam_size=(1280, 960))
    assert (cam.width, cam.height, proj.width, proj.height) == (1280, 960, 1024, 768)
    np.testing.assert_allclose(cam.K[:2, 2], [640.0, 480.0])
    np.testing.assert_allclose(proj.K[:2, 2], [512.0, 384.0])
    np.testing.assert_allclose(cam.dist, dc[0])
    cam_to_proj = rigid_inverse(proj.proj_to_cam)
    np.testing.assert_allclose(cam_to_proj[:3, :3], R, atol=1e-12)
    np.testing.assert_allclose(cam_to_proj[:3, 3], T[:, 0] / 1000, atol=1e-12)
    # a camera point lands where OpenCV says it does in the projector
    X = np.array([[0.05, -0.02, 0.9]])
    ref = cv2.projectPoints(X * 1000, cv2.Rodrigues(R)[0], T, Kp, None)[0][0, 0]
    px, _ = project_points(torch.tensor(X), proj.K, rigid_inverse(proj.proj_to_cam))
    np.testing.assert_allclose(px[0].numpy(), ref + 0.5, atol=1e-9)


def test_calibration_errors(tmp_path, rig):
    from fastneus.formats.opencv_calib import read_procam_calibration

    Kc, Kp, R, T, dc = rig
    f = tmp_path / "c.yml"
    _write_fs(f, {"M1": Kc, "D1": dc, "M2": Kp, "D2": dc, "R": R})
    with pytest.raises(FastneusError) as e:
        read_procam_calibration(f, proj_size=(1024, 768), cam_size=(1280, 960))
    _one_line(e, "c.yml", "T", "missing")
    _write_fs(f, {"M1": Kc, "D1": dc, "M2": Kp, "D2": dc, "R": R, "T": T})
    with pytest.raises(FastneusError) as e:
        read_procam_calibration(f, cam_size=(1280, 960))
    _one_line(e, "c.yml", "proj-size")
    _write_fs(f, {"M1": Kc, "D1": dc, "M2": Kp, "D2": dc, "R": R * 2, "T": T})
    with pytest.raises(FastneusError) as e:
        read_procam_calibration(f, proj_size=(1024, 768), cam_size=(1280, 960))
    _one_line(e, "c.yml", "R", "orthonormal")
    _write_fs(f, {"M1": Kc[:2], "D1": dc, "M2": Kp, "D2": dc, "R": R, "T": T})
    with pytest.raises(FastneusError) as e:
        read_procam_calibration(f, proj_size=(1024, 768), cam_size=(1280, 960))
    _one_line(e, "c.yml", "M1", "shape")


def test_import_calib_with_colmap(tmp_path, rig, capsys):
    Kc, Kp, R, T, dc = rig
    _write_fs(tmp_path / "calib.yml", {"cam_K": Kc, "cam_kc": dc, "proj_K": Kp, "proj_kc": np.zeros((1, 5)),
                                       "R": R, "T": T})
    (tmp_path / "imgs").mkdir()
    (tmp_path / "pats").mkdir()
    rng = np.random.default_rng(0)
    poses = []
    lines = ["# Image list", ""]
    for i in range(2):
        cv2.imwrite(str(tmp_path / f"imgs/{i:03d}.png"), np.zeros((960, 1280, 3), np.uint8))
        cv2.imwrite(str(tmp_path / f"pats/{i:03d}.png"), np.zeros((768, 1024, 3), np.uint8))
        c2w = look_at(rng.normal(size=3) * 0.1 + [0, 0, -1.5], [0, 0, 0], up=(0, -1, 0))
        poses.append(c2w)
        w2c = rigid_inverse(c2w)
        from scipy.spatial.transform import Rotation
        x, y, z, w = Rotation.from_matrix(w2c[:3, :3]).as_quat()
        lines += [f"{i + 1} {w} {x} {y} {z} {w2c[0, 3]} {w2c[1, 3]} {w2c[2, 3]} 1 {i:03d}.png", ""]
    (tmp_path / "model").mkdir()
    (tmp_path / "model" / "images.txt").write_text("\n".join(lines) + "\n")
    (tmp_path / "model" / "cameras.txt").write_text("1 PINHOLE 1280 960 1200 1190 640 480\n")
    rc = main(["import-calib", str(tmp_path / "calib.yml"), "--images", str(tmp_path / "imgs"), "--patterns",
               str(tmp_path / "pats"), "--colmap", str(tmp_path / "model"), "--proj-size", "1024x768",
               "--out", str(tmp_path / "scene")])
    assert rc == 0, capsys.readouterr().err
    s = Scene.load(tmp_path / "scene")
    for i in range(2):
        np.testing.assert_allclose(s.cam_to_world(i), poses[i], atol=1e-9)
    np.testing.assert_allclose(s.projectors["proj0"].proj_to_cam[:3, 3], -R.T @ T[:, 0] / 1000, atol=1e-12)
    np.testing.assert_allclose(s.bounds.center, 0, atol=0.2)
    # poses from the scene.json just written give the same scene
    rc = main(["import-calib", str(tmp_path / "calib.yml"), "--images", str(tmp_path / "imgs"), "--patterns",
               str(tmp_path / "pats" / "000.png"), "--poses", str(tmp_path / "scene" / "scene.json"),
               "--out", str(tmp_path / "scene2")])  # projector size from the pattern image
    assert rc == 0
    s2 = Scene.load(tmp_path / "scene2")
    assert len(s2.patterns) == 1
    np.testing.assert_allclose(s2.cam_to_world(1), s.cam_to_world(1))


# --------------------------------------------------------------------------- NeuS
def test_neus_reader(tmp_path):
    from fastneus.formats.neus import read_neus

    root = tmp_path / "dtu"
    (root / "image").mkdir(parents=True)
    (root / "mask").mkdir()
    K = np.array([[50.0, 0.2, 15.0], [0, 52.0, 11.0], [0, 0, 1]])
    S = np.diag([0.7, 0.7, 0.7, 1.0])
    S[:3, 3] = [0.1, 0.2, -0.3]
    rng = np.random.default_rng(5)
    d, c2ws = {}, []
    for i in range(2):
        c2w = look_at(rng.normal(size=3) + [0, 0, 3], [0.1, 0.2, -0.3])
        c2ws.append(c2w)
        P = np.eye(4)
        P[:3, :4] = 2.5 * K @ rigid_inverse(c2w)[:3, :4]  # arbitrary projective scale
        d[f"world_mat_{i}"] = P
        d[f"scale_mat_{i}"] = S
        cv2.imwrite(str(root / f"image/{i:06d}.png"), np.zeros((20, 30, 3), np.uint8))
        cv2.imwrite(str(root / f"mask/{i:03d}.png"), np.full((20, 30, 3), 255, np.uint8))
    np.savez(root / "cameras_sphere.npz", **d)
    s = load_scene(root)
    assert not s.projectors and len(s.frames) == 2 and s.mask(0).min() == 1.0
    Kx = K.copy()
    Kx[:2, 2] += 0.5
    np.testing.assert_allclose(s.cameras[s.frames[0].camera].K, Kx, atol=1e-9)
    for i in range(2):
        np.testing.assert_allclose(s.cam_to_world(i), c2ws[i], atol=1e-9)
    np.testing.assert_allclose(s.bounds.center, [0.1, 0.2, -0.3])
    assert s.bounds.radius == pytest.approx(0.7)
    d.pop("world_mat_1")
    np.savez(root / "cameras_sphere.npz", world_mat_0=d["world_mat_0"], scale_mat_0=S)
    with pytest.raises(FastneusError) as e:
        load_scene(root)
    _one_line(e, "world_mat_1", "missing")
