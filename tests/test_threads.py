"""CPU threading of the Warp ops: every chunked op gives the one-thread result.

Each op runs once with one thread and once with 3 or 4 threads and the minimum chunk sizes
scaled to zero, so even a two-core machine splits every launch into as many chunks as it
can (sizes chosen not to divide evenly, and 0 and 1 elements). Inputs are random and fresh
each run; the seed is printed in failure messages. Per-item results must agree exactly
or to float rounding; sums over chunks (table gradient with several point ranges, shared
parameters) agree up to float summation order.
"""
from __future__ import annotations

import os

import pytest
import torch

from fastneus.kernels import _warp
from fastneus.kernels import occupancy as occ
from fastneus.kernels.hashgrid import HashGridConfig, hash_encode, hash_encode_jac, init_table
from fastneus.kernels.project import identity_blur, project_pattern
from fastneus.kernels.raycast import raycast_mesh
from fastneus.kernels.render import render_pattern, render_pattern_torch
from test_render import make_inputs

MANY = (3, 4)  # thread counts forced on any machine


def _seed() -> int:
    return int.from_bytes(os.urandom(4), "little")


@pytest.fixture(autouse=True)
def chunks(monkeypatch):
    """Records the number of tasks of every ``run_tasks`` call (each op's launches)."""
    seen: list[int] = []
    real = _warp.run_tasks

    def spy(tasks, key=None):
        seen.append(len(tasks))
        return real(tasks, key=key)

    monkeypatch.setattr(_warp, "run_tasks", spy)
    return seen


def _run(fn, threads: int, chunks: list | None = None, n: int = 0):
    """``fn()`` with ``threads`` threads; more than one forces the smallest chunks.

    When ``chunks`` (the fixture) is given and the op has ``n >= threads`` items, checks
    that some launch was split.
    """
    if chunks is not None:
        chunks.clear()
    with _warp.threads(threads, min_chunk_scale=0.0 if threads > 1 else None):
        out = fn()
    if chunks is not None and n >= threads:
        # at least two chunks (splits by sample weight may merge ranges of empty rays)
        assert max(chunks, default=0) >= 2, f"no launch was split: {chunks}"
    return out


def _same(a, b, what, rtol=1e-6):
    """Equal to float rounding (relative to the largest magnitude), exactly for integers."""
    if a is None or b is None:
        assert a is None and b is None, what
        return
    assert a.shape == b.shape and a.dtype == b.dtype, what
    if not a.is_floating_point():
        assert torch.equal(a, b), what
        return
    if a.numel() == 0:
        return
    scale = max(b.abs().max().item(), 1e-12)
    err = (a - b).abs().max().item()
    assert err <= rtol * scale, f"{what}: max err {err:.3g} > {rtol} * {scale:.3g}"


def _grads(out, ins, seed):
    """Gradients of a random projection of ``out`` (a tensor or tuple) w.r.t. ``ins``."""
    outs = out if isinstance(out, (tuple, list)) else (out,)
    gen = torch.Generator().manual_seed(seed + 1)
    loss = sum((o * torch.randn(o.shape, generator=gen)).sum() for o in outs if o.is_floating_point())
    g = torch.autograd.grad(loss, ins, allow_unused=True)
    return [torch.zeros_like(x) if v is None else v for x, v in zip(ins, g)]


# ----------------------------------------------------------------------------- helpers themselves

@pytest.mark.parametrize("n,parts", [(0, 3), (1, 4), (5, 3), (7, 4), (1000, 3), (10, 10), (3, 8)])
def test_split_partitions(n, parts):
    r = _warp.split(n, parts)
    assert [x for a, b in r for x in range(a, b)] == list(range(n))
    assert all(b > a for a, b in r) and len(r) <= max(1, parts)
    if r:
        sizes = [b - a for a, b in r]
        assert max(sizes) - min(sizes) <= 1


def test_split_by_weight_partitions_and_balances():
    seed = _seed()
    gen = torch.Generator().manual_seed(seed)
    for R in (1, 2, 7, 300):
        counts = torch.randint(0, 40, (R,), generator=gen)
        offsets = torch.cumsum(counts, 0) - counts
        S = int(counts.sum())
        for parts in (2, 3, 4):
            r = _warp.split_by_weight(offsets.to(torch.int32), S, parts)
            assert [x for a, b in r for x in range(a, b)] == list(range(R)), f"seed {seed}"
            if R == 300 and S > 0:
                per = [int(counts[a:b].sum()) for a, b in r]
                assert max(per) <= S / parts + 40, f"seed {seed}: {per}"


def test_thread_count_resolution(monkeypatch):
    monkeypatch.delenv(_warp.THREADS_ENV, raising=False)
    assert _warp.default_threads() == (_warp.available_cpus(), "auto")
    monkeypatch.setenv(_warp.THREADS_ENV, "3")
    assert _warp.default_threads() == (3, f"env {_warp.THREADS_ENV}")
    for bad in ("0", "-2", "two"):
        monkeypatch.setenv(_warp.THREADS_ENV, bad)
        with pytest.raises(ValueError, match=_warp.THREADS_ENV):
            _warp.default_threads()
    monkeypatch.delenv(_warp.THREADS_ENV)
    with _warp.threads(5):
        assert _warp.get_threads() == 5
        # one chunk on one thread, off the CPU, or below two minimum chunks
        assert _warp.n_chunks(10 ** 6, torch.zeros(1), 1000) == 5 * _warp.CHUNKS_PER_THREAD
        assert _warp.n_chunks(1500, torch.zeros(1), 1000) == 1
    with _warp.threads(1):
        assert _warp.n_chunks(10 ** 6, torch.zeros(1), 1) == 1
    with pytest.raises(ValueError):
        _warp.set_threads(-1)


def test_task_errors_reach_the_caller():
    def boom():
        raise RuntimeError("chunk failed")

    with _warp.threads(3):
        with pytest.raises(RuntimeError, match="chunk failed"):
            _warp.run_tasks([lambda: None, boom, lambda: None, boom])


# ----------------------------------------------------------------------------- ops

@pytest.mark.parametrize("n,active", [(0, 8), (1, 3), (7, 8), (1001, 3), (1001, 5), (4099, 8)])
@pytest.mark.parametrize("threads", MANY)
def test_hash_encode(n, active, threads, chunks):
    seed = _seed()
    gen = torch.Generator().manual_seed(seed)
    cfg = HashGridConfig(levels=8, features=2, log2_table=12, base_res=4, finest_res=128)
    table0 = init_table(cfg, generator=gen) * 1e3
    u0 = torch.rand(n, 3, generator=gen) * 1.1 - 0.05  # a few outside [0, 1] (clamped)

    def once():
        u, table = u0.clone().requires_grad_(True), table0.clone().requires_grad_(True)
        out = hash_encode(u, table, cfg, active)
        return [out] + _grads(out, [u, table], seed)

    ref, got = _run(once, 1), _run(once, threads, chunks, n)
    for name, a, b in zip(("features", "d_u", "d_table"), got, ref):
        _same(a, b, f"{name} (seed {seed}, threads {threads})")


@pytest.mark.parametrize("n,active", [(0, 8), (1, 3), (7, 8), (1001, 3), (1001, 5), (4099, 8)])
@pytest.mark.parametrize("threads", MANY)
def test_hash_encode_jac(n, active, threads, chunks):
    """The analytic-normal op: points split in the forward, level groups in the backward
    (each group after the first with its own dL/du buffer)."""
    seed = _seed()
    gen = torch.Generator().manual_seed(seed)
    cfg = HashGridConfig(levels=8, features=2, log2_table=12, base_res=4, finest_res=128)
    table0 = init_table(cfg, generator=gen) * 1e3
    u0 = torch.rand(n, 3, generator=gen) * 1.1 - 0.05

    def once():
        u, table = u0.clone().requires_grad_(True), table0.clone().requires_grad_(True)
        feats, jac = hash_encode_jac(u, table, cfg, active)
        return [feats, jac] + _grads((feats, jac), [u, table], seed)

    ref, got = _run(once, 1), _run(once, threads, chunks, n)
    if n >= threads:  # the backward split the levels too
        assert sum(1 for c in chunks if c >= 2) >= 2, chunks
    for name, a, b in zip(("features", "jac", "d_u", "d_table"), got, ref):
        _same(a, b, f"{name} (seed {seed}, threads {threads})")


def test_hash_encode_table_gradient_bit_identical_by_levels():
    """Level groups alone (>= threads levels, table gradient only) change no summation order."""
    seed = _seed()
    gen = torch.Generator().manual_seed(seed)
    cfg = HashGridConfig(levels=8, features=2, log2_table=12, base_res=4, finest_res=128)
    table0 = init_table(cfg, generator=gen)
    u = torch.rand(3001, 3, generator=gen)
    up = torch.randn(3001, cfg.out_dim, generator=gen)

    def once():
        table = table0.clone().requires_grad_(True)
        hash_encode(u, table, cfg).backward(up)
        return table.grad

    with _warp.threads(4, min_chunk_scale=0.0):
        assert _warp.n_chunks(3001 * 8, u, 16384) == 8  # 8 level groups of one level, one point range
    assert torch.equal(_run(once, 1), _run(once, 4)), f"seed {seed}"


RENDER_SIZES = [(0, 2, 2, 8), (1, 2, 3, 1), (5, 2, 1, 0), (7, 3, 2, 20), (257, 2, 3, 32)]
RENDER_DIFF = ("sdf", "grad", "color", "pos", "inv_s", "i_r", "i_b", "proj_W")
RENDER_OUTS = ("color", "opacity", "depth", "texture")
SHARED = ("inv_s", "i_r", "i_b", "proj_W")
U32 = 2.0 ** -24  # float32 unit roundoff


def _ray_norms(inp: dict, q0, seed: int) -> dict:
    """L2 norm over rays of each ray's contribution to the shared-parameter gradients.

    Only the order in which the R per-ray contributions are added differs between chunkings
    (each ray's own term is the same code either way). Partial sums of terms with random
    signs are about this norm in size, so each float32 addition is off by up to ``u`` times
    it and R of them add up like a random walk: ``sqrt(R) u norm``, however much the signed
    total cancels. A ray lost or counted twice moves the result by a whole term, about
    ``norm / sqrt(R)``, thousands of times more. Computed exactly by the float64 torch twin,
    one batched backward pass per ray (the upstream gradient of ``_grads`` on that ray only).

    Returns:
        name -> tensor shaped like the parameter ([1], or [F, P, 3, 4] for proj_W).
    """
    args = {k: (v.detach().double().requires_grad_(k in SHARED) if isinstance(v, torch.Tensor)
                and v.is_floating_point() else v) for k, v in inp.items()}
    out = render_pattern_torch(**args, q_ext=None if q0 is None else q0.double())
    outs = [out[k] for k in RENDER_OUTS]
    gen = torch.Generator().manual_seed(seed + 1)  # the upstream gradient _grads draws
    ups = [torch.randn(o.shape, generator=gen).double() for o in outs]
    R = outs[0].shape[0]
    eye = torch.eye(R, dtype=torch.float64)
    per_ray = [eye.reshape(R, R, *([1] * (u.dim() - 1))) * u[None] for u in ups]
    g = torch.autograd.grad(outs, [args[k] for k in SHARED], grad_outputs=per_ray, is_grads_batched=True,
                            allow_unused=True)
    return {k: (torch.zeros_like(args[k]) if v is None else v.norm(dim=0)).float() for k, v in zip(SHARED, g)}


@pytest.mark.parametrize("size", RENDER_SIZES)
@pytest.mark.parametrize("threads", MANY)
@pytest.mark.parametrize("q_ext", [False, True])
def test_render_pattern(size, threads, q_ext, chunks):
    seed = _seed()
    inp = make_inputs(*size, seed)
    S = inp["sdf"].shape[0]
    q0 = torch.rand(S, 3, generator=torch.Generator().manual_seed(seed)) if q_ext else None

    def once():
        args = {k: (v.detach().clone().requires_grad_(k in RENDER_DIFF) if isinstance(v, torch.Tensor)
                    and v.is_floating_point() else v) for k, v in inp.items()}
        q = None if q0 is None else q0.clone().requires_grad_(True)
        out = render_pattern(**args, return_weights=True, q_ext=q)
        outs = [out[k] for k in RENDER_OUTS]
        ins = [args[k] for k in RENDER_DIFF] + ([q] if q is not None else [])
        return outs + [out["weights"]] + _grads(outs, ins, seed)

    ref, got = _run(once, 1), _run(once, threads, chunks, min(size[0], inp["sdf"].shape[0]))
    names = list(RENDER_OUTS) + ["weights"] + [f"d_{k}" for k in RENDER_DIFF] + ["d_q"]
    R = inp["offsets"].shape[0]
    norms = _ray_norms(inp, q0, seed) if R > 1 else {}
    for name, a, b in zip(names, got, ref):
        what = f"{name} (seed {seed}, size {size}, threads {threads})"
        if name[2:] in norms:
            # shared parameters: R per-ray terms summed per chunk, then over chunks; the signed
            # total may cancel (d_i_b 0.005 from 257 terms of about 0.57 each was seen)
            tol = 8 * R ** 0.5 * U32 * norms[name[2:]] + 1e-12
            err = (a - b).abs()
            assert bool((err <= tol).all()), f"{what}: max err {err.max():.3g}, tolerance {tol.min():.3g}"
        else:
            _same(a, b, what)


# project_pattern / laser_light are not split on CPU threads: their per-sample backward adds
# into shared (striped) gradient buffers with Warp's non-atomic CPU adds.


@pytest.mark.parametrize("R", [0, 1, 7, 1001])
@pytest.mark.parametrize("threads", MANY)
@pytest.mark.parametrize("bound", ["sphere", "box"])
def test_march_rays(R, threads, bound, chunks):
    seed = _seed()
    gen = torch.Generator().manual_seed(seed)
    res = 16
    bits = (torch.rand(res ** 3, generator=gen) < 0.4).to(torch.uint8)
    o = torch.randn(R, 3, generator=gen) * 1.5
    d = torch.nn.functional.normalize(torch.randn(R, 3, generator=gen) - 0.5 * o, dim=1)
    jitter = torch.rand(R, generator=gen)
    ref = _run(lambda: occ.march_rays(o, d, bits, res, 0.02, 40, jitter, bound, 0.0), 1)
    got = _run(lambda: occ.march_rays(o, d, bits, res, 0.02, 40, jitter, bound, 0.0), threads, chunks, R)
    for name, a, b in zip(("offsets", "counts", "t0", "t1", "ray_index"), got, ref):
        assert torch.equal(a, b), f"{name} (seed {seed}, R {R}, threads {threads})"


@pytest.mark.parametrize("M", [0, 1, 7, 70001])
@pytest.mark.parametrize("threads", MANY)
def test_occupancy_alpha(M, threads, chunks):
    seed = _seed()
    sdf = torch.randn(M, generator=torch.Generator().manual_seed(seed)) * 0.1
    ref = _run(lambda: occ.occupancy_alpha(sdf, 50.0, 0.02), 1)
    got = _run(lambda: occ.occupancy_alpha(sdf, 50.0, 0.02), threads, chunks, M)
    assert torch.equal(got, ref), f"seed {seed}, M {M}, threads {threads}"


@pytest.mark.parametrize("R", [0, 1, 7, 1001])
@pytest.mark.parametrize("threads", MANY)
def test_raycast_mesh(R, threads, chunks):
    import trimesh

    seed = _seed()
    gen = torch.Generator().manual_seed(seed)
    m = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    V = torch.tensor(m.vertices, dtype=torch.float32)
    F = torch.tensor(m.faces, dtype=torch.int32)
    o = torch.randn(R, 3, generator=gen) * 2.0
    d = torch.nn.functional.normalize(torch.randn(R, 3, generator=gen) * 0.3 - o, dim=1)
    ref = _run(lambda: raycast_mesh(V, F, o, d), 1)
    got = _run(lambda: raycast_mesh(V, F, o, d), threads, chunks, R)
    for name, a, b in zip(("t", "face", "normal"), got, ref):
        assert torch.equal(a, b), f"{name} (seed {seed}, R {R}, threads {threads})"


def test_identity_blur_projection_equals_render_sampling_when_threaded():
    """The chunked project_pattern feeds the chunked render as q_ext: same colour as the render's own sampling."""
    seed = _seed()
    inp = make_inputs(257, 2, 3, 32, seed)

    def once():
        q = project_pattern(inp["pos"], inp["ray_index"], inp["offsets"], inp["counts"], inp["ray_frame"],
                            inp["proj_K"], inp["proj_W"], inp["proj_pattern"], inp["patterns"], identity_blur(3))
        return render_pattern(**inp, q_ext=q)["color"], render_pattern(**inp)["color"]

    a, b = _run(once, 4)
    _same(a, b, f"seed {seed}", rtol=1e-5)


# ----------------------------------------------------------------------------- configuration

def test_cli_threads_option_header_and_run_json(small_scene, tmp_path, capsys, monkeypatch):
    import json

    from conftest import SMALL_RUN
    from fastneus.cli import main

    monkeypatch.setenv(_warp.THREADS_ENV, "2")  # --threads wins over the environment and the config key
    saved = (_warp.get_threads(), torch.get_num_threads())
    try:
        run = tmp_path / "run"
        assert main(["train", str(small_scene), "--out", str(run), "--device", "cpu", "--threads", "3",
                     "threads=1"] + SMALL_RUN) == 0
        out = capsys.readouterr().out
        assert out.count("threads: 3 (asked for") == 1, out
        assert json.loads((run / "run.json").read_text())["threads"] == 3
        assert _warp.get_threads() == 3 and torch.get_num_threads() == 3
        # without --threads: the config key, else the environment
        assert main(["train", str(small_scene), "--out", str(run), "--device", "cpu", "--overwrite"] + SMALL_RUN) == 0
        assert "threads: 2 (from FASTNEUS_THREADS" in capsys.readouterr().out
        assert json.loads((run / "run.json").read_text())["threads"] == 2
    finally:
        _warp.set_threads(saved[0])
        torch.set_num_threads(saved[1])


@pytest.mark.parametrize("argv,needle", [(["--threads", "0"], "--threads"), (["threads=-1"], "threads"),
                                         ([], "FASTNEUS_THREADS")])
def test_bad_thread_counts_are_one_line(argv, needle, small_scene, tmp_path, capsys, monkeypatch):
    from fastneus.cli import main

    if not argv:
        monkeypatch.setenv(_warp.THREADS_ENV, "many")
    assert main(["train", str(small_scene), "--out", str(tmp_path / "r"), "--device", "cpu"] + argv) == 2
    err = capsys.readouterr().err.strip()
    assert needle in err and len(err.splitlines()) == 1, err
