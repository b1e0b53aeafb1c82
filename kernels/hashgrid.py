"""Multiresolution hash-grid encoding (Instant-NGP style): Warp kernels and a torch twin.

Contract (docs/INTERNALS.md, "hash_encode"): level ``l`` has ``res_l + 1`` vertices per
axis and vertex coordinate ``u * res_l``; its features are the trilinear interpolation of
the 8 corner entries of ``table[l]``. A corner's entry is found by dense indexing
``x + y*(r+1) + z*(r+1)^2`` when ``(res_l+1)^3 <= T``, else by the spatial hash
``x ^ (y*2654435761) ^ (z*805459861) mod T`` in uint32 arithmetic. Levels
``>= active_levels`` output zeros (coarse-to-fine training) and get no gradient.

``hash_encode_jac`` returns the same features plus their spatial Jacobian d feats / d u from
one kernel (analytic SDF normals, docs/INTERNALS.md "hash_encode_jac").
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import warp as wp

from . import _warp
from ._warp import init, launch, to_wp

init()
# Gradients are hand-written below; skip Warp's generated adjoints (halves compile time).
wp.set_module_options({"enable_backward": False})

_PRIME_Y = 2654435761
_PRIME_Z = 805459861
_MAX_FEATURES = 8
# (point, level) pairs per CPU chunk at least: ~4 ms of backward work, far above the ~50 us
# that one more launch costs.
_MIN_CHUNK_WORK = 16384


@dataclass(frozen=True)
class HashGridConfig:
    """Hash-grid hyper-parameters.

    Attributes:
        levels: number of resolution levels L.
        features: features per level F (1..8).
        log2_table: log2 of the entries per level T.
        base_res: resolution of the coarsest level.
        finest_res: resolution of the finest level.
    """

    levels: int = 16
    features: int = 2
    log2_table: int = 19
    base_res: int = 16
    finest_res: int = 2048

    def __post_init__(self):
        if self.levels < 1:
            raise ValueError(f"HashGridConfig.levels must be >= 1, got {self.levels}")
        if not 1 <= self.features <= _MAX_FEATURES:
            raise ValueError(f"HashGridConfig.features must be in 1..{_MAX_FEATURES}, got {self.features}")
        if not 1 <= self.log2_table <= 30:
            raise ValueError(f"HashGridConfig.log2_table must be in 1..30, got {self.log2_table}")
        if self.base_res < 1 or self.finest_res < self.base_res:
            raise ValueError(
                f"HashGridConfig needs 1 <= base_res <= finest_res, got {self.base_res}, {self.finest_res}")

    @property
    def table_size(self) -> int:
        """Entries per level, T = 2**log2_table."""
        return 1 << self.log2_table

    @property
    def out_dim(self) -> int:
        """Width of the encoding, L * F."""
        return self.levels * self.features

    def growth(self) -> float:
        """Per-level growth factor b = exp(ln(finest / base) / (L - 1))."""
        if self.levels == 1:
            return 1.0
        return math.exp(math.log(self.finest_res / self.base_res) / (self.levels - 1))

    def resolutions(self) -> list[int]:
        """Per-level resolutions floor(base * b^l).

        A 1e-6 guard absorbs float rounding, so that e.g. 16 * b^15 = 2047.9999999999984
        gives the intended finest resolution 2048.
        """
        b = self.growth()
        return [int(math.floor(self.base_res * b ** l + 1e-6)) for l in range(self.levels)]

    def dense_levels(self) -> list[bool]:
        """True for levels whose (res + 1)^3 vertices fit in the table (indexed densely)."""
        return [(r + 1) ** 3 <= self.table_size for r in self.resolutions()]


def init_table(cfg: HashGridConfig, device="cpu", generator: torch.Generator | None = None) -> torch.Tensor:
    """Fresh feature table, uniform(-1e-4, 1e-4).

    Args:
        cfg: grid configuration.
        device: device of the returned table.
        generator: optional torch generator (the table is drawn on its device, then moved).

    Returns:
        table: [L, T, F] float32.
    """
    shape = (cfg.levels, cfg.table_size, cfg.features)
    gen_device = generator.device if generator is not None else device
    t = torch.rand(shape, generator=generator, device=gen_device, dtype=torch.float32)
    return (t * 2e-4 - 1e-4).to(device)


# ----------------------------------------------------------------------------- Warp kernels

_PY = wp.constant(wp.uint32(_PRIME_Y))
_PZ = wp.constant(wp.uint32(_PRIME_Z))


@wp.func
def _corner_index(x: int, y: int, z: int, r1: int, T: int, dense: int) -> int:
    """Entry of vertex (x, y, z) in a level's table (dense or uint32 spatial hash)."""
    if dense != 0:
        # (r+1)^3 <= T < 2^31 here, so int32 cannot overflow
        return x + y * r1 + z * r1 * r1
    h = wp.uint32(x) ^ (wp.uint32(y) * _PY) ^ (wp.uint32(z) * _PZ)
    # T is a power of two, so mod T is a mask (integer division is slow on GPUs)
    return wp.int32(h & wp.uint32(T - 1))


@wp.func
def _cell(u: float, res: int):
    """Clamped cell index and fraction of u * res (u = 1 lands in the last cell, frac 1)."""
    p = wp.clamp(u, 0.0, 1.0) * float(res)
    c = wp.min(int(wp.floor(p)), res - 1)
    return c, p - float(c)


@wp.func
def _corners(cx: int, cy: int, cz: int, r1: int, T: int, dense: int, base: int, F: int):
    """Flat table offsets (entry * F) of the 8 vertices of cell (cx, cy, cz) in the level whose
    table starts at entry ``base``, in the order 000, 100, 010, 110, 001, 101, 011, 111 (x fastest)."""
    return ((base + _corner_index(cx, cy, cz, r1, T, dense)) * F,
            (base + _corner_index(cx + 1, cy, cz, r1, T, dense)) * F,
            (base + _corner_index(cx, cy + 1, cz, r1, T, dense)) * F,
            (base + _corner_index(cx + 1, cy + 1, cz, r1, T, dense)) * F,
            (base + _corner_index(cx, cy, cz + 1, r1, T, dense)) * F,
            (base + _corner_index(cx + 1, cy, cz + 1, r1, T, dense)) * F,
            (base + _corner_index(cx, cy + 1, cz + 1, r1, T, dense)) * F,
            (base + _corner_index(cx + 1, cy + 1, cz + 1, r1, T, dense)) * F)


@wp.func
def _weights(fx: float, fy: float, fz: float):
    """Trilinear weights of the 8 cell vertices (order as :func:`_corners`) at fractions (fx, fy, fz)."""
    gx = 1.0 - fx
    gy = 1.0 - fy
    gz = 1.0 - fz
    return (gx * gy * gz, fx * gy * gz, gx * fy * gz, fx * fy * gz,
            gx * gy * fz, fx * gy * fz, gx * fy * fz, fx * fy * fz)


@wp.kernel
def _hash_fwd_kernel(
    u: wp.array(dtype=wp.vec3),  # [N]
    table: wp.array(dtype=float),  # [L*T*F] flat
    levels: wp.array2d(dtype=wp.int32),  # [L, 2] (res, dense)
    l0: int,  # first level of this launch
    n_lv: int,  # levels of this launch (l0 .. l0 + n_lv - 1, all active)
    active: wp.array(dtype=wp.int32),  # [1] levels >= active[0] are skipped (a captured step's count)
    T: int,
    F: int,
    out: wp.array2d(dtype=float),  # [N, L*F], zero-initialised
):
    # One thread per (point, level); level fastest so that writes to out coalesce.
    tid = wp.tid()
    n = tid // n_lv
    l = l0 + tid - n * n_lv
    if l >= active[0]:
        return  # inactive level: outputs stay 0, no gradient
    res = levels[l, 0]
    dense = levels[l, 1]
    r1 = res + 1
    p = u[n]
    cx, fx = _cell(p[0], res)
    cy, fy = _cell(p[1], res)
    cz, fz = _cell(p[2], res)
    i000, i100, i010, i110, i001, i101, i011, i111 = _corners(cx, cy, cz, r1, T, dense, l * T, F)
    w000, w100, w010, w110, w001, w101, w011, w111 = _weights(fx, fy, fz)
    col = l * F
    for f in range(F):
        out[n, col + f] = (
            w000 * table[i000 + f] + w100 * table[i100 + f] + w010 * table[i010 + f] + w110 * table[i110 + f]
            + w001 * table[i001 + f] + w101 * table[i101 + f] + w011 * table[i011 + f] + w111 * table[i111 + f]
        )


@wp.kernel
def _hash_bwd_kernel(
    u: wp.array(dtype=wp.vec3),  # [N]
    table: wp.array(dtype=float),  # [L*T*F] flat
    levels: wp.array2d(dtype=wp.int32),  # [L, 2] (res, dense)
    l0: int,  # first level of this launch
    n_lv: int,  # levels of this launch
    active: wp.array(dtype=wp.int32),  # [1] levels >= active[0] are skipped (a captured step's count)
    T: int,
    F: int,
    grad_out: wp.array2d(dtype=float),  # [N, L*F]
    need_table: int,
    need_u: int,
    grad_table: wp.array(dtype=float),  # [L*T*F] flat, zero-initialised (unused if not need_table)
    grad_u: wp.array(dtype=wp.vec3),  # [N], zero-initialised (unused if not need_u)
):
    # Serial order per table entry: points ascending (a launch over all points of a level
    # adds in the same order whatever the level grouping, so the sum is bit-identical).
    tid = wp.tid()
    n = tid // n_lv
    l = l0 + tid - n * n_lv
    if l >= active[0]:
        return  # inactive level: outputs stay 0, no gradient
    res = levels[l, 0]
    dense = levels[l, 1]
    r1 = res + 1
    p = u[n]
    cx, fx = _cell(p[0], res)
    cy, fy = _cell(p[1], res)
    cz, fz = _cell(p[2], res)
    gx = 1.0 - fx
    gy = 1.0 - fy
    gz = 1.0 - fz
    i000, i100, i010, i110, i001, i101, i011, i111 = _corners(cx, cy, cz, r1, T, dense, l * T, F)
    col = l * F
    if need_table != 0:
        w000, w100, w010, w110, w001, w101, w011, w111 = _weights(fx, fy, fz)
        for f in range(F):
            g = grad_out[n, col + f]
            wp.atomic_add(grad_table, i000 + f, w000 * g)
            wp.atomic_add(grad_table, i100 + f, w100 * g)
            wp.atomic_add(grad_table, i010 + f, w010 * g)
            wp.atomic_add(grad_table, i110 + f, w110 * g)
            wp.atomic_add(grad_table, i001 + f, w001 * g)
            wp.atomic_add(grad_table, i101 + f, w101 * g)
            wp.atomic_add(grad_table, i011 + f, w011 * g)
            wp.atomic_add(grad_table, i111 + f, w111 * g)
    if need_u != 0:
        # s_c = <grad_out, table[corner c]>: the upstream gradient seen by corner weight w_c
        s000 = float(0.0)
        s100 = float(0.0)
        s010 = float(0.0)
        s110 = float(0.0)
        s001 = float(0.0)
        s101 = float(0.0)
        s011 = float(0.0)
        s111 = float(0.0)
        for f in range(F):
            g = grad_out[n, col + f]
            s000 += g * table[i000 + f]
            s100 += g * table[i100 + f]
            s010 += g * table[i010 + f]
            s110 += g * table[i110 + f]
            s001 += g * table[i001 + f]
            s101 += g * table[i101 + f]
            s011 += g * table[i011 + f]
            s111 += g * table[i111 + f]
        # d w / d frac, times d frac / d u = res; zero where the clamp to [0, 1] is active
        rs = float(res)
        dx = (gy * gz * (s100 - s000) + fy * gz * (s110 - s010) + gy * fz * (s101 - s001) + fy * fz * (s111 - s011))
        dy = (gx * gz * (s010 - s000) + fx * gz * (s110 - s100) + gx * fz * (s011 - s001) + fx * fz * (s111 - s101))
        dz = (gx * gy * (s001 - s000) + fx * gy * (s101 - s100) + gx * fy * (s011 - s010) + fx * fy * (s111 - s110))
        if p[0] < 0.0 or p[0] > 1.0:
            dx = 0.0
        if p[1] < 0.0 or p[1] > 1.0:
            dy = 0.0
        if p[2] < 0.0 or p[2] > 1.0:
            dz = 0.0
        wp.atomic_add(grad_u, n, wp.vec3(dx * rs, dy * rs, dz * rs))


# ----------------------------------------------------------------------------- features + Jacobian
# Trilinear weights w_c = a_x a_y a_z with a = f (corner offset 1) or 1 - f (offset 0); their
# derivatives d w_c / d f_x = (+-1) a_y a_z, etc. With s = res on an axis where u lies in [0, 1]
# and s = 0 where the clamp is active, d feat / d u_k = s_k * sum_c (d w_c / d f_k) table[c].


@wp.func
def _axis_scale(u: float, res: int):
    """d (clamp(u, 0, 1) * res) / d u: res inside [0, 1] (ends included, as torch's clamp), else 0."""
    s = float(res)
    if u < 0.0 or u > 1.0:
        s = 0.0
    return s


@wp.kernel
def _hash_jac_fwd_kernel(
    u: wp.array(dtype=wp.vec3),  # [N]
    table: wp.array(dtype=float),  # [L*T*F] flat
    levels: wp.array2d(dtype=wp.int32),  # [L, 2] (res, dense)
    l0: int,  # first level of this launch
    n_lv: int,  # levels of this launch (l0 .. l0 + n_lv - 1, all active)
    active: wp.array(dtype=wp.int32),  # [1] levels >= active[0] are skipped (a captured step's count)
    T: int,
    F: int,
    out: wp.array2d(dtype=float),  # [N, L*F], zero-initialised
    jac: wp.array2d(dtype=wp.vec3),  # [N, L*F] of d feat / d u, zero-initialised
):
    # One thread per (point, active level), as _hash_fwd_kernel; the features are computed with
    # the same operations in the same order, so they equal hash_encode's bit for bit.
    tid = wp.tid()
    n = tid // n_lv
    l = l0 + tid - n * n_lv
    if l >= active[0]:
        return  # inactive level: outputs stay 0, no gradient
    res = levels[l, 0]
    dense = levels[l, 1]
    r1 = res + 1
    p = u[n]
    cx, fx = _cell(p[0], res)
    cy, fy = _cell(p[1], res)
    cz, fz = _cell(p[2], res)
    gx = 1.0 - fx
    gy = 1.0 - fy
    gz = 1.0 - fz
    sx = _axis_scale(p[0], res)
    sy = _axis_scale(p[1], res)
    sz = _axis_scale(p[2], res)
    i000, i100, i010, i110, i001, i101, i011, i111 = _corners(cx, cy, cz, r1, T, dense, l * T, F)
    w000, w100, w010, w110, w001, w101, w011, w111 = _weights(fx, fy, fz)
    col = l * F
    for f in range(F):
        t000 = table[i000 + f]
        t100 = table[i100 + f]
        t010 = table[i010 + f]
        t110 = table[i110 + f]
        t001 = table[i001 + f]
        t101 = table[i101 + f]
        t011 = table[i011 + f]
        t111 = table[i111 + f]
        out[n, col + f] = (
            w000 * t000 + w100 * t100 + w010 * t010 + w110 * t110
            + w001 * t001 + w101 * t101 + w011 * t011 + w111 * t111
        )
        dx = gy * gz * (t100 - t000) + fy * gz * (t110 - t010) + gy * fz * (t101 - t001) + fy * fz * (t111 - t011)
        dy = gx * gz * (t010 - t000) + fx * gz * (t110 - t100) + gx * fz * (t011 - t001) + fx * fz * (t111 - t101)
        dz = gx * gy * (t001 - t000) + fx * gy * (t101 - t100) + gx * fy * (t011 - t010) + fx * fy * (t111 - t110)
        jac[n, col + f] = wp.vec3(dx * sx, dy * sy, dz * sz)


@wp.kernel
def _hash_jac_bwd_kernel(
    u: wp.array(dtype=wp.vec3),  # [N]
    table: wp.array(dtype=float),  # [L*T*F] flat
    levels: wp.array2d(dtype=wp.int32),  # [L, 2] (res, dense)
    l0: int,  # first level of this launch
    n_lv: int,  # levels of this launch
    active: wp.array(dtype=wp.int32),  # [1] levels >= active[0] are skipped (a captured step's count)
    T: int,
    F: int,
    grad_out: wp.array2d(dtype=float),  # [N, L*F] dL/dfeats (unused if not has_gout)
    grad_jac: wp.array2d(dtype=wp.vec3),  # [N, L*F] dL/djac (unused if not has_gjac)
    has_gout: int,
    has_gjac: int,
    need_table: int,
    need_u: int,
    grad_table: wp.array(dtype=float),  # [L*T*F] flat, zero-initialised (unused if not need_table)
    grad_u: wp.array(dtype=wp.vec3),  # [N], zero-initialised (unused if not need_u)
):
    # dL/dtable[c, f] = w_c g_f + sum_k s_k (d w_c / d f_k) G_fk   (g = dL/dfeats, G = dL/djac)
    # dL/du_k         = sum_f jac_fk g_f                            (d jac / d u is dropped)
    tid = wp.tid()
    n = tid // n_lv
    l = l0 + tid - n * n_lv
    if l >= active[0]:
        return  # inactive level: outputs stay 0, no gradient
    res = levels[l, 0]
    dense = levels[l, 1]
    r1 = res + 1
    p = u[n]
    cx, fx = _cell(p[0], res)
    cy, fy = _cell(p[1], res)
    cz, fz = _cell(p[2], res)
    gx = 1.0 - fx
    gy = 1.0 - fy
    gz = 1.0 - fz
    sx = _axis_scale(p[0], res)
    sy = _axis_scale(p[1], res)
    sz = _axis_scale(p[2], res)
    i000, i100, i010, i110, i001, i101, i011, i111 = _corners(cx, cy, cz, r1, T, dense, l * T, F)
    col = l * F
    if need_table != 0:
        w000, w100, w010, w110, w001, w101, w011, w111 = _weights(fx, fy, fz)
        for f in range(F):
            g = float(0.0)
            if has_gout != 0:
                g = grad_out[n, col + f]
            a = float(0.0)
            b = float(0.0)
            c = float(0.0)
            if has_gjac != 0:
                gj = grad_jac[n, col + f]
                a = gj[0] * sx
                b = gj[1] * sy
                c = gj[2] * sz
            if g == 0.0 and a == 0.0 and b == 0.0 and c == 0.0:
                continue  # nothing to add (a captured step's padded samples): 8 atomics saved
            wp.atomic_add(grad_table, i000 + f, w000 * g - a * gy * gz - b * gx * gz - c * gx * gy)
            wp.atomic_add(grad_table, i100 + f, w100 * g + a * gy * gz - b * fx * gz - c * fx * gy)
            wp.atomic_add(grad_table, i010 + f, w010 * g - a * fy * gz + b * gx * gz - c * gx * fy)
            wp.atomic_add(grad_table, i110 + f, w110 * g + a * fy * gz + b * fx * gz - c * fx * fy)
            wp.atomic_add(grad_table, i001 + f, w001 * g - a * gy * fz - b * gx * fz + c * gx * gy)
            wp.atomic_add(grad_table, i101 + f, w101 * g + a * gy * fz - b * fx * fz + c * fx * gy)
            wp.atomic_add(grad_table, i011 + f, w011 * g - a * fy * fz + b * gx * fz + c * gx * fy)
            wp.atomic_add(grad_table, i111 + f, w111 * g + a * fy * fz + b * fx * fz + c * fx * fy)
    if need_u != 0 and has_gout != 0:
        # s_c = <grad_out, table[corner c]>, then jac^T grad_out as in _hash_bwd_kernel
        s000 = float(0.0)
        s100 = float(0.0)
        s010 = float(0.0)
        s110 = float(0.0)
        s001 = float(0.0)
        s101 = float(0.0)
        s011 = float(0.0)
        s111 = float(0.0)
        for f in range(F):
            g = grad_out[n, col + f]
            s000 += g * table[i000 + f]
            s100 += g * table[i100 + f]
            s010 += g * table[i010 + f]
            s110 += g * table[i110 + f]
            s001 += g * table[i001 + f]
            s101 += g * table[i101 + f]
            s011 += g * table[i011 + f]
            s111 += g * table[i111 + f]
        dx = (gy * gz * (s100 - s000) + fy * gz * (s110 - s010) + gy * fz * (s101 - s001) + fy * fz * (s111 - s011))
        dy = (gx * gz * (s010 - s000) + fx * gz * (s110 - s100) + gx * fz * (s011 - s001) + fx * fz * (s111 - s101))
        dz = (gx * gy * (s001 - s000) + fx * gy * (s101 - s100) + gx * fy * (s011 - s010) + fx * fy * (s111 - s110))
        wp.atomic_add(grad_u, n, wp.vec3(dx * sx, dy * sy, dz * sz))


# ----------------------------------------------------------------------------- wrappers

_level_cache: dict = {}


def _level_table(cfg: HashGridConfig, device: torch.device) -> torch.Tensor:
    """[L, 2] int32 (res, dense) on ``device``, cached so steady-state calls copy nothing."""
    key = (tuple(cfg.resolutions()), cfg.table_size, str(device))
    t = _level_cache.get(key)
    if t is None:
        t = torch.tensor([[r, int(d)] for r, d in zip(cfg.resolutions(), cfg.dense_levels())],
                         dtype=torch.int32).to(device)
        _level_cache[key] = t
    return t


def _n_active(cfg: HashGridConfig, active_levels) -> int:
    if active_levels is None:
        return cfg.levels
    return max(0, min(int(active_levels), cfg.levels))


# [1] int32 counts per (value, device) for calls given an int. Created on first use, which is never
# inside a CUDA graph capture: a captured step passes the field's device tensor (SDFField._levels_arg)
# and its eager warm-up runs first, as for _level_table.
_const_cache: dict = {}


def _active_args(cfg: HashGridConfig, active_levels, device) -> tuple[int, torch.Tensor]:
    """(levels to launch, [1] int32 device count the kernels skip levels at or above).

    ``active_levels`` may be an int (or None: all) or a [1] / 0-d integer tensor on ``device``:
    on CUDA the kernels read it at run time (all levels are launched and the inactive ones exit
    at once, so a captured graph follows the count); on the CPU it is read here.
    """
    if isinstance(active_levels, torch.Tensor):
        if active_levels.device.type != "cuda":
            active_levels = int(active_levels)
        else:
            t = active_levels.reshape(1)
            return cfg.levels, t if t.dtype == torch.int32 else t.to(torch.int32)
    n = _n_active(cfg, active_levels)
    key = (n, str(device))
    t = _const_cache.get(key)
    if t is None:
        t = _const_cache[key] = torch.full((1,), n, dtype=torch.int32, device=device)
    return n, t


def _check(u: torch.Tensor, table: torch.Tensor, cfg: HashGridConfig, op: str = "hash_encode") -> None:
    if u.dim() != 2 or u.shape[1] != 3:
        raise ValueError(f"{op}: u must be [N, 3], got {tuple(u.shape)}")
    want = (cfg.levels, cfg.table_size, cfg.features)
    if tuple(table.shape) != want:
        raise ValueError(f"{op}: table must be {list(want)} for this config, got {list(table.shape)}")
    if u.device != table.device:
        raise ValueError(f"{op}: u on {u.device} but table on {table.device}")


class _HashEncode(torch.autograd.Function):
    @staticmethod
    def forward(ctx, u, table, cfg, n_active, active):
        N = u.shape[0]
        L, T, F = cfg.levels, cfg.table_size, cfg.features
        u_c = u.detach().contiguous()
        t_c = table.detach().contiguous()
        levels = _level_table(cfg, u.device)
        out = torch.zeros((N, L * F), dtype=torch.float32, device=u.device)
        if N > 0 and n_active > 0:
            t_wp, lv_wp = to_wp(t_c.view(-1), ctype=True), to_wp(levels, ctype=True)
            act_wp = to_wp(active, ctype=True)

            def fwd(a: int, b: int):
                # rows a..b of u and out: every thread writes only its own point's row
                inp = [to_wp(u_c[a:b], dtype=wp.vec3, ctype=True), t_wp, lv_wp, 0, n_active, act_wp, T, F]
                outp = [to_wp(out[a:b], ctype=True)]
                return lambda: launch(_hash_fwd_kernel, (b - a) * n_active, inp, ref=u, outputs=outp)

            ranges = _warp.split(N, _warp.n_chunks(N * n_active, u, _MIN_CHUNK_WORK))
            _warp.run_tasks([fwd(a, b) for a, b in ranges], key=_hash_fwd_kernel)
        ctx.save_for_backward(u_c, t_c, active)
        ctx.cfg = cfg
        ctx.n_active = n_active
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out):
        u_c, t_c, active = ctx.saved_tensors
        cfg, n_active = ctx.cfg, ctx.n_active
        need_u, need_table = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        N = u_c.shape[0]
        grad_u = torch.zeros_like(u_c) if need_u else None
        grad_table = torch.zeros_like(t_c) if need_table else None
        if N > 0 and n_active > 0 and (need_u or need_table):
            go = grad_out.contiguous()
            if go.dtype != torch.float32:
                go = go.float()
            _backward_launches(u_c, t_c, go, cfg, n_active, active, grad_table, grad_u)
        return grad_u, grad_table, None, None, None


def _backward_launches(u_c, t_c, go, cfg: HashGridConfig, n_active: int, active: torch.Tensor, grad_table,
                       grad_u) -> None:
    """Launch the backward over (level group x point range) chunks on the CPU threads.

    Chunks of different level groups write disjoint parts of the table gradient; chunks of
    different point ranges write disjoint rows of the u gradient. Where two chunks could
    add to the same entry, all but the first write a private zeroed buffer, summed into the
    output afterwards in a fixed order. With one point range (the usual case: at least
    ``2 * threads`` active levels) the table gradient is bit-identical to one launch.
    """
    dev = u_c.device
    N = u_c.shape[0]
    need_table, need_u = grad_table is not None, grad_u is not None
    want = _warp.n_chunks(N * n_active, u_c, _MIN_CHUNK_WORK)
    # level groups first: they need no table-gradient buffers
    groups = max(1, min(n_active, want)) if need_table else 1
    parts = -(-want // groups)
    level_groups = _warp.split(n_active, groups)
    point_ranges = _warp.split(N, parts)
    dummy_vec = _warp.dummy((1, 3), u_c, "hash_bwd.u")
    dummy = _warp.dummy((1,), u_c, "hash_bwd.table")
    # table-gradient buffer per point range, u-gradient buffer per level group (index 0: the outputs)
    gt_bufs = [grad_table.view(-1) if need_table else dummy] + [
        torch.zeros_like(grad_table).view(-1) if need_table else dummy for _ in point_ranges[1:]]
    gu_bufs = [grad_u if need_u else dummy_vec] + [
        torch.zeros_like(grad_u) if need_u else dummy_vec for _ in level_groups[1:]]
    t_wp, lv_wp = to_wp(t_c.view(-1), ctype=True), to_wp(_level_table(cfg, dev), ctype=True)
    act_wp = to_wp(active, ctype=True)
    gt_wp = [to_wp(b, ctype=True) for b in gt_bufs]

    def task(g: int, p: int):
        (l0, l1), (a, b) = level_groups[g], point_ranges[p]
        gu = gu_bufs[g]
        gu_wp = to_wp(gu[a:b] if need_u else gu, dtype=wp.vec3, ctype=True)
        inp = [to_wp(u_c[a:b], dtype=wp.vec3, ctype=True), t_wp, lv_wp, l0, l1 - l0, act_wp, cfg.table_size,
               cfg.features, to_wp(go[a:b], ctype=True), int(need_table), int(need_u)]
        return lambda: launch(_hash_bwd_kernel, (b - a) * (l1 - l0), inp, ref=u_c, outputs=[gt_wp[p], gu_wp])

    _warp.run_tasks([task(g, p) for p in range(len(point_ranges)) for g in range(len(level_groups))],
                    key=_hash_bwd_kernel)
    if need_table:
        for extra in gt_bufs[1:]:
            grad_table.view(-1).add_(extra)
    if need_u:
        for extra in gu_bufs[1:]:
            grad_u.add_(extra)


def hash_encode(
    u: torch.Tensor,  # [N, 3] float32 in [0, 1]^3 (clamped)
    table: torch.Tensor,  # [L, T, F] float32
    cfg: HashGridConfig,
    active_levels: int | None = None,
) -> torch.Tensor:
    """Multiresolution hash encoding with Warp kernels (differentiable w.r.t. u and table).

    Runs on u's device and torch's current stream, without host synchronisation.

    Args:
        u: [N, 3] float32 grid coordinates, (x_n + 1) / 2; clamped to [0, 1] (zero
            gradient where the clamp is active).
        table: [L, T, F] float32 feature table.
        cfg: grid configuration (L, T, F must match the table).
        active_levels: levels >= this output zeros and get no gradient (None = all); an int or a
            [1] integer tensor on u's device (read by the kernels when they run, so a captured
            CUDA graph follows the count it holds at replay).

    Returns:
        feats: [N, L*F] float32, level-major (level l in columns l*F .. l*F+F-1).
    """
    _check(u, table, cfg)
    if u.dtype != torch.float32 or table.dtype != torch.float32:
        raise TypeError(f"hash_encode (warp) needs float32 u and table, got {u.dtype} and {table.dtype}")
    if cfg.levels * cfg.table_size * cfg.features >= 2 ** 31:
        raise ValueError("hash_encode: L*T*F must stay below 2^31 (int32 flat indices)")
    return _HashEncode.apply(u, table, cfg, *_active_args(cfg, active_levels, u.device))


class _HashEncodeJac(torch.autograd.Function):
    @staticmethod
    def forward(ctx, u, table, cfg, n_active, active):
        N = u.shape[0]
        L, T, F = cfg.levels, cfg.table_size, cfg.features
        u_c = u.detach().contiguous()
        t_c = table.detach().contiguous()
        levels = _level_table(cfg, u.device)
        out = torch.zeros((N, L * F), dtype=torch.float32, device=u.device)
        jac = torch.zeros((N, L * F, 3), dtype=torch.float32, device=u.device)
        if N > 0 and n_active > 0:
            t_wp, lv_wp = to_wp(t_c.view(-1), ctype=True), to_wp(levels, ctype=True)
            act_wp = to_wp(active, ctype=True)

            def fwd(a: int, b: int):
                # rows a..b of u, out and jac: every thread writes only its own point's rows
                inp = [to_wp(u_c[a:b], dtype=wp.vec3, ctype=True), t_wp, lv_wp, 0, n_active, act_wp, T, F]
                outp = [to_wp(out[a:b], ctype=True), to_wp(jac[a:b], dtype=wp.vec3, ctype=True)]
                return lambda: launch(_hash_jac_fwd_kernel, (b - a) * n_active, inp, ref=u, outputs=outp)

            ranges = _warp.split(N, _warp.n_chunks(N * n_active, u, _MIN_CHUNK_WORK))
            _warp.run_tasks([fwd(a, b) for a, b in ranges], key=_hash_jac_fwd_kernel)
        ctx.save_for_backward(u_c, t_c, active)
        ctx.cfg = cfg
        ctx.n_active = n_active
        ctx.set_materialize_grads(False)  # an unused output (often jac's) costs nothing
        return out, jac

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out, grad_jac):
        u_c, t_c, active = ctx.saved_tensors
        cfg, n_active = ctx.cfg, ctx.n_active
        need_u = ctx.needs_input_grad[0] and grad_out is not None  # dL/du = jac^T dL/dfeats only
        need_table = ctx.needs_input_grad[1] and (grad_out is not None or grad_jac is not None)
        N = u_c.shape[0]
        grad_u = torch.zeros_like(u_c) if ctx.needs_input_grad[0] else None
        grad_table = torch.zeros_like(t_c) if ctx.needs_input_grad[1] else None
        if N > 0 and n_active > 0 and (need_u or need_table):
            dev = u_c.device
            dummy = _warp.dummy((1,), u_c, "hash_jac_bwd.table")
            dummy2 = _warp.dummy((1, 1), u_c, "hash_jac_bwd.go")
            dummy_vec = _warp.dummy((1, 3), u_c, "hash_jac_bwd.u")
            dummy_jac = _warp.dummy((1, 1, 3), u_c, "hash_jac_bwd.gj")
            go = dummy2 if grad_out is None else grad_out.float().contiguous()
            gj = dummy_jac if grad_jac is None else grad_jac.float().contiguous()
            # CPU threads: one chunk per group of levels. Groups write disjoint parts of the table
            # gradient (no race between Warp's non-atomic CPU adds); each group after the first
            # adds dL/du into its own buffer, summed below in a fixed order.
            groups = _warp.split(n_active, max(1, min(n_active, _warp.n_chunks(N * n_active, u_c, _MIN_CHUNK_WORK))))
            gt_wp = to_wp(grad_table.view(-1), ctype=True) if need_table else to_wp(dummy, ctype=True)
            gu_bufs = [grad_u if need_u else dummy_vec] + [torch.zeros_like(u_c) if need_u else dummy_vec
                                                          for _ in groups[1:]]
            common = [to_wp(u_c, dtype=wp.vec3, ctype=True), to_wp(t_c.view(-1), ctype=True),
                      to_wp(_level_table(cfg, dev), ctype=True)]
            act_wp = to_wp(active, ctype=True)
            rest = [cfg.table_size, cfg.features, to_wp(go, ctype=True), to_wp(gj, dtype=wp.vec3, ctype=True),
                    int(grad_out is not None), int(grad_jac is not None), int(need_table), int(need_u)]

            def bwd(g: int):
                l0, l1 = groups[g]
                outp = [gt_wp, to_wp(gu_bufs[g], dtype=wp.vec3, ctype=True)]
                return lambda: launch(_hash_jac_bwd_kernel, N * (l1 - l0), common + [l0, l1 - l0, act_wp] + rest,
                                      ref=u_c, outputs=outp)

            _warp.run_tasks([bwd(g) for g in range(len(groups))], key=_hash_jac_bwd_kernel)
            if need_u:
                for extra in gu_bufs[1:]:
                    grad_u.add_(extra)
        return grad_u, grad_table, None, None, None


def hash_encode_jac(
    u: torch.Tensor,  # [N, 3] float32 in [0, 1]^3 (clamped)
    table: torch.Tensor,  # [L, T, F] float32
    cfg: HashGridConfig,
    active_levels: int | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Hash encoding and its spatial Jacobian from one Warp kernel (for analytic SDF normals).

    ``feats`` equals :func:`hash_encode`'s output bit for bit. ``jac[n, l*F + f, k]`` is
    d feats[n, l*F + f] / d u[n, k] = res_l * sum_c (d w_c / d frac_k) table[l, c, f] over the
    8 cell corners c (trilinear weights w_c); it is 0 on an axis where u lies outside [0, 1]
    (the clamp is active; u = 0 and u = 1 themselves count as inside, like torch's clamp),
    and 0 for levels >= ``active_levels``. At a cell face the derivative is the one-sided one
    of the cell that holds u (u * res = integer k belongs to cell k, and u = 1 to the last).

    Gradients (one Warp kernel): the table gets w_c dL/dfeats + sum_k res_l (d w_c / d frac_k)
    dL/djac_k at each corner entry; u gets jac^T dL/dfeats only. The second-order term
    dL/djac . d jac / d u is dropped: a trilinear cell's second derivatives are the cross terms
    d^2 w / d frac_j d frac_k (j != k) only (d^2 w / d frac_k^2 = 0), the SDF sample positions
    are not trained, and where they are (pose refinement, through the ray origins and
    directions) the first-order term, the photometric and SDF gradient, is what moves them;
    the dropped term is the eikonal loss's pull through the grid's piecewise-bilinear
    Hessian, which has no useful meaning for a pose.

    Runs on u's device and torch's current stream, without host synchronisation.

    Args:
        u: [N, 3] float32 grid coordinates, (x_n + 1) / 2; clamped to [0, 1].
        table: [L, T, F] float32 feature table.
        cfg: grid configuration (L, T, F must match the table).
        active_levels: levels >= this output zeros (features and Jacobian) and get no
            gradient (None = all); an int or a [1] integer tensor on u's device (as in
            :func:`hash_encode`).

    Returns:
        feats: [N, L*F] float32, level-major (as :func:`hash_encode`).
        jac: [N, L*F, 3] float32, d feats / d u.
    """
    _check(u, table, cfg, "hash_encode_jac")
    if u.dtype != torch.float32 or table.dtype != torch.float32:
        raise TypeError(f"hash_encode_jac (warp) needs float32 u and table, got {u.dtype} and {table.dtype}")
    if cfg.levels * cfg.table_size * cfg.features >= 2 ** 31:
        raise ValueError("hash_encode_jac: L*T*F must stay below 2^31 (int32 flat indices)")
    return _HashEncodeJac.apply(u, table, cfg, *_active_args(cfg, active_levels, u.device))


# ----------------------------------------------------------------------------- torch twin

def hash_index_torch(x: torch.Tensor, y: torch.Tensor, z: torch.Tensor, res: int, T: int) -> torch.Tensor:
    """Table entry of integer vertices (x, y, z) of a level of resolution ``res``.

    Args:
        x, y, z: integer tensors of one shape (any int dtype; computed in int64).
        res: level resolution (vertices per axis res + 1).
        T: entries in the level's table.

    Returns:
        int64 tensor of entries in [0, T), same shape as x.
    """
    x, y, z = x.long(), y.long(), z.long()
    r1 = res + 1
    if r1 ** 3 <= T:
        return x + y * r1 + z * (r1 * r1)
    # int64 products cannot overflow for coordinates < 2^31; the mask emulates uint32 wrap-around
    m = 0xFFFFFFFF
    h = (x & m) ^ ((y * _PRIME_Y) & m) ^ ((z * _PRIME_Z) & m)
    return h % T


def _level_mask_torch(cfg: HashGridConfig, active_levels, ref: torch.Tensor):
    """(int levels, [L*F] 0/1 mask or None): a tensor count becomes a mask (the twins' runtime
    count, multiplied in: the same values and zero gradients as skipping those levels)."""
    if not isinstance(active_levels, torch.Tensor):
        return active_levels, None
    lv = torch.arange(cfg.levels, device=ref.device).repeat_interleave(cfg.features)
    return None, (lv < active_levels.reshape(1).to(ref.device)).to(ref.dtype)


def hash_encode_torch(
    u: torch.Tensor,  # [N, 3] float in [0, 1]^3 (clamped)
    table: torch.Tensor,  # [L, T, F] float
    cfg: HashGridConfig,
    active_levels: int | None = None,
) -> torch.Tensor:
    """Pure-torch twin of :func:`hash_encode` (same maths, torch autograd).

    Works in u's dtype (float64 for gradcheck), on any device.

    Args:
        u: [N, 3] grid coordinates; clamped to [0, 1].
        table: [L, T, F] feature table.
        cfg: grid configuration.
        active_levels: levels >= this output zeros (None = all); an int or an integer tensor.

    Returns:
        feats: [N, L*F], level-major.
    """
    _check(u, table, cfg)
    N = u.shape[0]
    T, F = cfg.table_size, cfg.features
    active_levels, mask = _level_mask_torch(cfg, active_levels, u)
    n_active = _n_active(cfg, active_levels)
    uc = u.clamp(0.0, 1.0)
    outs = []
    for l, res in enumerate(cfg.resolutions()):
        if l >= n_active:
            outs.append(table.new_zeros((N, F)))
            continue
        p = uc * res  # [N, 3]
        c = torch.floor(p).clamp(max=res - 1).detach()  # u = 1 stays in the last cell
        frac = p - c  # d frac / d u = res
        ci = c.long()
        feat = 0.0
        for dz in (0, 1):
            wz = frac[:, 2] if dz else 1.0 - frac[:, 2]
            for dy in (0, 1):
                wy = frac[:, 1] if dy else 1.0 - frac[:, 1]
                for dx in (0, 1):
                    wx = frac[:, 0] if dx else 1.0 - frac[:, 0]
                    idx = hash_index_torch(ci[:, 0] + dx, ci[:, 1] + dy, ci[:, 2] + dz, res, T)
                    feat = feat + (wx * wy * wz)[:, None] * table[l][idx]  # [N, F]
        outs.append(feat)
    out = torch.cat(outs, dim=1)
    if n_active == 0:
        # keep the (all-zero) result on the autograd graph so backward() still works
        out = out + (table[:0].sum() + u[:0].sum())
    return out if mask is None else out * mask


def hash_encode_jac_torch(
    u: torch.Tensor,  # [N, 3] float in [0, 1]^3 (clamped)
    table: torch.Tensor,  # [L, T, F] float
    cfg: HashGridConfig,
    active_levels: int | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pure-torch twin of :func:`hash_encode_jac` (same maths, torch autograd).

    The Jacobian is the explicit derivative of the trilinear weights (not autograd). Its
    dependence on u goes through the detached cell fraction, so autograd drops
    dL/djac . d jac / d u exactly as the Warp backward does; every other gradient (u through
    ``feats``, the table through both outputs) is torch's own. Works in u's dtype (float64
    for gradcheck), on any device.

    Args:
        u: [N, 3] grid coordinates; clamped to [0, 1].
        table: [L, T, F] feature table.
        cfg: grid configuration.
        active_levels: levels >= this output zeros (None = all); an int or an integer tensor.

    Returns:
        feats: [N, L*F], level-major.
        jac: [N, L*F, 3], d feats / d u.
    """
    _check(u, table, cfg, "hash_encode_jac")
    N = u.shape[0]
    T, F = cfg.table_size, cfg.features
    active_levels, mask = _level_mask_torch(cfg, active_levels, u)
    n_active = _n_active(cfg, active_levels)
    uc = u.clamp(0.0, 1.0)
    inside = ((u >= 0.0) & (u <= 1.0)).to(u.dtype).detach()  # d clamp / d u, per axis
    outs, jacs = [], []
    for l, res in enumerate(cfg.resolutions()):
        if l >= n_active:
            outs.append(table.new_zeros((N, F)))
            jacs.append(table.new_zeros((N, F, 3)))
            continue
        p = uc * res  # [N, 3]
        c = torch.floor(p).clamp(max=res - 1).detach()  # u = 1 stays in the last cell
        frac = p - c  # d frac / d u = res
        fd = frac.detach()
        scale = inside * res  # [N, 3]
        ci = c.long()
        feat, jac = 0.0, 0.0
        for dz in (0, 1):
            for dy in (0, 1):
                for dx in (0, 1):
                    # weights (differentiable in u) and their frac-derivatives (constants in u)
                    a = [frac[:, k] if d else 1.0 - frac[:, k] for k, d in enumerate((dx, dy, dz))]
                    b = [fd[:, k] if d else 1.0 - fd[:, k] for k, d in enumerate((dx, dy, dz))]
                    sg = [1.0 if d else -1.0 for d in (dx, dy, dz)]
                    dw = torch.stack([sg[0] * b[1] * b[2], sg[1] * b[0] * b[2], sg[2] * b[0] * b[1]], 1)  # [N, 3]
                    idx = hash_index_torch(ci[:, 0] + dx, ci[:, 1] + dy, ci[:, 2] + dz, res, T)
                    entry = table[l][idx]  # [N, F]
                    feat = feat + (a[0] * a[1] * a[2])[:, None] * entry
                    jac = jac + entry[:, :, None] * (dw * scale)[:, None, :]
        outs.append(feat)
        jacs.append(jac)
    out = torch.cat(outs, dim=1)
    jac = torch.cat(jacs, dim=1)
    if n_active == 0:
        # keep the (all-zero) results on the autograd graph so backward() still works
        z = table[:0].sum() + u[:0].sum()
        out, jac = out + z, jac + z
    return (out, jac) if mask is None else (out * mask, jac * mask[:, None])


# ----------------------------------------------------------------------------- jac contraction
# The analytic SDF gradient from the MLP's input gradient g = [d f / d x (3), d f / d feats (F)]:
# grad[n] = g[n, :3] + scale * sum_f g[n, 3 + f] jac[n, f, :]. In torch this was a slice, a
# batched gemv (bmm [N,1,F] x [N,F,3]: 1.5 ms forward + backward at 2^18 samples on an H100),
# a scale and an add, and their backward copies; here one kernel each way.

@wp.kernel
def _grad_from_jac_fwd_kernel(g: wp.array2d(dtype=float), jac: wp.array2d(dtype=wp.vec3), scale: float,
                              out: wp.array(dtype=wp.vec3)):
    n = wp.tid()
    acc = wp.vec3(0.0, 0.0, 0.0)
    for f in range(jac.shape[1]):
        acc = acc + g[n, 3 + f] * jac[n, f]
    out[n] = wp.vec3(g[n, 0], g[n, 1], g[n, 2]) + scale * acc


@wp.kernel
def _grad_from_jac_bwd_kernel(g: wp.array(dtype=float), jac: wp.array(dtype=wp.vec3), d_out: wp.array(dtype=wp.vec3),
                              n_col: int, scale: float, need_g: int, need_jac: int,
                              d_g: wp.array(dtype=float), d_jac: wp.array(dtype=wp.vec3)):
    # one thread per entry of g [N, 3 + F], flat: neighbouring threads touch neighbouring entries
    # (a thread per point looping over features made every access strided: 1.9 ms at 2^18)
    i = wp.tid()
    n = i // n_col
    c = i - n * n_col
    do = d_out[n]
    if c < 3:
        if need_g != 0:
            d_g[i] = do[c]
    else:
        j = n * (n_col - 3) + c - 3
        if need_g != 0:
            d_g[i] = scale * wp.dot(jac[j], do)
        if need_jac != 0:
            d_jac[j] = (scale * g[i]) * do


_MIN_CHUNK_POINTS = 2048  # points per CPU chunk at least (~0.2 ms of work each at F = 16)


class _GradFromJac(torch.autograd.Function):
    @staticmethod
    def forward(ctx, g, jac, scale):
        gc, jc = g.detach().float().contiguous(), jac.detach().float().contiguous()
        N = gc.shape[0]
        out = torch.empty((N, 3), dtype=torch.float32, device=g.device)
        if N > 0:
            ranges = _warp.item_ranges(N, gc, _MIN_CHUNK_POINTS)
            _warp.launch_chunked(_grad_from_jac_fwd_kernel,
                                 [to_wp(gc, ctype=True), to_wp(jc, dtype=wp.vec3, ctype=True), float(scale)],
                                 [to_wp(out, dtype=wp.vec3, ctype=True)], gc, ranges,
                                 sliced_in={0: (gc, None), 1: (jc, wp.vec3)}, sliced_out={0: (out, wp.vec3)})
        ctx.save_for_backward(gc, jc)
        ctx.scale = float(scale)
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, d_out):
        gc, jc = ctx.saved_tensors
        need_g, need_jac = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        N, C = gc.shape
        d_g = torch.empty_like(gc) if need_g else _warp.dummy((1, 1), gc, "grad_from_jac_bwd.g")
        d_jac = torch.empty_like(jc) if need_jac else _warp.dummy((1, 1, 3), gc, "grad_from_jac_bwd.jac")
        if N > 0 and (need_g or need_jac):
            doc = d_out.float().contiguous()
            F = C - 3
            g1, j1, dg1, dj1 = gc.view(-1), jc.view(-1, 3), d_g.view(-1), d_jac.view(-1, 3)

            def task(a: int, b: int):  # whole points a..b
                inp = [to_wp(g1[a * C:b * C], ctype=True), to_wp(j1[a * F:b * F], dtype=wp.vec3, ctype=True),
                       to_wp(doc[a:b], dtype=wp.vec3, ctype=True), C, ctx.scale, int(need_g), int(need_jac)]
                outp = [to_wp(dg1[a * C:b * C] if need_g else dg1, ctype=True),
                        to_wp(dj1[a * F:b * F] if need_jac else dj1, dtype=wp.vec3, ctype=True)]
                return lambda: launch(_grad_from_jac_bwd_kernel, (b - a) * C, inp, ref=gc, outputs=outp)

            ranges = _warp.item_ranges(N, gc, _MIN_CHUNK_POINTS)
            _warp.run_tasks([task(a, b) for a, b in ranges], key=_grad_from_jac_bwd_kernel)
        return (d_g if need_g else None), (d_jac if need_jac else None), None


def _check_grad_from_jac(g: torch.Tensor, jac: torch.Tensor) -> None:
    if g.dim() != 2 or jac.dim() != 3 or jac.shape[0] != g.shape[0] or jac.shape[1] + 3 != g.shape[1] \
            or jac.shape[2] != 3:
        raise ValueError(f"grad_from_jac: g [N, 3 + F] and jac [N, F, 3], got {tuple(g.shape)} and {tuple(jac.shape)}")


def grad_from_jac(g: torch.Tensor, jac: torch.Tensor, scale: float) -> torch.Tensor:
    """``g[:, :3] + scale * sum_f g[:, 3 + f] jac[:, f, :]`` (Warp): the analytic SDF gradient
    from the MLP's input gradient (position part, then the hash features' part pulled back
    through :func:`hash_encode_jac`'s Jacobian; ``scale`` = d u / d x).

    Gradients (first order, one kernel): d g = [d out, scale jac . d out], d jac = scale g_f d out^T.

    Args:
        g: [N, 3 + F]; jac: [N, F, 3]; scale: float.
    Returns:
        [N, 3] float32.
    """
    _check_grad_from_jac(g, jac)
    return _GradFromJac.apply(g, jac, scale)


def grad_from_jac_torch(g: torch.Tensor, jac: torch.Tensor, scale: float) -> torch.Tensor:
    """Twin of :func:`grad_from_jac` in torch ops (any dtype, any order of derivatives)."""
    _check_grad_from_jac(g, jac)
    return g[:, :3] + scale * (g[:, 3:, None] * jac).sum(1)
