"""hash_encode: Warp kernels against the torch twin and a numpy reference (fresh random inputs)."""
import math

import numpy as np
import pytest
import torch

from fastneus.kernels import get_op
from fastneus.kernels.hashgrid import (
    HashGridConfig,
    hash_encode,
    hash_encode_torch,
    hash_index_torch,
    init_table,
)

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA"))]

# Small configs with both dense (coarse) and hashed (fine) levels, F = 2, 4 and 8.
CONFIGS = [
    HashGridConfig(levels=4, features=2, log2_table=8, base_res=2, finest_res=16),
    HashGridConfig(levels=6, features=4, log2_table=12, base_res=4, finest_res=64),
    HashGridConfig(levels=5, features=8, log2_table=10, base_res=3, finest_res=300),
]
CFG_IDS = ["L4F2T8", "L6F4T12", "L5F8T10"]


def _table(cfg, device):
    # O(1) values so relative tolerances mean something (the real init is +-1e-4)
    return (torch.rand(cfg.levels, cfg.table_size, cfg.features, device=device) * 2 - 1).contiguous()


def _points(n, device):
    u = torch.rand(n, 3, device=device)
    if n >= 8:
        # exercise the clamp and the u = 0 / u = 1 edges
        u[:4] = u[:4] * 1.4 - 0.2
        u[4, :] = 1.0
        u[5, :] = 0.0
    return u


def _rel(a, b):
    return ((a - b).abs().max() / b.abs().max().clamp_min(1e-12)).item() if b.numel() else 0.0


def test_config_resolutions():
    cfg = HashGridConfig()
    res = cfg.resolutions()
    assert len(res) == 16 and res[0] == 16 and res[-1] == 2048
    assert all(a < b for a, b in zip(res, res[1:]))
    b = math.exp(math.log(2048 / 16) / 15)
    assert res[5] == math.floor(16 * b ** 5)
    assert cfg.table_size == 2 ** 19
    t = init_table(HashGridConfig(levels=2, log2_table=8), "cpu")
    assert t.shape == (2, 256, 2) and t.dtype == torch.float32
    assert t.abs().max() <= 1e-4 and t.abs().max() > 0


def test_configs_mix_dense_and_hashed():
    for cfg in CONFIGS:
        d = cfg.dense_levels()
        assert any(d) and not all(d), cfg


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("cfg", CONFIGS, ids=CFG_IDS)
@pytest.mark.parametrize("n", [0, 1, 7, 513])
def test_forward_matches_twin(device, cfg, n):
    u, table = _points(n, device), _table(cfg, device)
    out = hash_encode(u, table, cfg)
    ref = hash_encode_torch(u, table, cfg)
    assert out.shape == (n, cfg.levels * cfg.features) and out.dtype == torch.float32
    assert out.device == u.device
    if n:
        assert ref.abs().max() > 0
        assert _rel(out, ref) < 1e-5


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("cfg", CONFIGS, ids=CFG_IDS)
@pytest.mark.parametrize("n", [1, 300])
def test_backward_matches_twin(device, cfg, n):
    u, table = _points(n, device), _table(cfg, device)
    u_w, t_w = u.clone().requires_grad_(), table.clone().requires_grad_()
    u_t, t_t = u.clone().requires_grad_(), table.clone().requires_grad_()
    out_w = hash_encode(u_w, t_w, cfg)
    out_t = hash_encode_torch(u_t, t_t, cfg)
    g = torch.randn_like(out_t)  # same upstream gradient for both
    gu_w, gt_w = torch.autograd.grad(out_w, (u_w, t_w), g)
    gu_t, gt_t = torch.autograd.grad(out_t, (u_t, t_t), g)
    assert gt_t.abs().max() > 0 and gu_t.abs().max() > 0
    assert _rel(gt_w, gt_t) < 1e-4
    assert _rel(gu_w, gu_t) < 1e-4


@pytest.mark.parametrize("device", DEVICES)
def test_grad_only_where_requested(device):
    cfg = CONFIGS[0]
    u, table = _points(50, device), _table(cfg, device)
    # table only (the usual case: u comes from detached samples)
    t = table.clone().requires_grad_()
    hash_encode(u, t, cfg).sum().backward()
    assert t.grad is not None and u.grad is None
    # u only (e.g. SDF normals with a frozen table)
    uu = u.clone().requires_grad_()
    hash_encode(uu, table, cfg).sum().backward()
    ref_u = u.clone().requires_grad_()
    hash_encode_torch(ref_u, table, cfg).sum().backward()
    assert _rel(uu.grad, ref_u.grad) < 1e-4


@pytest.mark.parametrize("device", DEVICES)
def test_empty_input_backward(device):
    cfg = CONFIGS[1]
    u = torch.rand(0, 3, device=device, requires_grad=True)
    t = _table(cfg, device).requires_grad_()
    out = hash_encode(u, t, cfg)
    out.sum().backward()
    assert u.grad.shape == (0, 3) and t.grad.abs().max() == 0


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("active", [0, 2, 5])
def test_active_levels_mask(device, active):
    cfg = CONFIGS[1]  # 6 levels
    F = cfg.features
    u, table = _points(200, device), _table(cfg, device)
    t_w = table.clone().requires_grad_()
    t_t = table.clone().requires_grad_()
    out_w = hash_encode(u, t_w, cfg, active_levels=active)
    out_t = hash_encode_torch(u, t_t, cfg, active_levels=active)
    assert out_w[:, active * F:].abs().max() == 0
    assert out_t[:, active * F:].abs().max() == 0
    full = hash_encode_torch(u, table, cfg)
    if active:
        assert _rel(out_w[:, :active * F], full[:, :active * F]) < 1e-5
    g = torch.randn_like(out_t)
    (gt_w,) = torch.autograd.grad(out_w, (t_w,), g)
    (gt_t,) = torch.autograd.grad(out_t, (t_t,), g)
    assert gt_w[active:].abs().max() == 0 and gt_t[active:].abs().max() == 0
    if active:
        assert _rel(gt_w, gt_t) < 1e-4


def _numpy_reference(u, table, cfg):
    """float64 encoding with uint64 hashing (independent of both implementations)."""
    u = np.clip(u.astype(np.float64), 0, 1)
    T, F = cfg.table_size, cfg.features
    out = np.zeros((u.shape[0], cfg.levels * F))
    for l, res in enumerate(cfg.resolutions()):
        p = u.astype(np.float32) * np.float32(res)  # same float32 cell as the kernels
        c = np.minimum(np.floor(p), res - 1).astype(np.uint64)
        fr = (p - c.astype(np.float32)).astype(np.float64)
        for corner in range(8):
            d = np.array([(corner >> k) & 1 for k in range(3)], dtype=np.uint64)
            v = c + d
            if (res + 1) ** 3 <= T:
                idx = v[:, 0] + v[:, 1] * np.uint64(res + 1) + v[:, 2] * np.uint64((res + 1) ** 2)
            else:
                h = v[:, 0] ^ (v[:, 1] * np.uint64(2654435761)) ^ (v[:, 2] * np.uint64(805459861))
                idx = (h & np.uint64(0xFFFFFFFF)) % np.uint64(T)
            w = np.prod(np.where(d[None, :] == 1, fr, 1 - fr), axis=1)
            out[:, l * F:(l + 1) * F] += w[:, None] * table[l][idx.astype(np.int64)]
    return out


def test_hash_index_overflow_against_numpy():
    T = 2 ** 19
    x, y, z = (torch.randint(0, 2 ** 31 - 1, (4096,), dtype=torch.int64) for _ in range(3))
    got = hash_index_torch(x, y, z, res=10 ** 6, T=T).numpy()
    xn, yn, zn = (a.numpy().astype(np.uint64) for a in (x, y, z))
    h = xn ^ (yn * np.uint64(2654435761)) ^ (zn * np.uint64(805459861))
    ref = (h & np.uint64(0xFFFFFFFF)) % np.uint64(T)
    assert np.array_equal(got, ref.astype(np.int64))


@pytest.mark.parametrize("device", DEVICES)
def test_fine_hashed_levels_against_numpy(device):
    # vertex coordinates up to 4096: every y*prime, z*prime product overflows uint32
    cfg = HashGridConfig(levels=3, features=2, log2_table=10, base_res=1000, finest_res=4096)
    assert not any(cfg.dense_levels())
    u = torch.rand(400, 3) * 0.2 + 0.8
    table = _table(cfg, "cpu")
    ref = _numpy_reference(u.numpy(), table.numpy(), cfg)
    out_w = hash_encode(u.to(device), table.to(device), cfg).cpu().double().numpy()
    out_t = hash_encode_torch(u, table, cfg).double().numpy()
    scale = np.abs(ref).max()
    assert np.abs(out_w - ref).max() / scale < 1e-5
    assert np.abs(out_t - ref).max() / scale < 1e-5


def test_twin_gradcheck():
    cfg = HashGridConfig(levels=2, features=2, log2_table=6, base_res=2, finest_res=5)  # dense + hashed
    assert cfg.dense_levels() == [True, False]
    # keep u away from cell boundaries at every level (the encoding is only C0 there)
    cand = torch.rand(256, 3, dtype=torch.float64)
    ok = torch.ones(256, dtype=torch.bool)
    for r in cfg.resolutions():
        fr = torch.frac(cand * r)
        ok &= ((fr > 0.05) & (fr < 0.95)).all(dim=1)
    u = cand[ok][:4].clone().requires_grad_()
    assert u.shape[0] == 4
    table = (torch.rand(cfg.levels, cfg.table_size, cfg.features, dtype=torch.float64) * 2 - 1).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: hash_encode_torch(a, b, cfg), (u, table), eps=1e-6, atol=1e-6)
    assert torch.autograd.gradcheck(lambda a, b: hash_encode_torch(a, b, cfg, active_levels=1), (u, table),
                                    eps=1e-6, atol=1e-6)


def test_get_op():
    assert get_op("hash_encode", "warp") is hash_encode
    assert get_op("hash_encode", "torch") is hash_encode_torch


def test_bad_shapes():
    cfg = CONFIGS[0]
    with pytest.raises(ValueError):
        hash_encode(torch.rand(5, 2), _table(cfg, "cpu"), cfg)
    with pytest.raises(ValueError):
        hash_encode(torch.rand(5, 3), torch.rand(1, 2, 3), cfg)
    with pytest.raises(TypeError):
        hash_encode(torch.rand(5, 3, dtype=torch.float64), _table(cfg, "cpu"), cfg)
