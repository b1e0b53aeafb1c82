"""Occupancy grid and ray marching: Warp ops against their torch twins and the contract."""
from __future__ import annotations

import math

import pytest
import torch

from fastneus.kernels import get_op
from fastneus.kernels import occupancy as occ

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA"))]


def _random_rays(R: int, device: str, gen: torch.Generator):
    """Rays from outside (some missing the sphere) and from inside the unit sphere."""
    o = torch.randn(R, 3, generator=gen) * 1.5
    o[: R // 4] *= 0.3  # a quarter start inside
    d = torch.nn.functional.normalize(torch.randn(R, 3, generator=gen), dim=1)
    # a few axis-aligned directions exercise the box slab test's d == 0 branch
    d[-3:] = torch.tensor([[1.0, 0, 0], [0, -1.0, 0], [0, 0, 1.0]])
    # aim half the outside rays roughly at the centre so that many hit
    aim = torch.nn.functional.normalize(-o + 0.4 * torch.randn(R, 3, generator=gen), dim=1)
    half = torch.rand(R, generator=gen) < 0.5
    d = torch.where(half[:, None], aim, d)
    return o.to(device), d.to(device), torch.rand(R, generator=gen).to(device)


def _assert_same(a, b):
    offsets, counts, t0, t1, ray = a
    offsets2, counts2, t02, t12, ray2 = b
    for x in a + b:
        assert x.dtype in (torch.int32, torch.float32)
    assert torch.equal(counts, counts2)
    assert torch.equal(offsets, offsets2)
    assert torch.equal(ray, ray2)
    assert t0.shape == t02.shape and t1.shape == t12.shape
    if t0.numel():
        assert (t0 - t02).abs().max().item() <= 1e-6
        assert (t1 - t12).abs().max().item() <= 1e-6
    # packing invariants
    assert torch.equal(offsets, torch.cumsum(counts, 0, dtype=torch.int32) - counts)
    if t0.numel():
        assert torch.equal(ray.long(), torch.repeat_interleave(torch.arange(len(counts), device=ray.device),
                                                                  counts.long()))
        assert bool((t1 > t0).all())


@pytest.mark.parametrize("device", DEVICES)
def test_march_writes_into_given_buffers(device):
    """``out``: the samples go into the first S entries of the caller's buffers (a captured
    step's fixed ones), the rest is left as it was; a buffer too short or of the wrong type is
    refused before anything is written; both backends alike."""
    gen = torch.Generator().manual_seed(int(torch.randint(0, 2**31 - 1, (1,))))
    res = 16
    bits = (torch.rand(res**3, generator=gen) < 0.4).to(torch.uint8).to(device)
    o, d, jitter = _random_rays(400, device, gen)
    args = (o, d, bits, res, 0.02, 32, jitter, "sphere", 0.0)
    for fn in (occ.march_rays, occ.march_rays_torch):
        ref = fn(*args)
        s = ref[2].shape[0]
        assert s > 100
        bufs = (torch.full((s + 50,), -7.0, device=device), torch.full((s + 50,), -7.0, device=device),
                torch.full((s + 50,), -7, dtype=torch.int32, device=device))
        seen = []
        got = fn(*args, out=lambda total: seen.append(total) or bufs)
        assert seen == [s]
        _assert_same(got, ref)
        for g, b in zip(got[2:], bufs):
            assert g.data_ptr() == b.data_ptr() and g.shape[0] == s
            assert bool((b[s:] == -7).all())  # the padding untouched
        _assert_same(fn(*args, out=lambda total: None), ref)  # None: fresh tensors
        for bad in ((bufs[0][:s - 1], bufs[1], bufs[2]), (bufs[0], bufs[1], bufs[2].float()),
                    (bufs[0], bufs[1][::2], bufs[2])):
            with pytest.raises(ValueError, match="march out buffer"):
                fn(*args, out=lambda total, bad=bad: bad)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("bound", ["sphere", "box"])
def test_march_matches_twin(device, bound):
    gen = torch.Generator().manual_seed(int(torch.randint(0, 2**31 - 1, (1,))))
    res = 24
    bits = (torch.rand(res**3, generator=gen) < 0.35).to(torch.uint8).to(device)
    o, d, jitter = _random_rays(1500, device, gen)
    args = (o, d, bits, res, 0.013, 48, jitter, bound, 0.05)
    w = get_op("march_rays", "warp")(*args)
    t = get_op("march_rays", "torch")(*args)
    _assert_same(w, t)
    counts = w[1]
    assert int(counts.sum()) > 1000 and bool((counts == 0).any())  # the test exercises both cases
    assert int(counts.max()) <= 48
    tn, tf, hit = occ.ray_bounds(o, d, bound, 0.05)
    assert bool((counts[~hit] == 0).all())
    if w[2].numel():
        ri = w[4].long()
        assert bool((w[2] >= tn[ri] - 1e-6).all()) and bool((w[3] <= tf[ri] + 1e-6).all())


@pytest.mark.parametrize("device", DEVICES)
def test_march_edge_cases(device):
    res = 8
    bits = torch.ones(res**3, dtype=torch.uint8, device=device)
    empty = torch.zeros(0, 3, device=device)
    for fn in (occ.march_rays, occ.march_rays_torch):
        out = fn(empty, empty, bits, res, 0.1, 16, torch.zeros(0, device=device))
        assert [x.shape[0] for x in out] == [0, 0, 0, 0, 0]
    # one ray through the centre along +x: t in [1, 3], 20 steps of 0.1, cap 16
    o = torch.tensor([[-2.0, 0.0, 0.0]], device=device)
    d = torch.tensor([[1.0, 0.0, 0.0]], device=device)
    j = torch.zeros(1, device=device)
    w = occ.march_rays(o, d, bits, res, 0.1, 16, j)
    _assert_same(w, occ.march_rays_torch(o, d, bits, res, 0.1, 16, j))
    assert w[1].tolist() == [16] and abs(w[2][0].item() - 1.0) < 1e-6
    w = occ.march_rays(o, d, bits, res, 0.1, 100, j)
    assert w[1].tolist() == [20] and abs(w[3][-1].item() - 3.0) < 1e-6
    # a ray that misses, and a ray pointing away from the sphere
    o2 = torch.tensor([[0.0, 2.0, 0.0], [0.0, 0.0, 2.0]], device=device)
    d2 = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], device=device)
    for fn in (occ.march_rays, occ.march_rays_torch):
        out = fn(o2, d2, bits, res, 0.1, 16, torch.rand(2, device=device))
        assert out[1].tolist() == [0, 0] and out[2].numel() == 0


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("bound", ["sphere", "box"])
def test_march_empty_and_full_grid(device, bound):
    gen = torch.Generator().manual_seed(int(torch.randint(0, 2**31 - 1, (1,))))
    res, step, cap = 16, 0.02, 90  # sphere spans reach 100 steps, box spans 173
    o, d, _ = _random_rays(800, device, gen)
    zeros = torch.zeros(800, device=device)
    for fn in (occ.march_rays, occ.march_rays_torch):
        out = fn(o, d, torch.zeros(res**3, dtype=torch.uint8, device=device), res, step, cap, zeros, bound)
        assert int(out[1].sum()) == 0 and out[2].numel() == 0
    full = torch.ones(res**3, dtype=torch.uint8, device=device)
    counts = occ.march_rays(o, d, full, res, step, cap, zeros, bound)[1].cpu().double()
    tn, tf, hit = occ.ray_bounds(o, d, bound)
    q = ((tf - tn).double() / step).cpu()
    expect = torch.where(hit.cpu(), torch.ceil(q), torch.zeros_like(q)).clamp(max=cap)
    # float32 rounding may move the count by one only where the span is a whole number of steps
    ok = (counts == expect) | ((q - q.round()).abs() < 1e-4)
    assert bool(ok.all())
    assert int((counts == cap).sum()) > 0 and int(((counts > 0) & (counts < cap)).sum()) > 0


def _sphere_sdf(x: torch.Tensor) -> torch.Tensor:
    return x.norm(dim=-1) - 0.5


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("backend", ["warp", "torch"])
def test_grid_update_sphere(device, backend):
    res = 32
    grid = occ.OccupancyGrid(res, device=device)
    assert grid.occupied_fraction() == 1.0  # occupied until the first update
    grid.update(_sphere_sdf, inv_s=20.0, step=0.01, chunk=5000, backend=backend)
    centre_sdf = _sphere_sdf(grid.cell_centers(jitter=False)).abs()
    half_diag = math.sqrt(3) / res  # half the diagonal of a cell of size 2/res
    shell = centre_sdf <= half_diag  # cells that contain a point of the surface
    far = centre_sdf > 5 * (2.0 / res)
    assert bool(grid.bits[shell].bool().all())
    assert not bool(grid.bits[far].bool().any())
    assert 0.0 < grid.occupied_fraction() < 0.5
    # EMA: a second update with a far-away surface keeps the shell through the decay...
    grid.update(lambda x: torch.full((x.shape[0],), 10.0, device=x.device), 20.0, 0.01, decay=0.95)
    assert bool(grid.bits[shell].bool().all())
    # ...and the state round-trips
    state = grid.state_dict()
    g2 = occ.OccupancyGrid(res, device=device)
    g2.load_state_dict(state)
    assert torch.equal(g2.bits, grid.bits) and torch.equal(g2.values, grid.values)
    # warm-up marks everything
    grid.update(_sphere_sdf, 20.0, 0.01, warmup=True)
    assert grid.occupied_fraction() == 1.0
    # a random subset only touches part of the grid
    g3 = occ.OccupancyGrid(res, device=device)
    g3.update(_sphere_sdf, 20.0, 0.01, subset=0.25, backend=backend)
    assert 0 < int((g3.values > 0).sum()) <= math.ceil(0.25 * res**3)


@pytest.mark.parametrize("device", DEVICES)
def test_grid_march_uses_bits(device):
    gen = torch.Generator().manual_seed(int(torch.randint(0, 2**31 - 1, (1,))))
    grid = occ.OccupancyGrid(16, device=device)
    grid.update(_sphere_sdf, 20.0, 0.02)
    o, d, j = _random_rays(300, device, gen)
    w = grid.march(o, d, 0.02, 64, j, backend="warp")
    _assert_same(w, grid.march(o, d, 0.02, 64, j, backend="torch"))
    if w[2].numel():  # every emitted midpoint lies in an occupied cell near the shell
        mid = (w[2] + w[3]) * 0.5
        x = o[w[4].long()] + mid[:, None] * d[w[4].long()]
        assert float(_sphere_sdf(x).abs().max()) < 0.5


@pytest.mark.parametrize("device", DEVICES)
def test_occupancy_alpha_matches_twin(device):
    sdf = (torch.randn(20000) * 0.3).to(device)
    for inv_s, step in ((20.0, 0.01), (300.0, 0.005), (4000.0, 0.002)):
        a = get_op("occupancy_alpha", "warp")(sdf, inv_s, step)
        b = get_op("occupancy_alpha", "torch")(sdf, inv_s, step)
        assert a.shape == sdf.shape and a.dtype == torch.float32
        assert (a - b).abs().max().item() <= 1e-6
        assert bool(((a >= 0) & (a <= 1)).all())
    # alpha falls with |sdf|, is symmetric in its sign, and equals the sigmoid-difference form
    x = torch.linspace(0, 1, 101, device=device)
    a = occ.occupancy_alpha(x, 50.0, 0.01)
    assert bool((a[1:] <= a[:-1]).all())
    xd = x.double()
    prev, nxt = torch.sigmoid(50.0 * (xd + 0.005)), torch.sigmoid(50.0 * (xd - 0.005))
    assert torch.allclose(a.double(), (prev - nxt) / prev, rtol=1e-5, atol=1e-7)
    assert torch.allclose(occ.occupancy_alpha(-x, 50.0, 0.01), a)
    assert occ.occupancy_alpha(torch.zeros(0, device=device), 50.0, 0.01).shape == (0,)


def test_rays_for_target():
    assert occ.rays_for_target(2**18, 64.0, 256, 2**16) == 4096
    assert occ.rays_for_target(2**18, 1.0, 256, 8192) == 8192
    assert occ.rays_for_target(2**18, 1e6, 256, 8192) == 256
    assert occ.rays_for_target(1000, 3.0, 1, 10**6) == 333
    assert occ.rays_for_target(1000, 0.0, 1, 77) == 77


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("bound", ["sphere", "box"])
def test_march_stop_cells_match_twin(device, bound):
    """Random stop cells: the Warp op and its twin end every ray at the same sample; each ray's
    samples are the unstopped march's first ones, and none lies at or past its first stop cell."""
    gen = torch.Generator().manual_seed(int(torch.randint(0, 2**31 - 1, (1,))))
    res = 24
    bits = (torch.rand(res**3, generator=gen) < 0.35).to(torch.uint8).to(device)
    stop = ((torch.rand(res**3, generator=gen) < 0.08).to(torch.uint8) * (1 - bits.cpu())).to(device)
    o, d, jitter = _random_rays(1500, device, gen)
    args = (o, d, bits, res, 0.013, 48, jitter, bound, 0.05)
    w = get_op("march_rays", "warp")(*args, stop)
    _assert_same(w, get_op("march_rays", "torch")(*args, stop))
    free = get_op("march_rays", "warp")(*args)
    assert bool((w[1] <= free[1]).all()) and int(w[1].sum()) < int(free[1].sum())  # rays were cut
    assert int(w[1].sum()) > 200
    for r in torch.nonzero(w[1] > 0).flatten()[:50].tolist():  # a prefix of the free march's samples
        a, n, fa = int(w[0][r]), int(w[1][r]), int(free[0][r])
        assert torch.equal(w[2][a:a + n], free[2][fa:fa + n])
    # no sample of a ray lies past a stop cell on its way: check the cells of its midpoints' path
    mid = (w[2] + w[3]) * 0.5
    x = o[w[4].long()] + mid[:, None] * d[w[4].long()]
    cell = ((x + 1) * 0.5 * res).floor().long().clamp(0, res - 1)
    lin = cell[:, 0] + cell[:, 1] * res + cell[:, 2] * res * res
    assert not bool(stop[lin].bool().any())
    # an all-zero stop grid is the plain march
    _assert_same(get_op("march_rays", "warp")(*args, torch.zeros_like(stop)), free)


@pytest.mark.parametrize("device", DEVICES)
def test_grid_stop_cells_are_deep_inside(device):
    """``inside`` marks the cells whose SDF is below -inside (never an occupied one); a ray
    through the sphere then keeps its front shell's samples and drops the back shell's."""
    res = 32
    grid = occ.OccupancyGrid(res, device=device)
    grid.update(_sphere_sdf, 100.0, 0.01, chunk=5000)
    assert grid.stop is None
    inside = 2 * 2.0 / res  # deep inside: |x| < 0.375, so a ray at |x| <= 0.15 crosses 0.68 of it
    # a sharp surface (s = 100): the occupied shell is thinner than the stop depth
    grid.update(_sphere_sdf, 100.0, 0.01, chunk=5000, margin=math.sqrt(3) / res, inside=inside)
    c = _sphere_sdf(grid.cell_centers(jitter=False))
    half_diag = math.sqrt(3) / res
    assert bool(grid.stop[c < -inside - half_diag].bool().all())
    assert not bool(grid.stop[c > -inside + half_diag].bool().any())
    assert not bool((grid.stop.bool() & grid.bits.bool()).any())
    o = torch.tensor([[0.0, 0.0, -2.0]], device=device).repeat(8, 1)
    o[:, 0] = torch.linspace(-0.15, 0.15, 8)
    d = torch.tensor([[0.0, 0.0, 1.0]], device=device).repeat(8, 1)
    w = grid.march(o, d, 0.01, 1024, torch.full((8,), 0.5, device=device))
    mid = o[w[4].long(), 2] + (w[2] + w[3]) * 0.5
    assert w[2].numel() > 0 and float(mid.max()) < 0.0  # all samples in the front half (z < 0)
    grid.stop = None
    full = grid.march(o, d, 0.01, 1024, torch.full((8,), 0.5, device=device))
    assert float((o[full[4].long(), 2] + (full[2] + full[3]) * 0.5).max()) > 0.5  # the back shell too
    grid.update(_sphere_sdf, 20.0, 0.01, warmup=True)
    assert grid.stop is None


def _with_neighbours(bits: torch.Tensor) -> torch.Tensor:
    """[R^3] bool: the set cells of a [R^3] grid and their 26 neighbours."""
    r = round(bits.numel() ** (1 / 3))
    return (torch.nn.functional.max_pool3d(bits.view(1, 1, r, r, r).float(), 3, 1, 1) > 0).view(-1)


@pytest.mark.parametrize("device", DEVICES)
def test_grid_update_near_queries_the_occupied_cells_and_their_neighbours(device):
    """``near``: a moved surface within a cell of the occupied shell is found as by a full update;
    the cells away from it are queried only at the ``near`` rate, so a surface that jumps far is
    missed at ``near=0`` and found at ``near=1``."""
    res = 32
    seen = []

    def sdf_at(r):
        def f(x):
            seen.append(x.shape[0])
            return x.norm(dim=-1) - r
        return f

    margin = math.sqrt(3) / res  # as the trainer: a cell the surface crosses stays occupied
    full, sparse = occ.OccupancyGrid(res, device=device), occ.OccupancyGrid(res, device=device)
    full.update(sdf_at(0.5), 100.0, 0.01, margin=margin)
    sparse.load_state_dict(full.state_dict())
    cell = 2.0 / res
    queried = _with_neighbours(sparse.bits)
    ring = int(queried.sum())
    full.update(sdf_at(0.5 + 0.4 * cell), 100.0, 0.01, margin=margin)
    seen.clear()
    sparse.update(sdf_at(0.5 + 0.4 * cell), 100.0, 0.01, margin=margin, near=0.0)
    # the cells that hold the moved surface are found, and every cell a full update occupies was
    # queried (bits outside the queried cells agree: only the cells' random query points differ)
    moved = (full.cell_centers(jitter=False).norm(dim=-1) - 0.5 - 0.4 * cell).abs() <= math.sqrt(3) / res
    assert bool(sparse.bits[moved].bool().all())
    assert torch.equal(full.bits[~queried], sparse.bits[~queried])
    assert int(full.bits[~queried].sum()) == 0
    # queried: exactly the occupied shell and its neighbours, far fewer than every cell
    assert sum(seen) == ring and int(sparse.bits.sum()) < ring < res ** 3 // 2
    # a surface far from the shell (radius 0.5 -> 0.9): not seen at near=0, seen at near=1
    far = (full.cell_centers(jitter=False).norm(dim=-1) - 0.9).abs() < 0.5 * cell
    g0, g1 = occ.OccupancyGrid(res, device=device), occ.OccupancyGrid(res, device=device)
    g0.load_state_dict(sparse.state_dict())
    g1.load_state_dict(sparse.state_dict())
    g0.update(sdf_at(0.9), 100.0, 0.01, margin=margin, near=0.0)
    g1.update(sdf_at(0.9), 100.0, 0.01, margin=margin, near=1.0)
    assert not bool(g0.bits[far].bool().any()) and bool(g1.bits[far].bool().all())
    # a fraction in between queries about that share of the other cells
    near_before = int(_with_neighbours(g0.bits).sum())
    seen.clear()
    g0.update(sdf_at(0.5), 100.0, 0.01, margin=margin, near=0.5)
    away = res ** 3 - near_before
    assert abs(sum(seen) - near_before - 0.5 * away) < 0.05 * away


@pytest.mark.parametrize("device", DEVICES)
def test_capped_march_matches_the_march_and_its_twin(device):
    """march_rays_capped: with room for every sample, the same as march_rays (written into the
    fixed buffers, total on the device); with too little room, the first C packed samples, each
    ray's count clamped to what fits, total unclamped; Warp and torch twin alike."""
    gen = torch.Generator().manual_seed(int(torch.randint(0, 2**31 - 1, (1,))))
    res = 16
    bits = (torch.rand(res**3, generator=gen) < 0.4).to(torch.uint8).to(device)
    o, d, jitter = _random_rays(300, device, gen)
    args = (o, d, bits, res, 0.02, 32, jitter, "sphere", 0.0, None)
    ref = occ.march_rays(*args)
    s = int(ref[2].shape[0])
    assert s > 200
    for cap in (s + 40, s // 2):
        got = []
        for fn in (occ.march_rays_capped, occ.march_rays_capped_torch):
            bufs = (torch.full((300,), -1, dtype=torch.int32, device=device), torch.full((300,), -1, dtype=torch.int32, device=device),
                    torch.zeros(1, dtype=torch.int32, device=device), torch.full((cap,), -7.0, device=device),
                    torch.full((cap,), -7.0, device=device), torch.full((cap,), -7, dtype=torch.int32, device=device))
            fn(*args, out=bufs)
            offsets, counts, total, t0, t1, ri = bufs
            assert int(total) == s and torch.equal(offsets, ref[0])
            n = min(s, cap)
            assert int(counts.sum()) == n and bool((counts <= ref[1]).all())
            assert bool(((offsets + counts <= cap) | (counts == 0)).all())
            assert torch.equal(t0[:n], ref[2][:n]) and torch.equal(ri[:n], ref[4][:n])
            assert bool((t0[n:] == -7).all())  # the rest untouched
            got.append(bufs)
        for x, y in zip(*got):
            assert torch.equal(x, y)
    with pytest.raises(ValueError, match="march out buffer"):
        occ.march_rays_capped(*args, out=(bufs[0][:10],) + bufs[1:])
