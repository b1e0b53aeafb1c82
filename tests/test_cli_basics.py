"""Small things a user of the command line and of shared folders expects."""
from __future__ import annotations

import json

import os
import stat
import subprocess
import sys

import numpy as np

from fastneus import __version__
from fastneus.cli import main
from fastneus.io import atomic_write_text
from fastneus.pipeline import provenance


def test_version(capsys):
    try:
        main(["--version"])
    except SystemExit as e:  # argparse's version action exits 0
        assert e.code == 0
    assert capsys.readouterr().out.strip() == f"fastneus {__version__}"


def test_atomic_writes_follow_the_umask(tmp_path):
    """mkstemp creates 0600 files: a report in a lab's shared folder must be readable like any other file."""
    old = os.umask(0o022)
    try:
        atomic_write_text(tmp_path / "a.txt", "x")
    finally:
        os.umask(old)
    mode = stat.S_IMODE((tmp_path / "a.txt").stat().st_mode)
    assert mode & ~0o022 == mode  # nothing the umask forbids
    # the value in io was read at import; with this process's umask the file is group/other readable
    if not old & 0o044:
        assert mode & 0o044 == 0o044, oct(mode)


def test_run_json_records_version_command_and_commit(monkeypatch):
    monkeypatch.setattr(sys, "argv", ["fastneus", "train", "my scene", "steps=3"])
    p = provenance()
    assert p["fastneus_version"] == __version__
    assert p["command"] == "fastneus train 'my scene' steps=3"
    monkeypatch.setattr(sys, "argv", ["/x/fastneus/__main__.py", "eval", "run"])  # python -m fastneus
    assert provenance()["command"] == "fastneus eval run"
    if subprocess.run(["git", "--version"], capture_output=True).returncode == 0 and "git_commit" in p:
        assert len(p["git_commit"].split("+")[0]) == 40


def test_mesh_verb_uses_the_runs_resolution(small_scene, tmp_path):
    import trimesh

    from conftest import SMALL_RUN

    run = tmp_path / "run"
    assert main(["train", str(small_scene), "--out", str(run), "--device", "cpu", *SMALL_RUN]) == 0
    assert main(["mesh", str(run), "--device", "cpu", "--out", str(tmp_path / "again.ply")]) == 0
    a, b = trimesh.load(run / "mesh.ply"), trimesh.load(tmp_path / "again.ply")
    assert len(a.vertices) == len(b.vertices) > 0  # mesh_resolution=16 of the run, not a 512^3 grid
    # the exports carry unit outward normals (a sphere here) and the learned colours
    header = (run / "mesh.ply").read_bytes().split(b"end_header")[0].decode()
    for prop in ("nx", "ny", "nz", "red", "green", "blue"):
        assert f" {prop}\n" in header, prop
    from fastneus.formats.detect import load_scene

    c = load_scene(small_scene).bounds.center
    radial = a.vertices - c
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    n = a.vertex_normals
    assert np.allclose(np.linalg.norm(n, axis=1), 1, atol=1e-3) and np.mean(np.sum(n * radial, 1) > 0.5) > 0.9
    rgb = a.visual.vertex_colors[:, :3]
    assert rgb.dtype == np.uint8 and rgb.std() >= 0 and rgb.max() > 0
    assert main(["mesh", str(run), "--device", "cpu", "--out", str(tmp_path / "m.glb")]) == 0
    g = trimesh.load(tmp_path / "m.glb", force="mesh")
    assert len(g.vertices) > 0 and g.visual.kind == "vertex"
    meta = json.loads((run / "run.json").read_text())  # run.json says what made the run and where
    assert meta["fastneus_version"] and meta["command"].startswith("fastneus") or "pytest" in meta["command"]
    assert meta["machine"]["cores"] >= 1 and meta["machine"]["python"] and meta["machine"]["torch"]


def test_piped_training_prints_plain_progress_lines(small_scene, tmp_path, capsys):
    """A cluster job's log gets plain unwrapped lines, not a bar redrawn in place."""
    from conftest import SMALL_RUN

    assert main(["train", str(small_scene), "--out", str(tmp_path / "run"), "--device", "cpu", *SMALL_RUN]) == 0
    out = capsys.readouterr().out
    lines = [x for x in out.splitlines() if x.startswith("train step")]
    assert lines and lines[-1].startswith("train step 4/4 (100%): step 4 loss"), out
    assert "━" not in out and "\r" not in out
