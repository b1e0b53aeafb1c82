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

``adam_update_multi`` / ``adam_nonfinite_multi`` do the same for a list of tensors: each large one
(the hash table) with the per-tensor kernel, the small ones (the heads, the illumination) up to
``MAX_TENSORS`` per launch (their addresses and element offsets are kernel arguments, so a captured
CUDA graph bakes them like any other argument): a model's ~15 parameter tensors cost 4 launches per
step instead of 30 (a small one's launch is ~2-5 us of device time for a few thousand floats).
"""
from __future__ import annotations

from typing import Any

import torch
import warp as wp

from . import _warp

_warp.init()
wp.set_module_options({"enable_backward": False})

# elements per CPU chunk at least: a few flops each
MIN_CHUNK = 1 << 16
# tensors per multi-tensor launch (more are split into several launches)
MAX_TENSORS = 16
# one length for all three (the offsets need MAX_TENSORS + 1), so one generic select serves them
_Ptrs = wp.types.vector(length=MAX_TENSORS + 1, dtype=wp.uint64)
_Offs = wp.types.vector(length=MAX_TENSORS + 1, dtype=wp.int32)
_Rows = wp.types.vector(length=MAX_TENSORS + 1, dtype=wp.int32)


@wp.func
def _adam_element(
    p: wp.array(dtype=float),
    g: wp.array(dtype=float),
    m: wp.array(dtype=float),
    v: wp.array(dtype=float),
    i: int,
    scal: wp.array(dtype=float),
    row: int,
    ok: wp.array(dtype=float),
    b1: float,
    b2: float,
    eps: float,
):
    # the maths of the module docstring for element i (both kernels)
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
    _adam_element(p, g, m, v, wp.tid(), scal, row, ok, b1, b2, eps)


@wp.kernel
def _nonfinite_kernel(g: wp.array(dtype=float), count: wp.array(dtype=float)):
    i = wp.tid()
    if not wp.isfinite(g[i]):
        wp.atomic_add(count, 0, 1.0)  # rare: only a broken step writes


@wp.func
def _which(i: int, offs: _Offs, ntens: int):
    # the tensor holding global element i: the last t with offs[t] <= i (ntens <= MAX_TENSORS)
    t = int(0)
    for s in range(1, MAX_TENSORS):  # unrolled: constant indices keep the argument in registers
        if s < ntens and i >= offs[s]:
            t = s
    return t


# A select with constant indices only: an argument vector indexed by a run-time value is copied to
# local memory by every thread (18x slower than the per-tensor kernel on an H200, perf note 39).
@wp.func
def _pick(v: Any, t: int):
    r = v[0]
    for s in range(1, MAX_TENSORS + 1):  # unrolled (a constant bound); every vector has MAX_TENSORS + 1
        if s == t:
            r = v[s]
    return r


@wp.kernel
def _adam_multi_kernel(
    pp: _Ptrs,
    gp: _Ptrs,
    mp: _Ptrs,
    vp: _Ptrs,
    offs: _Offs,
    rows: _Rows,
    ntens: int,
    first: int,
    scal: wp.array(dtype=float),
    ok: wp.array(dtype=float),
    b1: float,
    b2: float,
    eps: float,
):
    i = wp.tid() + first
    t = _which(i, offs, ntens)
    o = _pick(offs, t)
    n = _pick(offs, t + 1) - o
    j = i - o
    p = wp.array(ptr=_pick(pp, t), shape=(n,), dtype=float)
    g = wp.array(ptr=_pick(gp, t), shape=(n,), dtype=float)
    m = wp.array(ptr=_pick(mp, t), shape=(n,), dtype=float)
    v = wp.array(ptr=_pick(vp, t), shape=(n,), dtype=float)
    row = _pick(rows, t)
    _adam_element(p, g, m, v, j, scal, row, ok, b1, b2, eps)


@wp.kernel
def _nonfinite_multi_kernel(gp: _Ptrs, offs: _Offs, ntens: int, count: wp.array(dtype=float)):
    i = wp.tid()
    t = _which(i, offs, ntens)
    o = _pick(offs, t)
    g = wp.array(ptr=_pick(gp, t), shape=(_pick(offs, t + 1) - o,), dtype=float)
    if not wp.isfinite(g[i - o]):
        wp.atomic_add(count, 0, 1.0)


# tensors this large keep a launch of the per-tensor kernel: a launch costs nothing next to their
# traffic, and the plain kernel needs no search for its tensor
OWN_LAUNCH = 1 << 16


def _batches(tensors: list) -> list[list[int]]:
    """Indices of ``tensors`` smaller than OWN_LAUNCH in launches of at most MAX_TENSORS (their
    sum stays far below 2^31: the offsets are int32), empty and large tensors left out."""
    out, cur, n = [], [], 0
    for i, t in enumerate(tensors):
        k = t.numel()
        if k == 0 or k >= OWN_LAUNCH:
            continue
        if cur and len(cur) == MAX_TENSORS:
            out.append(cur)
            cur, n = [], 0
        cur.append(i)
        n += k
    if cur:
        out.append(cur)
    return out


def _ptrs(ts: list) -> _Ptrs:
    return _Ptrs(*([t.data_ptr() for t in ts] + [0] * (MAX_TENSORS + 1 - len(ts))))


def _offs(ts: list) -> tuple[_Offs, int]:
    o = [0]
    for t in ts:
        o.append(o[-1] + t.numel())
    return _Offs(*(o + [o[-1]] * (MAX_TENSORS + 1 - len(o)))), o[-1]


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


def _check_multi_count(gs: list, count: torch.Tensor) -> None:
    for g in gs:
        _check_count(g, count)


def adam_nonfinite_multi(gs: list, count: torch.Tensor) -> None:
    """:func:`adam_nonfinite` over the tensors ``gs``: the large ones (OWN_LAUNCH) one launch each,
    the others in one launch per MAX_TENSORS of them.

    Args:
        gs: list of any-shape float32 tensors (gradients) on one device.
        count: [1] float32 accumulator on their device.
    """
    _check_multi_count(gs, count)
    flat = [g.contiguous().reshape(-1) for g in gs]  # kept alive until the launches are queued
    for g in flat:
        if g.numel() >= OWN_LAUNCH:
            adam_nonfinite(g, count)
    for idx in _batches(flat):
        ts = [flat[i] for i in idx]
        offs, n = _offs(ts)
        # one launch (as adam_nonfinite): CPU threads' atomics would race on the shared count
        _warp.launch(_nonfinite_multi_kernel, n, [_ptrs(ts), offs, len(ts), _warp.to_wp(count, ctype=True)], count)


def adam_nonfinite_multi_torch(gs: list, count: torch.Tensor) -> None:
    """Twin of :func:`adam_nonfinite_multi`."""
    _check_multi_count(gs, count)
    for g in gs:
        adam_nonfinite_torch(g, count)


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


def adam_update_multi(ps: list, gs: list, ms: list, vs: list, scal: torch.Tensor, rows: list, ok: torch.Tensor,
                      b1: float, b2: float, eps: float) -> None:
    """:func:`adam_update` of the tensors ``ps``: each of OWN_LAUNCH elements or more with the
    per-tensor kernel, the others in one launch per MAX_TENSORS of them (on the CPU a chunked
    launch over their elements, split across the threads).

    Args:
        ps, gs, ms, vs: lists of the parameters, gradients and moments (each as :func:`adam_update`).
        scal: [R, 2] float32: row ``rows[k]`` holds (-lr / bc1, 1 / sqrt(bc2)) for ``ps[k]``.
        rows: list of ints, one per tensor.
        ok, b1, b2, eps: as :func:`adam_update` (shared by all tensors).
    """
    if not (len(ps) == len(gs) == len(ms) == len(vs) == len(rows)):
        raise ValueError("adam_update_multi: ps, gs, ms, vs and rows must have one entry per tensor")
    for p, g, m, v, r in zip(ps, gs, ms, vs, rows):
        _check(p, g, m, v, scal, r, ok)
    if not ps:
        return
    ref = ps[0]
    gc = [g.contiguous() for g in gs]  # kept alive until the launches are queued
    sc = _warp.to_wp(scal.contiguous().reshape(-1), ctype=True)
    okw = _warp.to_wp(ok.reshape(-1).to(torch.float32).contiguous(), ctype=True)
    for k, p in enumerate(ps):
        if p.numel() >= OWN_LAUNCH:
            adam_update(p, gc[k], ms[k], vs[k], scal, rows[k], ok, b1, b2, eps)
    for idx in _batches(ps):
        sel = [[lst[i] for i in idx] for lst in (ps, gc, ms, vs)]
        offs, n = _offs(sel[0])
        rws = _Rows(*([int(rows[i]) for i in idx] + [0] * (MAX_TENSORS + 1 - len(idx))))
        args = [_ptrs(sel[0]), _ptrs(sel[1]), _ptrs(sel[2]), _ptrs(sel[3]), offs, rws, len(idx), 0, sc, okw,
                float(b1), float(b2), float(eps)]
        # first (argument 7) = each chunk's first element: the threads split the elements
        _warp.launch_chunked(_adam_multi_kernel, args, [], ref, _warp.item_ranges(n, ref, MIN_CHUNK), first_arg=7)


def adam_update_multi_torch(ps: list, gs: list, ms: list, vs: list, scal: torch.Tensor, rows: list,
                            ok: torch.Tensor, b1: float, b2: float, eps: float) -> None:
    """Twin of :func:`adam_update_multi` (one :func:`adam_update_torch` per tensor)."""
    if not (len(ps) == len(gs) == len(ms) == len(vs) == len(rows)):
        raise ValueError("adam_update_multi: ps, gs, ms, vs and rows must have one entry per tensor")
    for p, g, m, v, r in zip(ps, gs, ms, vs, rows):
        adam_update_torch(p, g, m, v, scal, r, ok, b1, b2, eps)
