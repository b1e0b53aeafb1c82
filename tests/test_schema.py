"""fastneus/data/scene.schema.json agrees with the scene loader (docs/FORMAT.md).

(a) Every scene.json that fastneus writes validates: ``fastneus synth`` with every pattern kind,
    laser-plane projectors, water ports, projector blur, a Dark scene; the conftest scene; scenes
    converted through ActiveNeuS and NeRF and back; a free-projector variant.
(b) Invalid mutations (a missing required key, a wrong type, a non-positive size, ...) are
    rejected by both the schema and ``Scene.from_dict``.
(c) What only the loader can check (cross-references, rigidity, files) is listed, so that
    docs/FORMAT.md's list of loader-only checks stays true.
"""
from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest

jsonschema = pytest.importorskip("jsonschema")

from fastneus.data.scene import Scene  # noqa: E402
from fastneus.errors import FastneusError  # noqa: E402

SCHEMA_PATH = Path(__file__).resolve().parents[1] / "fastneus" / "data" / "scene.schema.json"


@pytest.fixture(scope="module")
def validator():
    schema = json.loads(SCHEMA_PATH.read_text())
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema)


def _errors(validator, data) -> list[str]:
    return [f"{'/'.join(map(str, e.absolute_path)) or '<root>'}: {e.message[:160]}" for e in validator.iter_errors(data)]


def test_schema_ships_as_package_data():
    """The installed package carries the schema (pyproject: package-data "fastneus.data" = ["*.json"])."""
    from importlib.resources import files

    text = files("fastneus.data").joinpath("scene.schema.json").read_text()
    assert json.loads(text)["$schema"].endswith("2020-12/schema")


# --------------------------------------------------------------------------- (a) what fastneus writes
SYNTH = {
    "crosslaser": ["--pattern", "crosslaser"],
    "graycode": ["--pattern", "graycode"],
    "phaseshift": ["--pattern", "phaseshift"],
    "grid": ["--pattern", "grid"],
    "colorline-dark-blur": ["--pattern", "colorline", "--illum", "dark", "--projector-blur", "1.0"],
    "dots": ["--pattern", "dots"],
    "laser-planes": ["--pattern", "crosslaser", "--laser-planes"],
    "water": ["--pattern", "crosslaser", "--medium", "water"],
}


@pytest.fixture(scope="module")
def synth_scenes(tmp_path_factory):
    """Tiny scenes written by the ``fastneus synth`` verb, one per projector / pattern kind."""
    from fastneus.cli import main

    root = tmp_path_factory.mktemp("schema-synth")
    out = {}
    for name, extra in SYNTH.items():
        folder = root / name
        rc = main(["synth", "--shape", "sphere", "--views", "2", "--size", "16x16", "--proj-size", "32x24",
                   "--device", "cpu", "--no-contact-sheet", "--out", str(folder), *extra])
        assert rc == 0, name
        out[name] = folder
    return out


def _load_json(folder: Path) -> dict:
    return json.loads((Path(folder) / "scene.json").read_text())


@pytest.mark.parametrize("name", list(SYNTH))
def test_synth_scenes_validate(validator, synth_scenes, name):
    data = _load_json(synth_scenes[name])
    assert _errors(validator, data) == []
    kinds = {p.get("kind", "pattern") for p in data.get("projectors", {}).values()}
    assert kinds == ({"laser"} if name == "laser-planes" else {"pattern"})
    if name == "water":
        assert all(c.get("port") for c in data["cameras"].values())


def test_conftest_scene_validates(validator, small_scene):
    assert _errors(validator, _load_json(small_scene)) == []


@pytest.mark.parametrize("via", ["activeneus", "nerf"])
def test_converted_scenes_validate(validator, synth_scenes, tmp_path, via):
    """A scene taken through another format and back to fastneus (``fastneus convert``) validates."""
    from fastneus.cli import main

    mid, back = tmp_path / via, tmp_path / "back"
    assert main(["convert", str(synth_scenes["crosslaser"]), "--to", via, "--out", str(mid)]) == 0
    assert main(["convert", str(mid), "--to", "fastneus", "--out", str(back)]) == 0
    assert _errors(validator, _load_json(back)) == []


def test_saved_variants_validate(validator, synth_scenes, tmp_path):
    """Scene.save of edited scenes: free projectors (per-frame proj_to_world), distortion, no GT mesh."""
    import numpy as np

    s = Scene.load(synth_scenes["crosslaser"])
    for pid, pj in s.projectors.items():
        for i, f in enumerate(s.frames):
            if pid in f.projectors:
                f.projectors[pid].proj_to_world = s.frames[i].cam_to_world @ pj.proj_to_cam
        pj.proj_to_cam = None
    s.cameras["cam0"].dist = np.array([0.01, -0.002, 0.0, 0.0, 0.0])
    s.gt_mesh = None
    s.sensor_bits = 12  # (a field for 16-bit photos; the loader checks that against the files)
    s.save(tmp_path)
    data = _load_json(tmp_path)
    assert all(p["proj_to_cam"] is None for p in data["projectors"].values())
    assert _errors(validator, data) == []
    Scene.from_dict(data, synth_scenes["crosslaser"], check_files=False)  # the loader agrees


def test_minimal_example_of_format_doc(validator):
    """The minimal example in docs/FORMAT.md is valid for the schema and the loader (files aside)."""
    doc = (Path(__file__).resolve().parents[1] / "docs" / "FORMAT.md").read_text()
    start = doc.index("```json\n", doc.index("## A minimal complete example")) + len("```json\n")
    data = json.loads(doc[start:doc.index("```", start)])
    assert _errors(validator, data) == []
    Scene.from_dict(data, Path("/nonexistent"), check_files=False)


# --------------------------------------------------------------------------- (b) invalid mutations
def _drop(*path):
    def f(d):
        node = d
        for k in path[:-1]:
            node = node[k]
        del node[path[-1]]
    return f


def _set(value, *path):
    def f(d):
        node = d
        for k in path[:-1]:
            node = node[k]
        node[path[-1]] = copy.deepcopy(value)
    return f


def _first(d, key):
    return next(iter(d[key]))


# (base scene, mutation): every one must be rejected by the schema and by the loader
MUTATIONS = {
    # missing required keys
    "no format": ("crosslaser", _drop("format")),
    "no version": ("crosslaser", _drop("version")),
    "no bounds": ("crosslaser", _drop("bounds")),
    "no bounds.radius": ("crosslaser", _drop("bounds", "radius")),
    "no cameras": ("crosslaser", _drop("cameras")),
    "no frames": ("crosslaser", _drop("frames")),
    "no camera K": ("crosslaser", lambda d: _drop("cameras", _first(d, "cameras"), "K")(d)),
    "no camera width": ("crosslaser", lambda d: _drop("cameras", _first(d, "cameras"), "width")(d)),
    "no projector K": ("crosslaser", lambda d: _drop("projectors", _first(d, "projectors"), "K")(d)),
    "no projector height": ("crosslaser", lambda d: _drop("projectors", _first(d, "projectors"), "height")(d)),
    "no pattern file": ("crosslaser", lambda d: _drop("patterns", _first(d, "patterns"), "file")(d)),
    "no frame image": ("crosslaser", _drop("frames", 0, "image")),
    "no frame camera": ("crosslaser", _drop("frames", 0, "camera")),
    "no frame cam_to_world": ("crosslaser", _drop("frames", 0, "cam_to_world")),
    "no laser planes": ("laser-planes", lambda d: _drop("projectors", _first(d, "projectors"), "planes")(d)),
    "no plane width": ("laser-planes", lambda d: _drop("projectors", _first(d, "projectors"), "planes", 0, "width")(d)),
    "no plane normal": ("laser-planes", lambda d: _drop("projectors", _first(d, "projectors"), "planes", 0, "normal")(d)),
    "no port distance": ("water", lambda d: _drop("cameras", _first(d, "cameras"), "port", "distance")(d)),
    "no port normal": ("water", lambda d: _drop("cameras", _first(d, "cameras"), "port", "normal")(d)),
    # wrong values of the header
    "format other": ("crosslaser", _set("nerf", "format")),
    "version 2": ("crosslaser", _set(2, "version")),
    "version string": ("crosslaser", _set("1", "version")),
    # wrong types
    "cameras a list": ("crosslaser", lambda d: _set(list(d["cameras"].values()), "cameras")(d)),
    "frames an object": ("crosslaser", lambda d: _set({"0": d["frames"][0]}, "frames")(d)),
    "width a string": ("crosslaser", lambda d: _set("16", "cameras", _first(d, "cameras"), "width")(d)),
    "width fractional": ("crosslaser", lambda d: _set(15.5, "cameras", _first(d, "cameras"), "width")(d)),
    "width boolean": ("crosslaser", lambda d: _set(True, "cameras", _first(d, "cameras"), "width")(d)),
    "radius a string": ("crosslaser", _set("1", "bounds", "radius")),
    "center of 2": ("crosslaser", _set([0.0, 0.0], "bounds", "center")),
    "K 2x3": ("crosslaser", lambda d: _set([[10, 0, 8], [0, 10, 8]], "cameras", _first(d, "cameras"), "K")(d)),
    "dist of 4": ("crosslaser", lambda d: _set([0, 0, 0, 0], "cameras", _first(d, "cameras"), "dist")(d)),
    "cam_to_world 3x4": ("crosslaser", lambda d: _set(d["frames"][0]["cam_to_world"][:3], "frames", 0,
                                                      "cam_to_world")(d)),
    "view negative": ("crosslaser", _set(-1, "frames", 0, "view")),
    "view fractional": ("crosslaser", _set(0.5, "frames", 0, "view")),
    "mask a number": ("crosslaser", _set(5, "frames", 0, "mask")),
    "image empty": ("crosslaser", _set("", "frames", 0, "image")),
    "laser on a string": ("laser-planes", lambda d: _set("yes", "frames", 0, "projectors",
                                                         _first(d["frames"][0], "projectors"), "on")(d)),
    "known a string": ("crosslaser", _set("yes", "illumination", "known")),
    "i_r a string": ("crosslaser", _set("0.4", "illumination", "i_r")),
    "name a number": ("crosslaser", _set(5, "name")),
    "units empty": ("crosslaser", _set("", "units")),
    "gt.mesh empty": ("crosslaser", _set("", "gt", "mesh")),
    # non-positive sizes and out-of-range values
    "width 0": ("crosslaser", lambda d: _set(0, "cameras", _first(d, "cameras"), "width")(d)),
    "height negative": ("crosslaser", lambda d: _set(-16, "cameras", _first(d, "cameras"), "height")(d)),
    "projector width 0": ("crosslaser", lambda d: _set(0, "projectors", _first(d, "projectors"), "width")(d)),
    "radius 0": ("crosslaser", _set(0.0, "bounds", "radius")),
    "radius negative": ("crosslaser", _set(-1.0, "bounds", "radius")),
    "fx 0": ("crosslaser", lambda d: _set(0.0, "cameras", _first(d, "cameras"), "K", 0, 0)(d)),
    "fy negative": ("crosslaser", lambda d: _set(-5.0, "cameras", _first(d, "cameras"), "K", 1, 1)(d)),
    "K last row": ("crosslaser", lambda d: _set([0, 0, 2], "cameras", _first(d, "cameras"), "K", 2)(d)),
    "pose last row": ("crosslaser", _set([0, 0, 1, 1], "frames", 0, "cam_to_world", 3)),
    "plane width 0": ("laser-planes", lambda d: _set(0.0, "projectors", _first(d, "projectors"), "planes", 0,
                                                     "width")(d)),
    "fan_deg 0": ("laser-planes", lambda d: _set(0.0, "projectors", _first(d, "projectors"), "planes", 0,
                                                 "fan_deg")(d)),
    "fan_deg 200": ("laser-planes", lambda d: _set(200.0, "projectors", _first(d, "projectors"), "planes", 0,
                                                   "fan_deg")(d)),
    "colour above 1": ("laser-planes", lambda d: _set([1.5, 0, 0], "projectors", _first(d, "projectors"), "planes",
                                                      0, "colour")(d)),
    "planes empty": ("laser-planes", lambda d: _set([], "projectors", _first(d, "projectors"), "planes")(d)),
    "port distance 0": ("water", lambda d: _set(0.0, "cameras", _first(d, "cameras"), "port", "distance")(d)),
    "port thickness negative": ("water", lambda d: _set(-0.01, "cameras", _first(d, "cameras"), "port",
                                                        "thickness")(d)),
    "n_glass below 1": ("water", lambda d: _set(0.9, "cameras", _first(d, "cameras"), "port", "n_glass")(d)),
    # empty collections and unknown names
    "frames empty": ("crosslaser", _set([], "frames")),
    "cameras empty": ("crosslaser", _set({}, "cameras")),
    "projector kind unknown": ("crosslaser", lambda d: _set("dlp", "projectors", _first(d, "projectors"), "kind")(d)),
    "laser behind a port": ("laser-planes", lambda d: _set({"normal": [0, 0, 1], "distance": 0.03}, "projectors",
                                                           _first(d, "projectors"), "port")(d)),
    "gt key unknown": ("crosslaser", _set({"albedo": "gt/000_albedo.png"}, "frames", 0, "gt")),
    "unsafe camera id": ("crosslaser", lambda d: _set(d["cameras"].pop(_first(d, "cameras")), "cameras", "../cam")(d)),
    "sensor_bits too many": ("crosslaser", _set(17, "sensor_bits")),
    "sensor_bits not a whole number": ("crosslaser", _set(12.5, "sensor_bits")),
}


@pytest.mark.parametrize("name", list(MUTATIONS))
def test_invalid_mutation_rejected_by_schema_and_loader(validator, synth_scenes, name):
    base, mutate = MUTATIONS[name]
    data = _load_json(synth_scenes[base])
    assert _errors(validator, data) == []  # the base is valid
    mutate(data)
    assert _errors(validator, data), f"schema accepted: {name}"
    with pytest.raises(FastneusError):
        Scene.from_dict(data, synth_scenes[base], check_files=False)


# --------------------------------------------------------------------------- (c) loader-only checks
LOADER_ONLY = {
    "unknown camera id": ("crosslaser", _set("nocam", "frames", 0, "camera")),
    "unknown pattern id": ("crosslaser", lambda d: _set("nopattern", "frames", 0, "projectors",
                                                        _first(d["frames"][0], "projectors"), "pattern")(d)),
    "not a rotation": ("crosslaser", lambda d: _set([2.0, 0.0, 0.0, d["frames"][0]["cam_to_world"][0][3]],
                                                    "frames", 0, "cam_to_world", 0)(d)),
    "laser shows a pattern": ("laser-planes", lambda d: _set("p", "frames", 0, "projectors",
                                                             _first(d["frames"][0], "projectors"), "pattern")(d)),
    "free projector without proj_to_world": (
        "crosslaser", lambda d: _set(None, "projectors", _first(d["frames"][0], "projectors"), "proj_to_cam")(d)),
    "duplicate image": ("crosslaser", lambda d: _set(d["frames"][0]["image"], "frames", 1, "image")(d)),
    "port facing backwards": ("water", lambda d: _set([0, 0, -1], "cameras", _first(d, "cameras"), "port",
                                                      "normal")(d)),
}


@pytest.mark.parametrize("name", list(LOADER_ONLY))
def test_loader_only_checks(validator, synth_scenes, name):
    """Cross-references and geometry the schema cannot express: valid JSON structure, refused on load."""
    base, mutate = LOADER_ONLY[name]
    data = _load_json(synth_scenes[base])
    mutate(data)
    assert _errors(validator, data) == [], name
    with pytest.raises(FastneusError):
        Scene.from_dict(data, synth_scenes[base], check_files=False)
