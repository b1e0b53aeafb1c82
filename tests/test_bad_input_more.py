"""More bad input (issue 20 items 5, 6, 9, 10): inputs that hung, ended as an "internal error",
or were accepted and silently trained something wrong.

One table of crafted inputs (built from the corpus's valid bases in ``tests/test_bad_input_corpus.py``)
run through the CLI in-process: each must exit 2 with exactly one line on stderr naming the file
and/or field at fault, and leave the output folder as it was. A few behaviours that are not a
refusal (EXIF orientation, JSON without NaN, a full disk) have their own tests below.
"""
from __future__ import annotations

import errno
import json
import shutil
import struct
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import pytest
import torch

from fastneus.cli import main
from test_bad_input_corpus import Ctx, _calib, _colmap, _snapshot, bases  # noqa: F401 - bases is a fixture

CASES: dict[str, Callable] = {}


def case(name: str):
    def reg(fn):
        assert name not in CASES
        CASES[name] = fn
        return fn
    return reg


def _yaml(c, text: str, name: str = "my.yaml") -> str:
    p = c.tmp / name
    p.write_text(text)
    return str(p)


def _ckpt(c, edit: Callable[[dict], None]) -> Path:
    """A copy of the base run whose checkpoint is edited by ``edit``."""
    run = c.run()
    st = torch.load(run / "checkpoint.pt", weights_only=True)
    edit(st)
    torch.save(st, run / "checkpoint.pt")
    return run


# --------------------------------------------------------------------------- item 5: unpickler work bound
@case("an-illumination-shared-references")
def _(c):
    leaf = [1.0]
    for _ in range(6):  # ~1 KB of pickle, 64^6 leaves when walked naively
        leaf = [leaf] * 64
    ip = np.array({"ambient": leaf, "diffuse": 0.4, "emissive": 0.1}, dtype=object)
    return c.train(c.npz("an", illumination_params=ip)) + (["cameras_sphere.npz", "illumination_params", "refused"],)


# --------------------------------------------------------------------------- item 6: EXIF orientation
def _jpeg_with_orientation(bgr: np.ndarray, orientation: int, big_endian: bool = False) -> bytes:
    """A JPEG whose APP1 Exif block holds only IFD0 with the Orientation tag (as a phone writes)."""
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 100])
    assert ok
    e = ">" if big_endian else "<"
    tiff = (b"MM" if big_endian else b"II") + struct.pack(e + "HI", 42, 8)
    ifd = struct.pack(e + "H", 1) + struct.pack(e + "HHIHH", 0x0112, 3, 1, orientation, 0) + struct.pack(e + "I", 0)
    payload = b"Exif\x00\x00" + tiff + ifd
    data = buf.tobytes()
    return data[:2] + b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload + data[2:]


def test_exif_orientation_is_ignored_with_a_warning(small_scene, tmp_path, capsys):
    """A photo tagged "rotate 90" is read as stored (as the size check, the masks and the intrinsics
    see it), and one warning line names the file."""
    from fastneus.data import Scene
    from fastneus.data.scene import exif_orientation

    d = tmp_path / "s"
    shutil.copytree(small_scene, d)
    bgr = np.zeros((24, 24, 3), np.uint8)
    bgr[:, :12] = (0, 0, 255)  # left half red, right half blue: a rotation moves them
    bgr[:, 12:] = (255, 0, 0)
    (d / "images" / "000.jpg").write_bytes(_jpeg_with_orientation(bgr, 6))
    (d / "images" / "001.jpg").write_bytes(_jpeg_with_orientation(bgr, 1, big_endian=True))
    data = json.loads((d / "scene.json").read_text())
    data["frames"][0]["image"] = "images/000.jpg"
    data["frames"][1]["image"] = "images/001.jpg"
    (d / "scene.json").write_text(json.dumps(data))
    capsys.readouterr()
    scene = Scene.load(d)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "000.jpg" in err[0] and "orientation 6" in err[0], err
    stored = cv2.imread(str(d / "images" / "000.jpg"), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)[:, :, ::-1]
    np.testing.assert_array_equal(scene.image(0), stored)
    assert scene.image(0)[12, 2, 0] > 200 and scene.image(0)[12, 21, 2] > 200  # red left, blue right
    assert exif_orientation(d / "images" / "001.jpg") == 1
    assert exif_orientation(d / "images" / "002.png") is None
    assert exif_orientation(d / "scene.json") is None
    Scene.load(d)  # warned once per file
    assert capsys.readouterr().err == ""


# --------------------------------------------------------------------------- the runner
@pytest.mark.parametrize("name", sorted(CASES))
def test_bad_input(name, bases, tmp_path, capsys):  # noqa: F811 - bases is the imported fixture
    c = Ctx(bases, tmp_path)
    argv, guard, needles = CASES[name](c)
    before = _snapshot(guard)
    try:
        rc = main(argv)
    except SystemExit as e:  # argparse usage errors
        rc = e.code
    err = capsys.readouterr().err.strip()
    assert rc == 2, f"{name}: exit {rc}:\n{err}"
    assert len(err.splitlines()) == 1, f"{name}: not one line:\n{err}"
    assert "Traceback" not in err and "internal error" not in err, err
    for n in needles:
        assert n in err, f"{name}: {n!r} not named in: {err}"
    assert _snapshot(guard) == before, f"{name}: the earlier result in {guard} changed"
    assert not [p for p in tmp_path.rglob(".*staging-*")], "staging folder left behind"
