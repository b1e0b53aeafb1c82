"""The hash ops' active-level count given as a device tensor (what a captured CUDA step passes:
the kernels read it when they run) against the same count given as an int, and the twins'."""
from __future__ import annotations

import os

import pytest
import torch

from fastneus.kernels.hashgrid import hash_encode, hash_encode_jac, hash_encode_jac_torch, hash_encode_torch
from test_hashgrid import CONFIGS, DEVICES  # noqa: E402


def _seed() -> int:
    return int.from_bytes(os.urandom(4), "little")


def _run(op, u, table, active, ups):
    """Outputs and the u / table gradients for fixed random upstream gradients."""
    u = u.clone().requires_grad_()
    t = table.clone().requires_grad_()
    out = op(u, t, CFG, active)
    outs = out if isinstance(out, tuple) else (out,)
    loss = sum((o * g).sum() for o, g in zip(outs, ups))
    gu, gt = torch.autograd.grad(loss, [u, t])
    return [o.detach() for o in outs] + [gu, gt]


CFG = CONFIGS[-1]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("jac", [False, True], ids=["encode", "encode_jac"])
def test_tensor_count_is_the_int_count(device, jac):
    seed = _seed()
    gen = torch.Generator().manual_seed(seed)
    u = (torch.rand(700, 3, generator=gen) * 1.1 - 0.05).to(device)
    table = (torch.rand(CFG.levels, CFG.table_size, CFG.features, generator=gen) * 2 - 1).to(device)
    L, F = CFG.levels, CFG.features
    ups = [torch.randn(700, L * F, generator=gen).to(device)] + ([torch.randn(700, L * F, 3, generator=gen).to(device)]
                                                                 if jac else [])
    op, twin = (hash_encode_jac, hash_encode_jac_torch) if jac else (hash_encode, hash_encode_torch)
    for k in sorted({0, 1, L // 2, L}):
        ref = _run(op, u, table, k, ups)
        got = _run(op, u, table, torch.tensor([k], dtype=torch.int32, device=device), ups)
        n_out = len(got) - 2
        for i, (a, b) in enumerate(zip(got, ref)):
            if i < n_out or device == "cpu":  # same kernels, the inactive threads return: bit for bit
                assert torch.equal(a, b), (seed, k, i)
            else:  # CUDA's float atomics add the gradients in a different order on every launch
                assert float((a - b).abs().max()) <= 1e-5 * max(float(b.abs().max()), 1e-12), (seed, k, i)
        tw_int = _run(twin, u, table, k, ups)
        tw_t = _run(twin, u, table, torch.tensor([k], device=device), ups)
        for a, b, c in zip(tw_t, tw_int, ref):
            torch.testing.assert_close(a, b, rtol=0, atol=0, msg=f"seed {seed}, k={k}: twin tensor vs int")
            # the op against its twin as the hash tests compare them (max error / max value)
            rel = float((c - a).abs().max()) / max(float(a.abs().max()), 1e-12)
            assert rel < 1e-4, f"seed {seed}, k={k}: op vs twin {rel}"
        if k < L:  # inactive levels: zero outputs, and their table rows get exactly no gradient
            assert float(got[0][:, k * F:].abs().max()) == 0.0
            assert float(got[-1][k:].abs().max()) == 0.0
