"""Laser-plane projectors: the laser_light op vs its twin (forward, gradients, gradcheck), a
closed form, scene.json round trip and errors, synth, the pattern approximation, import-calib
plane files, and training on a laser scene."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from fastneus.data import Scene
from fastneus.data.model import LaserPlane
from fastneus.errors import FastneusError
from fastneus.kernels.project import laser_light, laser_light_torch, pack_planes
from test_render import DEVICES, _close, _seed, make_inputs


def _planes(P, L, gen, sharp=False):
    out = []
    for k in range(P):
        if k == 1:  # a pattern projector in the same scene: no planes
            out.append(None)
            continue
        pl = []
        for _ in range(L):
            n = torch.randn(3, generator=gen, dtype=torch.float64)
            pl.append(LaserPlane(normal=(n / n.norm()).numpy(), offset=float(torch.rand(1, generator=gen) - 0.5),
                                 colour=torch.rand(3, generator=gen, dtype=torch.float64).numpy(),
                                 width=float(0.2 + 0.5 * torch.rand(1, generator=gen)),
                                 fan_deg=float(60 + 100 * torch.rand(1, generator=gen)),
                                 axis=np.array([0.0, 0.0, 1.0])))
        out.append(pl)
    return out


def _args(inp, on):
    return dict(pos=inp["pos"], ray_index=inp["ray_index"], offsets=inp["offsets"], counts=inp["counts"],
                ray_frame=inp["ray_frame"], proj_W=inp["proj_W"], laser_on=on)


def _fan_margin_ok(inp, planes64, on, margin=1e-4):
    """No sample within ``margin`` of a fan edge (where the hard cut makes gradients jump)."""
    pos, W = inp["pos"].double(), inp["proj_W"].double()
    planes64 = planes64.to(pos.device)  # callers pass CPU planes; the inputs may be on CUDA
    on = on.to(pos.device)
    fr = inp["ray_frame"].long()[inp["ray_index"].long()]
    for k in range(W.shape[1]):
        X = torch.einsum("sij,sj->si", W[fr, k, :, :3], pos) + W[fr, k, :, 3]
        for l in range(planes64.shape[1]):
            n, u, c = planes64[k, l, 0:3], planes64[k, l, 4:7], planes64[k, l, 7]
            if planes64[k, l, 11] <= 0:
                continue
            v = X - (X @ n)[:, None] * n
            cosang = (v @ u) / v.norm(dim=-1)
            if ((cosang - c).abs() < margin).any():
                return False
    return True


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("size", [(0, 2, 2, 8), (1, 2, 3, 1), (64, 3, 3, 24), (257, 2, 4, 32)])
def test_forward_backward_vs_twin(size, device):
    for _ in range(20):
        seed = _seed()
        R, F, P, m = size
        inp = make_inputs(R, F, P, m, seed, device=device)
        gen = torch.Generator().manual_seed(seed)
        planes = pack_planes(_planes(P, 3, gen), device)
        on = (torch.rand(F, P, generator=gen) < 0.8).to(torch.int32).to(device)
        on[:, 1 % P] = 0 if P > 1 else on[:, 0]
        if _fan_margin_ok(inp, planes.double().cpu(), on):
            break
    pos = inp["pos"].clone().requires_grad_(True)
    W = inp["proj_W"].clone().requires_grad_(True)
    q = laser_light(**dict(_args(inp, on), pos=pos, proj_W=W), planes=planes)
    pos64 = inp["pos"].double().requires_grad_(True)
    W64 = inp["proj_W"].double().requires_grad_(True)
    q64 = laser_light_torch(**dict(_args(inp, on), pos=pos64, proj_W=W64), planes=planes.double())
    _close(q, q64, 1e-5, f"q (seed {seed})")
    if q.shape[0] > 50:
        assert q.abs().max() > 1e-3
    up = torch.randn(q.shape, generator=gen, dtype=torch.float64).to(device)
    ga = torch.autograd.grad((q * up.float()).sum(), [pos, W], allow_unused=True)
    gb = torch.autograd.grad((q64 * up).sum(), [pos64, W64], allow_unused=True)
    for name, a, r in zip(("pos", "proj_W"), ga, gb):
        a = torch.zeros_like(r) if a is None else a
        r = torch.zeros_like(a) if r is None else r
        _close(a, r, 2e-4, f"d{name} (seed {seed})")


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("size,stripes", [((5, 2, 2, 0), 7), ((1, 2, 3, 1), 7), ((300, 2, 3, 40), 7),
                                          ((200, 1, 2, 60), 61)],
                         ids=lambda c: "R{}F{}P{}m{}".format(*c) if isinstance(c, tuple) else str(c))
def test_striped_gradients_vs_twin(size, stripes, device, monkeypatch):
    """The per-sample backward's striped proj_W gradient equals the float64 twin's: rows wrap
    many times, S is no multiple of the row count, rays without samples are interleaved."""
    from fastneus.kernels import project

    R, F, P, m = size
    monkeypatch.setattr(project, "STRIPES", {"cpu": stripes, "cuda": stripes})
    for _ in range(50):
        seed = _seed()
        inp = make_inputs(R, F, P, m, seed, device=device)
        gen = torch.Generator().manual_seed(seed)
        planes = pack_planes(_planes(P, 3, gen), device)
        on = torch.ones(F, P, dtype=torch.int32, device=device)
        S = inp["pos"].shape[0]
        if (S <= 1 or S % stripes != 0) and _fan_margin_ok(inp, planes.double().cpu(), on):
            break
    pos = inp["pos"].clone().requires_grad_(True)
    W = inp["proj_W"].clone().requires_grad_(True)
    q = laser_light(**dict(_args(inp, on), pos=pos, proj_W=W), planes=planes)
    pos64 = inp["pos"].double().requires_grad_(True)
    W64 = inp["proj_W"].double().requires_grad_(True)
    q64 = laser_light_torch(**dict(_args(inp, on), pos=pos64, proj_W=W64), planes=planes.double())
    _close(q, q64, 1e-5, f"q (seed {seed})")
    up = torch.randn(q.shape, generator=gen, dtype=torch.float64).to(device)
    ga = torch.autograd.grad((q * up.float()).sum(), [pos, W], allow_unused=True)
    gb = torch.autograd.grad((q64 * up).sum(), [pos64, W64], allow_unused=True)
    for name, a, r in zip(("pos", "proj_W"), ga, gb):
        a = torch.zeros_like(r) if a is None else a
        r = torch.zeros_like(a) if r is None else r
        _close(a, r, 2e-4, f"d{name}, {stripes} stripes, S={S} (seed {seed})")
    if S > 50:
        assert ga[1].abs().max() > 0, f"seed {seed}"


def test_gradcheck_twin():
    for _ in range(20):
        seed = _seed()
        inp = make_inputs(6, 2, 2, 4, seed, dtype=torch.float64)
        gen = torch.Generator().manual_seed(seed)
        planes = pack_planes(_planes(2, 2, gen)).double()
        on = torch.ones(2, 2, dtype=torch.int32)
        if _fan_margin_ok(inp, planes, on, 1e-3):
            break
    pos = inp["pos"].clone().requires_grad_(True)
    W = inp["proj_W"].clone().requires_grad_(True)
    f = lambda p, w: laser_light_torch(**dict(_args(inp, on), pos=p, proj_W=w), planes=planes)  # noqa: E731
    assert torch.autograd.gradcheck(f, (pos, W), eps=1e-7, atol=1e-6), f"seed {seed}"


@pytest.mark.parametrize("op", [laser_light, laser_light_torch])
def test_closed_form(op):
    """A point at distance t from a plane (inside the fan) gets colour * exp(-t^2 / 2 sigma^2),
    sigma = FWHM / 2.355; outside the fan, or with the laser off, nothing."""
    pl = LaserPlane(normal=np.array([1.0, 0, 0]), offset=0.1, colour=np.array([1.0, 0.5, 0]), width=0.2, fan_deg=60)
    planes = pack_planes([[pl]])
    sig = 0.2 / (2 * math.sqrt(2 * math.log(2)))
    # projector frame = normalised space shifted: X = p + (0, 0, 1)
    W = torch.tensor([[[[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 1]]]])
    pts = torch.tensor([[0.1, 0.0, 0.0], [0.15, 0.2, 0.5], [0.0, 0.0, 1.0], [0.1, 1.5, 0.0], [0.1, 0.0, -2.0]])
    n = pts.shape[0]
    idx = torch.arange(n, dtype=torch.int32)
    one = torch.ones(n, dtype=torch.int32)
    zero = torch.zeros(n, dtype=torch.int32)
    q = op(pts, idx, idx, one, zero, W, torch.ones(1, 1, dtype=torch.int32), planes)
    d = torch.tensor([0.0, 0.05, -0.1])
    expect = torch.exp(-0.5 * d ** 2 / sig ** 2)[:, None] * torch.tensor([1.0, 0.5, 0.0])
    torch.testing.assert_close(q[:3], expect.float(), atol=1e-6, rtol=1e-5)
    assert float(q[3:].abs().max()) == 0.0  # 56 deg and 180 deg from the fan axis
    off = op(pts, idx, idx, one, zero, W, torch.zeros(1, 1, dtype=torch.int32), planes)
    assert float(off.abs().max()) == 0.0


def test_scene_json_round_trip_and_errors(tmp_path):
    from test_formats import make_scene

    make_scene(tmp_path / "s", n=2, n_proj=1, seed=1)
    d = json.loads((tmp_path / "s" / "scene.json").read_text())
    d["projectors"]["L"] = {"kind": "laser", "proj_to_cam": np.eye(4).tolist(),
                            "planes": [{"normal": [2, 0, -0.2], "offset": 0.01, "colour": [1, 0, 0], "width": 0.002,
                                        "fan_deg": 50}]}
    d["frames"][0]["projectors"]["L"] = {"on": True}
    d["frames"][1]["projectors"]["L"] = {"on": False}
    (tmp_path / "s" / "scene.json").write_text(json.dumps(d))
    s = Scene.load(tmp_path / "s")
    pj = s.projectors["L"]
    assert pj.kind == "laser" and np.isclose(np.linalg.norm(pj.planes[0].normal), 1) and pj.planes[0].fan_deg == 50
    assert s.active_lasers(0) == ["L"] and s.active_lasers(1) == [] and s.active_projectors(0) == [("p0", "q0")]
    s.save(tmp_path / "s2")
    s2 = Scene.load(tmp_path / "s2")
    assert np.allclose(s2.projectors["L"].planes[0].normal, pj.planes[0].normal) and s2.active_lasers(1) == []
    from fastneus.train.rays import build_projection

    pr = build_projection(s, [0, 1], "cpu")
    assert pr.laser_on.tolist() == [[0, 1], [0, 0]] and pr.planes.shape == (2, 1, 12)
    assert int(pr.pattern[0, 1]) == -1 and float(pr.W[0, 1].abs().sum()) > 0
    for edit, fld in [
        (lambda d: d["projectors"]["L"]["planes"][0].__setitem__("normal", [0, 0, 0]), "projectors.L.planes[0].normal"),
        (lambda d: d["projectors"]["L"]["planes"][0].__setitem__("width", -1), "projectors.L.planes[0].width"),
        (lambda d: d["projectors"]["L"]["planes"][0].__setitem__("fan_deg", 270), "projectors.L.planes[0].fan_deg"),
        (lambda d: d["projectors"]["L"].__setitem__("kind", "beam"), "projectors.L.kind"),
        (lambda d: d["projectors"]["L"].__setitem__("port", {"normal": [0, 0, 1], "distance": 0.02}),
         "projectors.L.port"),
        (lambda d: d["frames"][0]["projectors"]["L"].__setitem__("pattern", "q0"), "frames[0].projectors.L.pattern"),
    ]:
        dd = json.loads(json.dumps(d))
        edit(dd)
        with pytest.raises(FastneusError) as e:
            Scene.from_dict(dd, tmp_path / "s")
        assert e.value.field == fld, str(e.value)


def test_synth_laser_planes_match_the_crosslaser_pattern(tmp_path):
    """The exact model and the pattern image agree where the approximation is exact (a surface
    at the reference depth): synth's laser-plane images ~ its crosslaser images."""
    from fastneus.light.lasers import pattern_approximation
    from fastneus.synth.render import synthesize

    kw = dict(shape="sphere", views=1, size=(48, 48), seed=0, device="cpu", progress=False, contact_sheet=False,
              proj_size=(96, 72), noise=0.0, cam_distance=4.0)
    synthesize(tmp_path / "pat", **kw)
    synthesize(tmp_path / "las", laser_planes=True, **kw)
    a, b = Scene.load(tmp_path / "pat"), Scene.load(tmp_path / "las")
    assert b.projectors["proj0"].kind == "laser" and not b.patterns and b.active_lasers(0) == list(b.projectors)
    ia, ib = a.image(0).astype(float), b.image(0).astype(float)
    lit_a, lit_b = ia.max(-1) > a.gt_clean(0).max(-1) + 30, ib.max(-1) > b.gt_clean(0).max(-1) + 30
    assert lit_b.sum() > 20
    assert (lit_a & lit_b).sum() > 0.4 * lit_b.sum()  # the same lines, up to their profile
    approx = pattern_approximation(b, tmp_path / "approx", 96, 72, 60.0, 4.0)
    assert approx.projectors["proj0"].kind == "pattern" and approx.active_projectors(0)
    assert np.array_equal(approx.image(0), b.image(0))
    pat = approx.pattern_image(approx.active_projectors(0)[0][1])
    assert pat[..., 0].max() > 200 and pat[..., 1].max() > 200


def test_train_on_laser_scene_and_pose_refine(tmp_path):
    from fastneus.config import load_config
    from fastneus.synth.render import synthesize
    from fastneus.train.trainer import Trainer

    synthesize(tmp_path / "las", shape="sphere", views=2, size=(24, 24), seed=0, device="cpu", progress=False,
               contact_sheet=False, laser_planes=True)
    scene = Scene.load(tmp_path / "las")
    over = ["occ_resolution=16", "target_samples=2048", "init_rays=128", "max_rays=256", "log_every=1",
            "save_every=100", "pose_refine=true"]
    for backend, steps, warm in (("warp", 6, 0.3), ("torch", 1, 0.0)):  # the torch twins are slow on CPU
        cfg = load_config("cpu-quick", over + [f"backend={backend}", f"steps={steps}", f"pose_warmup_frac={warm}"])
        tr = Trainer(scene, cfg, tmp_path / backend, "cpu")
        tr.fit()
        assert tr.step == steps and tr.skipped == 0
        assert float(tr.rig.proj_xi.detach().abs().max()) > 0  # the laser planes' pose gets gradients


def test_import_calib_laser_plane_file(tmp_path):
    import cv2

    from fastneus.formats.opencv_calib import make_scene_from_calibration
    from fastneus.light.lasers import read_laser_planes

    f = tmp_path / "planes.yaml"
    f.write_text("units: mm\nlasers:\n  red:\n    planes:\n"
                 "      - {normal: [1, 0, -0.1], offset: 5.0, colour: [1, 0, 0], width: 1.5, fan_deg: 45}\n"
                 "  green:\n    proj_to_cam: [[1,0,0,100],[0,1,0,0],[0,0,1,0],[0,0,0,1]]\n    planes:\n"
                 "      - {normal: [0, 1, 0], width: 2, fan_deg: 60, colour: [0, 1, 0]}\n")
    lasers = read_laser_planes(f)
    assert lasers["red"].planes[0].offset == pytest.approx(0.005) and lasers["red"].planes[0].width == pytest.approx(0.0015)
    assert lasers["green"].proj_to_cam[0, 3] == pytest.approx(0.1)
    (tmp_path / "img").mkdir()
    for i in range(2):
        cv2.imwrite(str(tmp_path / "img" / f"{i}.png"), np.zeros((16, 24, 3), np.uint8))
    poses = {"frames": [{"cam_to_world": np.eye(4).tolist()}, {"cam_to_world": np.eye(4).tolist()}],
             "bounds": {"center": [0, 0, 1], "radius": 0.5}}
    (tmp_path / "poses.json").write_text(json.dumps(poses))
    from fastneus.data.model import Camera

    cam = Camera(id="cam0", K=np.array([[20.0, 0, 12], [0, 20, 8], [0, 0, 1]]), width=24, height=16)
    s = make_scene_from_calibration((cam, None), sorted((tmp_path / "img").iterdir()), [], tmp_path / "poses.json",
                                    tmp_path / "out", lasers=lasers)
    assert sorted(s.projectors) == ["green", "red"] and s.active_lasers(1) == ["red", "green"]
    f.write_text("lasers:\n  red:\n    planes: []\n")
    with pytest.raises(FastneusError) as e:
        read_laser_planes(f)
    assert e.value.field == "lasers.red.planes"


def test_import_calib_cli_camera_only_with_laser_planes(tmp_path, capsys):
    import cv2

    from fastneus.cli import main
    from test_formats import _write_fs

    _write_fs(tmp_path / "cam.yml", {"cam_K": np.array([[30.0, 0, 11.5], [0, 30, 7.5], [0, 0, 1]]),
                                     "cam_kc": np.zeros((1, 5))})
    (tmp_path / "imgs").mkdir()
    for i in range(2):
        cv2.imwrite(str(tmp_path / "imgs" / f"{i:03d}.png"), np.zeros((16, 24, 3), np.uint8))
    from fastneus.data import look_at

    poses = [look_at(e, [0, 0, 0]).tolist() for e in ([1.0, 0, 0.5], [0, 1.0, 0.5])]
    (tmp_path / "poses.json").write_text(json.dumps({"frames": [{"cam_to_world": T} for T in poses]}))
    (tmp_path / "planes.yaml").write_text("lasers:\n  L:\n    planes:\n      - {normal: [1, 0, 0], width: 2, "
                                          "fan_deg: 40, colour: [1, 0, 0]}\n")
    base = ["import-calib", str(tmp_path / "cam.yml"), "--images", str(tmp_path / "imgs"), "--poses",
            str(tmp_path / "poses.json")]
    assert main(base + ["--out", str(tmp_path / "none")]) == 2
    err = capsys.readouterr().err.strip()
    assert "--laser-planes" in err and len(err.splitlines()) == 1
    assert main(base + ["--laser-planes", str(tmp_path / "planes.yaml"), "--out", str(tmp_path / "s")]) == 0
    s = Scene.load(tmp_path / "s")
    assert list(s.projectors) == ["L"] and s.projectors["L"].planes[0].width == pytest.approx(0.002)
    assert s.cameras["cam0"].K[0, 2] == pytest.approx(12.0)  # OpenCV -> fastneus pixel centres
