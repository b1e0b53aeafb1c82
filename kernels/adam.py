"""The guarded Adam update of one parameter tensor in one pass (Warp) and its torch twin.

Why: the foreach form of the update (``fastneus.train.adam._masked_update``) makes ~14 passes
over every tensor; for the 2^19 x 16 x 2 hash table (67 MB) that was ~1.2 ms of a 10.4-ms
captured step on an H100 (multi_tensor_apply, nan_to_num and fill kernels in
``scripts/step_profile.py``). One kernel reads p, g, m, v once and writes p, m, v once.

Maths (per element; ``w`` = the step's 0/1 guard, ``s`` = -lr / bc1, ``c`` = 1 / sqrt(bc2)):
    g  <- 0 where g is not finite
    m  <- m + w (1 - b1) (g - m)
    v  <- v + w (1 - b2) (g g - v)
    p  <- p + w s m / (sqrt(v) c + eps)
the same arithmetic, in the same order, as ``_masked_update``; a step with ``w = 0`` leaves
p, m, v bit-identical. ``s`` and ``c`` are read from a device array so a captured CUDA graph
reads each replay's learning rate. Not differentiable (an optimiser step).
"""
from __future__ import annotations

import torch
import warp as wp

from . import _warp

_warp.init()
wp.set_module_options({"enable_backward": False})

# elements per CPU chunk at least: a few flops each
MIN_CHUNK = 1 << 16


@wp.kernel
def _adam_kernel(
    p: wp.array(dtype=float),
    g: wp.array(dtype=float),
    m: wp.array(dtype=float),
    v: wp.array(dtype=float),
    scal: wp.array(dtype=float),
    row: int,
    ok: wp.array(dtype=float),
    b1: float,
    b2: float,
    eps: float,
):
    i = wp.tid()
    gi = g[i]
    if not wp.isfinite(gi):
        gi = 0.0
    w = ok[0]
    mi = m[i]
    vi = v[i]
    mi = mi + (gi - mi) * (w * (1.0 - b1))
    vi = vi + (gi * gi - vi) * (w * (1.0 - b2))
    m[i] = mi
    v[i] = vi
    denom = wp.sqrt(vi) * scal[2 * row + 1] + eps
    p[i] = p[i] + (mi / denom) * scal[2 * row] * w


@wp.kernel
def _nonfinite_kernel(g: wp.array(dtype=float), count: wp.array(dtype=float)):
    i = wp.tid()
    if not wp.isfinite(g[i]):
        wp.atomic_add(count, 0, 1.0)  # rare: only a broken step writes


def _check_count(g: torch.Tensor, count: torch.Tensor) -> None:
    if g.dtype != torch.float32 or count.dtype != torch.float32 or count.numel() != 1 or count.device != g.device:
        raise ValueError("adam_nonfinite: float32 g and a [1] float32 count on its device")


def adam_nonfinite(g: torch.Tensor, count: torch.Tensor) -> None:
    """Add the number of non-finite entries of ``g`` to ``count`` (one read pass, no host sync).

    Args:
        g: any-shape float32 tensor (a gradient).
        count: [1] float32 accumulator on g's device.
    """
    _check_count(g, count)
    flat = g.contiguous().reshape(-1)
    if flat.numel() == 0:
        return
    args = [_warp.to_wp(flat, ctype=True), _warp.to_wp(count, ctype=True)]
    # one launch: CPU threads' atomics would race on the shared count
    _warp.launch(_nonfinite_kernel, flat.numel(), args, g)


def adam_nonfinite_torch(g: torch.Tensor, count: torch.Tensor) -> None:
    """Twin of :func:`adam_nonfinite`."""
    _check_count(g, count)
    count.add_((~torch.isfinite(g)).sum().to(torch.float32).reshape(count.shape))


def _check(p, g, m, v, scal, row, ok):
    for name, t in (("grad", g), ("exp_avg", m), ("exp_avg_sq", v)):
        if t.shape != p.shape or t.dtype != torch.float32 or t.device != p.device:
            raise ValueError(f"adam_update: {name} must match the parameter ({tuple(p.shape)}, float32, {p.device})")
    if p.dtype != torch.float32:
        raise ValueError("adam_update: float32 parameters only")
    if not (p.is_contiguous() and m.is_contiguous() and v.is_contiguous()):
        raise ValueError("adam_update: parameter and moments must be contiguous (updated in place)")
    if scal.dtype != torch.float32 or scal.numel() < 2 * (row + 1) or ok.numel() != 1:
        raise ValueError("adam_update: scal must hold 2 floats per row, ok one float")


def adam_update(p: torch.Tensor, g: torch.Tensor, m: torch.Tensor, v: torch.Tensor, scal: torch.Tensor, row: int,
                ok: torch.Tensor, b1: float, b2: float, eps: float) -> None:
    """In-place guarded Adam update of one parameter (Warp, one pass).

    Args:
        p: parameter, any shape, float32, contiguous (updated in place).
        g: its gradient, same shape (read only; non-finite entries count as 0).
        m, v: Adam's first and second moments, same shape (updated in place).
        scal: [R, 2] float32 on p's device: row ``row`` holds (-lr / bc1, 1 / sqrt(bc2)).
        row: which row of ``scal`` (the parameter's group).
        ok: [1] float32 on p's device, 1 to apply the step, 0 to leave p, m, v unchanged.
        b1, b2, eps: Adam's constants.
    """
    _check(p, g, m, v, scal, row, ok)
    n = p.numel()
    if n == 0:
        return
    gc = g.contiguous()
    sc = scal.contiguous().reshape(-1)
    okc = ok.reshape(-1).to(torch.float32).contiguous()
    flat = [t.reshape(-1) for t in (p, gc, m, v)]
    args = [_warp.to_wp(t, ctype=True) for t in flat] + [_warp.to_wp(sc, ctype=True), int(row),
                                                          _warp.to_wp(okc, ctype=True), float(b1), float(b2), float(eps)]
    ranges = _warp.item_ranges(n, p, MIN_CHUNK)
    sliced = {j: (flat[j], None) for j in range(4)}
    _warp.launch_chunked(_adam_kernel, args, [], p, ranges, sliced_in=sliced)


def adam_update_torch(p: torch.Tensor, g: torch.Tensor, m: torch.Tensor, v: torch.Tensor, scal: torch.Tensor,
                      row: int, ok: torch.Tensor, b1: float, b2: float, eps: float) -> None:
    """Twin of :func:`adam_update` in torch ops (same arithmetic, same order)."""
    _check(p, g, m, v, scal, row, ok)
    sc = scal.reshape(-1)
    w = ok.reshape(()).to(torch.float32)
    gi = torch.nan_to_num(g, nan=0.0, posinf=0.0, neginf=0.0)
    m.add_((gi - m) * (w * (1.0 - b1)))
    v.add_((gi * gi - v) * (w * (1.0 - b2)))
    denom = v.sqrt() * sc[2 * row + 1] + eps
    p.add_((m / denom) * sc[2 * row] * w)
