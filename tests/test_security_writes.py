"""Writes stay inside the output folder and results are never lost (issue 20, items 1 and 3).

- Ids that name files (patterns, projectors, cameras) are checked at scene load against a
  safe character set, and writers check every destination again: a crafted pattern id
  ``../../sentinel/hook`` whose file is a PNG header followed by shell lines (the attack
  that overwrote a git hook) is refused with one line, and a sentinel folder next to the
  output is byte-identical afterwards.
- ``convert`` and ``synth`` build aside and swap in on success; a file fastneus did not
  write (no entry in ``.fastneus-manifest.json``) is never replaced or removed.
"""
from __future__ import annotations

from conftest import one_line_error as _one_line

import json
import os
import shutil
import stat
import struct
import zlib
from pathlib import Path

import pytest

from fastneus.cli import main
from fastneus.data import Scene
from fastneus.errors import FastneusError
MANIFEST = ".fastneus-manifest.json"  # fastneus.io.MANIFEST

TINY_SYNTH = ["--shape", "sphere", "--views", "1", "--size", "16x16", "--proj-size", "32x24", "--no-contact-sheet",
              "--device", "cpu"]


def _snapshot(folder: Path) -> dict:
    """Every entry under ``folder``: bytes and mode of files, link targets, folders."""
    snap = {}
    for root, dirs, files in os.walk(folder):
        for name in dirs + files:
            p = Path(root) / name
            rel = p.relative_to(folder).as_posix()
            if p.is_symlink():
                snap[rel] = ("link", os.readlink(p))
            elif p.is_dir():
                snap[rel] = ("dir",)
            else:
                snap[rel] = ("file", p.read_bytes(), stat.S_IMODE(p.stat().st_mode))
    return snap


def _sentinel(tmp_path: Path) -> Path:
    """A folder with an executable 'hook' (stands for .git/hooks/pre-commit) that must not change."""
    s = tmp_path / "sentinel"
    s.mkdir()
    (s / "hook").write_text("#!/bin/sh\necho original hook\n")
    (s / "hook").chmod(0o755)
    (s / "authorized_keys").write_text("ssh-ed25519 AAAA original\n")
    return s


def _png_header_then_shell(w: int, h: int, marker: Path) -> bytes:
    """A file fastneus' header check reads as a w x h RGB PNG, followed by shell lines."""
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    chunk = struct.pack(">I", 13) + b"IHDR" + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
    return b"\x89PNG\r\n\x1a\n" + chunk + f"\ntouch {marker}\n".encode()


def _hostile_scene(small_scene: Path, tmp_path: Path, bad_id: str) -> Path:
    """The small scene with its first pattern renamed ``bad_id`` and its file replaced by the payload."""
    src = tmp_path / "scene"
    shutil.copytree(small_scene, src)
    d = json.loads((src / "scene.json").read_text())
    old = sorted(d["patterns"])[0]
    pw, ph = d["projectors"][next(iter(d["projectors"]))]["width"], d["projectors"][next(iter(d["projectors"]))]["height"]
    (src / "patterns" / "hook").write_bytes(_png_header_then_shell(pw, ph, tmp_path / "PWNED"))
    d["patterns"][bad_id] = {"file": "patterns/hook"}
    del d["patterns"][old]
    for f in d["frames"]:
        for fp in f.get("projectors", {}).values():
            if fp.get("pattern") == old:
                fp["pattern"] = bad_id
    (src / "scene.json").write_text(json.dumps(d))
    return src


# --------------------------------------------------------------------------- item 1: paths from input data
@pytest.mark.parametrize("to", ["fastneus", "nerf", "activeneus"])
def test_convert_refuses_a_pattern_id_that_is_a_path(small_scene, tmp_path, capsys, to):
    sentinel = _sentinel(tmp_path)
    before = _snapshot(sentinel)
    src = _hostile_scene(small_scene, tmp_path, "../../sentinel/hook")
    out = tmp_path / "out"
    assert main(["convert", str(src), "--to", to, "--out", str(out)]) == 2
    _one_line(capsys, "scene.json", "patterns.../../sentinel/hook", "unsafe id")
    assert _snapshot(sentinel) == before and not (tmp_path / "PWNED").exists()
    assert not out.exists() and not list(tmp_path.glob(".out.*"))  # no staging leftovers


@pytest.mark.parametrize("bad", ["..", "a/b", ".hidden", "-rf", "x" * 65, "a\nb", "C:\\x", "p..q", ""])
def test_unsafe_ids_are_refused_at_load(small_scene, tmp_path, bad):
    src = _hostile_scene(small_scene, tmp_path, bad)
    with pytest.raises(FastneusError) as e:
        Scene.load(src)
    assert "unsafe id" in str(e.value) and "\n" not in str(e.value) and e.value.field.startswith("patterns.")


def test_unsafe_projector_and_camera_ids_are_refused_at_load(small_scene, tmp_path):
    src = tmp_path / "scene"
    shutil.copytree(small_scene, src)
    d = json.loads((src / "scene.json").read_text())
    d["cameras"]["../cam"] = d["cameras"].pop("cam0")
    (src / "scene.json").write_text(json.dumps(d))
    with pytest.raises(FastneusError, match="unsafe id") as e:
        Scene.load(src)
    assert e.value.field == "cameras.../cam"


def _with_pattern_id(scene: Scene, new: str) -> Scene:
    """``scene`` (in memory, not validated again) with its first pattern renamed ``new``."""
    old = sorted(scene.patterns)[0]
    q = scene.patterns.pop(old)
    q.id = new
    scene.patterns[new] = q
    for f in scene.frames:
        for fp in f.projectors.values():
            if fp.pattern == old:
                fp.pattern = new
    return scene


@pytest.mark.parametrize("writer", ["fastneus", "nerf"])
def test_writers_refuse_an_unsafe_id_given_directly(small_scene, tmp_path, writer):
    from fastneus.formats.fastneus import write_fastneus
    from fastneus.formats.nerf import write_nerf

    sentinel = _sentinel(tmp_path)
    before = _snapshot(sentinel)
    scene = _with_pattern_id(Scene.load(small_scene), "../../sentinel/hook")
    out = tmp_path / "out"
    with pytest.raises(FastneusError, match="unsafe id") as e:
        (write_fastneus if writer == "fastneus" else write_nerf)(scene, out)
    assert e.value.field == "patterns.../../sentinel/hook"
    assert _snapshot(sentinel) == before and not out.exists() and not list(tmp_path.glob(".out.*"))


def test_safe_dest_keeps_every_write_inside(tmp_path):
    from fastneus.io import safe_dest

    out = tmp_path / "out"
    (out / "ok").mkdir(parents=True)
    assert safe_dest(out, "ok/000.png") == (out / "ok" / "000.png").resolve()
    sentinel = _sentinel(tmp_path)
    (out / "link").symlink_to(sentinel)
    for rel in ["../x", "/etc/passwd", "a//b", "ok/../../x", ".git/hooks", "link/hook", "ok/a\nb", ""]:
        with pytest.raises(FastneusError, match="refusing to write"):
            safe_dest(out, rel, field="f")


def test_pattern_approximation_refuses_an_unsafe_projector_id(tmp_path):
    from fastneus.light.lasers import pattern_approximation
    from fastneus.synth.render import synthesize

    s = synthesize(tmp_path / "laser", shape="sphere", views=1, size=(16, 16), proj_size=(32, 24), baselines=(0.6,),
                   laser_planes=True, progress=False, contact_sheet=False)
    sentinel = _sentinel(tmp_path)
    before = _snapshot(sentinel)
    bad = "../../sentinel/hook"
    s.projectors[bad] = s.projectors.pop("proj0")
    s.projectors[bad].id = bad
    for f in s.frames:
        f.projectors[bad] = f.projectors.pop("proj0")
    with pytest.raises(FastneusError, match="unsafe id") as e:
        pattern_approximation(s, tmp_path / "approx" / "x", 32, 24, 60.0, 4.0)
    assert e.value.field == f"projectors.{bad}"
    assert _snapshot(sentinel) == before and not (tmp_path / "approx").exists()


def test_laser_plane_file_refuses_an_unsafe_laser_id(tmp_path):
    from fastneus.light.lasers import read_laser_planes

    f = tmp_path / "planes.yaml"
    f.write_text("lasers:\n  ../../x:\n    planes:\n      - {normal: [1, 0, 0], offset: 0, colour: [1, 0, 0], "
                 "width: 1, fan_deg: 60}\n")
    with pytest.raises(FastneusError, match="unsafe id") as e:
        read_laser_planes(f)
    assert e.value.field == "lasers.../../x"


# --------------------------------------------------------------------------- item 3: convert loses nothing
def _user_files(out: Path) -> None:
    for rel in ["images/keep.png", "masks/keep.png", "patterns/keep.png", "gt/keep.txt", "notes.txt"]:
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        (out / rel).write_bytes(b"the user's own " + rel.encode())


@pytest.mark.parametrize("to", ["activeneus", "nerf", "fastneus"])
def test_convert_keeps_the_users_files_in_out(small_scene, tmp_path, capsys, to):
    out = tmp_path / "out"
    _user_files(out)
    before = _snapshot(out)
    assert main(["convert", str(small_scene), "--to", to, "--out", str(out)]) == 0
    after = _snapshot(out)
    assert {k: v for k, v in after.items() if k in before} == before  # nothing of the user's changed
    from fastneus.formats.detect import load_scene

    assert len(load_scene(out).frames) == 3
    # a second conversion replaces fastneus's own files only
    assert main(["convert", str(small_scene), "--to", to, "--out", str(out)]) == 0
    assert {k: v for k, v in _snapshot(out).items() if k in before} == before
    assert not list(tmp_path.glob(".out.*"))


def test_convert_refuses_to_replace_a_users_file(small_scene, tmp_path, capsys):
    out = tmp_path / "out"
    (out / "image").mkdir(parents=True)
    (out / "image" / "001.png").write_bytes(b"a photo the user took")
    before = _snapshot(out)
    assert main(["convert", str(small_scene), "--to", "activeneus", "--out", str(out)]) == 2
    _one_line(capsys, str(out / "image" / "001.png"), "not written by fastneus", "choose another --out")
    assert _snapshot(out) == before and not list(tmp_path.glob(".out.*"))


def test_rewrite_removes_only_fastneus_stale_files(small_scene, tmp_path):
    from fastneus.formats.activeneus import write_activeneus

    out = tmp_path / "out"
    scene = Scene.load(small_scene)
    write_activeneus(scene, out)
    (out / "image" / "mine.png").write_bytes(b"user")
    assert (out / "image" / "002.png").is_file()
    write_activeneus(scene.subset([0, 1]), out)  # a shorter scene: frame 2's files were fastneus's
    assert not (out / "image" / "002.png").exists() and (out / "image" / "mine.png").read_bytes() == b"user"
    assert sorted(json.loads((out / MANIFEST).read_text())["files"])[0] == "cameras_sphere.npz"


def test_a_crafted_manifest_cannot_delete_outside(small_scene, tmp_path):
    sentinel = _sentinel(tmp_path)
    before = _snapshot(sentinel)
    out = tmp_path / "out"
    out.mkdir()
    (out / "link").symlink_to(sentinel)
    (out / MANIFEST).write_text(json.dumps({"files": ["../sentinel/hook", str(sentinel / "hook"), "link/hook",
                                                      "link", "../sentinel"]}))
    assert main(["convert", str(small_scene), "--to", "nerf", "--out", str(out)]) == 0
    assert _snapshot(sentinel) == before and (out / "link").is_symlink()


def test_convert_refuses_a_symlinked_subfolder(small_scene, tmp_path, capsys):
    sentinel = _sentinel(tmp_path)
    before = _snapshot(sentinel)
    out = tmp_path / "out"
    out.mkdir()
    (out / "image").symlink_to(sentinel)
    assert main(["convert", str(small_scene), "--to", "activeneus", "--out", str(out)]) == 2
    _one_line(capsys, "symbolic link")
    assert _snapshot(sentinel) == before


# --------------------------------------------------------------------------- item 3: synth loses nothing
@pytest.fixture
def previous_synth(tmp_path):
    out = tmp_path / "scene"
    assert main(["synth", *TINY_SYNTH, "--out", str(out)]) == 0
    (out / "notes.txt").write_text("the user's notes")
    return out


@pytest.mark.parametrize("bad", [["--ambient", "inf"], ["--ambient", "nan"], ["--noise", "nan"]])
def test_synth_bad_value_leaves_the_previous_scene(previous_synth, capsys, bad):
    before = _snapshot(previous_synth)
    assert main(["synth", *TINY_SYNTH, *bad, "--out", str(previous_synth)]) == 2
    _one_line(capsys, bad[0], "finite")
    assert _snapshot(previous_synth) == before
    assert not list(previous_synth.parent.glob(".scene.*"))


def test_synth_interrupted_mid_render_leaves_the_previous_scene(previous_synth, monkeypatch):
    import fastneus.synth.render as synth

    before = _snapshot(previous_synth)
    real = synth.write_png
    calls = []

    def write_png(path, rgb):
        if "images" in Path(path).parts:  # the first rendered photo: Ctrl-C
            calls.append(path)
            raise KeyboardInterrupt
        real(path, rgb)

    monkeypatch.setattr(synth, "write_png", write_png)
    with pytest.raises(KeyboardInterrupt):
        synth.synthesize(previous_synth, shape="torus", views=2, size=(16, 16), proj_size=(32, 24), progress=False,
                         contact_sheet=False)
    assert calls, "the interruption did not happen mid-render"
    assert _snapshot(previous_synth) == before
    assert not list(previous_synth.parent.glob(".scene.*"))  # no staging leftovers
    assert len(Scene.load(previous_synth).frames) == 1


def test_synth_rerun_replaces_its_own_files_only(previous_synth, tmp_path):
    (previous_synth / MANIFEST).unlink()  # as written before manifests existed: still recognised as ours
    assert main(["synth", *TINY_SYNTH, "--views", "2", "--out", str(previous_synth)]) == 0
    assert len(Scene.load(previous_synth).frames) == 2
    assert (previous_synth / "notes.txt").read_text() == "the user's notes"
    assert main(["synth", *TINY_SYNTH, "--out", str(previous_synth)]) == 0
    assert not (previous_synth / "images" / "001.png").exists()
    assert (previous_synth / "notes.txt").read_text() == "the user's notes"


def test_import_calib_keeps_the_users_files_in_out(small_scene, tmp_path, capsys):
    import cv2
    import numpy as np

    fs = cv2.FileStorage(str(tmp_path / "calib.yml"), cv2.FILE_STORAGE_WRITE)
    for k, v in {"cam_K": np.array([[30.0, 0, 12], [0, 30, 12], [0, 0, 1]]), "cam_kc": np.zeros((1, 5)),
                 "proj_K": np.array([[60.0, 0, 32], [0, 60, 24], [0, 0, 1]]), "proj_kc": np.zeros((1, 5)),
                 "R": np.eye(3), "T": np.array([[100.0], [0], [0]])}.items():
        fs.write(k, v)
    fs.release()
    for d, (w, h) in (("imgs", (24, 24)), ("pats", (64, 48))):
        (tmp_path / d).mkdir()
        for i in range(3):
            cv2.imwrite(str(tmp_path / d / f"{i:03d}.png"), np.full((h, w, 3), 40 * i, np.uint8))
    out = tmp_path / "out"
    (out / "image").mkdir(parents=True)
    (out / "image" / "keep.png").write_bytes(b"the user's photo")
    args = ["import-calib", str(tmp_path / "calib.yml"), "--images", str(tmp_path / "imgs"), "--patterns",
            str(tmp_path / "pats"), "--poses", str(small_scene / "scene.json"), "--out", str(out)]
    assert main(args) == 0, capsys.readouterr().err
    assert len(Scene.load(out).frames) == 3 and (out / "image" / "keep.png").read_bytes() == b"the user's photo"
    assert main(args) == 0  # again: its own files are replaced, the user's kept
    assert (out / "image" / "keep.png").read_bytes() == b"the user's photo"
