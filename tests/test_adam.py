"""fastneus.train.adam.Adam against torch.optim.Adam: same updates step by step (groups with
their own lr, an lr changed mid-run, parameters without a gradient on some steps), checkpoints
interchangeable both ways, and no TorchDynamo import (the reason it exists)."""
from __future__ import annotations

import io
import os
import subprocess
import sys

import pytest
import torch

from fastneus.train.adam import Adam


def _params(gen):
    return [torch.randn(s, generator=gen, dtype=torch.float64) for s in ((7, 3), (5,), (2, 2, 2), (1,))]


def _groups(ps, names=("a", "b")):
    return [{"params": ps[:2], "lr": 1e-2, "name": names[0]}, {"params": ps[2:], "lr": 3e-3, "name": names[1]}]


def _run(opt, ps, grads):
    for t, gs in enumerate(grads):
        if t == 7:
            for g in opt.param_groups:
                g["lr"] *= 0.5
        for p, g in zip(ps, gs):
            p.grad = None if g is None else g.clone()
        opt.step()


def test_matches_torch_adam_step_by_step():
    seed = int.from_bytes(os.urandom(4), "little")
    gen = torch.Generator().manual_seed(seed)
    init = _params(gen)
    grads = [[None if (t % 4 == 3 and i == 1) else torch.randn(p.shape, generator=gen, dtype=torch.float64) * 10 ** (i - 2)
              for i, p in enumerate(init)] for t in range(15)]
    ours = [p.clone().requires_grad_(True) for p in init]
    ref = [p.clone().requires_grad_(True) for p in init]
    a = Adam(_groups(ours), betas=(0.9, 0.99), eps=1e-15)
    b = torch.optim.Adam(_groups(ref), betas=(0.9, 0.99), eps=1e-15, foreach=True)
    _run(a, ours, grads)
    _run(b, ref, grads)
    for x, y in zip(ours, ref):
        torch.testing.assert_close(x, y, rtol=1e-12, atol=1e-14, msg=f"seed {seed}")
    assert not all(torch.equal(x, y) for x, y in zip(ours, init))  # it moved


def test_checkpoints_interchangeable_with_torch_adam():
    seed = int.from_bytes(os.urandom(4), "little")
    gen = torch.Generator().manual_seed(seed)
    init = _params(gen)
    grads = [[torch.randn(p.shape, generator=gen, dtype=torch.float64) for p in init] for _ in range(10)]
    for first, second in ((Adam, torch.optim.Adam), (torch.optim.Adam, Adam)):
        p1 = [p.clone().requires_grad_(True) for p in init]
        o1 = first(_groups(p1), betas=(0.9, 0.99), eps=1e-15)
        _run(o1, p1, grads[:5])
        buf = io.BytesIO()  # through a file, as a checkpoint goes (plain data: weights_only)
        torch.save(o1.state_dict(), buf)
        buf.seek(0)
        sd = torch.load(buf, weights_only=True)
        p2 = [p.detach().clone().requires_grad_(True) for p in p1]
        o2 = second(_groups(p2, names=("x", "y")), betas=(0.9, 0.99), eps=1e-15)
        o2.load_state_dict(sd)
        assert [g["name"] for g in o2.param_groups] == ["a", "b"]  # group options come from the file
        _run(o1, p1, grads[5:])
        _run(o2, p2, grads[5:])
        for x, y in zip(p1, p2):
            torch.testing.assert_close(x, y, rtol=1e-12, atol=1e-14, msg=f"{first.__name__} -> {second.__name__}")


def test_zero_grad_and_mismatched_state():
    p = torch.zeros(3, requires_grad=True)
    opt = Adam([p], lr=0.1)
    p.grad = torch.ones(3)
    opt.zero_grad(set_to_none=False)
    assert torch.equal(p.grad, torch.zeros(3))
    opt.zero_grad()
    assert p.grad is None
    try:
        Adam([p, torch.zeros(2, requires_grad=True)]).load_state_dict(opt.state_dict())
    except ValueError as e:
        assert "parameter groups" in str(e)
    else:
        raise AssertionError("a state for other parameters was accepted")


def test_no_torchdynamo_import():
    code = ("import sys, torch\nfrom fastneus.train.adam import Adam\n"
            "p = torch.zeros(4, requires_grad=True)\nopt = Adam([{'params': [p], 'lr': 0.1}])\n"
            "p.grad = torch.ones(4)\nopt.step()\nopt.load_state_dict(opt.state_dict())\n"
            "assert 'torch._dynamo' not in sys.modules\nprint('ok')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]


def test_gated_step_matches_step_and_skips_exactly():
    """The device-gated update (CUDA's NaN guard without a host sync) against the plain step:
    ``ok`` true gives the same parameters and moments, ``ok`` false with NaN/Inf gradients
    leaves every parameter and moment exactly as it was."""
    seed = int.from_bytes(os.urandom(4), "little")
    gen = torch.Generator().manual_seed(seed)
    init = _params(gen)
    grads = [[torch.randn(p.shape, generator=gen, dtype=torch.float64) * 10 ** (i - 2) for i, p in enumerate(init)]
             for _ in range(6)]
    ours = [p.clone().requires_grad_(True) for p in init]
    ref = [p.clone().requires_grad_(True) for p in init]
    a, b = Adam(_groups(ours), betas=(0.9, 0.99), eps=1e-15), Adam(_groups(ref), betas=(0.9, 0.99), eps=1e-15)
    for gs in grads:
        for p, q, g in zip(ours, ref, gs):
            p.grad, q.grad = g.clone(), g.clone()
        a.gated_step(torch.tensor(True))
        b.step()
    for x, y in zip(ours, ref):
        torch.testing.assert_close(x, y, rtol=1e-12, atol=1e-14, msg=f"seed {seed}")
    for x, y in zip(ours, ref):
        torch.testing.assert_close(a.state[x]["exp_avg_sq"], b.state[y]["exp_avg_sq"], rtol=1e-12, atol=1e-20)
    before = [p.detach().clone() for p in ours]
    moments = [(a.state[p]["exp_avg"].clone(), a.state[p]["exp_avg_sq"].clone()) for p in ours]
    for i, p in enumerate(ours):
        g = torch.randn(p.shape, generator=gen, dtype=torch.float64)
        g.view(-1)[0] = (float("nan"), float("inf"), -float("inf"), 1.0)[i % 4]
        p.grad = g
    a.gated_step(torch.tensor(False))
    for p, b0, (m, v) in zip(ours, before, moments):
        assert torch.equal(p.detach(), b0) and torch.equal(a.state[p]["exp_avg"], m)
        assert torch.equal(a.state[p]["exp_avg_sq"], v)


def test_device_update_matches_gated_step():
    """The captured update (host half prepare_device_step + device half device_update, the
    learning rates read from a device tensor) against gated_step over steps with a changing
    learning rate, and an exact skip."""
    seed = int.from_bytes(os.urandom(4), "little")
    gen = torch.Generator().manual_seed(seed)
    init = _params(gen)
    ours = [p.clone().requires_grad_(True) for p in init]
    ref = [p.clone().requires_grad_(True) for p in init]
    a, b = Adam(_groups(ours), betas=(0.9, 0.99), eps=1e-15), Adam(_groups(ref), betas=(0.9, 0.99), eps=1e-15)
    a._scal = torch.zeros(2, 2, dtype=torch.float64)
    for t in range(6):
        for o in (a, b):
            for g in o.param_groups:
                g["lr"] = 1e-2 / (1 + t)
        for p, q in zip(ours, ref):
            g = torch.randn(p.shape, generator=gen, dtype=torch.float64)
            p.grad, q.grad = g.clone(), g.clone()
        a.prepare_device_step()
        a.device_update(torch.tensor(True))
        b.gated_step(torch.tensor(True))
    assert a.uniform_steps()
    for x, y in zip(ours, ref):
        torch.testing.assert_close(x, y, rtol=1e-12, atol=1e-14, msg=f"seed {seed}")
    before = [p.detach().clone() for p in ours]
    for p in ours:
        p.grad = torch.full_like(p, float("nan"))
    a.prepare_device_step()
    a.device_update(torch.tensor(False))
    assert all(torch.equal(p.detach(), q) for p, q in zip(ours, before))


# ----------------------------------------------------------------- the fused update (kernels/adam.py)
def _devices():
    return ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def _fused_case(gen, device, n=70001):
    p = torch.randn(n, generator=gen).to(device)
    g = (torch.randn(n, generator=gen) * 10 ** torch.randint(-3, 2, (n,), generator=gen)).to(device)
    g[::997] = float("nan")
    g[5::1009] = float("inf")
    g[7::1013] = -float("inf")
    m = (torch.randn(n, generator=gen) * 0.1).to(device)
    v = torch.rand(n, generator=gen).to(device) * 0.01
    scal = torch.tensor([[-1e-3, 1.3], [-2e-2, 1.05]], device=device)
    return p, g, m, v, scal


@pytest.mark.parametrize("device", _devices())
def test_fused_adam_kernel_matches_its_torch_twin_and_skips_exactly(device):
    from fastneus.kernels import get_op

    seed = int.from_bytes(os.urandom(4), "little")
    gen = torch.Generator().manual_seed(seed)
    warp_op, torch_op = get_op("adam_update", "warp"), get_op("adam_update", "torch")
    p, g, m, v, scal = _fused_case(gen, device)
    for row in (0, 1):
        a = [t.clone() for t in (p, m, v)]
        b = [t.clone() for t in (p, m, v)]
        ok = torch.ones(1, device=device)
        warp_op(a[0], g, a[1], a[2], scal, row, ok, 0.9, 0.99, 1e-15)
        torch_op(b[0], g, b[1], b[2], scal, row, ok, 0.9, 0.99, 1e-15)
        for x, y in zip(a, b):  # Warp may contract a*b+c into one rounding
            torch.testing.assert_close(x, y, rtol=2e-6, atol=1e-6, msg=f"seed {seed}")
        assert torch.isfinite(a[0]).all() and not torch.equal(a[0], p)  # non-finite gradients counted as 0
        off = [t.clone() for t in (p, m, v)]
        warp_op(off[0], g, off[1], off[2], scal, row, torch.zeros(1, device=device), 0.9, 0.99, 1e-15)
        assert all(torch.equal(x, y) for x, y in zip(off, (p, m, v)))


@pytest.mark.parametrize("device", _devices())
def test_fused_nonfinite_count_matches_its_twin(device):
    from fastneus.kernels import get_op

    gen = torch.Generator().manual_seed(int.from_bytes(os.urandom(4), "little"))
    _, g, _, _, _ = _fused_case(gen, device)
    for x in (g, torch.randn(1000, generator=gen).to(device)):
        counts = []
        for backend in ("warp", "torch"):
            c = torch.full((1,), 2.0, device=device)
            get_op("adam_nonfinite", backend)(x, c)
            counts.append(float(c))
        assert counts[0] == counts[1] == 2.0 + float((~torch.isfinite(x)).sum())


@pytest.mark.parametrize("backend", ["warp", "torch"])
def test_fused_adam_matches_foreach_update_over_steps(backend):
    """Adam.use_fused: gated_step and the guard give the foreach path's parameters (float32
    rounding), a NaN step is skipped exactly, and the guard's count finds it."""
    from fastneus.train.guard import finite_flag

    seed = int.from_bytes(os.urandom(4), "little")
    gen = torch.Generator().manual_seed(seed)
    init = [t.float() for t in _params(gen)]
    ours = [p.clone().requires_grad_(True) for p in init]
    ref = [p.clone().requires_grad_(True) for p in init]
    a, b = Adam(_groups(ours), betas=(0.9, 0.99), eps=1e-15), Adam(_groups(ref), betas=(0.9, 0.99), eps=1e-15)
    a.use_fused(backend)
    loss = torch.tensor(1.0)
    for t in range(8):
        for o in (a, b):
            for g in o.param_groups:
                g["lr"] = 1e-2 / (1 + t)
        for p, q in zip(ours, ref):
            g = torch.randn(p.shape, generator=gen)
            p.grad, q.grad = g.clone(), g.clone()
        ok_a, ok_b = finite_flag(a, loss), finite_flag(b, loss)
        assert bool(ok_a) and bool(ok_b)
        a.gated_step(ok_a)
        b.gated_step(ok_b)
    for x, y in zip(ours, ref):
        torch.testing.assert_close(x, y, rtol=1e-5, atol=1e-7, msg=f"seed {seed}")
    before = [p.detach().clone() for p in ours]
    for i, p in enumerate(ours):
        p.grad = torch.randn(p.shape, generator=gen)
    ours[1].grad.view(-1)[0] = float("nan")
    ok = finite_flag(a, loss)
    assert not bool(ok) and float(a.nonfinite_count()) == 1.0
    a.gated_step(ok)
    assert all(torch.equal(p.detach(), q) for p, q in zip(ours, before))


def _multi_case(gen, device, sizes):
    """Tensors of the given sizes (the hash table and the small heads), some gradients non-finite."""
    ps, gs, ms, vs = [], [], [], []
    for n in sizes:
        g = torch.randn(n, generator=gen) * 1e-2
        if n > 9:
            g[3::7] = float("nan")
        ps.append(torch.randn(n, generator=gen).to(device))
        gs.append(g.to(device))
        ms.append((torch.randn(n, generator=gen) * 0.1).to(device))
        vs.append((torch.rand(n, generator=gen) * 0.01).to(device))
    return ps, gs, ms, vs


@pytest.mark.parametrize("device", _devices())
@pytest.mark.parametrize("sizes", [(70001, 5, 1, 64 * 33, 3), tuple(range(1, 20)), (1 << 17,), (3000, 1 << 16, 7)])
def test_multi_tensor_adam_matches_per_tensor_and_its_twin(device, sizes):
    """adam_update_multi (large tensors one launch each, up to MAX_TENSORS small ones per launch;
    19 tensors split in two)
    against one adam_update per tensor and against its torch twin, rows from two groups; the
    guard off leaves every tensor bit-identical. The multi-tensor count equals the per-tensor sum."""
    from fastneus.kernels import get_op

    seed = int.from_bytes(os.urandom(4), "little")
    gen = torch.Generator().manual_seed(seed)
    ps, gs, ms, vs = _multi_case(gen, device, sizes)
    rows = [k % 2 for k in range(len(ps))]
    scal = torch.tensor([[-1e-3, 1.3], [-2e-2, 1.05]], device=device)
    ok = torch.ones(1, device=device)
    multi = [[t.clone() for t in lst] for lst in (ps, ms, vs)]
    get_op("adam_update_multi", "warp")(multi[0], gs, multi[1], multi[2], scal, rows, ok, 0.9, 0.99, 1e-15)
    one = [[t.clone() for t in lst] for lst in (ps, ms, vs)]
    for k in range(len(ps)):
        get_op("adam_update", "warp")(one[0][k], gs[k], one[1][k], one[2][k], scal, rows[k], ok, 0.9, 0.99, 1e-15)
    twin = [[t.clone() for t in lst] for lst in (ps, ms, vs)]
    get_op("adam_update_multi", "torch")(twin[0], gs, twin[1], twin[2], scal, rows, ok, 0.9, 0.99, 1e-15)
    for a, b, c in zip(multi, one, twin):
        for x, y, z in zip(a, b, c):
            assert torch.equal(x, y), f"seed {seed}"  # the same arithmetic per element
            torch.testing.assert_close(x, z, rtol=2e-6, atol=1e-6, msg=f"seed {seed}")
    assert all(torch.isfinite(x).all() for x in multi[0]) and not torch.equal(multi[0][0], ps[0])
    off = [[t.clone() for t in lst] for lst in (ps, ms, vs)]
    get_op("adam_update_multi", "warp")(off[0], gs, off[1], off[2], scal, rows, torch.zeros(1, device=device),
                                        0.9, 0.99, 1e-15)
    assert all(torch.equal(x, y) for a, b in zip(off, (ps, ms, vs)) for x, y in zip(a, b))
    counts = []
    for backend in ("warp", "torch"):
        c = torch.full((1,), 1.0, device=device)
        get_op("adam_nonfinite_multi", backend)(gs, c)
        counts.append(float(c))
    assert counts[0] == counts[1] == 1.0 + sum(float((~torch.isfinite(g)).sum()) for g in gs)


def test_multi_tensor_adam_refuses_mismatched_lists():
    from fastneus.kernels import get_op

    p = torch.zeros(4)
    with pytest.raises(ValueError, match="one entry per tensor"):
        get_op("adam_update_multi", "warp")([p], [p.clone()], [p.clone()], [], torch.zeros(1, 2), [0],
                                            torch.ones(1), 0.9, 0.99, 1e-15)
    with pytest.raises(ValueError, match="must match the parameter"):
        get_op("adam_update_multi", "warp")([p], [torch.zeros(3)], [p.clone()], [p.clone()], torch.zeros(1, 2), [0],
                                            torch.ones(1), 0.9, 0.99, 1e-15)
