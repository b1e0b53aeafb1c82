"""Fast mesh extraction: sparse evaluation vs the dense reference, Warp marching cubes vs the
scikit-image twin, the PLY writer, floater removal, orientation and bad input.

Analytic fields stand in for a trained one (an object with ``.sdf``); their radii are offset by
an irrational amount so that no grid node is exactly on the surface (where marching-cubes
implementations disagree about zero-area triangles).
"""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from fastneus.errors import FastneusError
from fastneus.export.mesh import (MeshArrays, extract_mesh, extract_mesh_arrays, keep_large_components,
                                  mesh_from_grid, save_mesh, sdf_grid, sparse_sdf, surface_cells, write_ply)
from fastneus.kernels.mesh import marching_cubes, marching_cubes_torch

EPS = 1e-3 * math.pi
DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


class Torus:
    def __init__(self, k: float = 1.0):
        self.k = k

    def sdf(self, x):
        q = torch.stack([torch.sqrt(x[:, 0] ** 2 + x[:, 2] ** 2) - 0.5, x[:, 1]], -1)
        return self.k * (q.norm(dim=-1) - (0.2 + EPS))


class Blobs:
    """A sphere and a small floater sphere (two pieces)."""

    def __init__(self, k: float = 1.0):
        self.k = k

    def sdf(self, x):
        a = (x * torch.tensor([1.0, 1.5, 1.0], device=x.device)).norm(dim=-1) - (0.45 + EPS)
        b = (x - torch.tensor([0.75, 0.0, 0.0], device=x.device)).norm(dim=-1) - (0.1 + EPS)
        return self.k * torch.minimum(a, b)


SCENE = SimpleNamespace(bounds=SimpleNamespace(center=np.array([0.1, -0.2, 0.3]), radius=2.0))


def _assert_same_points(a: np.ndarray, b: np.ndarray, tol: float) -> None:
    """Equal point sets (up to order and ``tol``)."""
    from scipy.spatial import cKDTree

    assert len(a) == len(b)
    assert cKDTree(b).query(a)[0].max() < tol and cKDTree(a).query(b)[0].max() < tol


def _signed_volume(v: np.ndarray, f: np.ndarray) -> float:
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6)


def _chamfer(a: np.ndarray, b: np.ndarray) -> float:
    from scipy.spatial import cKDTree

    return 0.5 * (cKDTree(b).query(a)[0].mean() + cKDTree(a).query(b)[0].mean())


@pytest.mark.parametrize("field,res", [(Torus(), 41), (Blobs(), 64), (Blobs(), 97)])
def test_sparse_evaluation_gives_the_dense_mesh(field, res):
    dense = mesh_from_grid(sdf_grid(field, res, "cpu"), SCENE.bounds.center, 2.0, keep_fraction=0)
    sparse = extract_mesh_arrays(field, SCENE, res, "cpu", mc="skimage", keep_fraction=0)
    assert len(sparse.faces) == len(dense.faces) > 100
    _assert_same_points(sparse.vertices, np.asarray(dense.vertices), 1e-5)
    st = sparse.stats
    assert st["points"] < st["dense_points"] and st["cells"] > 0 and st["mc"] == "skimage"


def test_sparse_evaluation_at_the_grid_edge():
    """An odd resolution (the last blocks are cut by the grid's edge) and a surface leaving the box."""
    class Corner:
        def sdf(self, x):
            return (x - 0.8).norm(dim=-1) - (0.35 + EPS)

    sc = SimpleNamespace(bounds=SimpleNamespace(center=np.zeros(3), radius=1.0))
    for res in (66, 51):
        dense = mesh_from_grid(sdf_grid(Corner(), res, "cpu", bound="box"), np.zeros(3), 1.0, keep_fraction=0)
        sparse = extract_mesh_arrays(Corner(), sc, res, "cpu", bound="box", mc="skimage", keep_fraction=0)
        assert len(sparse.faces) == len(dense.faces) > 50
        _assert_same_points(sparse.vertices, np.asarray(dense.vertices), 1e-5)


def test_sparse_evaluation_follows_a_steep_field():
    """|grad| = 20 breaks the assumed bound (2): blocks given opposite signs and neighbour activation
    still find the whole surface (a piece smaller than a block could be missed: not tested)."""
    field = Torus(k=20.0)
    dense = mesh_from_grid(sdf_grid(field, 64, "cpu"), np.zeros(3), 1.0, keep_fraction=0)
    m = extract_mesh_arrays(field, SimpleNamespace(bounds=SimpleNamespace(center=np.zeros(3), radius=1.0)), 64,
                            "cpu", mc="skimage", keep_fraction=0)
    assert len(m.faces) == len(dense.faces)


def test_sparse_respects_allowed_cells_like_dense():
    r = 8
    lin = (torch.arange(r) + 0.5) * (2.0 / r) - 1.0
    z, y, x = torch.meshgrid(lin, lin, lin, indexing="ij")
    allowed = ((x < 0.6) & (y > -0.6)).reshape(-1)                # the floater and a slab are unseen
    field = Blobs()
    dense = mesh_from_grid(sdf_grid(field, 57, "cpu", allowed=allowed), np.zeros(3), 1.0, keep_fraction=0)
    sparse = extract_mesh_arrays(field, SimpleNamespace(bounds=SimpleNamespace(center=np.zeros(3), radius=1.0)),
                                 57, "cpu", allowed=allowed, mc="skimage", keep_fraction=0)
    assert len(sparse.faces) == len(dense.faces)
    _assert_same_points(sparse.vertices, np.asarray(dense.vertices), 1e-5)
    assert sparse.vertices[:, 0].max() < 0.6 and sparse.vertices[:, 1].min() > -0.6 - 1e-6


@pytest.mark.parametrize("device", DEVICES)
def test_warp_marching_cubes_matches_skimage(device):
    field = Blobs()
    a = extract_mesh_arrays(field, SCENE, 80, device, mc="warp", keep_fraction=0)
    b = extract_mesh_arrays(field, SCENE, 80, device, mc="skimage", keep_fraction=0)
    assert a.stats["mc"] == "warp" and b.stats["mc"] == "skimage"
    voxel = 2.0 * 2.0 / 79
    assert _chamfer(a.vertices, b.vertices) < 1e-3 * voxel       # the same vertices (one per crossed edge)
    assert abs(len(a.faces) - len(b.faces)) <= 0.02 * len(b.faces)
    assert len(a.vertices) == len(b.vertices)
    va, vb = _signed_volume(a.vertices, a.faces), _signed_volume(b.vertices, b.faces)
    assert va > 0 and vb > 0 and abs(va - vb) < 1e-3 * vb        # same orientation: outward normals
    tm = a.to_trimesh()
    assert tm.is_watertight and tm.is_winding_consistent


@pytest.mark.parametrize("op", [marching_cubes, marching_cubes_torch])
def test_marching_cubes_ops_only_triangulate_the_listed_cells(op):
    n = 24
    x = torch.linspace(-1, 1, n)
    X, Y, Z = torch.meshgrid(x, x, x, indexing="ij")
    grid = (torch.sqrt(X ** 2 + Y ** 2 + Z ** 2) - (0.6 + EPS)).contiguous()
    h = 2.0 / (n - 1)
    neg = (grid < 0).to(torch.uint8)
    cnt = sum(neg[a:n - 1 + a, b:n - 1 + b, c:n - 1 + c] for a in (0, 1) for b in (0, 1) for c in (0, 1))
    cells = ((cnt > 0) & (cnt < 8)).nonzero().to(torch.int32)
    v, f = op(grid, cells, -1.0, h)
    assert f.dtype == torch.int64 and v.dtype == torch.float32 and int(f.max()) < v.shape[0]
    r = v.norm(dim=-1)
    assert float((r - 0.6).abs().max()) < h                       # on the sphere, in grid coordinates
    half = cells[cells[:, 0] < n // 2]                             # only the cells with x < 0
    v2, f2 = op(grid, half, -1.0, h)
    assert 0 < f2.shape[0] < f.shape[0] and float(v2[:, 0].max()) <= 0.0 + h
    v3, f3 = op(grid, cells[:0], -1.0, h)
    assert v3.shape == (0, 3) and f3.shape == (0, 3)
    with pytest.raises(ValueError, match="out of range"):
        op(grid, cells + n, -1.0, h)
    with pytest.raises(ValueError, match="int32"):
        op(grid, cells.float(), -1.0, h)
    with pytest.raises(ValueError, match="float32"):
        op(grid.double(), cells, -1.0, h)


def test_components_like_trimesh_split():
    field = Blobs()
    m = extract_mesh_arrays(field, SCENE, 64, "cpu", keep_fraction=0)
    tm = m.to_trimesh()
    parts = tm.split(only_watertight=False)
    assert len(parts) == 2
    big = max(len(p.faces) for p in parts)
    for frac in (0.02, 0.5):
        v, f = keep_large_components(m.vertices, m.faces, frac)
        want = sum(len(p.faces) for p in parts if len(p.faces) >= frac * big)
        assert len(f) == want and f.max() == len(v) - 1
    kept = extract_mesh_arrays(field, SCENE, 64, "cpu", keep_fraction=0.5)
    assert len(kept.faces) == big and np.linalg.norm(kept.vertices - SCENE.bounds.center, axis=1).max() < 1.0


@pytest.mark.parametrize("device", DEVICES)
def test_torch_components_match_scipy(device):
    from fastneus.export.mesh import component_labels, keep_large_components_torch

    m = extract_mesh_arrays(Blobs(), SCENE, 48, "cpu", keep_fraction=0)
    extra = np.array([[0, 1, 2]]) + len(m.vertices)                 # a third piece: one triangle
    v = np.concatenate([m.vertices, np.eye(3)])
    f = np.concatenate([m.faces, extra])
    vt, ft = torch.from_numpy(v).to(device), torch.from_numpy(f).to(device)
    lab = component_labels(ft, len(v))
    assert len(torch.unique(lab)) == 3 and bool((lab <= torch.arange(len(v), device=device)).all())
    for frac in (0.0, 1e-4, 0.02, 0.5):
        a_v, a_f = keep_large_components(v, f, frac)
        b_v, b_f = keep_large_components_torch(vt, ft, frac)
        np.testing.assert_array_equal(b_f.cpu().numpy(), a_f)
        np.testing.assert_array_equal(b_v.cpu().numpy(), a_v)


def test_no_surface_gives_an_empty_mesh_and_a_valid_ply(tmp_path):
    class Empty:
        def sdf(self, x):
            return x.norm(dim=-1) + 0.3

    m = extract_mesh_arrays(Empty(), SCENE, 32, "cpu")
    assert m.vertices.shape == (0, 3) and m.faces.shape == (0, 3)
    import trimesh

    save_mesh(m, tmp_path / "e.ply")
    assert len(trimesh.load(tmp_path / "e.ply", force="mesh").faces) == 0
    assert len(mesh_from_grid(sdf_grid(Empty(), 16, "cpu"), np.zeros(3), 1.0).faces) == 0


def test_ply_writer_round_trip_and_obj(tmp_path):
    import trimesh

    m = extract_mesh_arrays(Torus(), SCENE, 33, "cpu")
    save_mesh(m, tmp_path / "m.ply")
    back = trimesh.load(tmp_path / "m.ply", force="mesh", process=False)
    np.testing.assert_allclose(back.vertices, m.vertices, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(back.faces, m.faces)
    assert back.volume > 0                                          # outward normals survive the file
    save_mesh(m.to_trimesh(), tmp_path / "m2.ply")                  # a trimesh goes through the same writer
    assert (tmp_path / "m2.ply").read_bytes() == (tmp_path / "m.ply").read_bytes()
    save_mesh(m, tmp_path / "m.obj")
    assert len(trimesh.load(tmp_path / "m.obj", force="mesh").faces) == len(m.faces)
    for fmt in ("stl", "off"):  # other tools' formats through trimesh: the same faces come back
        save_mesh(m, tmp_path / f"m.{fmt}")
        back = trimesh.load(tmp_path / f"m.{fmt}", force="mesh", process=False)
        assert len(back.faces) == len(m.faces) and abs(back.volume - m.to_trimesh().volume) < 1e-6 * max(1, back.volume)
    with pytest.raises(FastneusError, match=r"\.ply, \.obj, \.glb, \.stl or \.off"):
        save_mesh(m, tmp_path / "m.xyz")
    with pytest.raises(FastneusError, match="out of range"):
        write_ply(tmp_path / "bad.ply", m.vertices, m.faces + len(m.vertices))
    assert not (tmp_path / "bad.ply").exists()


def test_extract_mesh_returns_a_trimesh():
    tm = extract_mesh(Torus(), SCENE, 33, "cpu")
    assert len(tm.faces) > 100 and tm.volume > 0


@pytest.mark.parametrize("kw,msg", [
    (dict(resolution=1), "resolution"), (dict(resolution="64"), "resolution"), (dict(resolution=True), "resolution"),
    (dict(bound="cube"), "bound"), (dict(block=0), "block"), (dict(lipschitz=-1.0), "lipschitz"),
    (dict(lipschitz=float("nan")), "lipschitz"), (dict(mc="marching"), "marching-cubes"),
    (dict(allowed=torch.ones(10, dtype=torch.bool)), "allowed"), (dict(allowed=torch.ones(8)), "allowed"),
])
def test_bad_arguments_raise_one_clear_error(kw, msg):
    args = dict(resolution=32, bound="sphere")
    args.update(kw)
    res = args.pop("resolution")
    with pytest.raises(FastneusError, match=msg):
        extract_mesh_arrays(Torus(), SCENE, res, "cpu", **args)


def test_bad_field_output_is_reported():
    class Wrong:
        def sdf(self, x):
            return x  # [N, 3] instead of [N]

    with pytest.raises(FastneusError, match="field.sdf returned shape"):
        sparse_sdf(Wrong(), 16, "cpu")


def test_surface_cells_are_the_sign_changes():
    sp = sparse_sdf(Torus(), 33, "cpu")
    cells = surface_cells(sp)
    d = torch.from_numpy(sdf_grid(Torus(), 33, "cpu"))
    neg = (d < 0).to(torch.uint8)
    cnt = sum(neg[a:32 + a, b:32 + b, c:32 + c] for a in (0, 1) for b in (0, 1) for c in (0, 1))
    want = set(map(tuple, ((cnt > 0) & (cnt < 8)).nonzero().tolist()))
    assert set(map(tuple, cells.tolist())) == want and cells.dtype == torch.int32


def test_mesh_arrays_to_trimesh_keeps_arrays():
    m = MeshArrays(np.zeros((3, 3)), np.array([[0, 1, 2]]))
    assert len(m.to_trimesh().faces) == 1


def test_marching_cubes_kernels_can_be_preloaded():
    """prime() loads Warp's marching-cubes module on CUDA before training: the op names it."""
    from fastneus.kernels import prepare_kernels
    from fastneus.kernels.mesh import warp_modules

    mods = warp_modules()
    assert mods and all("sparse_marching_cubes" in m.name for m in mods)
    rep: dict = {}
    s = prepare_kernels("cpu", ops=("marching_cubes",), report=rep)
    assert s >= 0 and isinstance(rep["compiled"], list)


def test_an_empty_mesh_converts_and_evaluates():
    """A run that lost its surface (it happened on a GPU matrix cell) gets an empty mesh and
    infinite errors, not a trimesh traceback from empty normals/colours."""
    import numpy as np

    from fastneus.export.mesh import MeshArrays

    m = MeshArrays(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64), normals=np.zeros((0, 3), np.float32),
                   colors=np.zeros((0, 3), np.uint8))
    tm = m.to_trimesh()
    assert len(tm.vertices) == 0 and len(tm.faces) == 0
