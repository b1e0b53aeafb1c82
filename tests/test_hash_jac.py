"""hash_encode_jac (features + spatial Jacobian) and the analytic SDF gradient built on it.

Inputs are random and fresh each run (the seed is printed in failure messages). Tests that
differentiate in u keep the points away from cell faces at every level (the encoding is
only piecewise smooth there); Warp-vs-twin comparisons also cover the clamp and the u = 0 /
u = 1 edges, where both use the same float32 cell.
"""
from __future__ import annotations

import copy
import os

import pytest
import torch

from fastneus.kernels import get_op
from fastneus.kernels.hashgrid import (
    HashGridConfig,
    hash_encode,
    hash_encode_jac,
    hash_encode_jac_torch,
    hash_encode_torch,
)

# dense (coarse) and hashed (fine) levels, F = 2, 4 and 8: the configs of the hash_encode tests
from test_hashgrid import CFG_IDS, CONFIGS, DEVICES  # noqa: E402


def _seed() -> int:
    return int.from_bytes(os.urandom(4), "little")


def _table(cfg, gen, dtype=torch.float32, device="cpu"):
    # O(1) values so relative tolerances mean something (the real init is +-1e-4)
    t = torch.rand(cfg.levels, cfg.table_size, cfg.features, generator=gen, dtype=torch.float64) * 2 - 1
    return t.to(dtype=dtype, device=device).contiguous()


def _points(n, gen, dtype=torch.float32, device="cpu"):
    """Random u in [0, 1]^3, with a few outside the box (clamp) and the u = 0 / u = 1 corners."""
    u = torch.rand(n, 3, generator=gen, dtype=torch.float64)
    if n >= 8:
        u[:4] = u[:4] * 1.4 - 0.2
        u[4, :] = 1.0
        u[5, :] = 0.0
        u[6, 0], u[6, 1], u[6, 2] = -0.3, 0.5, 1.2  # one axis clamped low, one high
    return u.to(dtype=dtype, device=device).contiguous()


def _interior_points(n, cfg, gen, margin=0.05, dtype=torch.float64, lo=0.0, hi=1.0):
    """u strictly inside [lo, hi]^3 and at least ``margin`` (in cells) from every cell face at every level."""
    cand = lo + (hi - lo) * torch.rand(64 * n + 256, 3, generator=gen, dtype=torch.float64)
    ok = torch.ones(cand.shape[0], dtype=torch.bool)
    for r in cfg.resolutions():
        fr = torch.frac(cand * r)
        ok &= ((fr > margin) & (fr < 1 - margin)).all(dim=1)
    u = cand[ok][:n]
    assert u.shape[0] == n, "not enough interior points; widen the candidate pool"
    return u.to(dtype).contiguous()


def _rel(a, b):
    return ((a - b).abs().max() / b.abs().max().clamp_min(1e-12)).item() if b.numel() else 0.0


# ----------------------------------------------------------------------------- (a) forward
@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("cfg", CONFIGS, ids=CFG_IDS)
@pytest.mark.parametrize("n", [0, 1, 7, 513])
def test_forward_matches_twin(device, cfg, n):
    seed = _seed()
    gen = torch.Generator().manual_seed(seed)
    u, table = _points(n, gen, device=device), _table(cfg, gen, device=device)
    feats, jac = hash_encode_jac(u, table, cfg)
    f_t, j_t = hash_encode_jac_torch(u, table, cfg)
    LF = cfg.levels * cfg.features
    assert feats.shape == (n, LF) and jac.shape == (n, LF, 3), seed
    assert feats.dtype == jac.dtype == torch.float32 and feats.device == jac.device == u.device
    if n:
        assert j_t.abs().max() > 0, seed
        # the features are hash_encode's, bit for bit (same float operations in the same order)
        assert torch.equal(feats, hash_encode(u, table, cfg)), f"seed {seed}"
        assert _rel(feats, f_t) < 1e-5, f"seed {seed}"
        assert _rel(jac, j_t) < 1e-5, f"seed {seed}: jac rel {_rel(jac, j_t)}"
        # clamped axes have a zero Jacobian in both
        out = (u < 0) | (u > 1)  # [n, 3]
        if out.any():
            m = out[:, None, :].expand_as(jac)
            assert jac[m].abs().max() == 0 and j_t[m].abs().max() == 0, f"seed {seed}"


# ----------------------------------------------------------------------------- (b) backward
@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("cfg", CONFIGS, ids=CFG_IDS)
@pytest.mark.parametrize("n", [1, 300])
def test_backward_matches_twin(device, cfg, n):
    seed = _seed()
    gen = torch.Generator().manual_seed(seed)
    u, table = _points(n, gen, device=device), _table(cfg, gen, device=device)
    u_w, t_w = u.clone().requires_grad_(), table.clone().requires_grad_()
    u_t, t_t = u.clone().requires_grad_(), table.clone().requires_grad_()
    out_w = hash_encode_jac(u_w, t_w, cfg)
    out_t = hash_encode_jac_torch(u_t, t_t, cfg)
    # the same random upstream gradients for feats and jac in both
    g_f = torch.randn(out_t[0].shape, generator=gen, dtype=torch.float64).float().to(device)
    g_j = torch.randn(out_t[1].shape, generator=gen, dtype=torch.float64).float().to(device)
    gu_w, gt_w = torch.autograd.grad(out_w, (u_w, t_w), (g_f, g_j))
    gu_t, gt_t = torch.autograd.grad(out_t, (u_t, t_t), (g_f, g_j))
    assert gt_t.abs().max() > 0 and gu_t.abs().max() > 0, seed
    assert _rel(gt_w, gt_t) < 1e-4, f"seed {seed}: table rel {_rel(gt_w, gt_t)}"
    assert _rel(gu_w, gu_t) < 1e-4, f"seed {seed}: u rel {_rel(gu_w, gu_t)}"
    # dL/du is jac^T dL/dfeats (the d jac / d u term is dropped by design)
    assert _rel(gu_w, torch.einsum("nfk,nf->nk", out_t[1].detach(), g_f)) < 1e-4, f"seed {seed}"


@pytest.mark.parametrize("device", DEVICES)
def test_backward_skips_rows_without_gradient(device):
    """Rows whose upstream gradients are all zero (a captured step's padded samples) add nothing
    (the kernel skips their atomics): the table gradient equals the twin's and that of the live
    rows alone; a row zero in one feature only still adds its other features."""
    seed = _seed()
    gen = torch.Generator().manual_seed(seed)
    cfg = CONFIGS[0]
    u, table = _points(400, gen, device=device), _table(cfg, gen, device=device)
    g_f = torch.randn(400, cfg.levels * cfg.features, generator=gen, dtype=torch.float64).float().to(device)
    g_j = torch.randn(400, cfg.levels * cfg.features, 3, generator=gen, dtype=torch.float64).float().to(device)
    g_f[250:], g_j[250:] = 0.0, 0.0  # padding
    g_f[10, ::cfg.features], g_j[10, ::cfg.features] = 0.0, 0.0  # one feature of a live row
    grads = []
    for fn, rows in ((hash_encode_jac, 400), (hash_encode_jac_torch, 400), (hash_encode_jac, 250)):
        t = table.clone().requires_grad_()
        out = fn(u[:rows], t, cfg)
        grads.append(torch.autograd.grad(out, t, (g_f[:rows], g_j[:rows]))[0])
    assert grads[0].abs().max() > 0
    assert _rel(grads[0], grads[1]) < 1e-4, f"seed {seed}"
    assert _rel(grads[0], grads[2]) < 1e-5, f"seed {seed}"


@pytest.mark.parametrize("device", DEVICES)
def test_backward_one_output_used(device):
    """Only feats or only jac reaching the loss (the other's gradient is None inside)."""
    seed = _seed()
    gen = torch.Generator().manual_seed(seed)
    cfg = CONFIGS[1]
    u, table = _points(200, gen, device=device), _table(cfg, gen, device=device)
    for k in (0, 1):
        u_w, t_w = u.clone().requires_grad_(), table.clone().requires_grad_()
        u_t, t_t = u.clone().requires_grad_(), table.clone().requires_grad_()
        o_w = hash_encode_jac(u_w, t_w, cfg)[k]
        o_t = hash_encode_jac_torch(u_t, t_t, cfg)[k]
        g = torch.randn(o_t.shape, generator=gen, dtype=torch.float64).float().to(device)
        (o_w * g).sum().backward()
        (o_t * g).sum().backward()
        assert _rel(t_w.grad, t_t.grad) < 1e-4, f"seed {seed}, output {k}"
        if k == 0:
            assert _rel(u_w.grad, u_t.grad) < 1e-4, f"seed {seed}"
        else:  # jac alone gives u no gradient (dropped second-order term), but a defined zero one
            assert u_w.grad is not None and u_w.grad.abs().max() == 0, f"seed {seed}"
            assert u_t.grad is None or u_t.grad.abs().max() == 0, f"seed {seed}"


@pytest.mark.parametrize("device", DEVICES)
def test_empty_input_backward(device):
    cfg = CONFIGS[1]
    u = torch.rand(0, 3, device=device, requires_grad=True)
    t = _table(cfg, torch.Generator().manual_seed(_seed()), device=device).requires_grad_()
    f, j = hash_encode_jac(u, t, cfg)
    (f.sum() + j.sum()).backward()
    assert u.grad.shape == (0, 3) and t.grad.abs().max() == 0


# ----------------------------------------------------------------------------- (c) gradcheck
def test_twin_gradcheck():
    seed = _seed()
    gen = torch.Generator().manual_seed(seed)
    cfg = HashGridConfig(levels=2, features=2, log2_table=6, base_res=2, finest_res=5)  # dense + hashed
    assert cfg.dense_levels() == [True, False]
    u = _interior_points(4, cfg, gen).requires_grad_()
    table = _table(cfg, gen, dtype=torch.float64).requires_grad_()
    for act in (None, 1):
        # feats in (u, table); both outputs in the table
        assert torch.autograd.gradcheck(lambda a, b: hash_encode_jac_torch(a, b, cfg, act)[0], (u, table),
                                        eps=1e-6, atol=1e-6), f"seed {seed}"
        assert torch.autograd.gradcheck(lambda b: hash_encode_jac_torch(u.detach(), b, cfg, act), (table,),
                                        eps=1e-6, atol=1e-6), f"seed {seed}"


def test_dropped_second_order_term_is_cross_terms_only():
    """d jac / d u, which the backward drops, has a zero diagonal (d^2 w / d frac_k^2 = 0)."""
    seed = _seed()
    gen = torch.Generator().manual_seed(seed)
    cfg = CONFIGS[0]
    u = _interior_points(16, cfg, gen, margin=0.01)
    table = _table(cfg, gen, dtype=torch.float64)
    h = 1e-6
    cross = 0.0
    for k in range(3):
        e = torch.zeros(3, dtype=torch.float64)
        e[k] = h
        dj = (hash_encode_jac_torch(u + e, table, cfg)[1] - hash_encode_jac_torch(u - e, table, cfg)[1]) / (2 * h)
        assert dj[:, :, k].abs().max() < 1e-6, f"seed {seed}: axis {k}"
        cross = max(cross, dj.abs().max().item())
    assert cross > 1.0, f"seed {seed}: cross terms {cross}"  # the dropped term is not trivially zero


# ----------------------------------------------------------------------------- (d) finite differences
@pytest.mark.parametrize("cfg", CONFIGS, ids=CFG_IDS)
def test_jac_matches_finite_differences(cfg):
    seed = _seed()
    gen = torch.Generator().manual_seed(seed)
    u = _interior_points(64, cfg, gen, margin=0.01)
    table = _table(cfg, gen, dtype=torch.float64)
    _, jac = hash_encode_jac_torch(u, table, cfg)
    h = 1e-7  # far below the 1% cell margin of the finest level
    for k in range(3):
        e = torch.zeros(3, dtype=torch.float64)
        e[k] = h
        fd = (hash_encode_torch(u + e, table, cfg) - hash_encode_torch(u - e, table, cfg)) / (2 * h)
        assert _rel(jac[:, :, k], fd) < 1e-6, f"seed {seed}: axis {k} rel {_rel(jac[:, :, k], fd)}"
    # and the Warp kernel's float32 Jacobian against the float64 one
    _, jac_w = hash_encode_jac(u.float(), table.float(), cfg)
    assert _rel(jac_w.double(), jac) < 1e-4, f"seed {seed}"


# ----------------------------------------------------------------------------- (e) inactive levels
@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("active", [0, 2, 5])
def test_active_levels_mask(device, active):
    seed = _seed()
    gen = torch.Generator().manual_seed(seed)
    cfg = CONFIGS[1]  # 6 levels
    F = cfg.features
    u, table = _points(200, gen, device=device), _table(cfg, gen, device=device)
    t_w, t_t = table.clone().requires_grad_(), table.clone().requires_grad_()
    u_w, u_t = u.clone().requires_grad_(), u.clone().requires_grad_()
    f_w, j_w = hash_encode_jac(u_w, t_w, cfg, active_levels=active)
    f_t, j_t = hash_encode_jac_torch(u_t, t_t, cfg, active_levels=active)
    for a in (f_w, f_t, j_w, j_t):
        assert a[:, active * F:].abs().max() == 0, f"seed {seed}"
    full_f, full_j = hash_encode_jac_torch(u, table, cfg)
    if active:
        assert _rel(f_w[:, :active * F], full_f[:, :active * F]) < 1e-5, f"seed {seed}"
        assert _rel(j_w[:, :active * F], full_j[:, :active * F]) < 1e-5, f"seed {seed}"
    g_f = torch.randn(f_t.shape, generator=gen, dtype=torch.float64).float().to(device)
    g_j = torch.randn(j_t.shape, generator=gen, dtype=torch.float64).float().to(device)
    gu_w, gt_w = torch.autograd.grad((f_w, j_w), (u_w, t_w), (g_f, g_j))
    gu_t, gt_t = torch.autograd.grad((f_t, j_t), (u_t, t_t), (g_f, g_j))
    assert gt_w[active:].abs().max() == 0 and gt_t[active:].abs().max() == 0, f"seed {seed}"
    if active:
        assert _rel(gt_w, gt_t) < 1e-4 and _rel(gu_w, gu_t) < 1e-4, f"seed {seed}"
    else:
        assert gu_w.abs().max() == 0 and gt_w.abs().max() == 0, f"seed {seed}"


def test_get_op_and_bad_inputs():
    assert get_op("hash_encode_jac", "warp") is hash_encode_jac
    assert get_op("hash_encode_jac", "torch") is hash_encode_jac_torch
    cfg = CONFIGS[0]
    t = _table(cfg, torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match="hash_encode_jac"):
        hash_encode_jac(torch.rand(5, 2), t, cfg)
    with pytest.raises(TypeError):
        hash_encode_jac(torch.rand(5, 3, dtype=torch.float64), t, cfg)


# ----------------------------------------------------------------------------- (f) SDF gradient
def _field(backend, sdf_grad, seed, hash_weight=0.0, table_scale=1.0, extra=()):
    from fastneus.config import load_config
    from fastneus.field.model import SDFField

    cfg = load_config("cpu-quick", [f"backend={backend}", f"sdf_grad={sdf_grad}", "log2_table=12",
                                    "levels=6", "finest_res=128", *extra])
    torch.manual_seed(seed)
    f = SDFField(cfg.hashgrid, cfg.network, "cpu", backend=cfg.run.backend)
    gen = torch.Generator().manual_seed(seed + 1)
    with torch.no_grad():
        f.table.mul_(table_scale)
        w = f.sdf_net[0].weight
        w[:, 3:] = hash_weight * torch.randn(w[:, 3:].shape, generator=gen)
    return f


def test_analytic_grad_close_to_fd_on_sphere_init():
    """Sphere initialisation (hash features silent, a smooth Softplus MLP): FD tends to the analytic gradient."""
    seed = _seed() % 2 ** 31
    fa = _field("warp", "analytic", seed)
    ffd = _field("warp", "fd", seed)
    gen = torch.Generator().manual_seed(seed)
    x = torch.rand(2000, 3, generator=gen) * 1.6 - 0.8
    x = x[x.norm(dim=-1) > 0.2]
    sa, _, ga, _ = fa.sdf_and_grad(x)
    sf, _, gf, _ = ffd.sdf_and_grad(x)
    # the same centre SDF; the fd path evaluates it in one batch with its 4 taps, and the GEMM's
    # blocking for that shape may round differently (seed 294913048: 6e-8), so a few ulp are allowed
    assert torch.equal(sa, fa.sdf(x)), seed
    torch.testing.assert_close(sa, sf, rtol=0, atol=1e-6, msg=f"seed {seed}")
    # the default step (2 / finest res = 0.016) blurs the Softplus(100) MLP's curvature by a few %
    err = (ga - gf).norm(dim=-1) / gf.norm(dim=-1)
    assert err.max() < 0.3 and err.median() < 0.03, f"seed {seed}: {err.max()}, {err.median()}"
    # a 1e-3 step converges toward the analytic gradient (error ~ eps^2 beta^2 + float32 noise)
    ffd.normal_eps = lambda: 1e-3
    _, _, gf3, _ = ffd.sdf_and_grad(x)
    err3 = (ga - gf3).norm(dim=-1) / gf3.norm(dim=-1)
    assert err3.max() < 0.03 and err3.median() < 2e-3, f"seed {seed}: {err3.max()}, {err3.median()}"
    assert err3.median() < 0.3 * err.median(), f"seed {seed}"


@pytest.mark.parametrize("backend", ["warp", "torch"])
def test_analytic_grad_matches_autograd_and_fd_on_smooth_grid(backend):
    """Hash features live (random first-layer weights, O(1e-2) table): the analytic gradient is
    torch's exact derivative of the SDF through hash_encode, and close to finite differences
    with a small step away from cell faces."""
    seed = _seed() % 2 ** 31
    f = _field(backend, "analytic", seed, hash_weight=1.0, table_scale=100.0)
    gen = torch.Generator().manual_seed(seed)
    # include points outside the box (clamped axes): there only the MLP's x input counts
    x = (torch.rand(600, 3, generator=gen) * 2.4 - 1.2).contiguous()
    _, _, g, _ = f.sdf_and_grad(x)
    xr = x.clone().requires_grad_()
    (ref,) = torch.autograd.grad(f.sdf(xr).sum(), xr)
    assert ref.abs().max() > 0.1
    assert _rel(g, ref) < 1e-4, f"seed {seed}: {_rel(g, ref)}"
    # central differences in float64 through the twin, away from cell faces
    f64 = copy.deepcopy(f).double()
    f64.encode = hash_encode_torch
    u = _interior_points(200, f.grid_cfg, gen, margin=0.02, lo=0.05, hi=0.95)
    xi = u * 2 - 1
    h = 1e-7
    with torch.no_grad():
        fd = torch.stack([(f64.sdf(xi + h * e) - f64.sdf(xi - h * e)) / (2 * h)
                          for e in torch.eye(3, dtype=torch.float64)], 1)
    # float32 points (the grid cell of x and of float(x) agree: the margin is 2% of a cell)
    _, _, gi, _ = f.sdf_and_grad(xi.float())
    assert _rel(gi.double(), fd) < 1e-3, f"seed {seed}: {_rel(gi.double(), fd)}"


def test_analytic_grad_gradients_warp_vs_twin():
    """A loss on (sdf, geo, grad) gives the table and every MLP weight the same gradient with the
    Warp op as with the twin (jac's backward + torch's double backward through the MLP)."""
    seed = _seed() % 2 ** 31
    gen = torch.Generator().manual_seed(seed)
    x = torch.rand(500, 3, generator=gen) * 2.2 - 1.1
    grads = {}
    for be in ("warp", "torch"):
        f = _field(be, "analytic", seed, hash_weight=1.0, table_scale=1000.0)
        s, geo, g, _ = f.sdf_and_grad(x)
        loss = ((g.norm(dim=-1) - 1) ** 2).mean() + s.abs().mean() + geo.square().mean()
        params = [f.table] + list(f.sdf_net.parameters())
        grads[be] = torch.autograd.grad(loss, params, allow_unused=True)
    for i, (a, b) in enumerate(zip(grads["warp"], grads["torch"])):
        if b is None:
            assert a is None
            continue
        assert _rel(a, b) < 1e-4, f"seed {seed}: param {i} rel {_rel(a, b)}"
    assert grads["warp"][0].abs().max() > 0, seed


def test_analytic_grad_table_gradient_is_exact():
    """The eikonal gradient into the table equals torch's own double backward through the twin."""
    seed = _seed() % 2 ** 31
    gen = torch.Generator().manual_seed(seed)
    f = _field("torch", "analytic", seed, hash_weight=1.0, table_scale=1000.0)
    x = torch.rand(300, 3, generator=gen) * 2 - 1
    _, _, g, _ = f.sdf_and_grad(x)
    (ga,) = torch.autograd.grad(((g.norm(dim=-1) - 1) ** 2).sum(), f.table)
    xr = x.clone().requires_grad_()
    (ref,) = torch.autograd.grad(f.sdf(xr).sum(), xr, create_graph=True)  # exact, through hash_encode_torch
    (gr,) = torch.autograd.grad(((ref.norm(dim=-1) - 1) ** 2).sum(), f.table)
    assert gr.abs().max() > 0 and _rel(ga, gr) < 1e-4, f"seed {seed}: {_rel(ga, gr)}"


@pytest.mark.parametrize("backend", ["warp", "torch"])
def test_analytic_grad_under_no_grad_and_frozen_geometry(backend):
    seed = _seed() % 2 ** 31
    f = _field(backend, "analytic", seed, hash_weight=1.0, table_scale=100.0)
    x = torch.rand(100, 3, generator=torch.Generator().manual_seed(seed)) * 2 - 1
    s, geo, g, _ = f.sdf_and_grad(x)
    with torch.no_grad():  # mesh extraction, normal renders
        s0, geo0, g0, _ = f.sdf_and_grad(x)
    assert not (s0.requires_grad or geo0.requires_grad or g0.requires_grad)
    assert torch.equal(s0, s.detach()) and _rel(g0, g.detach()) < 1e-6, seed
    # geometry frozen (colour warm-up): the gradient still exists, nothing needs a graph
    for p in [f.table, *f.sdf_net.parameters()]:
        p.requires_grad_(False)
    _, _, g1, _ = f.sdf_and_grad(x)
    assert _rel(g1.detach(), g.detach()) < 1e-6, seed


def test_analytic_curvature_uses_taps():
    seed = _seed() % 2 ** 31
    fa = _field("warp", "analytic", seed, hash_weight=1.0, table_scale=100.0)
    ffd = _field("warp", "fd", seed, hash_weight=1.0, table_scale=100.0)
    x = torch.rand(100, 3, generator=torch.Generator().manual_seed(seed)) * 2 - 1
    sa, _, ga, ca = fa.sdf_and_grad(x, with_curvature=True)
    sf, _, gf, cf = ffd.sdf_and_grad(x, with_curvature=True)
    assert ca is not None and cf is not None
    assert _rel(ca, cf) < 1e-4 and _rel(sa, sf) < 1e-5, seed
    _, _, ga2, _ = fa.sdf_and_grad(x)
    assert torch.equal(ga, ga2)  # the gradient stays the analytic one
    ca.abs().mean().backward()
    assert fa.table.grad is not None and fa.table.grad.abs().max() > 0


def test_config_sdf_grad_validated():
    from fastneus.config import load_config
    from fastneus.errors import FastneusError

    assert load_config("cpu-quick").network.sdf_grad == "analytic"  # the default (BENCHMARKS "Speed (issue 10)")
    assert load_config("fewview").network.sdf_grad == "analytic"
    assert load_config("cpu-quick", ["sdf_grad=fd"]).network.sdf_grad == "fd"
    with pytest.raises(FastneusError, match="sdf_grad"):
        load_config("cpu-quick", ["sdf_grad=autograd"])


def test_training_steps_analytic(small_scene, tmp_path):
    from conftest import SMALL_RUN
    from fastneus.config import load_config
    from fastneus.data import Scene
    from fastneus.train.trainer import Trainer

    scene = Scene.load(small_scene)
    cfg = load_config("cpu-quick", SMALL_RUN + ["sdf_grad=analytic", "curvature_weight=1e-4"])
    tr = Trainer(scene, cfg, tmp_path / "run", "cpu")
    t0 = tr.field.table.detach().clone()
    recs = [tr.train_step() for _ in range(4)]
    assert any(r is not None for r in recs)
    assert all(torch.isfinite(p).all() for p in tr.field.parameters())
    assert not torch.equal(t0, tr.field.table.detach())


# ----------------------------------------------------------------- grad_from_jac (Warp) vs its twin
@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("F", [1, 16, 32])
def test_grad_from_jac_matches_twin_values_and_gradients(device, F):
    from fastneus.kernels.hashgrid import grad_from_jac, grad_from_jac_torch

    seed = _seed()
    gen = torch.Generator().manual_seed(seed)
    n = 5003
    g0 = torch.randn(n, F + 3, generator=gen).to(device)
    j0 = torch.randn(n, F, 3, generator=gen).to(device)
    up = torch.randn(n, 3, generator=gen).to(device)
    res = []
    for op in (grad_from_jac, grad_from_jac_torch):
        g, j = g0.clone().requires_grad_(True), j0.clone().requires_grad_(True)
        out = op(g, j, 0.5)
        res.append((out.detach(), *torch.autograd.grad(out, [g, j], up)))
    for a, b in zip(*res):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5, msg=f"seed {seed}")
    for need in ("g", "jac"):  # one input without a gradient
        g = g0.clone().requires_grad_(need == "g")
        j = j0.clone().requires_grad_(need == "jac")
        (d,) = torch.autograd.grad(grad_from_jac(g, j, 0.5), [g if need == "g" else j], up)
        torch.testing.assert_close(d, res[1][1 if need == "g" else 2], rtol=1e-5, atol=1e-5)


def test_grad_from_jac_twin_gradcheck_float64_and_shape_errors():
    from fastneus.kernels.hashgrid import grad_from_jac, grad_from_jac_torch

    gen = torch.Generator().manual_seed(_seed())
    g = torch.randn(4, 8, generator=gen, dtype=torch.float64, requires_grad=True)
    j = torch.randn(4, 5, 3, generator=gen, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda g, j: grad_from_jac_torch(g, j, 0.5), (g, j))
    with pytest.raises(ValueError, match="grad_from_jac"):
        grad_from_jac(torch.zeros(4, 8), torch.zeros(4, 6, 3), 0.5)
    assert grad_from_jac(torch.zeros(0, 8), torch.zeros(0, 5, 3), 0.5).shape == (0, 3)
