"""Projection helpers, mesh ray casting and the synthetic renderer (image formation, GT, CLI)."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
import trimesh

from fastneus.cli import main
from fastneus.data import Scene, look_at
from fastneus.kernels.raycast import raycast_mesh, raycast_mesh_torch
from fastneus.geometry.projection import Z_MIN, pixel_rays, project_points, sample_pattern
from fastneus.synth.render import synthesize


def _random_pose(rng) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    T = np.eye(4)
    T[:3, :3] = q
    T[:3, 3] = rng.normal(size=3)
    return T


# --------------------------------------------------------------------------- projection
def test_project_points_matches_opencv():
    rng = np.random.default_rng()
    K = np.array([[900.0, 0.0, 512.2], [0, 880.0, 380.7], [0, 0, 1]])  # cv2 ignores skew
    w2p = _random_pose(rng)
    # points in front of the device: sample in device coords, map back to world
    Xp = np.c_[rng.uniform(-2, 2, (500, 2)), rng.uniform(1, 6, 500)]
    p2w = np.linalg.inv(w2p)
    pts = Xp @ p2w[:3, :3].T + p2w[:3, 3]
    px, z = project_points(torch.tensor(pts), torch.tensor(K), torch.tensor(w2p))
    rvec, _ = cv2.Rodrigues(w2p[:3, :3])
    ref, _ = cv2.projectPoints(pts, rvec, w2p[:3, 3], K, None)
    assert px.dtype == torch.float64
    np.testing.assert_allclose(px.numpy(), ref[:, 0], atol=1e-4)
    np.testing.assert_allclose(z.numpy(), Xp[:, 2], atol=1e-9)
    px32, _ = project_points(torch.tensor(pts, dtype=torch.float32), K, w2p)
    assert px32.dtype == torch.float32


def test_sample_pattern_matches_grid_sample():
    g = torch.Generator().manual_seed(int(np.random.default_rng().integers(1 << 30)))
    pat = torch.randint(0, 256, (30, 40, 3), dtype=torch.uint8, generator=g)
    px = torch.rand(1000, 2, generator=g, dtype=torch.float64) * torch.tensor([46.0, 36.0], dtype=torch.float64) - 3
    valid = torch.rand(1000, generator=g) > 0.2
    out = sample_pattern(pat, px, valid)
    grid = torch.stack([px[:, 0] / 40 * 2 - 1, px[:, 1] / 30 * 2 - 1], dim=-1).view(1, 1, -1, 2)
    ref = torch.nn.functional.grid_sample(pat.permute(2, 0, 1)[None].double() / 255, grid, mode="bilinear",
                                          padding_mode="zeros", align_corners=False)[0, :, 0].T
    ref = ref * valid[:, None]
    torch.testing.assert_close(out, ref, atol=1e-9, rtol=0)
    # pixel (j, i) centred at (j + 0.5, i + 0.5): exact value there
    c = sample_pattern(pat, torch.tensor([[7.5, 4.5]]))
    torch.testing.assert_close(c[0], pat[4, 7].float() / 255)


def test_pixel_rays_hit_projected_points():
    rng = np.random.default_rng()
    K = np.array([[100.0, 0, 32], [0, 110.0, 24], [0, 0, 1]])
    c2w = _random_pose(rng)
    S = np.diag([2.0, 2.0, 2.0, 1.0])
    S[:3, 3] = [0.3, -0.1, 0.2]
    Xc = np.c_[rng.uniform(-1, 1, (50, 2)), rng.uniform(1, 5, 50)]
    pts = Xc @ c2w[:3, :3].T + c2w[:3, 3]
    uv, _ = project_points(torch.tensor(pts), K, np.linalg.inv(c2w))
    o, d = pixel_rays(torch.tensor(K), torch.tensor(c2w), uv, torch.tensor(S))
    pn = (torch.tensor(pts) - torch.tensor(S[:3, 3])) / 2.0  # points in normalised space
    t = ((pn - o) * d).sum(1)
    torch.testing.assert_close(o + t[:, None] * d, pn, atol=1e-9, rtol=0)
    torch.testing.assert_close(d.norm(dim=1), torch.ones(50, dtype=torch.float64))


# --------------------------------------------------------------------------- ray casting
def test_raycast_warp_matches_torch():
    rng = np.random.default_rng()
    m = trimesh.creation.torus(major_radius=0.6, minor_radius=0.25, major_sections=24, minor_sections=12)
    m.apply_transform(_random_pose(rng) @ np.diag([1, 1, 1, 1.0]))
    V = torch.tensor(m.vertices, dtype=torch.float32)
    F = torch.tensor(m.faces, dtype=torch.int32)
    c = torch.tensor(m.centroid, dtype=torch.float32)
    o = c + torch.tensor(rng.normal(size=(3000, 3)), dtype=torch.float32) * 2.0
    target = c + torch.tensor(rng.normal(size=(3000, 3)), dtype=torch.float32) * 0.4
    d = target - o
    d = d / d.norm(dim=1, keepdim=True)
    max_t = torch.tensor(rng.uniform(0.5, 6.0, 3000), dtype=torch.float32)
    t_w, f_w, n_w = raycast_mesh(V, F, o, d, max_t)
    t_t, f_t, n_t = raycast_mesh_torch(V, F, o, d, max_t)
    hit = f_t >= 0
    assert 300 < int(hit.sum()) < 2900
    assert (f_w == f_t).float().mean() > 0.998  # ties on shared edges may pick either face
    same = (f_w == f_t) & hit
    torch.testing.assert_close(t_w[same], t_t[same], atol=1e-4, rtol=1e-5)
    torch.testing.assert_close(n_w[same], n_t[same], atol=1e-5, rtol=0)
    assert torch.isinf(t_w[f_w < 0]).all() and (n_w[f_w < 0] == 0).all()
    assert ((n_w[same] * d[same]).sum(1) <= 0).all()  # normals face against the ray


# --------------------------------------------------------------------------- synthesis
def _world_points(scene: Scene, i: int):
    """World points of the object pixels of frame i from its GT depth: (P [N,3], (rows, cols))."""
    depth = scene.gt_depth(i).astype(np.float64)
    cam = scene.frame_camera(i)
    rows, cols = np.nonzero(depth > 0)
    uv1 = np.c_[cols + 0.5, rows + 0.5, np.ones(len(rows))]
    Xc = (uv1 @ np.linalg.inv(cam.K).T) * depth[rows, cols][:, None]
    T = scene.cam_to_world(i)
    return Xc @ T[:3, :3].T + T[:3, 3], (rows, cols)


@pytest.fixture(scope="module")
def sphere_scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("sphere")
    return synthesize(out / "s", shape="sphere", views=2, size=(96, 96), noise=0.0, seed=1, progress=False)


def test_sphere_depth_matches_analytic(sphere_scene):
    s = sphere_scene
    R = np.linalg.norm(trimesh.load(s.path(s.gt_mesh)).vertices, axis=1).max()
    assert abs(R - 1.0) < 1e-6 and np.allclose(s.bounds.center, 0, atol=1e-6) and abs(s.bounds.radius - 1.1) < 1e-6
    for i in range(len(s.frames)):
        cam, T = s.frame_camera(i), s.cam_to_world(i)
        jj, ii = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
        dc = np.c_[jj.ravel() + 0.5, ii.ravel() + 0.5, np.ones(jj.size)] @ np.linalg.inv(cam.K).T  # z = 1
        d = dc @ T[:3, :3].T
        o = T[:3, 3]
        a, b, c = (d * d).sum(1), 2 * d @ o, o @ o - R * R
        disc = b * b - 4 * a * c
        hit = disc > 0
        t = (-b - np.sqrt(np.where(hit, disc, 0))) / (2 * a)  # t along d with d_cam.z = 1: z-depth
        depth = s.gt_depth(i).ravel()
        mask = s.mask(i).ravel() > 0.5
        P = o + t[:, None] * d
        cos = np.abs(((P / R) * d).sum(1)) / np.linalg.norm(d, axis=1)
        core = hit & (cos > 0.3)
        assert core.sum() > 500
        assert mask[core].all() and (depth[~hit] == 0).all()
        rel = np.abs(depth[core] - t[core]) / t[core]
        assert rel.max() < 1e-4, rel.max()


def test_pattern_formula_on_lit_pixels(sphere_scene):
    s = sphere_scene
    il = s.illumination
    assert il.known and (il.i_r, il.i_b, il.ambient) == (0.4, 0.1, 1.0)
    n_lit = 0
    for i in range(len(s.frames)):
        P, (rows, cols) = _world_points(s, i)
        img = s.image(i)[rows, cols].astype(np.float64)
        D = s.gt_clean(i)[rows, cols].astype(np.float64) / 255  # noise 0: round(D * 255)
        n = P / np.linalg.norm(P, axis=1, keepdims=True)  # analytic sphere normal
        expect = D.copy()
        ambiguous = np.zeros(len(P), bool)
        lit = np.zeros(len(P), bool)
        for pid, qid in s.active_projectors(i):
            pj = s.projectors[pid]
            px, z = project_points(torch.tensor(P), pj.K, s.world_to_proj(i, pid))
            Q = sample_pattern(torch.from_numpy(s.pattern_image(qid)), px, z > Z_MIN).numpy()
            C = s.proj_to_world(i, pid)[:3, 3]
            to_c = (C - P) / np.linalg.norm(C - P, axis=1, keepdims=True)
            cosp = (n * to_c).sum(1)
            V = (cosp > 0).astype(np.float64)  # a convex sphere shadows only its back side
            ambiguous |= (np.abs(cosp) < 0.05) & (Q.max(1) > 0)
            lit |= (Q.max(1) > 0.05) & (V > 0)
            expect += (il.i_r * D + il.i_b) * Q * V[:, None]
        ok = ~ambiguous
        err = np.abs(img[ok] - np.clip(expect[ok], 0, 1) * 255)
        assert err.max() <= 1.5, err.max()
        n_lit += int((lit & ok).sum())
    assert n_lit > 50, n_lit


def test_shadowed_point_gets_no_pattern(tmp_path):
    """A ball between the rig and a wall: wall points whose path to the projector crosses the
    ball must show no pattern; other wall points are lit."""
    ball_c, ball_r = np.array([0.0, -1.5, 0.0]), 0.3
    ball = trimesh.creation.icosphere(subdivisions=4, radius=ball_r)
    ball.apply_translation(ball_c)
    wall = trimesh.creation.box((3.2, 0.05, 3.2))
    wall.apply_translation((0, 0.5, 0))
    mesh = trimesh.util.concatenate([ball, wall])
    pose = look_at([0, -4, 0], [0, 0, 0], up=(0, 0, 1))
    white = np.full((96, 128, 3), 255, np.uint8)
    s = synthesize(tmp_path / "shadow", mesh=mesh, poses=[pose], normalise=False, size=(96, 96), pattern=white,
                   proj_size=(128, 96), baselines=(1.2,), noise=0.0, ambient=0.5, albedo="uniform", progress=False)
    P, (rows, cols) = _world_points(s, 0)
    on_wall = P[:, 1] > 0.45
    C = s.proj_to_world(0, "proj0")[:3, 3]
    seg = C - P
    tt = np.clip(((ball_c - P) * seg).sum(1) / (seg * seg).sum(1), 0, 1)
    dist = np.linalg.norm(P + tt[:, None] * seg - ball_c, axis=1)  # segment-to-ball-centre distance
    shadow = on_wall & (dist < ball_r - 0.02)
    sunny = on_wall & (dist > ball_r + 0.02)
    img = s.image(0)[rows, cols].astype(int)
    clean = s.gt_clean(0)[rows, cols].astype(int)
    assert shadow.sum() > 20 and sunny.sum() > 20
    assert np.abs(img[shadow] - clean[shadow]).max() <= 1
    assert (img[sunny] - clean[sunny]).min() >= 20


def test_graycode_sequence_and_determinism(tmp_path):
    s = synthesize(tmp_path / "g", shape="torus", views=1, size=(32, 24), pattern="graycode", progress=False)
    assert len(s.frames) == 20 and s.views() == {0: list(range(20))}
    assert len(s.projectors) == 1 and len(s.patterns) == 20
    assert len({f.projectors["proj0"].pattern for f in s.frames}) == 20
    s2 = synthesize(tmp_path / "g2", shape="torus", views=1, size=(32, 24), pattern="graycode", progress=False)
    np.testing.assert_array_equal(s.image(5), s2.image(5))


def test_cli_synth(tmp_path, capsys):
    out = tmp_path / "tmp"
    rc = main(["synth", "--shape", "sphere", "--views", "2", "--size", "48x48", "--out", str(out), "--device", "cpu"])
    assert rc == 0
    s = Scene.load(out)
    assert len(s.frames) == 2 and len(s.projectors) == 4
    assert s.image(0).shape == (48, 48, 3) and s.mask(1).shape == (48, 48)
    assert s.gt_depth(0).dtype == np.float32 and s.gt_normal(0).shape == (48, 48, 3)
    assert (out / "contact_sheet.png").is_file() and (out / "gt_mesh.ply").is_file()
    n = s.gt_normal(0)[s.mask(0) > 0.5]
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=0.02)
    # rerun into the same folder replaces it; a foreign non-empty folder is refused with one line
    assert main(["synth", "--shape", "sphere", "--views", "1", "--size", "48x48", "--out", str(out)]) == 0
    assert len(Scene.load(out).frames) == 1 and not (out / "images/001.png").exists()
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "keep.txt").write_text("x")
    capsys.readouterr()
    assert main(["synth", "--shape", "sphere", "--views", "1", "--out", str(tmp_path / "other")]) == 2
    assert "--out" in capsys.readouterr().err


def test_cli_synth_mesh_file(tmp_path):
    box = trimesh.creation.box((3.0, 1.0, 0.5))
    box.apply_translation((5.0, 0, 0))
    box.export(tmp_path / "box.obj")
    out = tmp_path / "boxscene"
    assert main(["synth", "--mesh", str(tmp_path / "box.obj"), "--views", "1", "--size", "40x30",
                 "--pattern", "colorline", "--albedo", "checker", "--out", str(out)]) == 0
    s = Scene.load(out)
    src = s.meta["source"]
    assert src["mesh"].endswith("box.obj") and abs(src["scale"] * np.linalg.norm([1.5, 0.5, 0.25]) - 1) < 1e-6
    v = trimesh.load(s.path(s.gt_mesh)).vertices
    np.testing.assert_allclose(v.mean(axis=0), 0, atol=1e-6)  # centred, bounding radius 1
    assert abs(np.linalg.norm(v, axis=1).max() - 1) < 1e-6 and s.mask(0).sum() > 20
