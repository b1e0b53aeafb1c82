"""Scene formats register in one place (fastneus/formats/registry.py): a toy format registered from
this file is detected and read by ``load_scene`` like the built-in ones, and is gone once unregistered."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from fastneus.data import Scene, look_at
from fastneus.errors import FastneusError
from fastneus.formats.detect import detect_format, load_scene
from fastneus.formats.registry import (SceneFormat, formats, get_format, register_format, registered,
                                       unregister_format, writable)


def read_toy(path) -> Scene:
    """The toy format: ``toy.json`` = {"photo": file, "focal": px, "distance": m}; one camera looking
    at the origin from ``distance`` along +z, the unit sphere as bounds."""
    data = json.loads((path / "toy.json").read_text())
    h, w = cv2.imread(str(path / data["photo"])).shape[:2]
    f = float(data["focal"])
    return Scene.from_dict({
        "format": "fastneus-scene", "version": 1, "name": "toy",
        "bounds": {"center": [0, 0, 0], "radius": 1.0},
        "cameras": {"cam": {"K": [[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]], "width": w, "height": h}},
        "frames": [{"image": data["photo"], "camera": "cam",
                    "cam_to_world": look_at([0, 0, float(data["distance"])], [0, 0, 0]).tolist()}],
    }, path, file=path / "toy.json")


TOY = SceneFormat("toy", "a folder with toy.json (test only)", lambda p: (p / "toy.json").is_file(),
                  reader=f"{__name__}:read_toy")


@pytest.fixture
def toy_folder(tmp_path):
    cv2.imwrite(str(tmp_path / "photo.png"), np.full((12, 16, 3), 128, np.uint8))
    (tmp_path / "toy.json").write_text(json.dumps({"photo": "photo.png", "focal": 20, "distance": 3}))
    return tmp_path


def test_builtin_formats_in_detection_order():
    assert [f.name for f in formats()] == ["fastneus", "nerf", "activeneus", "neus"]
    assert writable() == ("fastneus", "nerf", "activeneus")
    assert get_format("neus").writer is None and get_format("activeneus").writer_options == ("downscale",)


def test_a_toy_format_registered_from_a_test_loads_through_load_scene(toy_folder):
    with pytest.raises(FastneusError, match="not a scene folder"):
        load_scene(toy_folder)
    register_format(TOY)
    try:
        assert detect_format(toy_folder) == "toy"
        s = load_scene(toy_folder)
        assert len(s) == 1 and s.cameras["cam"].width == 16 and s.image(0).shape == (12, 16, 3)
        assert "toy" not in writable()  # read only: not a convert --to target
        with pytest.raises(FastneusError, match="read only"):
            get_format("toy").write(s, toy_folder / "out")
        with pytest.raises(ValueError, match="already registered"):
            register_format(TOY)
    finally:
        unregister_format("toy")
    assert "toy" not in [f.name for f in formats()]
    with pytest.raises(FastneusError, match="not a scene folder"):
        load_scene(toy_folder)


def test_registered_context_manager_removes_the_format(toy_folder):
    with registered(TOY):
        assert load_scene(toy_folder).name == "toy"
    with pytest.raises(FastneusError, match="unknown scene format 'toy'"):
        get_format("toy")


def test_reader_and_writer_are_module_function_strings():
    with pytest.raises(ValueError, match="module:function"):
        register_format(SceneFormat("bad", "no colon", lambda p: False, reader="read_toy"))
    assert "bad" not in [f.name for f in formats()]
