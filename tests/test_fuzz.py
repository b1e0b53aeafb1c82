"""Property-based fuzz of every input parser (issue 20), and the bugs it found.

Random structural mutations of a valid small input (strategies in tests/fuzz_strategies.py)
must load or be refused with a one-line FastneusError naming an input file: never another
exception, never a hang, never an unpickled payload. The examples are derandomised so CI
is reproducible; ``scripts/fuzz.py`` runs the same strategies at random for long runs.
"""
from __future__ import annotations

import contextlib
import io
import json
import shutil

import numpy as np
import pytest
from hypothesis import HealthCheck, given, note, settings

import fuzz_strategies as fz
from fastneus.cli import main
from fastneus.errors import FastneusError

# examples per target: ~540 in all, about 17 s on 2 cores
EXAMPLES = {"scene": 70, "nerf": 60, "activeneus": 70, "neus": 50, "opencv": 70, "colmap": 60, "colmap_bin": 60,
            "config": 50, "overrides": 50}
FUZZ = settings(deadline=2000, derandomize=True, database=None, print_blob=True,
                suppress_health_check=list(HealthCheck))


@pytest.fixture(scope="module")
def fuzz(small_scene, tmp_path_factory):
    root = tmp_path_factory.mktemp("fuzz")
    f = fz.Fuzz(fz.build_bases(root / "bases", small_scene), root / "work")
    for t in ("scene", "nerf", "activeneus", "colmap", "colmap_bin"):  # warm imports: not the first example's deadline
        fz.check_case(f, fz.Case(t, {}))
    fz.check_case(f, fz.Case("opencv", {"calib.yml": f.b["calib"].read_bytes()}))
    return f


@pytest.mark.parametrize("target", fz.TARGETS)
def test_fuzz_parser(fuzz, target):
    """Mutated inputs load, or fail with one line naming the file; nothing else, no hang, no pickle."""
    @settings(FUZZ, max_examples=EXAMPLES[target])
    @given(case=fuzz.strategy(target))
    def run(case):
        note(f"mutation: {case.what}")
        fz.check_case(fuzz, case)

    run()


def test_fuzz_bases_load(fuzz):
    """Unmutated, every base loads (else the fuzz would only test the first check)."""
    for t in ("scene", "nerf", "activeneus", "neus", "colmap", "colmap_bin"):
        assert fz.check_case(fuzz, fz.Case(t, {})) == "ok", t
    calib = {"calib.yml": fuzz.b["calib"].read_bytes()}
    assert fz.check_case(fuzz, fz.Case("opencv", calib)) == "ok"
    assert fz.check_case(fuzz, fz.Case("overrides", items=["steps=3"])) == "ok"


@pytest.mark.parametrize("target", ["scene", "nerf", "activeneus", "opencv", "colmap", "colmap_bin"])
def test_fuzz_through_cli(fuzz, target):
    """A few mutated inputs through ``fastneus.cli.main``: exit 0, or 2 with exactly one stderr line."""
    out = fuzz.work / "cli-out"
    b = fuzz.b

    @settings(FUZZ, max_examples=4)
    @given(case=fuzz.strategy(target))
    def run(case):
        note(f"mutation: {case.what}")
        files = fuzz.write(case)
        shutil.rmtree(out, ignore_errors=True)
        if target in ("opencv", "colmap", "colmap_bin"):
            where = ["--poses", str(b["poses"])] if target == "opencv" else ["--colmap", str(fuzz.folder(target))]
            argv = ["import-calib", str(files[0] if target == "opencv" else b["calib"]), "--images", str(b["images"]),
                    "--patterns", str(b["pattern"]), *where, "--units", "m", "--out", str(out)]
        else:
            argv = ["convert", str(fuzz.folder(target)), "--to", "fastneus", "--out", str(out)]
        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()), fz.hang_guard():
            rc = main(argv)
        lines = err.getvalue().splitlines()
        note(f"rc {rc}, stderr {lines}")
        assert rc in (0, 2)
        if rc == 2:
            errors = [ln for ln in lines if not ln.startswith("warning:")]
            assert len(errors) == 1 and "internal error" not in errors[0] and "error: " in errors[0]

    run()


# --------------------------------------------------------------------------- bugs the fuzz found
def _calib(fuzz, tmp_path, text: str, name: str = "calib.yml"):
    p = tmp_path / name
    p.write_text(text)
    return fz.check_case(fuzz, fz.Case("opencv", {name: p.read_bytes()}))


@pytest.mark.parametrize("fmt", ["yml", "xml"])
def test_calibration_nested_deep_is_refused(fuzz, tmp_path, fmt):
    """OpenCV's FileStorage parser recursed until the process crashed (SIGSEGV) on ~50k nesting levels."""
    n = 60_000
    text = ("%YAML:1.0\n---\nx: " + "[" * n + "1" + "]" * n + "\n") if fmt == "yml" else \
        ('<?xml version="1.0"?>\n<opencv_storage>\n<x>' + "<_>" * n + "1" + "</_>" * n + "</x>\n</opencv_storage>\n")
    msg = _calib(fuzz, tmp_path, text, f"calib.{fmt}")
    assert f"calib.{fmt}" in msg and "nested" in msg


def test_calibration_matrix_size_mismatch_is_one_line(fuzz, tmp_path):
    """rows x cols disagreeing with data raised a bare cv2.error (an internal error)."""
    text = fz.render_yaml([("cam_K", ("mat", "3", "3", "d", ["1.0"] * 8))])
    msg = _calib(fuzz, tmp_path, text)
    assert "calib.yml: cam_K: matrix of 3x3 holds 8 values" in msg


def test_calibration_top_level_not_a_mapping(fuzz, tmp_path):
    """A top-level sequence raised a bare cv2.error from FileNode.keys()."""
    msg = _calib(fuzz, tmp_path, "%YAML:1.0\n---\n- 1\n- 2\n")
    assert "calib.yml" in msg and "mapping" in msg


def test_nerf_bounds_center_object(fuzz):
    """``bounds.center`` as an object raised TypeError in np.asarray (an internal error)."""
    d = json.loads(json.dumps(fuzz.transforms))
    d["bounds"] = {"center": {"x": 1}, "radius": 1.0}
    msg = fz.check_case(fuzz, fz.Case("nerf", {"transforms.json": json.dumps(d).encode()}))
    assert "transforms.json: bounds.center:" in msg


def test_colmap_pose_far_away_names_images_txt(fuzz):
    """A COLMAP pose far outside the bounds was refused naming the removed staging scene.json."""
    text = fuzz.colmap_files["images.txt"].splitlines()
    t = text[2].split()
    t[7] = "-4e16"  # tz of the second image
    text[2] = " ".join(t)
    msg = fz.check_case(fuzz, fz.Case("colmap", {"images.txt": "\n".join(text).encode()}))
    assert "images.txt: 001.png:" in msg and "staging" not in msg


def test_import_calib_bounds_nan_names_option(fuzz, tmp_path):
    """``--bounds`` NaN was blamed on the staging scene.json; now on the option."""
    from fastneus.formats.opencv_calib import make_scene_from_calibration

    b = fuzz.b
    with pytest.raises(FastneusError) as e:
        make_scene_from_calibration(b["calib"], sorted(b["images"].iterdir()), [b["pattern"]], b["poses"],
                                    tmp_path / "out", units="m", bounds=([np.nan, 0, 0], 1.0))
    assert e.value.field == "--bounds" and e.value.file is None


@pytest.mark.parametrize("rows, cols, fmt", [("3", "-3", "yml"), ("3", "x", "yml"), ("", "1", "xml")])
def test_calibration_bad_matrix_header_is_refused(fuzz, tmp_path, rows, cols, fmt):
    """OpenCV trusts rows/cols: a negative cols corrupted the heap (the process aborted later), a
    non-number could allocate a garbage size; now refused before cv2 reads the matrix."""
    model = [(k, ("mat", rows, cols, "d", n[4]) if k == "R" else n) for k, n in fuzz.calib_model]
    msg = _calib(fuzz, tmp_path, (fz.render_yaml if fmt == "yml" else fz.render_xml)(model), f"calib.{fmt}")
    assert f"calib.{fmt}: R: bad matrix header" in msg


def test_look_point_of_degenerate_poses_is_nan():
    """Non-finite axes (a COLMAP quaternion near 1e300 normalises to NaN) raised LinAlgError in the
    least squares; now NaN, which the callers refuse naming the poses file."""
    from fastneus.formats.opencv_calib import axes_meeting_point

    T = np.eye(4)
    T[:3, :3] = np.nan
    assert np.all(np.isnan(axes_meeting_point([T, np.eye(4)])))


@pytest.mark.parametrize("key", ["line\nbreak", "a\rb"])
def test_unknown_config_key_with_line_break_is_one_line(fuzz, tmp_path, key):
    """An unknown key holding a line break was printed as is, splitting the error over two lines."""
    msg = fz.check_case(fuzz, fz.Case("overrides", items=[f"{key}=1"]))
    assert "unknown config key" in msg and repr(key) in msg
    cfg = tmp_path / "c.yaml"
    cfg.write_text(json.dumps({key: 1}))  # JSON is YAML
    msg = fz.check_case(fuzz, fz.Case("config", {"config.yaml": cfg.read_bytes()}))
    assert "unknown config key" in msg and repr(key) in msg


def test_deep_config_is_refused_before_yaml_parses_it(tmp_path, monkeypatch):
    """PyYAML recursed through 100k brackets for seconds before its RecursionError; the depth is now
    checked first, so the parser never sees such a file."""
    import yaml

    from fastneus.config import load_config

    cfg = tmp_path / "deep.yaml"
    cfg.write_text("steps: " + "[" * 100_000 + "]" * 100_000 + "\n")
    real = yaml.safe_load
    monkeypatch.setattr(yaml, "safe_load", lambda t: real(t) if len(t) < 10_000 else pytest.fail("parsed"))
    with pytest.raises(FastneusError) as e:
        load_config(str(cfg))
    assert str(cfg) in str(e.value) and "nested too deeply" in str(e.value)


@pytest.mark.parametrize("where", ["projectors", "gt"])
def test_scene_key_with_line_break_is_one_line(fuzz, where):
    """A frame's projector id or ground-truth key holding a line break split the error over two lines."""
    d = json.loads(json.dumps(fuzz.scene_json))
    d["frames"][0].setdefault(where, {})["line\nbreak"] = {} if where == "projectors" else "x.npy"
    msg = fz.check_case(fuzz, fz.Case("scene", {"scene.json": json.dumps(d).encode()}))
    assert f"frames[0].{where}.'line\\nbreak'" in msg


def test_any_error_is_one_line(fuzz):
    """A path from the input holding a line break (a NeRF pattern path here) was printed as is, splitting
    the error; FastneusError now escapes line breaks and unprintable characters wherever they come from."""
    d = json.loads(json.dumps(fuzz.transforms))
    d["frames"][0]["projectors"] = {"proj0": "pat\r\nx\x85.png"}
    msg = fz.check_case(fuzz, fz.Case("nerf", {"transforms.json": json.dumps(d).encode()}))
    assert "file not found" in msg and "pat\\r\\nx\\x85.png" in msg
    e = FastneusError("bad\nvalue \u2028", file="a\nb.json", field="k\r")
    assert len(str(e).splitlines()) == 1 and e.file == "a\nb.json"
