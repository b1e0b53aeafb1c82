"""The ground-truth mesh is checked before training from its header (no trimesh import: ~1 s
between process start and mesh.ply), and parsed in full at evaluation."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import trimesh

from fastneus.data.groundtruth import mesh_file_problem
from fastneus.export.mesh import write_ply


@pytest.mark.parametrize("suffix", ["ply", "obj", "stl", "off", "glb"])
def test_meshes_trimesh_writes_pass(tmp_path, suffix):
    m = trimesh.creation.icosphere(subdivisions=1)
    p = tmp_path / f"m.{suffix}"
    m.export(p)
    assert mesh_file_problem(p) is None
    assert len(trimesh.load(p, force="mesh").faces) > 0  # and trimesh reads it (what evaluation does)


def test_our_ply_passes_ascii_too(tmp_path):
    m = trimesh.creation.box()
    write_ply(tmp_path / "a.ply", m.vertices, m.faces, None, None)
    assert mesh_file_problem(tmp_path / "a.ply") is None
    (tmp_path / "b.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                                    "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
                                    "end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    assert mesh_file_problem(tmp_path / "b.ply") is None


def _truncated_binary_ply(p):
    m = trimesh.creation.icosphere(subdivisions=2)
    write_ply(p, m.vertices, m.faces, None, None)
    data = p.read_bytes()
    p.write_bytes(data[: data.index(b"end_header") + 200])


@pytest.mark.parametrize("name,make,needle", [
    ("bad.ply", lambda p: p.write_text("not a mesh"), "not a PLY"),
    ("empty.ply", lambda p: p.write_bytes(b""), "empty"),
    ("nofaces.ply", lambda p: p.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"
                                           "element face 0\nend_header\n"), "no triangles"),
    ("odd.ply", lambda p: p.write_text("ply\nformat weird 1.0\nelement vertex 3\nelement face 1\nend_header\n"),
     "format"),
    ("cut.ply", _truncated_binary_ply, "ends before"),
    ("bad.obj", lambda p: p.write_text("# nothing here\n"), "vertex and face"),
    ("bad.stl", lambda p: p.write_bytes(b"\0" * 84), "STL"),
    ("bad.off", lambda p: p.write_text("hello"), "OFF"),
    ("bad.glb", lambda p: p.write_bytes(b"JUNKJUNK"), "glTF"),
])
def test_broken_meshes_say_why(tmp_path, name, make, needle):
    p = tmp_path / name
    make(p)
    why = mesh_file_problem(p)
    assert why is not None and needle in why, why


def test_missing_file_says_why(tmp_path):
    assert "cannot read" in mesh_file_problem(tmp_path / "nope.ply")


def test_check_inputs_does_not_import_trimesh(small_scene, tmp_path):
    """The checks before training leave trimesh (and its ~1 s import) to evaluation."""
    import shutil

    scene = tmp_path / "s"
    shutil.copytree(small_scene, scene)
    m = trimesh.creation.icosphere(subdivisions=1)
    write_ply(scene / "gt_mesh.ply", np.asarray(m.vertices), np.asarray(m.faces), None, None)
    import json

    d = json.loads((scene / "scene.json").read_text())
    d["gt"] = {"mesh": "gt_mesh.ply"}
    (scene / "scene.json").write_text(json.dumps(d))
    code = ("import sys\nfrom fastneus.data import Scene\nfrom fastneus.pipeline import check_inputs\n"
            f"s = Scene.load({str(scene)!r})\ncheck_inputs(s, [0])\nprint('trimesh' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"
