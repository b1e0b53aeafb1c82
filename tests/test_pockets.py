"""scripts/pockets.py: pockets in an SDF grid, which views see into them, and the grid file."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))

N = 41


def _coords(n: int = N):
    lin = np.linspace(-1.0, 1.0, n)
    return np.meshgrid(lin, lin, lin, indexing="ij")


def _ball_with_cavity(channel: bool) -> np.ndarray:
    """A solid ball (radius 0.6) with an empty cavity (radius 0.2) at its centre and, optionally, a
    one-node-wide channel from the cavity to the outside along +x."""
    x, y, z = _coords()
    r = np.sqrt(x * x + y * y + z * z)
    g = np.maximum(r - 0.6, 0.2 - r)          # solid shell between 0.2 and 0.6
    if channel:
        h = 2.0 / (N - 1)
        tube = (x > 0) & (np.abs(y) < 0.5 * h) & (np.abs(z) < 0.5 * h)
        g = np.where(tube, np.abs(g) + h, g)   # one row of nodes set empty
    return g.astype(np.float32)


def test_an_enclosed_void_is_a_pocket_at_radius_zero():
    from pockets import narrow_pockets

    g = _ball_with_cavity(channel=False)
    pk = narrow_pockets(g, 0)
    x, y, z = _coords()
    cavity = np.sqrt(x * x + y * y + z * z) < 0.2
    assert pk[N // 2, N // 2, N // 2] and pk[cavity].all()
    assert not pk[np.sqrt(x * x + y * y + z * z) > 0.6].any()      # the outside is reached


def test_a_cavity_behind_a_narrow_opening_is_filled_only_once_the_closing_spans_it():
    from pockets import narrow_pockets

    g = _ball_with_cavity(channel=True)
    assert not narrow_pockets(g, 0).any()                           # open to the outside
    pk = narrow_pockets(g, 1)                                       # a one-node opening closes at r = 1
    x, y, z = _coords()
    assert pk[N // 2, N // 2, N // 2] and pk[np.sqrt(x * x + y * y + z * z) < 0.2].all()
    assert not pk[(g < 0)].any()                                    # the solid itself is never marked
    # a ball wider than the cavity closes it whole; the cavity is still found (far from the outside)
    pk3 = narrow_pockets(g, 5)
    assert pk3[N // 2, N // 2, N // 2] and not pk3[(g < 0)].any()


def test_a_wide_open_concavity_is_not_a_pocket():
    from pockets import narrow_pockets

    x, y, z = _coords()
    ball = np.sqrt(x * x + y * y + z * z) - 0.6
    bowl = 0.35 - np.sqrt((x - 0.55) ** 2 + y * y + z * z)         # a dent with a ~0.6-wide mouth
    g = np.maximum(ball, bowl).astype(np.float32)
    for r in (0, 1, 2):
        assert not narrow_pockets(g, r).any(), r


def test_depth_maps_and_view_counts_see_the_front_not_the_inside(tmp_path):
    from pockets import depth_maps, view_counts

    from fastneus.data import Scene
    from fastneus.synth.render import synthesize

    import trimesh

    synthesize(tmp_path / "sc", shape="sphere", views=3, size=(24, 24), pattern="crosslaser", illum="normal", seed=0,
               device="cpu", proj_size=(64, 48), progress=False, contact_sheet=False)
    scene = Scene.load(tmp_path / "sc")
    gt = trimesh.load(scene.path(scene.gt_mesh), force="mesh", process=False)
    S = scene.normalisation()
    c_w = gt.bounds.mean(0)
    rad_w = 0.5 * float((gt.bounds[1] - gt.bounds[0]).max())
    c_n, rad_n = (c_w - S[:3, 3]) / S[0, 0], rad_w / S[0, 0]
    n = 48
    lin = np.linspace(-1.0, 1.0, n)
    x, y, z = np.meshgrid(lin, lin, lin, indexing="ij")
    g = (np.sqrt((x - c_n[0]) ** 2 + (y - c_n[1]) ** 2 + (z - c_n[2]) ** 2) - rad_n).astype(np.float32)
    frames = list(range(len(scene.frames)))
    depth = depth_maps(g, scene, frames, steps=256)
    # the sphere's centre pixel of view 0 meets the surface at (distance to the centre - radius) in camera z
    cam0 = scene.cam_to_world(0)[:3, 3]
    dist = float(np.linalg.norm(cam0 - c_w))
    assert np.isfinite(depth[0]).any() and np.isinf(depth[0]).any()  # the sphere and the backdrop around it
    near = float(depth[0][np.isfinite(depth[0])].min())
    assert abs(near - (dist - rad_w)) < 0.05 * rad_w + 2 * (2 * S[0, 0] / (n - 1))
    toward = (cam0 - c_w) / dist
    pts = np.stack([c_w, c_w + 1.1 * rad_w * toward])                 # the centre; just in front of the surface
    framed, seen = view_counts(pts, scene, frames, depth, margin=2 * S[0, 0] / (n - 1))
    assert framed[0] == len(frames) and seen[0] == 0                  # inside: framed by all, seen by none
    assert seen[1] >= 1                                               # in front of view 0's surface: seen
    # the grid's own mesh against the GT sphere: within about a grid cell
    from pockets import analyse

    res = analyse(scene, g, frames, closings=(0,), views=False)
    cell_mm = 2 * S[0, 0] / (n - 1) * 1000
    assert res["fill"][0]["filled_nodes"] == 0 and res["fill"][0]["chamfer_sym_mm"] < cell_mm


def test_the_grid_file_round_trips_and_refuses_pickles(tmp_path):
    from pockets import CLIP, load_grid, save_grid

    g = _ball_with_cavity(channel=False)
    save_grid(tmp_path / "g.npz", g, [0, 2, 5])
    back, frames = load_grid(tmp_path / "g.npz")
    assert frames == [0, 2, 5]
    assert np.abs(back - np.clip(g, -CLIP, CLIP)).max() < 2e-6
    # a link at the destination is replaced, not written through
    other = tmp_path / "user.txt"
    other.write_text("the user's file")
    (tmp_path / "link.npz").symlink_to(other)
    save_grid(tmp_path / "link.npz", g, [1])
    assert other.read_text() == "the user's file" and not (tmp_path / "link.npz").is_symlink()
    assert load_grid(tmp_path / "link.npz")[1] == [1]
    np.savez(tmp_path / "evil.npz", sdf=np.array([{"a": 1}], dtype=object), frames=np.zeros(1))
    with pytest.raises(ValueError):
        load_grid(tmp_path / "evil.npz")
