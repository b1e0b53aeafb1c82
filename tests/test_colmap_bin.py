"""COLMAP binary models (cameras.bin, images.bin, points3D.bin) read like the text ones.

The binary files are written here with ``struct`` from COLMAP's documented layout
(``tests/fuzz_strategies.colmap_binary``), independently of the reader; the same model is
written as text, and both must load to exactly the same cameras, poses and points. Damaged
binaries (every truncation, odd counts, unknown model ids, names without a terminator,
trailing bytes) give one FastneusError line naming the file and the field.
"""
from __future__ import annotations

import json
import shutil
import struct

import numpy as np
import pytest

import fuzz_strategies as fz
from fastneus.errors import FastneusError
from fastneus.formats.colmap import model_files, read_colmap_model

CAMERAS = [(1, "PINHOLE", 640, 480, [500.25, 501.5, 320.0, 240.125]),
           (7, "OPENCV", 800, 600, [700.0, 710.0, 400.5, 300.5, -0.1, 0.01, 1e-4, -2e-4]),
           (3, "SIMPLE_RADIAL", 1024, 768, [900.0, 512.0, 384.0, 0.02]),
           (9, "RAD_TAN_THIN_PRISM_FISHEYE", 64, 48, [30.0, 31.0, 32.0, 24.0] + [0.001 * k for k in range(12)])]
IMAGES = [(5, (0.9, 0.1, -0.3, 0.2), (0.5, -1.25, 3.0), 1, "000.png", [(1.5, 2.5, -1), (10.0, 20.0, 2)]),
          (2, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 7, "sub dir/001.png", []),
          (11, (-0.2, 0.7, 0.1, 0.6), (1e-3, 2.0, -0.75), 9, "é-002.jpg", [(0.0, 0.0, 1)])]
POINTS = [(1, (0.1, 0.2, 0.3), (255, 0, 10), 0.5, [(5, 0), (11, 0)]),
          (2, (-1.5, 0.25, 4.0), (1, 2, 3), 1.25, [(5, 1)]),
          (40, (3.0, -2.0, 1.0), (0, 0, 0), 0.0, [])]


def _write_text(folder, cameras=CAMERAS, images=IMAGES, points=POINTS) -> None:
    """The same model as COLMAP text (repr floats: exact)."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "cameras.txt").write_text("# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n" + "".join(
        f"{cid} {m} {w} {h} {' '.join(map(repr, p))}\n" for cid, m, w, h, p in cameras))
    lines = []
    for iid, q, t, cid, name, p2 in images:
        lines.append(" ".join(map(repr, (iid, *q, *t, cid))) + " " + name)
        lines.append(" ".join(f"{x!r} {y!r} {pid}" for x, y, pid in p2))
    (folder / "images.txt").write_text("\n".join(lines) + "\n")
    (folder / "points3D.txt").write_text("".join(
        f"{pid} {' '.join(map(repr, xyz))} {' '.join(map(str, rgb))} {err!r} "
        f"{' '.join(f'{a} {b}' for a, b in tr)}\n" for pid, xyz, rgb, err, tr in points))


def _write_bin(folder, cameras=CAMERAS, images=IMAGES, points=POINTS) -> dict:
    folder.mkdir(parents=True, exist_ok=True)
    files, fields = fz.colmap_binary(cameras, images, points)
    for n, data in files.items():
        (folder / n).write_bytes(data)
    return fields


def _error(folder) -> FastneusError:
    with pytest.raises(FastneusError) as e:
        read_colmap_model(folder)
    msg = str(e.value)
    assert "\n" not in msg and e.value.file is not None
    return e.value


def test_binary_model_equals_text_model(tmp_path):
    """The same model in text and in binary loads to identical cameras, poses and points."""
    _write_text(tmp_path / "txt")
    _write_bin(tmp_path / "bin")
    cams_t, ims_t, pts_t = read_colmap_model(tmp_path / "txt")
    cams_b, ims_b, pts_b = read_colmap_model(tmp_path / "bin")
    assert sorted(cams_t) == sorted(cams_b) == sorted(c[0] for c in CAMERAS)
    for cid, ct in cams_t.items():
        cb = cams_b[cid]
        assert (cb.id, cb.model, cb.width, cb.height) == (ct.id, ct.model, ct.width, ct.height)
        assert cb.params.dtype == np.float64 and np.array_equal(cb.params, ct.params)
    assert sorted(ims_t) == sorted(ims_b) == sorted(i[4] for i in IMAGES)
    for name, it in ims_t.items():
        ib = ims_b[name]
        assert (ib.id, ib.camera_id) == (it.id, it.camera_id)
        assert np.array_equal(ib.world_to_cam, it.world_to_cam), name
        assert np.allclose(ib.world_to_cam[:3, :3] @ ib.world_to_cam[:3, :3].T, np.eye(3))
    assert pts_b is not None and np.array_equal(pts_b, pts_t)
    assert np.array_equal(pts_b, np.array([p[1] for p in POINTS]))


def test_binary_model_values(tmp_path):
    """Spot values straight from the layout: model names from ids, translation as written."""
    _write_bin(tmp_path)
    cams, ims, _ = read_colmap_model(tmp_path)
    assert cams[9].model == "RAD_TAN_THIN_PRISM_FISHEYE" and cams[9].params.shape == (16,)
    assert cams[7].model == "OPENCV" and cams[7].params[4] == -0.1
    assert np.array_equal(ims["000.png"].world_to_cam[:3, 3], [0.5, -1.25, 3.0])
    assert np.allclose(ims["sub dir/001.png"].world_to_cam, np.eye(4))


def test_sparse_0_and_text_first(tmp_path):
    """A COLMAP project folder's sparse/0 is found; text is read where both kinds are present."""
    _write_bin(tmp_path / "proj" / "sparse" / "0")
    f = model_files(tmp_path / "proj")
    assert f.binary and f.images == tmp_path / "proj" / "sparse" / "0" / "images.bin"
    assert len(read_colmap_model(tmp_path / "proj")[1]) == 3
    _write_text(tmp_path / "both", images=IMAGES[:1])
    _write_bin(tmp_path / "both")
    assert not model_files(tmp_path / "both").binary and list(read_colmap_model(tmp_path / "both")[1]) == ["000.png"]
    (tmp_path / "empty").mkdir()
    e = _error(tmp_path / "empty")
    assert "cameras.bin" in str(e) and "images.txt" in str(e)


def test_points3d_bin_is_optional(tmp_path):
    _write_bin(tmp_path)
    (tmp_path / "points3D.bin").unlink()
    assert read_colmap_model(tmp_path)[2] is None


@pytest.mark.parametrize("name", ["cameras.bin", "images.bin", "points3D.bin"])
def test_every_truncation_is_one_line(tmp_path, name):
    """Each prefix of each file is refused with one line naming that file (never another exception)."""
    _write_bin(tmp_path / "good")
    data = (tmp_path / "good" / name).read_bytes()
    d = tmp_path / "cut"
    shutil.copytree(tmp_path / "good", d)
    for n in range(len(data)):
        (d / name).write_bytes(data[:n])
        e = _error(d)
        assert e.file == str(d / name), (n, str(e))


def _patch(fields, name, label, k=0):
    """(offset, format) of the k-th field called ``label`` in file ``name``."""
    return [(o, f) for o, f, lab in fields[name] if lab == label][k]


@pytest.mark.parametrize("name, label, value, needle", [
    ("cameras.bin", "num_cameras", 2 ** 63, "claims 9223372036854775808 entries"),
    ("cameras.bin", "num_cameras", 3, "bytes after the 3 cameras"),
    ("cameras.bin", "num_cameras", 5, "file ends at byte 360"),
    ("cameras.bin", "num_cameras", 8, "claims 8 entries"),
    ("cameras.bin", "model_id", 12, "unknown camera model id 12"),
    ("cameras.bin", "model_id", -1, "unknown camera model id -1"),
    ("images.bin", "num_reg_images", 2 ** 64 - 1, "claims 18446744073709551615 entries"),
    ("images.bin", "num_reg_images", 2, "bytes after the 2 images"),
    ("images.bin", "num_points2D", 2 ** 61, "claims 2305843009213693952 entries"),
    ("points3D.bin", "num_points", 10 ** 12, "claims 1000000000000 entries"),
    ("points3D.bin", "track_length", 2 ** 62, "track of 4611686018427387904 entries"),
    ("images.bin", "qvec", float("nan"), "bad pose"),
    ("images.bin", "tvec", float("inf"), "bad pose"),
    ("points3D.bin", "xyz", float("-inf"), "non-finite position"),
])
def test_corrupt_field_is_one_line(tmp_path, name, label, value, needle):
    """A count, id or value overwritten: one line naming the file, what is wrong and where."""
    fields = _write_bin(tmp_path)
    data = bytearray((tmp_path / name).read_bytes())
    off, fmt = _patch(fields, name, label)
    struct.pack_into("<" + fmt[0], data, off, value)
    (tmp_path / name).write_bytes(bytes(data))
    e = _error(tmp_path)
    assert e.file == str(tmp_path / name) and needle in str(e), str(e)
    assert e.field, str(e)


def test_name_damage(tmp_path):
    """A name with no NUL before the file ends, a non-UTF-8 name, and trailing bytes."""
    fields = _write_bin(tmp_path, images=IMAGES[:1])
    data = (tmp_path / "images.bin").read_bytes()
    off = _patch(fields, "images.bin", "name")[0]
    (tmp_path / "images.bin").write_bytes(data[:off] + b"x" * 5000)
    assert "no NUL-terminated name" in str(_error(tmp_path))
    (tmp_path / "images.bin").write_bytes(data[:off] + b"\xff\xfe.png" + data[off + len("000.png"):])
    assert "is not UTF-8" in str(_error(tmp_path))
    (tmp_path / "images.bin").write_bytes(data + b"\0")
    e = _error(tmp_path)
    assert "1 bytes after the 1 images" in str(e) and e.field == "end of file"


def test_duplicates_refused(tmp_path):
    _write_bin(tmp_path / "cams", cameras=CAMERAS + CAMERAS[:1])
    assert "duplicate camera id 1" in str(_error(tmp_path / "cams"))
    dup = (99,) + IMAGES[0][1:]
    _write_bin(tmp_path / "ims", images=IMAGES + [dup])
    e = _error(tmp_path / "ims")
    assert "duplicate image '000.png'" in str(e) and e.field == "000.png"


def test_import_calib_from_binary_equals_text(small_scene, tmp_path):
    """import-calib --colmap builds the same scene.json from the binary model as from the text one."""
    from fastneus.formats.opencv_calib import make_scene_from_calibration

    b = fz.build_bases(tmp_path / "bases", small_scene)
    images = sorted(b["images"].iterdir())
    out = {}
    for kind in ("colmap", "colmap_bin"):
        make_scene_from_calibration(b["calib"], images, [b["pattern"]], b[kind], tmp_path / kind, units="m")
        out[kind] = json.loads((tmp_path / kind / "scene.json").read_text())
    # the text model prints floats with str(): equal to the binary doubles to ~1e-15
    ft, fb = out["colmap"]["frames"], out["colmap_bin"]["frames"]
    assert len(ft) == len(fb) == len(images)
    for a, c in zip(ft, fb):
        assert np.allclose(a["cam_to_world"], c["cam_to_world"], rtol=0, atol=1e-12)
    assert out["colmap"]["cameras"] == out["colmap_bin"]["cameras"]
