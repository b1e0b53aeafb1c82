"""project_pattern (Warp) vs its torch twin, gradcheck, a closed form (the blurred pattern),
and the render op's q_ext input (same maths as its own pattern sampling)."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from fastneus.kernels.project import (identity_blur, port_dir_torch, port_row, project_pattern,
                                      project_pattern_torch)
from fastneus.kernels.render import render_pattern, render_pattern_torch
from fastneus.geometry.projection import sample_pattern
from test_render import DEVICES, _close, _close_to_ref, _seed, make_inputs

PROJ_ARGS = ("pos", "ray_index", "offsets", "counts", "ray_frame", "proj_K", "proj_W", "proj_pattern", "patterns")


def _blur(P, n, gen, dtype=torch.float32):
    b = torch.rand(P, n * n, generator=gen, dtype=torch.float64) + 0.05
    return (b / b.sum(1, keepdim=True)).to(dtype)


def _pargs(inp, **kw):
    d = {k: inp[k] for k in PROJ_ARGS}
    d.update(kw)
    return d


def _medium(P, gen, device, dtype=torch.float32):
    """Random flat ports on every projector but the first, and a random attenuation."""
    rows = []
    for k in range(P):
        if k == 0:
            rows.append([0.0] * 8)
            continue
        nrm = torch.tensor([0.0, 0.0, 1.0]) + 0.2 * torch.randn(3, generator=gen)
        d0, t = (0.05 + 0.2 * torch.rand(2, generator=gen)).tolist()
        rows.append(port_row(nrm.tolist(), d0, t, 1.0, 1.5, 1.333))
    sigma = 0.05 + 0.4 * torch.rand(3, generator=gen, dtype=torch.float64)
    return torch.tensor(rows, dtype=dtype, device=device), sigma.to(dtype).to(device)


def _vs_twin(inp, blur, port, sigma, gen, device, tag):
    """project_pattern (float32) against the float64 twin: q, then the gradients of pos, W,
    blur (and sigma) for one random upstream gradient. Returns the op's gradients."""
    medium = sigma is not None
    pos = inp["pos"].clone().requires_grad_(True)
    W = inp["proj_W"].clone().requires_grad_(True)
    b = blur.clone().requires_grad_(True)
    sg = None if sigma is None else sigma.clone().requires_grad_(True)
    q = project_pattern(**_pargs(inp, pos=pos, proj_W=W), blur=b, port=port, sigma=sg)
    pos64 = inp["pos"].double().requires_grad_(True)
    W64 = inp["proj_W"].double().requires_grad_(True)
    b64 = blur.double().requires_grad_(True)
    sg64 = None if sigma is None else sigma.double().requires_grad_(True)
    q64 = project_pattern_torch(**_pargs(inp, pos=pos64, proj_W=W64), blur=b64,
                                port=None if port is None else port.double(), sigma=sg64)
    with torch.no_grad():  # the float32 twin: the rounding any float32 implementation shows
        q32 = project_pattern_torch(**_pargs(inp), blur=blur, port=port, sigma=sigma)
    # one sample of 0.02 once differed by 2.5e-7 (1.3e-5 relative): float32 rounding, not maths
    _close_to_ref(q, q64, q32, 1e-5, f"q ({tag})")
    if q.shape[0] > 50:
        assert q.abs().max() > 0  # some samples are lit
    up = torch.randn(q.shape, generator=gen, dtype=torch.float64).to(device)
    ins_a = [pos, W, b] + ([sg] if medium else [])
    ins_b = [pos64, W64, b64] + ([sg64] if medium else [])
    ga = torch.autograd.grad((q * up.float()).sum(), ins_a, allow_unused=True)
    gb = torch.autograd.grad((q64 * up).sum(), ins_b, allow_unused=True)
    for name, a, r in zip(("pos", "proj_W", "blur", "sigma"), ga, gb):
        a = torch.zeros_like(r) if a is None else a
        r = torch.zeros_like(a) if r is None else r
        assert a.shape == r.shape and a.dtype == torch.float32, f"d{name} ({tag})"
        _close(a, r, 3e-4, f"d{name} ({tag})")
    return ga


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("size,n,medium", [((0, 2, 2, 8), 3, False), ((1, 2, 3, 1), 1, False),
                                           ((64, 3, 4, 24), 3, False), ((257, 2, 3, 32), 5, False),
                                           ((64, 3, 3, 24), 1, True), ((200, 2, 3, 16), 3, True)])
def test_forward_backward_vs_twin(size, n, medium, device):
    seed = _seed()
    R, F, P, m = size
    inp = make_inputs(R, F, P, m, seed, device=device)
    gen = torch.Generator().manual_seed(seed)
    blur = _blur(P, n, gen).to(device)
    port, sigma = _medium(P, gen, device) if medium else (None, None)
    if medium:  # keep refracted projections off the pixel-cell boundaries, as make_inputs does for pinholes
        _avoid_cell_edges(inp, port, n)
    _vs_twin(inp, blur, port, sigma, gen, device, f"seed {seed}")


# ((R, F, P, max samples per ray), stripe rows, medium): no samples at all, one sample, and
# ~2-5 k samples over a few (frame, projector) pairs, so every row is hit many times over
STRIPE_CASES = [((5, 2, 2, 0), 7, False), ((1, 2, 3, 1), 7, True), ((300, 2, 3, 40), 1, False),
                ((300, 2, 3, 40), 7, False), ((300, 2, 3, 40), 61, False), ((150, 1, 2, 70), 61, True),
                ((200, 2, 2, 30), 7, True)]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("size,stripes,medium", STRIPE_CASES,
                         ids=lambda c: "R{}F{}P{}m{}".format(*c) if isinstance(c, tuple) else str(c))
def test_striped_gradients_vs_twin(size, stripes, medium, device, monkeypatch):
    """The per-sample backward's striped d_W / d_blur / d_sigma sums equal the float64 twin's
    gradients, whatever the row count: rows wrap many times, the sample count is not a
    multiple of it, d_W has fewer rows than d_blur, and rays without samples are interleaved."""
    from fastneus.kernels import project

    R, F, P, m = size
    monkeypatch.setattr(project, "STRIPES", {"cpu": stripes, "cuda": stripes})
    monkeypatch.setattr(project, "STRIPE_FLOATS_W", F * P * 12 * 3)  # d_W: at most 3 rows
    for _ in range(50):
        seed = _seed()
        inp = make_inputs(R, F, P, m, seed, device=device)
        S = inp["pos"].shape[0]
        if S <= 1 or stripes == 1 or S % stripes != 0:
            break
    assert S <= 1 or stripes == 1 or S % stripes != 0, f"seed {seed}"
    if R > 3 and m > 0:
        assert int((inp["counts"][1:-1] == 0).sum()) > 0  # empty rays between non-empty ones
    gen = torch.Generator().manual_seed(seed)
    blur = _blur(P, 3, gen).to(device)
    port, sigma = _medium(P, gen, device) if medium else (None, None)
    if medium:
        _avoid_cell_edges(inp, port, 3)
    ga = _vs_twin(inp, blur, port, sigma, gen, device, f"{stripes} stripes, S={S}, seed {seed}")
    if S > 50:  # the shared gradients are not trivially zero
        assert ga[1].abs().max() > 0 and ga[2].abs().max() > 0, f"seed {seed}"


def test_stripe_rows():
    """CUDA gets many rows, capped by the d_W budget and the sample count; CPU one."""
    from fastneus.kernels import project

    cuda, cpu = torch.device("cuda"), torch.device("cpu")
    assert project._stripes(cpu, 10 ** 5, 48 * 12) == (1, 1)
    assert project._stripes(cuda, 10 ** 5, 48 * 12) == (project.STRIPES["cuda"],) * 2
    assert project._stripes(cuda, 5, 48 * 12) == (5, 5)
    assert project._stripes(cuda, 0, 48 * 12) == (1, 1)
    rows_w, rows_b = project._stripes(cuda, 10 ** 5, 2000 * 8 * 12)
    assert 1 <= rows_w < rows_b and rows_w * 2000 * 8 * 12 <= project.STRIPE_FLOATS_W


def _avoid_cell_edges(inp, port, n, margin=2e-3, min_cos=0.35):
    """Redraw sample positions whose refracted projection sits near a pixel-cell boundary, or
    whose air-side ray meets the port within acos(min_cos) ~ 70 deg of grazing.

    Near grazing, cos = sqrt(1 - s^2) loses its digits in float32 (seeds 442, 727: cos 0.026
    gave 3e-3 px of float32 error in the Warp op and in the float32 twin alike, so q differed
    from the float64 twin by 2e-4); a flat port's field of view never reaches there.
    """
    pos, W, K = inp["pos"], inp["proj_W"], inp["proj_K"]
    fr = inp["ray_frame"].long()[inp["ray_index"].long()]
    for _ in range(100):
        bad = torch.zeros(pos.shape[0], dtype=torch.bool, device=pos.device)
        for k in range(W.shape[1]):
            X = torch.einsum("sij,sj->si", W[fr, k, :, :3].double(), pos.double()) + W[fr, k, :, 3].double()
            V = port_dir_torch(X, port[k].double()) if float(port[k, 7]) else X
            if float(port[k, 7]):
                cos = (V @ port[k, :3].double()) / V.norm(dim=-1).clamp(min=1e-12)
                bad |= (cos < min_cos) & (X[:, 2] > 0)
            u = torch.einsum("sij,sj->si", K[fr, k].double(), V)
            for c in (0, 1):
                x = u[:, c] / V[:, 2] - 0.5
                fx = x - torch.floor(x)
                bad |= (torch.minimum(fx, 1 - fx) < margin) & (V[:, 2] > 0)
        if not bad.any():
            return
        pos[bad] = (torch.rand(int(bad.sum()), 3, device=pos.device) * 2.4 - 1.2).to(pos.dtype)


def test_port_direction_obeys_snell_and_reaches_the_point():
    """Trace the air ray V through the port (Snell at both glass faces): it passes through X."""
    gen = torch.Generator().manual_seed(_seed())
    port = torch.tensor(port_row([0.1, -0.05, 1.0], 0.08, 0.02, 1.0, 1.5, 1.333), dtype=torch.float64)
    X = torch.randn(50, 3, generator=gen, dtype=torch.float64) * torch.tensor([0.6, 0.6, 0.3]) + \
        torch.tensor([0.0, 0.0, 1.5])
    V = port_dir_torch(X, port)
    n = port[:3]

    def refract(d, eta):
        cos = d @ n
        tang = d - cos[:, None] * n
        return eta * tang + torch.sqrt(1 - eta ** 2 * (tang * tang).sum(-1))[:, None] * n

    A = V * (0.08 / (V @ n))[:, None]
    g = refract(V, 1 / 1.5)
    B = A + g * (0.02 / (g @ n))[:, None]
    w = refract(g, 1.5 / 1.333)
    t = ((X - B) * w).sum(-1)
    miss = (B + t[:, None] * w - X).norm(dim=-1)
    assert float(miss.max()) < 1e-9
    assert torch.allclose(V.norm(dim=-1), torch.ones(50, dtype=torch.float64))


def test_gradcheck_twin():
    seed = _seed()
    inp = make_inputs(5, 2, 2, 4, seed, px_margin=1e-2, dtype=torch.float64)
    gen = torch.Generator().manual_seed(seed)
    blur = _blur(2, 3, gen, torch.float64).requires_grad_(True)
    pos = inp["pos"].clone().requires_grad_(True)
    W = inp["proj_W"].clone().requires_grad_(True)

    def f(p, w, b):
        return project_pattern_torch(**_pargs(inp, pos=p, proj_W=w), blur=b)

    assert torch.autograd.gradcheck(f, (pos, W, blur), eps=1e-7, atol=1e-5), f"seed {seed}"
    port, sigma = _medium(2, gen, "cpu", torch.float64)
    _avoid_cell_edges(inp, port, 3, margin=1e-2)
    pos = inp["pos"].clone().requires_grad_(True)
    sigma.requires_grad_(True)

    def g(p, w, b, sg):
        return project_pattern_torch(**_pargs(inp, pos=p, proj_W=w), blur=b, port=port, sigma=sg)

    assert torch.autograd.gradcheck(g, (pos, W, blur, sigma), eps=1e-7, atol=1e-5), f"seed {seed}"


@pytest.mark.parametrize("op", [project_pattern, project_pattern_torch])
def test_closed_form_blurred_pattern(op):
    """Inside the pattern, Q with an n x n kernel = the pattern correlated with it (cv2.filter2D),
    sampled bilinearly."""
    for _ in range(50):  # patterns are small (4..24 px): draw until some samples land well inside
        seed = _seed()
        inp = make_inputs(60, 1, 1, 16, seed)
        pat = inp["patterns"].image(int(inp["proj_pattern"][0, 0])).numpy().astype(np.float64) / 255.0
        W, K = inp["proj_W"][0, 0].double(), inp["proj_K"][0, 0].double()
        X = inp["pos"].double() @ W[:, :3].T + W[:, 3]
        px = (X @ K.T)[:, :2] / X[:, 2:]
        h, w = pat.shape[:2]
        inner = (X[:, 2] > 0) & (px[:, 0] > 2.5) & (px[:, 0] < w - 2.5) & (px[:, 1] > 2.5) & (px[:, 1] < h - 2.5)
        if inner.sum() >= 5:
            break
    assert inner.sum() >= 5
    gen = torch.Generator().manual_seed(seed)
    blur = _blur(1, 3, gen)
    q = op(**_pargs(inp), blur=blur)
    conv = cv2.filter2D(pat, -1, blur[0].reshape(3, 3).double().numpy(), borderType=cv2.BORDER_CONSTANT)
    ref = sample_pattern(torch.from_numpy(conv), px)
    _close(q[inner], ref[inner], 1e-5, f"closed form (seed {seed})")


@pytest.mark.parametrize("render", [render_pattern, render_pattern_torch])
def test_render_with_identity_q_ext_equals_own_sampling(render):
    """q_ext from project_pattern with the 1x1 identity kernel reproduces the render op's own
    pattern sampling: colour and every gradient (pos and proj_W now flow through q_ext)."""
    seed = _seed()
    inp = make_inputs(64, 3, 3, 16, seed)
    gen = torch.Generator().manual_seed(seed)
    names = ("sdf", "color", "pos", "proj_W", "i_r", "i_b")
    ups = {k: torch.randn(64, *(3,) * (k in ("color", "texture")), generator=gen) for k in
           ("color", "opacity", "depth", "texture")}

    def run(with_q):
        x = {k: (v.detach().clone().requires_grad_(k in names) if isinstance(v, torch.Tensor) and v.is_floating_point()
                 else v) for k, v in inp.items()}
        kw = {}
        if with_q:
            kw["q_ext"] = project_pattern(**_pargs(x), blur=identity_blur(3))
        out = render(**x, **kw)
        loss = sum((out[k] * ups[k]).sum() for k in ups)
        return out, dict(zip(names, torch.autograd.grad(loss, [x[k] for k in names])))

    (oa, ga), (ob, gb) = run(False), run(True)
    for k in ups:
        _close(ob[k], oa[k], 1e-5, f"{k} (seed {seed})")
    for k in names:
        _close(gb[k], ga[k], 2e-4, f"d{k} (seed {seed})")


@pytest.mark.parametrize("device", DEVICES)
def test_render_q_ext_gradient_vs_twin(device):
    seed = _seed()
    inp = make_inputs(64, 2, 2, 16, seed, device=device)
    gen = torch.Generator().manual_seed(seed)
    S = inp["sdf"].shape[0]
    q = (torch.rand(S, 3, generator=gen)).to(device)
    ups = torch.randn(64, 3, generator=gen).to(device)
    qa = q.clone().requires_grad_(True)
    qb = q.double().requires_grad_(True)
    a = render_pattern(**inp, q_ext=qa)["color"]
    b = render_pattern_torch(**{k: (v.double() if isinstance(v, torch.Tensor) and v.is_floating_point() else v)
                                for k, v in inp.items()}, q_ext=qb)["color"]
    _close(a, b, 1e-4, f"color (seed {seed})")
    _close(torch.autograd.grad((a * ups).sum(), qa)[0], torch.autograd.grad((b * ups.double()).sum(), qb)[0], 1e-4,
           f"dq_ext (seed {seed})")
