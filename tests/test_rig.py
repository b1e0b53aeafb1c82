"""Real-rig corrections (fastneus/train/rig.py): SE(3) maths, exact undo of a known perturbation,
pose recovery through the render kernel (both backends) and the camera rays, trainer hook."""
from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
import torch

from fastneus.config import load_config
from fastneus.eval.poses import pose_errors
from fastneus.geometry.se3 import rigid_inverse_torch, se3_matrix, so3_exp
from fastneus.synth.perturb import perturb_scene
from fastneus.train.rig import Rig
from fastneus.train.rays import RayBank, build_projection
from test_formats import make_scene


def test_so3_exp_matches_rodrigues_and_gradcheck():
    rng = np.random.default_rng()
    om = rng.normal(size=(5, 3)) * np.array([[1e-5], [1e-3], [0.1], [1.0], [2.5]])
    R = so3_exp(torch.tensor(om)).numpy()
    for o, r in zip(om, R):
        assert np.allclose(r, cv2.Rodrigues(o)[0], atol=1e-12)
    xi = torch.tensor(rng.normal(size=(3, 6)) * 0.3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: se3_matrix(x, 1.7), (xi,))
    xi0 = torch.zeros(2, 6, dtype=torch.float64, requires_grad=True)  # smooth through the identity
    assert torch.autograd.gradcheck(lambda x: se3_matrix(x, 1.0), (xi0,))
    T = se3_matrix(xi.detach(), 2.0)
    assert torch.allclose(rigid_inverse_torch(T) @ T, torch.eye(4, dtype=torch.float64).expand(3, 4, 4), atol=1e-12)


def _undo_xi(E: np.ndarray, radius: float) -> np.ndarray:
    """xi with se3_matrix(xi, radius) == inverse(E)."""
    Ei = np.linalg.inv(E)
    return np.r_[cv2.Rodrigues(Ei[:3, :3])[0].ravel(), Ei[:3, 3] / radius]


def _cfg(**kw):
    return load_config("cpu-quick", ["pose_refine=true"] + [f"{k}={v}" for k, v in kw.items()])


def test_corrections_undo_a_known_perturbation_exactly(tmp_path):
    truth = make_scene(tmp_path / "s", n=3, n_proj=2, seed=4)
    pert = perturb_scene(truth, deg=2.0, metres=0.05, seed=1)
    frames = [0, 1, 2]
    bank, proj = RayBank(pert, frames, "cpu"), build_projection(pert, frames, "cpu")
    rig = Rig(pert, frames, bank, proj, _cfg().rig, "cpu")
    with torch.no_grad():  # set the corrections that undo the perturbation
        for v in (1, 2):
            E = np.linalg.inv(truth.cam_to_world(v)) @ pert.cam_to_world(v)
            rig.cam_xi[v] = torch.tensor(_undo_xi(E, rig.radius))
        for k, pid in enumerate(rig.proj_ids):
            E = np.linalg.inv(truth.projectors[pid].proj_to_cam) @ pert.projectors[pid].proj_to_cam
            rig.proj_xi[k] = torch.tensor(_undo_xi(E, rig.radius))
    b_true = RayBank(truth, frames, "cpu")
    g = torch.Generator().manual_seed(0)
    batch = bank.sample(64, g)
    fixed = rig.rays(batch)
    u = (batch["pix"] - bank.offset[batch["fidx"].long()]) % bank.wh[batch["fidx"].long(), 0]
    v = (batch["pix"] - bank.offset[batch["fidx"].long()]) // bank.wh[batch["fidx"].long(), 0]
    o_t, d_t = b_true.rays(batch["fidx"].long(), u.float() + 0.5, v.float() + 0.5)
    torch.testing.assert_close(fixed["origins"], o_t, atol=2e-6, rtol=0)
    torch.testing.assert_close(fixed["dirs"], d_t, atol=2e-6, rtol=0)
    assert not torch.allclose(batch["dirs"], d_t, atol=1e-3)  # the perturbation was real
    torch.testing.assert_close(rig.projection().W, build_projection(truth, frames, "cpu").W, atol=2e-5, rtol=0)
    # and the refined scene (and the whole-scene copy used for renders) carries the true poses
    errs = pose_errors(rig.refined_scene(), truth, frames)
    assert max(errs.values()) < 1e-4, errs
    errs = pose_errors(rig.eval_scene(), truth, frames)
    assert max(errs.values()) < 1e-4, errs
    assert pose_errors(pert, truth, frames)["cam_rot_deg_mean"] == pytest.approx(2.0, rel=1e-6)


def test_scale_gauge_is_the_global_scale_mode_and_is_removed(tmp_path):
    """Corrections along ``rig.gauge`` scale the rig about the anchor camera (every other camera
    centre and every projector position by the same factor, rotations unchanged): the one move
    that leaves all images unchanged. ``fix_gauge`` removes exactly that component."""
    scene = make_scene(tmp_path / "s", n=4, n_proj=2, seed=int(np.random.default_rng().integers(1 << 30)))
    frames = [0, 1, 2, 3]
    rig = Rig(scene, frames, RayBank(scene, frames, "cpu"), build_projection(scene, frames, "cpu"), _cfg().rig, "cpu")
    g = rig.gauge.double()
    assert g.shape == (3 * (len(rig.view_ids) + len(rig.proj_ids)),) and abs(float(g.norm()) - 1) < 1e-6
    eps = 1e-4
    V = len(rig.view_ids)
    with torch.no_grad():
        rig.cam_xi[:, 3:] = (eps * g[: 3 * V]).view(V, 3).float()
        rig.proj_xi[:, 3:] = (eps * g[3 * V:]).view(-1, 3).float()
    ref = rig.refined_poses()
    c0 = scene.cam_to_world(0)[:3, 3]
    ratios = []
    for a, i in enumerate(frames[1:], 1):
        c, c_new = scene.cam_to_world(i)[:3, 3], ref["cam_to_world"][a][:3, 3]
        assert np.allclose(ref["cam_to_world"][a][:3, :3], scene.cam_to_world(i)[:3, :3], atol=1e-6)
        d, r = c_new - c, c - c0
        lam = float(d @ r / (r @ r))
        assert np.linalg.norm(d - lam * r) < 1e-3 * np.linalg.norm(d), "camera moved off the scale direction"
        ratios.append(lam)
    for pid in rig.proj_ids:
        t, t_new = scene.projectors[pid].proj_to_cam[:3, 3], ref["projectors"][pid]["proj_to_cam"][:3, 3]
        ratios.append(float((t_new - t) @ t / (t @ t)))
    assert min(ratios) > 0 and max(ratios) / min(ratios) < 1 + 1e-3, ratios  # one common factor
    # fix_gauge: a pure scale move vanishes; a random correction keeps everything but that part
    rig.fix_gauge()
    assert float(rig.cam_xi.detach().abs().max()) < 1e-9 and float(rig.proj_xi.detach().abs().max()) < 1e-9
    with torch.no_grad():
        rig.cam_xi.normal_(0, 1e-2)
        rig.proj_xi.normal_(0, 1e-2)
    before = torch.cat([rig.cam_xi[:, 3:].reshape(-1), rig.proj_xi[:, 3:].reshape(-1)]).detach().double()
    rot = (rig.cam_xi[:, :3].clone(), rig.proj_xi[:, :3].clone())
    rig.fix_gauge()
    after = torch.cat([rig.cam_xi[:, 3:].reshape(-1), rig.proj_xi[:, 3:].reshape(-1)]).detach().double()
    assert abs(float(after.detach() @ g)) < 1e-6
    torch.testing.assert_close(after, before - (before @ g) * g, atol=1e-6, rtol=0)
    assert torch.equal(rot[0], rig.cam_xi[:, :3]) and torch.equal(rot[1], rig.proj_xi[:, :3])
    off = Rig(scene, frames, RayBank(scene, frames, "cpu"), build_projection(scene, frames, "cpu"),
              _cfg(pose_fix_scale="false").rig, "cpu")
    assert off.gauge is None


def _smooth_pattern(h, w, seed):
    rng = np.random.default_rng(seed)
    p = cv2.GaussianBlur(rng.uniform(0, 255, (h, w, 3)).astype(np.float32), (0, 0), 3)
    p = (p - p.min()) / (p.max() - p.min()) * 255
    return p.astype(np.uint8)


@pytest.mark.parametrize("backend", ["warp", "torch"])
def test_projector_pose_recovered_through_render_kernel(tmp_path, backend):
    """Colours of lit points pin the projector pose: gradients of the render op w.r.t. its
    projector transform drive the learned correction back to the truth."""
    from fastneus.kernels import get_op

    truth = make_scene(tmp_path / "s", n=1, n_proj=1, seed=6)
    cv2.imwrite(str(tmp_path / "s" / "patterns" / "q0.png"), _smooth_pattern(24, 32, 1))
    pert = perturb_scene(truth, deg=1.5, metres=0.03, seed=2)
    bank, proj = RayBank(pert, [0], "cpu"), build_projection(pert, [0], "cpu")
    rig = Rig(pert, [0], bank, proj, _cfg().rig, "cpu")
    proj_true = build_projection(truth, [0], "cpu")
    # points the projector lights (inside its image), one fully opaque sample per ray
    rng = np.random.default_rng(3)
    pts = torch.tensor(rng.uniform(-0.6, 0.6, (4000, 3)), dtype=torch.float32)
    Wt = proj_true.W[0, 0]
    X = pts @ Wt[:, :3].T + Wt[:, 3]
    px = X @ proj_true.K[0, 0].T
    px = px[:, :2] / X[:, 2:]
    ok = (X[:, 2] > 0) & (px[:, 0] > 4) & (px[:, 0] < 28) & (px[:, 1] > 4) & (px[:, 1] < 20)
    pos = pts[ok][:600].contiguous()
    n = pos.shape[0]
    dirs = torch.nn.functional.normalize(torch.randn(n, 3), dim=-1)
    kw = dict(sdf=torch.zeros(n), grad=-dirs, color=torch.full((n, 3), 0.5), pos=pos, t0=torch.zeros(n),
              t1=torch.full((n,), 0.1), ray_index=torch.arange(n, dtype=torch.int32),
              offsets=torch.arange(n, dtype=torch.int32), counts=torch.ones(n, dtype=torch.int32), dirs=dirs,
              ray_frame=torch.zeros(n, dtype=torch.int32), inv_s=torch.tensor([1e3]), cos_anneal=1.0,
              i_r=torch.tensor([0.4]), i_b=torch.tensor([0.1]))
    render = get_op("render_pattern", backend)
    target = render(proj_K=proj_true.K, proj_W=proj_true.W, proj_pattern=proj_true.pattern,
                    patterns=proj_true.store, **kw)["color"]
    before = pose_errors(rig.refined_scene(), truth, [0])
    opt = torch.optim.Adam([rig.proj_xi], lr=1e-2)
    for it in range(400):
        for g in opt.param_groups:
            g["lr"] = 1e-2 * (0.5 * (1 + math.cos(math.pi * it / 400)) * 0.95 + 0.05)
        p = rig.projection()
        out = render(proj_K=p.K, proj_W=p.W, proj_pattern=p.pattern, patterns=p.store, **kw)["color"]
        loss = ((out - target) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    after = pose_errors(rig.refined_scene(), truth, [0])
    assert after["proj_rot_deg_max"] < 0.1 * before["proj_rot_deg_max"], (before, after)
    assert after["proj_trans_mm_max"] < 0.2 * before["proj_trans_mm_max"], (before, after)


def test_camera_pose_recovered_through_rays(tmp_path):
    """A textured plane seen through the corrected rays pins a moved camera (planar pose)."""
    truth = make_scene(tmp_path / "s", n=2, n_proj=1, seed=8, size=(48, 32))
    pert = perturb_scene(truth, deg=1.0, metres=0.02, seed=5)
    bank = RayBank(pert, [0, 1], "cpu")
    rig = Rig(pert, [0, 1], bank, build_projection(pert, [0, 1], "cpu"), _cfg().rig, "cpu")
    b_true = RayBank(truth, [0, 1], "cpu")
    o_t, d_t, _ = b_true.image_rays(1)
    nrm = torch.nn.functional.normalize(o_t[0] + torch.tensor([0.3, -0.2, 0.1]), dim=0)  # plane through 0
    freq = torch.tensor(np.random.default_rng(0).normal(size=(4, 3)) * 6.0, dtype=torch.float32)

    def tex(o, d):
        t = -(o @ nrm) / (d @ nrm)
        P = o + t[:, None] * d
        return torch.sin(P @ freq.T).sum(-1)

    target = tex(o_t, d_t)
    o_p, d_p, _ = bank.image_rays(1)
    fidx = torch.ones(o_p.shape[0], dtype=torch.int32)
    before = pose_errors(rig.refined_scene(), truth, [0, 1])
    opt = torch.optim.Adam([rig.cam_xi], lr=1e-2)
    for it in range(300):
        for g in opt.param_groups:
            g["lr"] = 1e-2 * (0.5 * (1 + math.cos(math.pi * it / 300)) * 0.95 + 0.05)
        b = rig.rays({"fidx": fidx, "origins": o_p, "dirs": d_p})
        loss = ((tex(b["origins"], b["dirs"]) - target) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    after = pose_errors(rig.refined_scene(), truth, [0, 1])
    assert after["cam_rot_deg_max"] == pose_errors(rig.refined_scene(), truth, [0, 1], anchor=False)["cam_rot_deg_max"]
    assert after["cam_rot_deg_max"] < 0.1 * before["cam_rot_deg_max"], (before, after)
    assert after["cam_trans_mm_max"] < 0.1 * before["cam_trans_mm_max"], (before, after)


def test_trainer_learns_corrections_after_warmup_and_resumes(tmp_path):
    from fastneus.synth.render import synthesize
    from fastneus.train.trainer import Trainer, load_checkpoint

    synthesize(tmp_path / "sc", shape="sphere", views=3, size=(24, 24), seed=0, device="cpu", progress=False,
               contact_sheet=False, proj_size=(64, 48))
    from fastneus.data import Scene

    scene = perturb_scene(Scene.load(tmp_path / "sc"), 0.5, 0.01, seed=0)
    over = ["steps=12", "pose_warmup_frac=0.5", "occ_resolution=16", "target_samples=2048", "init_rays=128",
            "max_rays=256", "log_every=4", "save_every=100"]
    tr = Trainer(scene, load_config("cpu-quick", over + ["pose_refine=true"]), tmp_path / "run", "cpu")
    for _ in range(6):
        tr.train_step()
    assert float(tr.rig.proj_xi.detach().abs().max()) == 0.0  # frozen during the warm-up
    tr.fit()
    assert float(tr.rig.proj_xi.abs().max()) > 0 and float(tr.rig.cam_xi[1:].abs().max()) > 0
    rig = json.loads((tmp_path / "run" / "rig.json").read_text())["pose"]
    assert rig["anchor_view"] == 0 and rig["camera_correction_deg"][0] == 0.0 and len(rig["cam_to_world"]) == 3
    st = load_checkpoint(tmp_path / "run")
    tr2 = Trainer(scene, load_config("cpu-quick", over + ["pose_refine=true", "steps=14"]), tmp_path / "run", "cpu")
    tr2.load_state(st)
    assert torch.equal(tr2.rig.proj_xi, tr.rig.proj_xi)
    tr2.fit()
    assert tr2.step == 14
    off = Trainer(scene, load_config("cpu-quick", over), tmp_path / "run_off", "cpu")
    assert off.rig.param_groups() == [] and off.rig.projection() is off.proj


# --------------------------------------------------------------------------- projector blur
def test_blur_kernel_recovered_through_project_op(tmp_path):
    """Light from a defocused projector (a known 5x5 Gaussian) pins the learned kernel."""
    from fastneus.kernels import get_op
    from fastneus.light.patterns import make_pattern
    from fastneus.synth.render import blur_kernel

    scene = make_scene(tmp_path / "s", n=1, n_proj=1, seed=6)
    cv2.imwrite(str(tmp_path / "s" / "patterns" / "q0.png"),
                make_pattern("crosslaser", 32, 24, seed=1, count=4, line_width=1)[0][:, :, ::-1])
    bank, proj = RayBank(scene, [0], "cpu"), build_projection(scene, [0], "cpu")
    rig = Rig(scene, [0], bank, proj, load_config("cpu-quick", ["projector_blur=5"]).rig, "cpu")
    rng = np.random.default_rng(3)
    pos = torch.tensor(rng.uniform(-0.6, 0.6, (3000, 3)), dtype=torch.float32)
    n = pos.shape[0]
    idx = torch.arange(n, dtype=torch.int32)
    args = (pos, idx, idx, torch.ones(n, dtype=torch.int32), torch.zeros(n, dtype=torch.int32), proj.K, proj.W,
            proj.pattern, proj.store)
    op = get_op("project_pattern", "warp")
    true_k = torch.tensor(blur_kernel(0.9), dtype=torch.float32).reshape(1, 25)
    target = op(*args, true_k)
    assert float(target.max()) > 0.05
    err0 = float((rig.blur_kernels() - true_k).abs().sum().detach())
    opt = torch.optim.Adam([rig.blur_raw], lr=1e-2)
    for _ in range(300):
        loss = ((op(*args, rig.blur_kernels()) - target) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    err = float((rig.blur_kernels() - true_k).abs().sum().detach())
    assert err < 0.1 * err0, (err0, err)


def test_blur_identity_at_init_and_learned_in_training(tmp_path):
    from fastneus.data import Scene
    from fastneus.field.renderer import render_rays
    from fastneus.synth.render import synthesize
    from fastneus.train.trainer import Trainer

    synthesize(tmp_path / "sc", shape="sphere", views=2, size=(24, 24), seed=0, device="cpu", progress=False,
               contact_sheet=False, proj_size=(64, 48), projector_blur=1.0)
    scene = Scene.load(tmp_path / "sc")
    assert np.isclose(np.sum(scene.meta["projector_blur_kernel"]), 1.0)
    over = ["steps=10", "blur_warmup_frac=0.5", "occ_resolution=16", "target_samples=2048", "init_rays=128",
            "max_rays=256", "log_every=5", "save_every=100", "projector_blur=5"]
    tr = Trainer(scene, load_config("cpu-quick", over), tmp_path / "run", "cpu")
    tr.grid.update(tr.field.sdf, 0.0, tr.cfg.rays.march_step, warmup=True)
    b = tr.bank.sample(128, torch.Generator().manual_seed(0))
    kw = dict(i_r=torch.tensor([0.4]), i_b=torch.tensor([0.1]), cos_anneal=1.0, jitter=False)
    with torch.no_grad():
        a = render_rays(tr.field, tr.grid.bits, tr.grid.resolution, tr.rig.projection(), b["origins"], b["dirs"],
                        b["fidx"], tr.cfg, **kw)
        c = render_rays(tr.field, tr.grid.bits, tr.grid.resolution, tr.proj, b["origins"], b["dirs"], b["fidx"],
                        tr.cfg, **kw)
    assert tr.rig.projection().blur is not None and tr.proj.blur is None
    torch.testing.assert_close(a["color"], c["color"], atol=1e-6, rtol=1e-5)
    assert float((a["color"] - a["texture"]).abs().max()) > 0  # the pattern reaches the surface
    tr.fit()
    k = json.loads((tmp_path / "run" / "rig.json").read_text())["blur"]
    assert k["size"] == 5 and abs(np.sum(k["kernels"]["proj0"]) - 1) < 1e-6
    assert float((tr.rig.blur_kernels().detach() - torch.eye(25)[12]).abs().max()) > 0  # learned after the warm-up
    assert torch.allclose(tr.rig.blur_kernels().sum(-1), torch.ones(1))


def test_synth_projector_blur_changes_only_the_lit_pixels(tmp_path):
    from fastneus.data import Scene
    from fastneus.errors import FastneusError
    from fastneus.synth.render import synthesize

    kw = dict(shape="sphere", views=1, size=(32, 32), seed=0, device="cpu", progress=False, contact_sheet=False,
              proj_size=(64, 48), noise=0.0)
    synthesize(tmp_path / "a", **kw)
    synthesize(tmp_path / "b", projector_blur=1.2, **kw)
    a, b = Scene.load(tmp_path / "a"), Scene.load(tmp_path / "b")
    ia, ib = a.image(0).astype(int), b.image(0).astype(int)
    assert np.abs(ia - ib).max() > 10 and np.array_equal(a.gt_clean(0), b.gt_clean(0))
    with pytest.raises(FastneusError, match="blur"):
        synthesize(tmp_path / "c", projector_blur=-1, **kw)


def test_config_keys_validate_and_accept_exponent_floats():
    from fastneus.errors import FastneusError

    c = load_config("cpu-quick", ["lr_pose=3e-3", "projector_blur=5", "medium=off", "pose_warmup_frac=0.2"])
    assert c.rig.lr_pose == 3e-3 and c.rig.projector_blur == 5 and c.rig.medium == "off"
    for bad, key in (("projector_blur=4", "projector_blur"), ("medium=oil", "medium"),
                     ("pose_warmup_frac=1.5", "pose_warmup_frac"), ("lr_blur=0", "lr_blur"), ("lr_pose=x", "lr_pose")):
        with pytest.raises(FastneusError) as e:
            load_config("cpu-quick", [bad])
        assert e.value.field == f"rig.{key}"


def test_pose_errors_image_shift_tells_a_turn_from_an_orbit(tmp_path):
    """cam_shift_px: a turn of the camera about its own centre moves every image point by about
    f * angle; an orbit about the scene centre (the same turn plus the sideways move that keeps
    the centre in place) moves them far less, although its rotation and translation errors are
    larger. Exact poses score 0."""
    import copy

    truth = make_scene(tmp_path / "s", n=2, n_proj=1, seed=3, size=(64, 48))
    th = math.radians(0.5)
    turn = np.eye(4)
    turn[:3, :3] = cv2.Rodrigues(np.array([0.0, th, 0.0]))[0]
    T = truth.cam_to_world(1)
    c_cam = (np.linalg.inv(T) @ np.r_[truth.bounds.center, 1.0])[:3]  # scene centre in camera 1
    orbit = np.eye(4)
    orbit[:3, :3] = turn[:3, :3]
    orbit[:3, 3] = c_cam - turn[:3, :3] @ c_cam
    errs = {}
    for name, E in (("turn", turn), ("orbit", orbit)):
        s = copy.deepcopy(truth)
        s.frames[1].cam_to_world = T @ E
        errs[name] = pose_errors(s, truth, [0, 1])
    f = truth.frame_camera(1).K[0, 0]
    assert errs["turn"]["cam_shift_px_mean"] == pytest.approx(f * th, rel=0.1)
    assert errs["orbit"]["cam_shift_px_mean"] < 0.5 * errs["turn"]["cam_shift_px_mean"]
    assert errs["orbit"]["cam_trans_mm_max"] > errs["turn"]["cam_trans_mm_max"]
    assert errs["orbit"]["cam_rot_deg_max"] == pytest.approx(0.5, rel=1e-6)
    assert pose_errors(truth, truth, [0, 1])["cam_shift_px_max"] == 0.0
