"""The fused SDF MLP node (fastneus/field/sdf_mlp.py) against autograd's double backward."""
from __future__ import annotations

import pytest
import torch
import torch.nn as nn

from fastneus.field.sdf_mlp import _SoftplusMLPWithGrad, fusable, mlp_and_input_grad

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def _net(d_in, hidden, d_out, beta, dtype, device, seed):
    torch.manual_seed(seed)
    net = nn.Sequential(nn.Linear(d_in, hidden), nn.Softplus(beta=beta), nn.Linear(hidden, d_out))
    return net.to(device=device, dtype=dtype)


def _reference(net, a):
    """out and d out[:, 0] / d a through autograd (create_graph), as SDFField did before."""
    if not a.requires_grad:
        a = a.detach().requires_grad_()
    out = net(a)
    (g,) = torch.autograd.grad(out[:, 0].sum(), a, create_graph=True)
    return out, g


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("seed", [0, 1])
def test_outputs_and_gradients_match_autograd(device, seed):
    """Same out and g, and the same gradients to the input and every weight for the same random
    upstream gradients on both outputs (fresh inputs; some pre-activations on softplus's linear
    branch above the threshold, where s = 1 and s' = 0)."""
    net = _net(35, 64, 16, 100.0, torch.float32, device, seed)
    g0 = torch.Generator(device="cpu").manual_seed(100 + seed)
    a = (torch.randn(3000, 35, generator=g0) * 0.5).to(device)
    a[:50] *= 40.0                                   # beta * z well above 20 for some units
    up_out = torch.randn(3000, 16, generator=g0).to(device)
    up_g = torch.randn(3000, 35, generator=g0).to(device)

    results = []
    for fused in (True, False):
        for p in net.parameters():
            p.grad = None
        ai = a.clone().requires_grad_()
        if fused:  # as the field calls it: position and hash-feature blocks, no concatenation
            ax, af = ai[:, :3].detach().requires_grad_(), ai[:, 3:].detach().requires_grad_()
            out, g = mlp_and_input_grad(net, ax, af)
        else:
            out, g = _reference(net, ai)
        ((out * up_out).sum() + (g * up_g).sum()).backward()
        da = torch.cat([ax.grad, af.grad], 1) if fused else ai.grad
        results.append([out.detach(), g.detach(), da] + [p.grad.clone() for p in net.parameters()])
    names = ["out", "g", "d a", "d W1", "d b1", "d W2", "d b2"]
    for name, x, y in zip(names, *results):
        scale = float(y.abs().max()) + 1e-12
        assert float((x - y).abs().max()) <= 2e-5 * scale, name


@pytest.mark.parametrize("device", DEVICES)
def test_gradcheck_float64(device):
    """float64 gradcheck of the node's first-order backward on a tiny network."""
    net = _net(5, 4, 3, 3.0, torch.float64, device, 0)
    a = torch.randn(6, 5, dtype=torch.float64, device=device, requires_grad=True)
    params = [p.detach().clone().requires_grad_() for p in net.parameters()]

    def fn(a, w1, b1, w2, b2):
        return _SoftplusMLPWithGrad.apply(3.0, w1, b1, w2, b2, a[:, :2], a[:, 2:])

    assert torch.autograd.gradcheck(fn, (a, *params), eps=1e-6, atol=1e-6)


def test_no_grad_inference_matches():
    """Under no_grad the node still returns the input gradient (mesh normals need it)."""
    net = _net(8, 6, 4, 100.0, torch.float32, "cpu", 3)
    a = torch.randn(50, 8) * 0.1
    with torch.no_grad():
        out, g = mlp_and_input_grad(net, a)
    ro, rg = _reference(net, a)
    assert torch.allclose(out, ro.detach(), atol=1e-6) and torch.allclose(g, rg.detach(), atol=1e-5)
    assert not out.requires_grad and not g.requires_grad


def test_fusable_shapes():
    assert fusable(nn.Sequential(nn.Linear(3, 4), nn.Softplus(), nn.Linear(4, 2)))
    assert not fusable(nn.Sequential(nn.Linear(3, 4), nn.Softplus(), nn.Linear(4, 4), nn.Softplus(),
                                     nn.Linear(4, 2)))
    assert not fusable(nn.Sequential(nn.Linear(3, 4), nn.ReLU(), nn.Linear(4, 2)))


@pytest.mark.parametrize("device", DEVICES)
def test_field_fused_vs_autograd_whole_loss(device):
    """SDFField: a loss on sdf, geometry features and the analytic gradient (eikonal) gives the
    table, every MLP weight and x the same gradients with the fused node as with autograd."""
    from fastneus.config import load_config
    from fastneus.field.model import SDFField

    cfg = load_config("cpu-quick", ["log2_table=12", "levels=6", "finest_res=128"])
    torch.manual_seed(5)
    f = SDFField(cfg.hashgrid, cfg.network, device)
    assert f.fused_mlp
    with torch.no_grad():
        f.table.mul_(1000.0)
        f.sdf_net[0].weight[:, 3:].normal_()
    x0 = (torch.rand(700, 3, generator=torch.Generator().manual_seed(6)) * 2.2 - 1.1).to(device)
    res = []
    for fused in (True, False):
        f.fused_mlp = fused
        x = x0.clone().requires_grad_()
        s, geo, g, _ = f.sdf_and_grad(x)
        loss = ((g.norm(dim=-1) - 1) ** 2).mean() + s.abs().mean() + geo.square().mean() + (g * x).sum()
        res.append(torch.autograd.grad(loss, [f.table, x, *f.sdf_net.parameters()]))
    for i, (a, b) in enumerate(zip(*res)):
        assert float(b.abs().max()) > 0, i
        assert float((a - b).abs().max()) <= 1e-4 * float(b.abs().max()), i


@pytest.mark.parametrize("device", DEVICES)
def test_colour_stack_and_colsum_match_autograd(device):
    """mlp_forward (the colour network's Linear nodes with the bias gradient as a matrix
    product) against calling the module: same output and gradients to the input and every
    weight for the same random upstream gradient; colsum against sum(0)."""
    from fastneus.field.sdf_mlp import colsum, mlp_forward

    g0 = torch.Generator(device="cpu").manual_seed(int(torch.randint(0, 2**31 - 1, (1,))))
    net = nn.Sequential(nn.Linear(21, 64), nn.ReLU(inplace=True), nn.Linear(64, 64), nn.ReLU(inplace=True),
                        nn.Linear(64, 3)).to(device)
    x = torch.randn(5000, 21, generator=g0).to(device)
    up = torch.randn(5000, 3, generator=g0).to(device)
    results = []
    for ours in (True, False):
        for p in net.parameters():
            p.grad = None
        xi = x.clone().requires_grad_()
        out = mlp_forward(net, xi) if ours else net(xi)
        (out * up).sum().backward()
        results.append([out.detach(), xi.grad] + [p.grad.clone() for p in net.parameters()])
    for i, (a, b) in enumerate(zip(*results)):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5 * (float(b.abs().max()) + 1e-12), msg=str(i))
    y = torch.randn(70001, 16, generator=g0).to(device)
    # against float64: float32 sums of 70k values differ by ~1e-3 between summation orders; a
    # dropped or doubled row (|y| ~ 1) would be far outside this bound
    ref = y.double().sum(0)
    bound = 1e-6 * y.double().abs().sum(0) + 1e-4
    for gemm in (None, True, False):
        err = (colsum(y, gemm).double() - ref).abs()
        assert bool((err <= bound).all()), (gemm, float((err - bound).max()))


def test_colour_stack_gradcheck_float64():
    from fastneus.field.sdf_mlp import mlp_forward

    torch.manual_seed(3)
    net = nn.Sequential(nn.Linear(5, 6), nn.ReLU(inplace=True), nn.Linear(6, 2)).double()
    x = torch.randn(7, 5, dtype=torch.float64, requires_grad=True)
    params = list(net.parameters())
    assert torch.autograd.gradcheck(lambda x, *p: mlp_forward(net, x), (x, *params))
