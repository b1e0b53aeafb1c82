"""Occupancy grid and ray marching (empty-space skipping), Warp kernels and torch twins.

Contract: docs/INTERNALS.md, section "Occupancy grid and marching".

The marching rule is fixed so that the Warp op and its torch twin emit *exactly* the same
samples: every float quantity is computed with the same float32 operations in the same
order (no FMA contraction: this module is compiled with ``fuse_fp=False``), and sample
``k`` of a ray has ``t0 = t_near + (k + jitter) * step`` computed from the integer ``k``
rather than by accumulating ``step``.
"""
from __future__ import annotations

import functools
import math
from typing import Callable

import numpy as np
import torch
import warp as wp

from . import _warp

_warp.init()
# Bit-exact agreement with the torch twin needs a*b+c to round twice, as torch does.
wp.set_module_options({"fuse_fp": False, "enable_backward": False})

# Stand-in for infinity in the slab test (keeps inf*0 NaNs out of the arithmetic).
_BIG = wp.constant(1.0e30)

BOUNDS = ("sphere", "box")
# Items per CPU chunk at least (each chunk is one more ~50 us launch): a ray marches tens to
# hundreds of steps; a cell's alpha is a few flops.
MIN_CHUNK_RAYS = 256
MIN_CHUNK_CELLS = 65536


# ----------------------------------------------------------------------------- Warp kernels

@wp.func
def _slab(o: float, d: float):
    # Interval of t where -1 <= o + t d <= 1 along one axis.
    lo = float(-_BIG)
    hi = float(_BIG)
    if d == 0.0:
        if o < -1.0 or o > 1.0:
            lo = float(_BIG)
            hi = float(-_BIG)
    else:
        ta = (-1.0 - o) / d
        tb = (1.0 - o) / d
        lo = wp.min(ta, tb)
        hi = wp.max(ta, tb)
    return lo, hi


@wp.func
def _bounds(o: wp.vec3, d: wp.vec3, box: int, near_min: float):
    # Returns (t_near, t_far, hit); hit == 0 means the ray gets no samples.
    tn = float(0.0)
    tf = float(0.0)
    hit = int(0)
    if box == 0:
        b = o[0] * d[0] + o[1] * d[1] + o[2] * d[2]
        c = o[0] * o[0] + o[1] * o[1] + o[2] * o[2] - 1.0
        disc = b * b - c
        if disc > 0.0:
            sq = wp.sqrt(disc)
            tn = -b - sq
            tf = -b + sq
            hit = 1
    else:
        lx, hx = _slab(o[0], d[0])
        ly, hy = _slab(o[1], d[1])
        lz, hz = _slab(o[2], d[2])
        tn = wp.max(wp.max(lx, ly), lz)
        tf = wp.min(wp.min(hx, hy), hz)
        if tf > tn:
            hit = 1
    tn = wp.max(tn, near_min)
    if tf <= tn:
        hit = 0
    return tn, tf, hit


@wp.func
def _cell(x: float, fres: float, res: int):
    i = int(wp.floor((x + 1.0) * 0.5 * fres))
    return wp.clamp(i, 0, res - 1)


@wp.func
def _occupied(o: wp.vec3, d: wp.vec3, t: float, bits: wp.array(dtype=wp.uint8), res: int):
    fres = float(res)
    ix = _cell(o[0] + t * d[0], fres, res)
    iy = _cell(o[1] + t * d[1], fres, res)
    iz = _cell(o[2] + t * d[2], fres, res)
    return bits[ix + iy * res + iz * res * res] != wp.uint8(0)


@wp.kernel
def _march_count_kernel(
    origins: wp.array(dtype=wp.vec3),
    dirs: wp.array(dtype=wp.vec3),
    jitter: wp.array(dtype=float),
    bits: wp.array(dtype=wp.uint8),
    res: int,
    step: float,
    max_samples: int,
    box: int,
    near_min: float,
    stop: wp.array(dtype=wp.uint8),
    use_stop: int,
    counts: wp.array(dtype=wp.int32),
):
    r = wp.tid()
    o = origins[r]
    d = dirs[r]
    tn, tf, hit = _bounds(o, d, box, near_min)
    n = int(0)
    if hit != 0:
        j = jitter[r]
        k = int(0)
        t0 = tn + (float(k) + j) * step
        while t0 < tf and n < max_samples:
            t1 = wp.min(t0 + step, tf)
            if use_stop != 0:
                if _occupied(o, d, (t0 + t1) * 0.5, stop, res):
                    break
            if _occupied(o, d, (t0 + t1) * 0.5, bits, res):
                n += 1
            k += 1
            t0 = tn + (float(k) + j) * step
    counts[r] = wp.int32(n)


@wp.kernel
def _march_fill_kernel(
    origins: wp.array(dtype=wp.vec3),
    dirs: wp.array(dtype=wp.vec3),
    jitter: wp.array(dtype=float),
    bits: wp.array(dtype=wp.uint8),
    res: int,
    step: float,
    max_samples: int,
    box: int,
    near_min: float,
    stop: wp.array(dtype=wp.uint8),
    use_stop: int,
    offsets: wp.array(dtype=wp.int32),
    counts: wp.array(dtype=wp.int32),
    r0: int,  # global index of this launch's first ray (launches may cover a slice of the rays)
    out_t0: wp.array(dtype=float),
    out_t1: wp.array(dtype=float),
    out_ray: wp.array(dtype=wp.int32),
):
    r = wp.tid()
    cnt = int(counts[r])
    if cnt == 0:
        return
    o = origins[r]
    d = dirs[r]
    tn, tf, hit = _bounds(o, d, box, near_min)
    base = int(offsets[r])
    j = jitter[r]
    n = int(0)
    k = int(0)
    t0 = tn + (float(k) + j) * step
    # Same walk as the count pass; `cnt` bounds the writes even if a caller passes stale counts.
    while t0 < tf and n < cnt:
        t1 = wp.min(t0 + step, tf)
        if use_stop != 0:
            if _occupied(o, d, (t0 + t1) * 0.5, stop, res):
                break
        if _occupied(o, d, (t0 + t1) * 0.5, bits, res):
            out_t0[base + n] = t0
            out_t1[base + n] = t1
            out_ray[base + n] = wp.int32(r0 + r)
            n += 1
        k += 1
        t0 = tn + (float(k) + j) * step


@wp.kernel
def _alpha_kernel(sdf: wp.array(dtype=float), inv_s: float, half_step: float, scale: float,
                  alpha: wp.array(dtype=float)):
    i = wp.tid()
    # scale * sigmoid(inv_s * (half_step - |sdf|)); see occupancy_alpha for why this form
    z = inv_s * (half_step - wp.abs(sdf[i]))
    alpha[i] = wp.clamp(scale / (1.0 + wp.exp(-z)), 0.0, 1.0)


# ----------------------------------------------------------------------------- helpers

def _f32(x: float) -> float:
    """Round a python float to float32 so Warp's float arg and torch's scalar agree."""
    return float(np.float32(float(x)))


def _alpha_scale(inv_s: float, step: float) -> float:
    """1 - exp(-inv_s * step), the alpha of a step right at the surface's far limit (float32)."""
    return _f32(-math.expm1(-float(inv_s) * float(step)))


def _check_rays(origins, dirs, bits, resolution, jitter, bound, max_samples):
    if bound not in BOUNDS:
        raise ValueError(f"bound must be one of {BOUNDS}, got {bound!r}")
    if origins.ndim != 2 or origins.shape[-1] != 3 or dirs.shape != origins.shape:
        raise ValueError(f"origins and dirs must both be [R, 3]; got {tuple(origins.shape)} and {tuple(dirs.shape)}")
    if bits.numel() != resolution ** 3:
        raise ValueError(f"bits has {bits.numel()} cells, expected resolution^3 = {resolution ** 3}")
    if max_samples < 0:
        raise ValueError(f"max_samples must be >= 0, got {max_samples}")
    R = origins.shape[0]
    dev = origins.device
    if jitter is None:
        jitter = torch.zeros(R, device=dev)
    jitter = jitter.detach().reshape(-1).to(device=dev, dtype=torch.float32).contiguous()
    if jitter.shape[0] != R:
        raise ValueError(f"jitter must be [R] = [{R}], got {tuple(jitter.shape)}")
    return (origins.detach().to(torch.float32).contiguous(), dirs.detach().to(dev, torch.float32).contiguous(),
            bits.detach().reshape(-1).to(dev, torch.uint8).contiguous(), jitter)


@functools.lru_cache(maxsize=8)
def _no_stop(device: torch.device) -> torch.Tensor:
    """The 1-cell placeholder the kernels get without stop cells, made once per device (the
    march runs every step: no allocation and fill kernel for it each time). Never written."""
    return torch.zeros(1, dtype=torch.uint8, device=device)


def _check_stop(stop: torch.Tensor | None, bits: torch.Tensor) -> tuple[torch.Tensor, int]:
    """(stop cells as a contiguous uint8 array, 1) or (a 1-cell placeholder, 0) when None."""
    if stop is None:
        return _no_stop(bits.device), 0
    if stop.numel() != bits.numel():
        raise ValueError(f"stop has {stop.numel()} cells, the grid {bits.numel()}")
    return stop.detach().reshape(-1).to(bits.device, torch.uint8).contiguous(), 1


def _empty_result(R: int, device) -> tuple[torch.Tensor, ...]:
    z = torch.zeros(R, dtype=torch.int32, device=device)
    return (z, z.clone(), torch.zeros(0, device=device), torch.zeros(0, device=device),
            torch.zeros(0, dtype=torch.int32, device=device))


def _check_out(b: torch.Tensor, dtype, n: int, device, exact: bool) -> None:
    """A caller's output buffer: a contiguous ``dtype`` vector on ``device`` of ``n`` (``exact``)
    or at least ``n`` entries; else a ValueError (a wrong buffer would be written past its end)."""
    if (b.dtype != dtype or b.dim() != 1 or (b.shape[0] != n if exact else b.shape[0] < n)
            or not b.is_contiguous() or b.device != torch.device(device)):
        raise ValueError(f"march out buffer: need a contiguous {dtype} vector of {'' if exact else '>= '}{n} "
                         f"entries on {device}, got {b.dtype} {tuple(b.shape)} on {b.device}")


def _sample_buffers(total: int, device, out) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """t0, t1 [total] float32 and ray_index [total] int32: fresh, or the first ``total`` entries
    of the buffers ``out(total)`` returns (checked: a wrong buffer would be written past its end)."""
    bufs = None if out is None else out(total)
    if bufs is None:
        return (torch.empty(total, dtype=torch.float32, device=device),
                torch.empty(total, dtype=torch.float32, device=device),
                torch.empty(total, dtype=torch.int32, device=device))
    for b, dt in zip(bufs, (torch.float32, torch.float32, torch.int32)):
        _check_out(b, dt, total, device, exact=False)
    return tuple(b[:total] for b in bufs)


# ----------------------------------------------------------------------------- marching

def ray_bounds(origins: torch.Tensor, dirs: torch.Tensor, bound: str = "sphere",
               near_min: float = 0.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Clip rays to the unit sphere or the [-1, 1]^3 box (torch; same float ops as the kernel).

    Args:
        origins: [R, 3] float32 ray origins, normalised space.
        dirs: [R, 3] float32 unit directions.
        bound: "sphere" or "box".
        near_min: t_near is raised to at least this.

    Returns:
        (t_near [R] float32, t_far [R] float32, hit [R] bool). Where ``hit`` is False the ray
        gets no samples (it misses, or the clipped interval is empty); t_near/t_far are then
        meaningless.
    """
    if bound not in BOUNDS:
        raise ValueError(f"bound must be one of {BOUNDS}, got {bound!r}")
    o = origins.to(torch.float32)
    d = dirs.to(torch.float32)
    near_min = _f32(near_min)
    if bound == "sphere":
        b = o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1] + o[:, 2] * d[:, 2]
        c = o[:, 0] * o[:, 0] + o[:, 1] * o[:, 1] + o[:, 2] * o[:, 2] - 1.0
        disc = b * b - c
        hit = disc > 0.0
        # torch's CPU float32 sqrt is not always correctly rounded (off by an ulp for ~0.6% of
        # inputs); sqrt in float64 rounded to float32 is, like sqrtf in the Warp kernel.
        sq = torch.sqrt(torch.where(hit, disc, torch.ones_like(disc)).double()).float()
        tn = torch.where(hit, -b - sq, torch.zeros_like(b))
        tf = torch.where(hit, -b + sq, torch.zeros_like(b))
    else:
        zero = d == 0.0
        safe_d = torch.where(zero, torch.ones_like(d), d)
        ta = (-1.0 - o) / safe_d
        tb = (1.0 - o) / safe_d
        lo = torch.minimum(ta, tb)
        hi = torch.maximum(ta, tb)
        outside = (o < -1.0) | (o > 1.0)
        big = torch.full_like(lo, _BIG)
        lo = torch.where(zero, torch.where(outside, big, -big), lo)
        hi = torch.where(zero, torch.where(outside, -big, big), hi)
        tn = torch.maximum(torch.maximum(lo[:, 0], lo[:, 1]), lo[:, 2])
        tf = torch.minimum(torch.minimum(hi[:, 0], hi[:, 1]), hi[:, 2])
        hit = tf > tn
    tn = torch.clamp_min(tn, near_min)
    hit = hit & (tf > tn)
    return tn, tf, hit


def march_rays(
    origins: torch.Tensor,  # [R, 3] float32, normalised space
    dirs: torch.Tensor,  # [R, 3] float32, unit length
    bits: torch.Tensor,  # [res^3] uint8, cell x + y*res + z*res^2
    resolution: int,
    step: float,
    max_samples: int,
    jitter: torch.Tensor | None,  # [R] float32 in [0, 1) (None = zeros)
    bound: str = "sphere",
    near_min: float = 0.0,
    stop: torch.Tensor | None = None,  # [res^3] uint8: a ray ends at the first such cell (None = none)
    out=None,  # callable total -> (t0, t1, ray_index) buffers of >= total entries, or None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """March rays through the occupancy grid and pack the samples in occupied cells (Warp).

    Sample k of ray r has ``t0 = t_near + (k + jitter[r]) * step`` and
    ``t1 = min(t0 + step, t_far)`` for k = 0, 1, ... while ``t0 < t_far``; it is emitted when
    the cell holding the midpoint ``(t0 + t1) / 2`` is occupied, at most ``max_samples`` per
    ray; with ``stop``, a ray ends at the first sample whose midpoint lies in a cell with a
    non-zero ``stop`` value (the grid's cells deep inside the surface: nothing behind them is
    seen). Two passes (count, fill) with one host read of the total sample count in between.
    Not differentiable.

    Args:
        origins: [R, 3] float32 ray origins (normalised space).
        dirs: [R, 3] float32 unit ray directions.
        bits: [res^3] uint8 occupancy bits (non-zero = occupied).
        resolution: grid resolution res per axis (cells cover [-1, 1]^3).
        step: marching step length (normalised units).
        max_samples: cap on samples per ray.
        jitter: [R] float32 per-ray offset of the first sample, in units of ``step``.
        bound: "sphere" (unit sphere) or "box" ([-1, 1]^3) clip of the rays.
        near_min: lower limit of t_near.
        stop: None or [res^3] uint8 cells that end a ray (:attr:`OccupancyGrid.stop`).
        out: None, or a callable given the total sample count S (on the host, after the count
            pass) that returns None or three contiguous buffers (float32, float32, int32, on the
            rays' device) of at least S entries: the samples are written into their first S
            entries and the rest is left as it was (a captured step's fixed buffers: no copy).

    Returns:
        offsets [R] int32 (exclusive cumsum of counts), counts [R] int32, t0 [S] float32,
        t1 [S] float32, ray_index [S] int32; samples packed by ray, in order of t (with ``out``:
        views of its buffers' first S entries).
    """
    o, d, bits, jitter = _check_rays(origins, dirs, bits, resolution, jitter, bound, max_samples)
    stop, use_stop = _check_stop(stop, bits)
    R = o.shape[0]
    dev = o.device
    if R == 0:
        return _empty_result(0, dev)
    count, fill = _march_passes(o, d, jitter, bits, stop, use_stop, resolution, _f32(step), max_samples,
                                1 if bound == "box" else 0, _f32(near_min))
    counts = torch.empty(R, dtype=torch.int32, device=dev)
    count(counts)
    csum = torch.cumsum(counts, 0, dtype=torch.int32)
    offsets = csum - counts
    total = int(csum[-1].item())  # the one host sync: the output size must be known
    t0, t1, ray_index = _sample_buffers(total, dev, out)
    if total > 0:
        fill(offsets, counts, t0, t1, ray_index)
    return offsets, counts, t0, t1, ray_index


def _march_passes(o, d, jitter, bits, stop, use_stop: int, resolution: int, step, max_samples: int, box: int,
                  near_min):
    """The march's two Warp passes over the rays ``o, d`` (checked): ``count(counts [R])`` and
    ``fill(offsets [R], counts [R], t0, t1, ray_index)`` (one thread per ray, chunked on the CPU)."""
    # array descriptors (ctype): a quarter of wp.array's host time per argument; on the GPU the
    # fill launch sat between the count read and the replay, with the device idle
    common = [_warp.to_wp(o, wp.vec3, ctype=True), _warp.to_wp(d, wp.vec3, ctype=True),
              _warp.to_wp(jitter, ctype=True), _warp.to_wp(bits, ctype=True), int(resolution), step,
              int(max_samples), box, near_min, _warp.to_wp(stop, ctype=True), use_stop]
    per_ray = {0: (o, wp.vec3), 1: (d, wp.vec3), 2: (jitter, None)}  # each thread reads only its own ray
    ranges = _warp.item_ranges(o.shape[0], o, MIN_CHUNK_RAYS)

    def count(counts: torch.Tensor) -> None:
        _warp.launch_chunked(_march_count_kernel, common + [_warp.to_wp(counts, ctype=True)], [], o, ranges,
                             sliced_in={**per_ray, 11: (counts, None)})

    def fill(offsets: torch.Tensor, counts: torch.Tensor, t0: torch.Tensor, t1: torch.Tensor,
             ray_index: torch.Tensor) -> None:
        _warp.launch_chunked(_march_fill_kernel, common + [_warp.to_wp(offsets, ctype=True),
                                                           _warp.to_wp(counts, ctype=True), 0],
                             [_warp.to_wp(t0, ctype=True), _warp.to_wp(t1, ctype=True),
                              _warp.to_wp(ray_index, ctype=True)], o, ranges,
                             sliced_in={**per_ray, 11: (offsets, None), 12: (counts, None)}, first_arg=13)

    return count, fill


def _capped(counts: torch.Tensor, offsets: torch.Tensor, counts_out: torch.Tensor, total: torch.Tensor,
            capacity: int) -> None:
    """The capped march's bookkeeping on the device: ``total`` [1] = all samples (unclamped),
    ``counts_out`` = each ray's count clamped to the room left before ``capacity``."""
    total.copy_(offsets[-1:] + counts[-1:])
    torch.minimum(counts, (capacity - offsets).clamp_min(0), out=counts_out)


def march_rays_capped(
    origins: torch.Tensor,  # [R, 3] float32, normalised space
    dirs: torch.Tensor,  # [R, 3] float32, unit length
    bits: torch.Tensor,  # [res^3] uint8
    resolution: int,
    step: float,
    max_samples: int,
    jitter: torch.Tensor | None,  # [R] float32 in [0, 1)
    bound: str,
    near_min: float,
    stop: torch.Tensor | None,  # [res^3] uint8 or None
    out: tuple,  # (offsets [R] int32, counts [R] int32, total [1] int32, t0 [C], t1 [C], ray_index [C] int32)
) -> None:
    """:func:`march_rays` into fixed buffers of capacity C with no host read (Warp).

    The samples of :func:`march_rays` are written in the same order into ``t0, t1, ray_index``
    as far as they fit: ``counts`` holds each ray's samples clamped to the room left before C
    (a ray that starts past C gets none, one that straddles it keeps its first samples), and
    ``offsets`` the unclamped exclusive cumsum; ``total`` the unclamped sample count on the device
    (> C: the step did not fit; its caller skips the update). Entries of ``t0, t1, ray_index``
    past the written samples are left as they were. Nothing waits for the device: a captured
    training step's march (the count that sizes :func:`march_rays`'s output is the step's one
    host sync).
    """
    offsets, counts, total, t0, t1, ray_index = out
    o, d, bits, jitter = _check_rays(origins, dirs, bits, resolution, jitter, bound, max_samples)
    stop, use_stop = _check_stop(stop, bits)
    R, dev = o.shape[0], o.device
    cap = int(t0.shape[0])
    for b, dt, n in ((offsets, torch.int32, R), (counts, torch.int32, R), (total, torch.int32, 1), (t0, torch.float32, cap),
                     (t1, torch.float32, cap), (ray_index, torch.int32, cap)):
        _check_out(b, dt, n, dev, exact=True)
    if R == 0:
        total.zero_()
        return
    count, fill = _march_passes(o, d, jitter, bits, stop, use_stop, resolution, _f32(step), max_samples,
                                1 if bound == "box" else 0, _f32(near_min))
    raw = torch.empty(R, dtype=torch.int32, device=dev)
    count(raw)
    torch.sub(torch.cumsum(raw, 0, dtype=torch.int32), raw, out=offsets)
    _capped(raw, offsets, counts, total, cap)
    fill(offsets, counts, t0, t1, ray_index)


def march_rays_capped_torch(origins, dirs, bits, resolution, step, max_samples, jitter, bound, near_min, stop,
                            out: tuple) -> None:
    """Pure-torch twin of :func:`march_rays_capped` (same arguments and results; it reads the
    sample count on the host, as :func:`march_rays_torch` does)."""
    offsets, counts, total, t0, t1, ray_index = out
    o, c, a, b, r = march_rays_torch(origins, dirs, bits, resolution, step, max_samples, jitter, bound, near_min, stop)
    offsets.copy_(o)
    _capped(c, offsets, counts, total, int(t0.shape[0]))
    n = min(int(a.shape[0]), int(t0.shape[0]))  # the packed samples that fit: the first n
    t0[:n], t1[:n], ray_index[:n] = a[:n], b[:n], r[:n]


def march_rays_torch(
    origins: torch.Tensor,  # [R, 3] float32, normalised space
    dirs: torch.Tensor,  # [R, 3] float32, unit length
    bits: torch.Tensor,  # [res^3] uint8, cell x + y*res + z*res^2
    resolution: int,
    step: float,
    max_samples: int,
    jitter: torch.Tensor | None,  # [R] float32 in [0, 1) (None = zeros)
    bound: str = "sphere",
    near_min: float = 0.0,
    stop: torch.Tensor | None = None,  # [res^3] uint8: a ray ends at the first such cell (None = none)
    out=None,  # callable total -> (t0, t1, ray_index) buffers of >= total entries, or None
    chunk_elems: int = 1 << 23,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pure-torch twin of :func:`march_rays` (same arguments, identical outputs).

    Enumerates k = 0..K-1 for all rays at once (K = the most steps any ray needs), masks
    the samples past t_far or in empty cells, and keeps the first ``max_samples`` per ray.
    Rays are processed in chunks of about ``chunk_elems`` candidate samples.

    Returns:
        offsets [R] int32, counts [R] int32, t0 [S] float32, t1 [S] float32, ray_index [S] int32.
    """
    o, d, bits, jitter = _check_rays(origins, dirs, bits, resolution, jitter, bound, max_samples)
    stop, use_stop = _check_stop(stop, bits)
    R = o.shape[0]
    dev = o.device
    if R == 0:
        return _empty_result(0, dev)
    step = _f32(step)
    tn, tf, hit = ray_bounds(o, d, bound, near_min)
    span = torch.where(hit, tf - tn, torch.zeros_like(tn))
    # +2 covers float rounding of (k + jitter) * step; checked (and grown) below.
    K = int(math.ceil(float(span.max().item()) / step)) + 2 if bool(hit.any()) else 1
    res = int(resolution)
    counts = torch.zeros(R, dtype=torch.int32, device=dev)
    t0s, t1s, rids = [], [], []
    rows = max(1, chunk_elems // max(K, 1))
    for a in range(0, R, rows):
        b = min(R, a + rows)
        c_o, c_d, c_tn, c_tf, c_hit, c_j = o[a:b], d[a:b], tn[a:b, None], tf[a:b, None], hit[a:b, None], jitter[a:b, None]
        while True:
            k = torch.arange(K, device=dev, dtype=torch.float32)[None, :]
            t0 = c_tn + (k + c_j) * step  # [r, K]
            inside = (t0 < c_tf) & c_hit
            if not bool(inside[:, -1].any()):
                break
            K *= 2
        t1 = torch.minimum(t0 + step, c_tf.expand_as(t0))
        mid = (t0 + t1) * 0.5
        idx = []
        for ax in range(3):
            p = c_o[:, ax:ax + 1] + mid * c_d[:, ax:ax + 1]
            idx.append(torch.floor((p + 1.0) * 0.5 * float(res)).to(torch.int64).clamp_(0, res - 1))
        lin = idx[0] + idx[1] * res + idx[2] * (res * res)
        if use_stop:  # the first stop cell along the ray and everything after it: not marched
            inside = inside & (torch.cumsum((inside & (stop[lin] != 0)).to(torch.int32), 1) == 0)
        emit = inside & (bits[lin] != 0)
        emit &= torch.cumsum(emit.to(torch.int32), 1) <= max_samples
        counts[a:b] = emit.sum(1).to(torch.int32)
        t0s.append(t0[emit])  # boolean indexing is row-major: packed by ray, then k
        t1s.append(t1[emit])
        rids.append(torch.arange(a, b, device=dev, dtype=torch.int32)[:, None].expand_as(emit)[emit])
    offsets = torch.cumsum(counts, 0, dtype=torch.int32) - counts
    t0, t1, rid = torch.cat(t0s), torch.cat(t1s), torch.cat(rids)
    if out is None:
        return offsets, counts, t0, t1, rid
    bufs = _sample_buffers(int(t0.shape[0]), dev, out)
    for b, v in zip(bufs, (t0, t1, rid)):
        b.copy_(v)
    return (offsets, counts, *bufs)


# ----------------------------------------------------------------------------- occupancy alpha

def occupancy_alpha(
    sdf: torch.Tensor,  # [M] float32
    inv_s: float,
    step: float,
) -> torch.Tensor:
    """NeuS alpha of one marching step of length ``step`` centred at distance |sdf| (Warp).

    ``alpha = clamp((Phi(|sdf| + step/2) - Phi(|sdf| - step/2)) / Phi(|sdf| + step/2), 0, 1)``
    with ``Phi(x) = sigmoid(inv_s * x)``: a ray heading straight at the surface (SDF falling
    at unit rate) would get this opacity from the step (instant-nsr-pl's ``occ_eval_fn``,
    on |sdf| so that cells deep inside are freed too). Not differentiable.

    It is evaluated in the algebraically equal, cancellation-free form
    ``(1 - exp(-inv_s * step)) * sigmoid(inv_s * (step/2 - |sdf|))`` (the direct difference of
    two sigmoids near 1 is rounding noise far from the surface, and not monotone there).

    Args:
        sdf: [M] float32 SDF values.
        inv_s: NeuS sharpness s.
        step: marching step length.

    Returns:
        alpha [M] float32 in [0, 1].
    """
    s = sdf.detach().reshape(-1).to(torch.float32).contiguous()
    out = torch.empty_like(s)
    _warp.launch_chunked(_alpha_kernel, [_warp.to_wp(s), _f32(inv_s), _f32(0.5 * step), _alpha_scale(inv_s, step),
                                         _warp.to_wp(out)], [], s, _warp.item_ranges(s.shape[0], s, MIN_CHUNK_CELLS),
                         sliced_in={0: (s, None), 4: (out, None)})
    return out


def occupancy_alpha_torch(
    sdf: torch.Tensor,  # [M] float32
    inv_s: float,
    step: float,
) -> torch.Tensor:
    """Pure-torch twin of :func:`occupancy_alpha` (same formula). Returns alpha [M] float32."""
    f = sdf.detach().reshape(-1).to(torch.float32)
    z = _f32(inv_s) * (_f32(0.5 * step) - f.abs())
    return (_alpha_scale(inv_s, step) * torch.sigmoid(z)).clamp(0.0, 1.0)


# ----------------------------------------------------------------------------- grid

class OccupancyGrid:
    """Dense occupancy grid over [-1, 1]^3 with an EMA of the per-cell step opacity.

    Attributes:
        resolution: cells per axis (res).
        values: [res^3] float32 EMA of the alpha estimate (cell x + y*res + z*res^2).
        bits: [res^3] uint8, 1 where ``values > threshold`` (or everywhere during warm-up),
            and only where ``allowed`` (when set).
        allowed: None or [res^3] bool: cells that may ever be occupied (e.g. the volume the
            training cameras see); derived from the scene, so not part of ``state_dict``.
        stop: None or [res^3] uint8, 1 where the last update found the SDF below
            ``-inside`` (deep inside the surface: a ray that reaches such a cell sees nothing
            behind it, :func:`march_rays`'s ``stop``); None before the first update with
            ``inside > 0``. Derived, so not part of ``state_dict``.
    """

    def __init__(self, resolution: int = 128, device: str | torch.device = "cpu"):
        self.resolution = int(resolution)
        self.device = torch.device(device)
        n = self.resolution ** 3
        self.values = torch.zeros(n, dtype=torch.float32, device=self.device)
        self.bits = torch.ones(n, dtype=torch.uint8, device=self.device)  # all occupied until first update
        self.allowed: torch.Tensor | None = None
        self.stop: torch.Tensor | None = None
        self._ijk = None

    def set_allowed(self, allowed: torch.Tensor | None) -> None:
        """Restrict occupancy to ``allowed`` ([res^3] bool) from now on (None = everywhere)."""
        if allowed is not None:
            allowed = allowed.reshape(-1).to(device=self.device, dtype=torch.bool)
            if allowed.numel() != self.num_cells:
                raise ValueError(f"allowed has {allowed.numel()} cells, the grid {self.num_cells}")
            self.bits &= allowed.to(torch.uint8)
        self.allowed = allowed

    @property
    def num_cells(self) -> int:
        return self.resolution ** 3

    def _cell_ijk(self) -> torch.Tensor:
        # [res^3, 3] float32 integer cell coordinates, cached (12 bytes per cell).
        if self._ijk is None:
            r = self.resolution
            i = torch.arange(r ** 3, device=self.device)
            self._ijk = torch.stack([i % r, (i // r) % r, i // (r * r)], 1).to(torch.float32)
        return self._ijk

    def cell_centers(self, jitter: bool = False, index: torch.Tensor | None = None) -> torch.Tensor:
        """Cell centres in normalised coordinates, optionally jittered uniformly inside the cell.

        Args:
            jitter: move each point uniformly within its cell.
            index: [M] int64 cell indices to return (None = all cells).

        Returns:
            [M, 3] float32 points (M = res^3 when ``index`` is None), order of the linear index.
        """
        ijk = self._cell_ijk() if index is None else self._cell_ijk()[index]
        off = torch.rand_like(ijk) if jitter else torch.full_like(ijk, 0.5)
        return (ijk + off) * (2.0 / self.resolution) - 1.0

    @torch.no_grad()
    def update(self, sdf_fn: Callable[[torch.Tensor], torch.Tensor], inv_s: float, step: float,
               threshold: float = 0.01, decay: float = 0.95, warmup: bool = False, chunk: int | None = None,
               subset: float | None = None, margin: float = 0.0, backend: str = "warp", inside: float = 0.0,
               near: float | None = None) -> None:
        """Refresh the grid from the current SDF.

        Every cell decays (``values *= decay``); the evaluated cells (all, a random ``subset``
        fraction, or with ``near`` the occupied cells, their 26 neighbours and a random ``near``
        fraction of the rest) take ``max(values, alpha)`` with alpha = :func:`occupancy_alpha`
        of ``max(|sdf(p)| - margin, 0)`` at a jittered point p of the cell; then
        ``bits = values > threshold``. ``warmup=True`` only marks every cell occupied (no SDF
        evaluation: the field is still meaningless then).

        Args:
            sdf_fn: maps [M, 3] float32 normalised points to [M] (or [M, 1]) SDF values.
            inv_s: current NeuS sharpness s.
            step: marching step length used for rendering.
            threshold: occupancy threshold on the EMA.
            decay: EMA decay per update.
            warmup: mark all cells occupied and return.
            chunk: points per ``sdf_fn`` call; None: 2^21 on CUDA (a 128^3 grid in one call: the
                update was ~500 small launches in 8 chunks, 13.7 ms of host time for 2.6 ms of
                device work every 16 steps on an H200; ~1.5 GB of temporaries), 2^18 on the CPU.
            subset: fraction in (0, 1] of cells evaluated this call (None = all).
            near: fraction in [0, 1] of the cells away from the occupied ones (not occupied, no
                occupied neighbour) evaluated this call; the occupied cells and their neighbours
                always are (the surface moves less than a cell between updates, and an occupied
                cell far from it decays out over ~90 updates anyway). None = ``subset``'s rule.
                On the CPU a full update was 23 % of a 1-thread training step (64^3 SDF queries
                every 16 steps; docs/perf-notes/2026-11-28-occupancy-near-cells.md).
            margin: subtracted from |sdf| before the alpha (e.g. half a cell diagonal,
                sqrt(3)/res, keeps thin shells occupied at large s); 0 = plain rule.
            backend: "warp" or "torch" for the alpha op.
            inside: > 0: also mark :attr:`stop` where the SDF at the cell's point is below
                ``-inside`` (normalised units); 0: no stop cells.
        """
        if warmup:
            self.stop = None
            self.bits.fill_(1)
            if self.allowed is not None:
                self.bits &= self.allowed.to(torch.uint8)
            return
        n = self.num_cells
        index = None
        if near is not None and near < 1.0:
            r = self.resolution
            b = self.bits.view(1, 1, r, r, r).to(torch.float32)
            pick = torch.nn.functional.max_pool3d(b, 3, stride=1, padding=1).view(-1) > 0
            pick |= torch.rand(n, device=self.device) < near
            if self.allowed is not None:  # a cell never allowed stays empty: no need to query it
                pick &= self.allowed
            index = pick.nonzero().squeeze(1)
        elif subset is not None and subset < 1.0:
            m = max(1, int(math.ceil(subset * n)))
            index = torch.randperm(n, device=self.device)[:m]
        if chunk is None:
            chunk = 2 ** 21 if torch.device(self.device).type == "cuda" else 2 ** 18
        pts = self.cell_centers(jitter=True, index=index)
        alpha_fn = occupancy_alpha if backend == "warp" else occupancy_alpha_torch
        alpha = torch.empty(pts.shape[0], dtype=torch.float32, device=self.device)
        deep = torch.empty(pts.shape[0], dtype=torch.uint8, device=self.device) if inside > 0 else None
        for a in range(0, pts.shape[0], chunk):
            f = sdf_fn(pts[a:a + chunk]).reshape(-1).to(torch.float32)
            if deep is not None:
                deep[a:a + chunk] = f < -inside
            if margin:
                f = (f.abs() - margin).clamp_min(0.0)
            alpha[a:a + chunk] = alpha_fn(f, inv_s, step)
        self.values.mul_(decay)
        if index is None:
            torch.maximum(self.values, alpha, out=self.values)
        else:
            self.values[index] = torch.maximum(self.values[index], alpha)
        occ = self.values > threshold
        if self.allowed is not None:
            occ &= self.allowed
        self.bits.copy_(occ)
        if deep is None:
            self.stop = None
        else:
            if self.stop is None:
                self.stop = torch.zeros(n, dtype=torch.uint8, device=self.device)
            if index is None:
                self.stop.copy_(deep)
            else:
                self.stop[index] = deep
            self.stop &= ~occ.to(torch.uint8) & 1  # an occupied cell is sampled, never a ray's end

    def occupied_fraction(self) -> float:
        """Fraction of occupied cells (host sync; for logging only)."""
        return float(self.bits.float().mean().item())

    def march(self, origins: torch.Tensor, dirs: torch.Tensor, step: float, max_samples: int,
              jitter: torch.Tensor | None = None, bound: str = "sphere", near_min: float = 0.0,
              backend: str = "warp"):
        """:func:`march_rays` (backend "warp") or :func:`march_rays_torch` on this grid's bits.

        Args:
            origins: [R, 3] float32; dirs: [R, 3] float32 unit; jitter: [R] float32 or None.
        """
        fn = march_rays if backend == "warp" else march_rays_torch
        return fn(origins, dirs, self.bits, self.resolution, step, max_samples, jitter, bound, near_min, self.stop)

    def state_dict(self) -> dict:
        return {"resolution": self.resolution, "values": self.values.clone(), "bits": self.bits.clone()}

    def load_state_dict(self, state: dict) -> None:
        if int(state["resolution"]) != self.resolution:
            raise ValueError(f"occupancy grid resolution {state['resolution']} != {self.resolution}")
        self.values.copy_(state["values"])
        self.bits.copy_(state["bits"])
        self.stop = None  # derived at the next update
        if self.allowed is not None:
            self.bits &= self.allowed.to(torch.uint8)

    def to(self, device) -> "OccupancyGrid":
        self.device = torch.device(device)
        self.values = self.values.to(self.device)
        self.bits = self.bits.to(self.device)
        self.stop = None if self.stop is None else self.stop.to(self.device)
        if self.allowed is not None:
            self.allowed = self.allowed.to(self.device)
        self._ijk = None
        return self


def rays_for_target(target_samples: int, mean_samples_per_ray: float, lo: int, hi: int) -> int:
    """Ray count that should give about ``target_samples`` samples: int(target / mean), in [lo, hi]."""
    if not mean_samples_per_ray > 0:  # also catches NaN
        return int(hi)
    return int(min(max(int(target_samples / mean_samples_per_ray), lo), hi))
