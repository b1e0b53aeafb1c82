"""NeuS volume rendering with pattern projection (ActiveNeuS), forward and backward.

``render_pattern`` is the Warp op (one thread per ray, hand-written backward, wrapped in a
``torch.autograd.Function``); ``render_pattern_torch`` is its pure-torch twin with the same
signature and maths (the test reference and the torch backend). See docs/INTERNALS.md,
section "render_pattern", for the contract.

Per sample i of a ray with direction d (a = cos_anneal, s = inv_s, dt = t1 - t0):

    cos      = dot(d, grad_i)
    iter_cos = -(relu(0.5 - 0.5 cos) (1 - a) + relu(-cos) a)
    prev     = sdf_i - iter_cos dt / 2,   next = sdf_i + iter_cos dt / 2
    alpha_i  = clamp((sig(s prev) - sig(s next) + 1e-5) / (sig(s prev) + 1e-5), 0, 1 - 1e-4)
    T_i      = prod_{j<i} (1 - alpha_j),  w_i = T_i alpha_i
    Q(P)     = sum_k bilinear(pattern_k, K_k X / X.z - 0.5),  X = W_k [P, 1]  (0 if X.z <= 1e-6)
    c_i      = D_i + (i_r D_i + i_b + e_i) * Q(P_i)    (e_i: optional per-sample highlight, else 0)
    color = sum w c, texture = sum w D, opacity = sum w, depth = sum w (t0 + t1) / 2

The forward saves T_i per sample ([S] float32); the backward scans each ray in reverse,
recomputing alpha, Q and c, and folds the upstream gradients of all four outputs into one
per-sample scalar v_i, so dL/dalpha_i = T_i v_i - (sum_{j>i} w_j v_j) / (1 - alpha_i) needs no
subtraction of nearly equal totals. Shared parameters (inv_s, i_r, i_b, proj_W) are summed
per ray first and added with one atomic per ray.
"""
from __future__ import annotations

from functools import partial
from typing import Sequence

import numpy as np
import torch
import warp as wp

from . import _warp

_warp.init()
# Launch arguments as Warp's light array descriptors: ~4x less host time per argument, and
# a render call passes ~60 of them.
_wp = partial(_warp.to_wp, ctype=True)
# The backward is written by hand: skip Warp's adjoint code generation (halves compile time).
wp.set_module_options({"enable_backward": False})

MAX_PROJECTORS = 8  # per frame; bounds the per-ray proj_W gradient accumulator below
_ALPHA_MAX = 1.0 - 1e-4
_EPS = 1e-5
_Z_MIN = 1e-6

mat34 = wp.types.matrix(shape=(3, 4), dtype=wp.float32)
# Per-ray accumulator of d loss / d proj_W for every projector of the ray's frame: rays share
# their frame, so summing over the ray's samples first cuts same-address atomics ~S/R-fold.
_wacc = wp.types.matrix(shape=(MAX_PROJECTORS, 12), dtype=wp.float32)


# ----------------------------------------------------------------------------------------
# Pattern store
# ----------------------------------------------------------------------------------------
class PatternStore:
    """All projector patterns packed once into one flat uint8 buffer.

    Pattern ``p`` occupies ``buffer[meta[p, 0] : meta[p, 0] + 3 * W * H]`` in row-major
    (row, column, RGB) order, with ``meta[p] = (offset, width, height)``. Values are read as
    ``uint8 / 255``. Keeping uint8 (not float per pattern) keeps memory flat in the number of
    patterns (DESIGN.md, performance model).

    Args:
        patterns: sequence of uint8 [H, W, 3] RGB numpy arrays or torch tensors.
        device: torch device the packed buffer lives on.
    """

    def __init__(self, patterns: Sequence, device: str | torch.device = "cpu"):
        chunks, meta, offset = [], [], 0
        for i, p in enumerate(patterns):
            t = p if isinstance(p, torch.Tensor) else torch.from_numpy(np.ascontiguousarray(p))
            if t.dtype != torch.uint8 or t.ndim != 3 or t.shape[2] != 3:
                raise ValueError(f"pattern {i}: expected uint8 [H, W, 3], got {t.dtype} {tuple(t.shape)}")
            h, w = int(t.shape[0]), int(t.shape[1])
            chunks.append(t.detach().contiguous().reshape(-1))
            meta.append((offset, w, h))
            offset += 3 * w * h
        if offset >= 2**31:
            raise ValueError(f"patterns hold {offset} bytes; the int32 offsets allow < 2^31")
        # packed where the patterns are when they all are on ``device`` (no host round trip)
        dev = torch.device(device)
        same = all(c.device.type == dev.type for c in chunks)
        buf = torch.cat(chunks if same else [c.cpu() for c in chunks]) if chunks else torch.zeros(0, dtype=torch.uint8)
        self.buffer = buf.to(device)  # [sum 3*W*H] uint8
        self.meta = torch.tensor(meta, dtype=torch.int32).reshape(-1, 3).to(device)  # [NPat, 3] int32

    @classmethod
    def _from_parts(cls, buffer: torch.Tensor, meta: torch.Tensor) -> "PatternStore":
        obj = cls.__new__(cls)
        obj.buffer, obj.meta = buffer, meta
        return obj

    @property
    def device(self) -> torch.device:
        return self.buffer.device

    def to(self, device: str | torch.device) -> "PatternStore":
        """This store on ``device`` (``self`` when already there)."""
        device = torch.device(device)
        if device.type == self.buffer.device.type and (device.index is None or device == self.buffer.device):
            return self
        return PatternStore._from_parts(self.buffer.to(device), self.meta.to(device))

    def __len__(self) -> int:
        return int(self.meta.shape[0])

    def image(self, p: int) -> torch.Tensor:
        """Pattern ``p`` as a uint8 [H, W, 3] view (for inspection and tests)."""
        off, w, h = (int(v) for v in self.meta[p].tolist())
        return self.buffer[off:off + 3 * w * h].view(h, w, 3)


# ----------------------------------------------------------------------------------------
# Warp functions shared by forward and backward (identical code -> identical decisions)
# ----------------------------------------------------------------------------------------
@wp.func
def _sigmoid(x: float):
    return 1.0 / (1.0 + wp.exp(-x))


@wp.func
def _iter_cos(cos: float, a: float):
    return -(wp.max(-cos * 0.5 + 0.5, 0.0) * (1.0 - a) + wp.max(-cos, 0.0) * a)


@wp.func
def _raw_alpha(sdf: float, ic: float, dt: float, s: float):
    prev = sdf - ic * dt * 0.5
    nxt = sdf + ic * dt * 0.5
    sp = _sigmoid(prev * s)
    sn = _sigmoid(nxt * s)
    return (sp - sn + 1e-5) / (sp + 1e-5)


@wp.func
def _transform(Wf: mat34, p: wp.vec3):
    return wp.vec3(
        Wf[0, 0] * p[0] + Wf[0, 1] * p[1] + Wf[0, 2] * p[2] + Wf[0, 3],
        Wf[1, 0] * p[0] + Wf[1, 1] * p[1] + Wf[1, 2] * p[2] + Wf[1, 3],
        Wf[2, 0] * p[0] + Wf[2, 1] * p[1] + Wf[2, 2] * p[2] + Wf[2, 3],
    )


@wp.func
def _transform_vjp(Wf: mat34, g: wp.vec3):
    """Gradient w.r.t. p of <g, W p>: W[:, :3]^T g."""
    return wp.vec3(
        Wf[0, 0] * g[0] + Wf[1, 0] * g[1] + Wf[2, 0] * g[2],
        Wf[0, 1] * g[0] + Wf[1, 1] * g[1] + Wf[2, 1] * g[2],
        Wf[0, 2] * g[0] + Wf[1, 2] * g[1] + Wf[2, 2] * g[2],
    )


@wp.func
def _pixel_vjp(Kf: wp.mat33, g2: wp.vec2, px: float, py: float, z: float):
    """Gradient w.r.t. the projector-frame point X of <g2, (px, py)>, px = (K X)_0 / z, py = (K X)_1 / z."""
    gX = (g2[0] * wp.vec3(Kf[0, 0], Kf[0, 1], Kf[0, 2]) + g2[1] * wp.vec3(Kf[1, 0], Kf[1, 1], Kf[1, 2])) / z
    return gX - wp.vec3(0.0, 0.0, (g2[0] * px + g2[1] * py) / z)


@wp.func
def _texel(pat: wp.array(dtype=wp.uint8), off: int, w: int, h: int, xi: int, yi: int):
    if xi < 0 or xi >= w or yi < 0 or yi >= h:
        return wp.vec3(0.0)
    idx = off + (yi * w + xi) * 3
    return wp.vec3(float(pat[idx]) / 255.0, float(pat[idx + 1]) / 255.0, float(pat[idx + 2]) / 255.0)


@wp.func
def _cell_ok(xf: float, yf: float, w: int, h: int):
    # Some corner of the cell is inside the pattern (also false for NaN / huge coordinates,
    # which keeps the int conversion below defined).
    return xf >= -1.0 and xf < float(w) and yf >= -1.0 and yf < float(h)


@wp.func
def _bilinear(pat: wp.array(dtype=wp.uint8), off: int, w: int, h: int, x: float, y: float):
    xf = wp.floor(x)
    yf = wp.floor(y)
    if not _cell_ok(xf, yf, w, h):
        return wp.vec3(0.0)
    x0 = int(xf)
    y0 = int(yf)
    fx = x - xf
    fy = y - yf
    v00 = _texel(pat, off, w, h, x0, y0)
    v10 = _texel(pat, off, w, h, x0 + 1, y0)
    v01 = _texel(pat, off, w, h, x0, y0 + 1)
    v11 = _texel(pat, off, w, h, x0 + 1, y0 + 1)
    return (v00 * (1.0 - fx) + v10 * fx) * (1.0 - fy) + (v01 * (1.0 - fx) + v11 * fx) * fy


@wp.func
def _bilinear_vg(pat: wp.array(dtype=wp.uint8), off: int, w: int, h: int, x: float, y: float, gq: wp.vec3):
    """bilinear(x, y) and d <gq, bilinear(x, y)> / d (x, y) from one fetch of the 4 texels.

    The cell corner (floor) carries no gradient, as in torch.
    """
    xf = wp.floor(x)
    yf = wp.floor(y)
    if not _cell_ok(xf, yf, w, h):
        return wp.vec3(0.0), wp.vec2(0.0)
    x0 = int(xf)
    y0 = int(yf)
    fx = x - xf
    fy = y - yf
    v00 = _texel(pat, off, w, h, x0, y0)
    v10 = _texel(pat, off, w, h, x0 + 1, y0)
    v01 = _texel(pat, off, w, h, x0, y0 + 1)
    v11 = _texel(pat, off, w, h, x0 + 1, y0 + 1)
    top = v00 * (1.0 - fx) + v10 * fx
    bot = v01 * (1.0 - fx) + v11 * fx
    gx = wp.dot(gq, (v10 - v00) * (1.0 - fy) + (v11 - v01) * fy)
    gy = wp.dot(gq, bot - top)
    return top * (1.0 - fy) + bot * fy, wp.vec2(gx, gy)


@wp.func
def _pattern_sum(p: wp.vec3, f: int, P: int, K: wp.array2d(dtype=wp.mat33), W: wp.array2d(dtype=mat34),
                 proj_pattern: wp.array2d(dtype=wp.int32), pat: wp.array(dtype=wp.uint8),
                 meta: wp.array(dtype=wp.vec3i)):
    q = wp.vec3(0.0)
    for k in range(P):
        pid = proj_pattern[f, k]
        if pid >= 0:
            X = _transform(W[f, k], p)
            if X[2] > 1e-6:
                u = K[f, k] * X
                m = meta[pid]
                q += _bilinear(pat, m[0], m[1], m[2], u[0] / X[2] - 0.5, u[1] / X[2] - 0.5)
    return q


# ----------------------------------------------------------------------------------------
# Kernels
# ----------------------------------------------------------------------------------------
@wp.kernel
def _render_fwd(
    sdf: wp.array(dtype=float), grad: wp.array(dtype=wp.vec3), col: wp.array(dtype=wp.vec3),
    pos: wp.array(dtype=wp.vec3), t0: wp.array(dtype=float), t1: wp.array(dtype=float),
    offsets: wp.array(dtype=wp.int32), counts: wp.array(dtype=wp.int32), dirs: wp.array(dtype=wp.vec3),
    ray_frame: wp.array(dtype=wp.int32), K: wp.array2d(dtype=wp.mat33), W: wp.array2d(dtype=mat34),
    proj_pattern: wp.array2d(dtype=wp.int32), pat: wp.array(dtype=wp.uint8), meta: wp.array(dtype=wp.vec3i),
    inv_s: wp.array(dtype=float), cos_anneal: wp.array(dtype=float), i_r: wp.array(dtype=float),
    i_b: wp.array(dtype=float),
    write_weights: int, q_ext: wp.array(dtype=wp.vec3), use_qext: int,
    spec: wp.array(dtype=float), use_spec: int,
    out_color: wp.array(dtype=wp.vec3), out_opacity: wp.array(dtype=float), out_depth: wp.array(dtype=float),
    out_texture: wp.array(dtype=wp.vec3), out_weights: wp.array(dtype=float), out_trans: wp.array(dtype=float),
):
    r = wp.tid()
    start = offsets[r]
    n = counts[r]
    d = dirs[r]
    f = ray_frame[r]
    P = proj_pattern.shape[1]
    s = inv_s[0]
    ir = i_r[0]
    ib = i_b[0]
    T = float(1.0)
    C = wp.vec3(0.0)
    tex = wp.vec3(0.0)
    op = float(0.0)
    dep = float(0.0)
    for i in range(start, start + n):
        a0 = t0[i]
        a1 = t1[i]
        ic = _iter_cos(wp.dot(d, grad[i]), cos_anneal[0])
        alpha = wp.clamp(_raw_alpha(sdf[i], ic, a1 - a0, s), 0.0, 0.9999)
        w = T * alpha
        D = col[i]
        q = wp.vec3(0.0)
        if use_qext != 0:
            q = q_ext[i]
        else:
            q = _pattern_sum(pos[i], f, P, K, W, proj_pattern, pat, meta)
        b = ib
        if use_spec != 0:
            b += spec[i]
        c = D + wp.cw_mul(D * ir + wp.vec3(b), q)
        C += w * c
        tex += w * D
        op += w
        dep += w * (a0 + a1) * 0.5
        if write_weights != 0:
            out_weights[i] = w
        out_trans[i] = T  # lets the backward scan in reverse without a cancelling subtraction
        T *= 1.0 - alpha
    out_color[r] = C
    out_opacity[r] = op
    out_depth[r] = dep
    out_texture[r] = tex


@wp.kernel
def _render_bwd(
    sdf: wp.array(dtype=float), grad: wp.array(dtype=wp.vec3), col: wp.array(dtype=wp.vec3),
    pos: wp.array(dtype=wp.vec3), t0: wp.array(dtype=float), t1: wp.array(dtype=float),
    offsets: wp.array(dtype=wp.int32), counts: wp.array(dtype=wp.int32), dirs: wp.array(dtype=wp.vec3),
    ray_frame: wp.array(dtype=wp.int32), K: wp.array2d(dtype=wp.mat33), W: wp.array2d(dtype=mat34),
    proj_pattern: wp.array2d(dtype=wp.int32), pat: wp.array(dtype=wp.uint8), meta: wp.array(dtype=wp.vec3i),
    inv_s: wp.array(dtype=float), cos_anneal: wp.array(dtype=float), i_r: wp.array(dtype=float),
    i_b: wp.array(dtype=float),
    # the forward's per-sample transmittance and the upstream gradients
    trans: wp.array(dtype=float), q_ext: wp.array(dtype=wp.vec3), use_qext: int, need_qext: int,
    spec: wp.array(dtype=float), use_spec: int, need_spec: int,
    g_color: wp.array(dtype=wp.vec3), g_opacity: wp.array(dtype=float), g_depth: wp.array(dtype=float),
    g_texture: wp.array(dtype=wp.vec3),
    # which input gradients to write (0/1)
    need_sdf: int, need_grad: int, need_col: int, need_pos: int, need_invs: int, need_ir: int, need_ib: int,
    need_W: int,
    # input gradients (zero-initialised; dummies of size 1 where not needed)
    d_sdf: wp.array(dtype=float), d_grad: wp.array(dtype=wp.vec3), d_col: wp.array(dtype=wp.vec3),
    d_pos: wp.array(dtype=wp.vec3), d_invs: wp.array(dtype=float), d_ir: wp.array(dtype=float),
    d_ib: wp.array(dtype=float), d_W: wp.array(dtype=float), d_qext: wp.array(dtype=wp.vec3),
    d_spec: wp.array(dtype=float),
):
    r = wp.tid()
    start = offsets[r]
    n = counts[r]
    if n == 0:
        return
    d = dirs[r]
    f = ray_frame[r]
    P = proj_pattern.shape[1]
    s = inv_s[0]
    ir = i_r[0]
    ib = i_b[0]
    a = cos_anneal[0]
    gc = g_color[r]
    go = g_opacity[r]
    gd = g_depth[r]
    gx = g_texture[r]
    # All four outputs are weighted sums sum_i w_i v_i of per-sample values; fold the upstream
    # gradients into one scalar v_i so one scan serves them all. Scanning in reverse,
    # suf = sum_{j>i} w_j v_j and dL/dalpha_i = T_i v_i - suf / (1 - alpha_i)  (1 - alpha_i >= 1e-4).
    # (The forward-order form V - acc_i cancels catastrophically in float32 once T is small.)
    need_alpha = need_sdf + need_grad + need_invs
    need_proj = need_pos + need_W
    suf = float(0.0)
    gs = float(0.0)
    gir = float(0.0)
    gib = float(0.0)
    accW = _wacc()
    for j in range(n):
        i = start + n - 1 - j
        a0 = t0[i]
        a1 = t1[i]
        dt = a1 - a0
        sd = sdf[i]
        cos = wp.dot(d, grad[i])
        ic = _iter_cos(cos, a)
        prev = sd - ic * dt * 0.5
        nxt = sd + ic * dt * 0.5
        sp = _sigmoid(prev * s)
        sn = _sigmoid(nxt * s)
        den = sp + 1e-5
        raw = (sp - sn + 1e-5) / den
        alpha = wp.clamp(raw, 0.0, 0.9999)
        T = trans[i]
        w = T * alpha
        D = col[i]
        p = pos[i]
        b = ib  # the light's albedo-free part: i_b plus this sample's highlight
        if use_spec != 0:
            b += spec[i]
        gcw = w * gc  # dL/dc_i
        q = wp.vec3(0.0)
        if use_qext != 0:
            # Q given (project_pattern): its gradient goes back through q_ext, not pos / W here
            q = q_ext[i]
            if need_qext != 0:
                d_qext[i] = wp.cw_mul(gcw, D * ir + wp.vec3(b))
        elif need_proj > 0:
            # one pass over the projectors gives Q and, from the same texels, dL/dpos and dL/dW
            gq = wp.cw_mul(gcw, D * ir + wp.vec3(b))  # dL/dQ_k, the same for every projector
            gp = wp.vec3(0.0)
            for k in range(P):
                pid = proj_pattern[f, k]
                if pid >= 0:
                    Wf = W[f, k]
                    X = _transform(Wf, p)
                    z = X[2]
                    if z > 1e-6:
                        Kf = K[f, k]
                        u = Kf * X
                        px = u[0] / z
                        py = u[1] / z
                        m = meta[pid]
                        qk, g2 = _bilinear_vg(pat, m[0], m[1], m[2], px - 0.5, py - 0.5, gq)
                        q += qk
                        gX = _pixel_vjp(Kf, g2, px, py, z)
                        gp += _transform_vjp(Wf, gX)
                        if need_W != 0:
                            for row in range(3):
                                accW[k, row * 4 + 0] = accW[k, row * 4 + 0] + gX[row] * p[0]
                                accW[k, row * 4 + 1] = accW[k, row * 4 + 1] + gX[row] * p[1]
                                accW[k, row * 4 + 2] = accW[k, row * 4 + 2] + gX[row] * p[2]
                                accW[k, row * 4 + 3] = accW[k, row * 4 + 3] + gX[row]
            if need_pos != 0:
                d_pos[i] = gp
        else:
            q = _pattern_sum(p, f, P, K, W, proj_pattern, pat, meta)
        c = D + wp.cw_mul(D * ir + wp.vec3(b), q)
        v = wp.dot(gc, c) + go + gd * (a0 + a1) * 0.5 + wp.dot(gx, D)
        if need_alpha > 0:
            g_alpha = T * v - suf / (1.0 - alpha)
            g_raw = float(0.0)
            if raw >= 0.0 and raw <= 0.9999:  # torch.clamp passes gradient on the closed range
                g_raw = g_alpha
            # raw = (sp - sn + eps) / den: d raw / d sp = sn / den^2, d raw / d sn = -1 / den
            A = sn / (den * den) * sp * (1.0 - sp)  # d raw / d (s prev)
            B = -sn * (1.0 - sn) / den  # d raw / d (s next)
            if need_sdf != 0:
                d_sdf[i] = g_raw * s * (A + B)
            if need_grad != 0:
                g_ic = g_raw * s * (B - A) * dt * 0.5
                dic = float(0.0)  # d iter_cos / d cos, relu'(0) = 0 as in torch
                if -cos * 0.5 + 0.5 > 0.0:
                    dic += 0.5 * (1.0 - a)
                if -cos > 0.0:
                    dic += a
                d_grad[i] = (g_ic * dic) * d
            gs += g_raw * (A * prev + B * nxt)
        suf += w * v
        if need_col != 0:
            d_col[i] = wp.cw_mul(gcw, wp.vec3(1.0) + ir * q) + w * gx
        gir += wp.dot(gcw, wp.cw_mul(D, q))
        gq1 = wp.dot(gcw, q)
        gib += gq1
        if need_spec != 0:
            d_spec[i] = gq1
    # One atomic per ray (not per sample) for the shared parameters.
    if need_invs != 0:
        wp.atomic_add(d_invs, 0, gs)
    if need_ir != 0:
        wp.atomic_add(d_ir, 0, gir)
    if need_ib != 0:
        wp.atomic_add(d_ib, 0, gib)
    if need_W != 0:
        for k in range(P):
            if proj_pattern[f, k] >= 0:
                base = (f * P + k) * 12
                for j in range(12):
                    wp.atomic_add(d_W, base + j, accW[k, j])



# ----------------------------------------------------------------------------------------
# CPU chunking (kernels/_warp.py runs the chunks on its thread pool)
# ----------------------------------------------------------------------------------------
# Samples per CPU chunk at least: ~0.5 ms of forward work, far above the ~50 us that one
# more launch costs.
MIN_CHUNK_SAMPLES = 2048


# ----------------------------------------------------------------------------------------
# Wrapper
# ----------------------------------------------------------------------------------------
def _f32(t: torch.Tensor) -> torch.Tensor:
    return t.contiguous() if t.dtype == torch.float32 else t.float().contiguous()


def _i32(t: torch.Tensor) -> torch.Tensor:
    return t.contiguous() if t.dtype == torch.int32 else t.to(torch.int32).contiguous()


def _param(x, ref: torch.Tensor) -> torch.Tensor:
    """A scalar parameter as a [1] tensor on ``ref``'s device (floats become constants)."""
    if not isinstance(x, torch.Tensor):
        return torch.full((1,), float(x), dtype=torch.float32, device=ref.device)
    return x.reshape(1)


class _RenderPattern(torch.autograd.Function):
    @staticmethod
    def forward(ctx, sdf, grad, color, pos, inv_s, i_r, i_b, proj_W, q_ext, spec,
                t0, t1, offsets, counts, dirs, ray_frame, proj_K, proj_pattern, pat_buf, pat_meta,
                cos_anneal, return_weights):
        ref = sdf
        # the ratio as a [1] device array: a captured step reads it at replay (the ramp's steps
        # replay one graph instead of running eagerly)
        cos_anneal = _param(cos_anneal, ref).float()
        R, S = offsets.shape[0], sdf.shape[0]
        out_color = torch.empty((R, 3), dtype=torch.float32, device=ref.device)
        out_opacity = torch.empty((R,), dtype=torch.float32, device=ref.device)
        out_depth = torch.empty((R,), dtype=torch.float32, device=ref.device)
        out_texture = torch.empty((R, 3), dtype=torch.float32, device=ref.device)
        # Samples outside every ray's range (none in a well-formed batch) keep weight 0.
        weights = torch.zeros((S if return_weights else 1,), dtype=torch.float32, device=ref.device)
        trans = torch.zeros((S,), dtype=torch.float32, device=ref.device)  # [S] T_i, saved for backward
        common = [
            _wp(sdf), _wp(grad, wp.vec3), _wp(color, wp.vec3), _wp(pos, wp.vec3),
            _wp(t0), _wp(t1), _wp(offsets), _wp(counts),
            _wp(dirs, wp.vec3), _wp(ray_frame), _wp(proj_K, wp.mat33),
            _wp(proj_W, mat34), _wp(proj_pattern), _wp(pat_buf),
            _wp(pat_meta, wp.vec3i), _wp(inv_s), _wp(cos_anneal), _wp(i_r),
            _wp(i_b),
        ]
        use_q = q_ext is not None
        q_arr = q_ext if use_q else _warp.dummy((1, 3), ref, "render_fwd.q")
        use_e = spec is not None
        e_arr = spec if use_e else _warp.dummy((1,), ref, "render_fwd.e")
        inputs = common + [int(return_weights), _wp(q_arr, wp.vec3), int(use_q), _wp(e_arr), int(use_e)]
        per_ray_in = {6: (offsets, None), 7: (counts, None), 8: (dirs, wp.vec3), 9: (ray_frame, None)}
        outputs = [_wp(out_color, wp.vec3), _wp(out_opacity), _wp(out_depth), _wp(out_texture, wp.vec3),
                   _wp(weights), _wp(trans)]
        per_ray_out = {0: (out_color, wp.vec3), 1: (out_opacity, None), 2: (out_depth, None),
                       3: (out_texture, wp.vec3)}

        # A ray's thread writes only its own outputs and its own samples' weights and T.
        _warp.launch_chunked(_render_fwd, inputs, outputs, ref, _warp.ray_ranges(offsets, S, ref, MIN_CHUNK_SAMPLES),
                             sliced_in=per_ray_in, sliced_out=per_ray_out)
        ctx.save_for_backward(sdf, grad, color, pos, inv_s, i_r, i_b, proj_W, q_arr, e_arr, t0, t1, offsets, counts,
                              dirs, ray_frame, proj_K, proj_pattern, pat_buf, pat_meta, trans, cos_anneal)
        ctx.use_q, ctx.use_e = use_q, use_e
        ctx.mark_non_differentiable(weights)
        return out_color, out_opacity, out_depth, out_texture, weights

    @staticmethod
    def backward(ctx, g_color, g_opacity, g_depth, g_texture, _g_weights):
        (sdf, grad, color, pos, inv_s, i_r, i_b, proj_W, q_arr, e_arr, t0, t1, offsets, counts, dirs, ray_frame,
         proj_K, proj_pattern, pat_buf, pat_meta, trans, cos_anneal) = ctx.saved_tensors
        needs = ctx.needs_input_grad[:10]
        if not any(needs):
            return (None,) * 22
        dev = sdf.device

        def buf(i, shape):
            # zero-initialised gradient buffer, or a size-1 dummy the kernel never writes
            if not needs[i]:
                return _warp.dummy((1,) + tuple(shape[1:]), dev, f"render_bwd.{i}")
            return torch.zeros(shape, dtype=torch.float32, device=dev)

        S = sdf.shape[0]
        d_sdf, d_grad, d_col, d_pos = buf(0, (S,)), buf(1, (S, 3)), buf(2, (S, 3)), buf(3, (S, 3))
        d_invs, d_ir, d_ib = buf(4, (1,)), buf(5, (1,)), buf(6, (1,))
        d_W = torch.zeros(proj_W.shape, dtype=torch.float32, device=dev) if needs[7] else _warp.dummy((1,), dev, "render_bwd.W")
        d_q = torch.zeros(q_arr.shape, dtype=torch.float32, device=dev) if needs[8] else _warp.dummy((1, 3), dev, "render_bwd.q")
        d_e = torch.zeros(e_arr.shape, dtype=torch.float32, device=dev) if needs[9] else _warp.dummy((1,), dev, "render_bwd.e")
        g_color, g_opacity, g_depth, g_texture = (_f32(g) for g in (g_color, g_opacity, g_depth, g_texture))
        inputs = [
            _wp(sdf), _wp(grad, wp.vec3), _wp(color, wp.vec3), _wp(pos, wp.vec3),
            _wp(t0), _wp(t1), _wp(offsets), _wp(counts),
            _wp(dirs, wp.vec3), _wp(ray_frame), _wp(proj_K, wp.mat33),
            _wp(proj_W, mat34), _wp(proj_pattern), _wp(pat_buf),
            _wp(pat_meta, wp.vec3i), _wp(inv_s), _wp(cos_anneal), _wp(i_r),
            _wp(i_b),
            _wp(trans), _wp(q_arr, wp.vec3), int(ctx.use_q), int(needs[8]), _wp(e_arr), int(ctx.use_e), int(needs[9]),
            _wp(g_color, wp.vec3), _wp(g_opacity), _wp(g_depth), _wp(g_texture, wp.vec3),
            int(needs[0]), int(needs[1]), int(needs[2]), int(needs[3]), int(needs[4]), int(needs[5]),
            int(needs[6]), int(needs[7]),
        ]
        R = offsets.shape[0]
        per_ray_in = {6: (offsets, None), 7: (counts, None), 8: (dirs, wp.vec3), 9: (ray_frame, None),
                      26: (g_color, wp.vec3), 27: (g_opacity, None), 28: (g_depth, None), 29: (g_texture, wp.vec3)}
        outputs = [_wp(d_sdf), _wp(d_grad, wp.vec3), _wp(d_col, wp.vec3), _wp(d_pos, wp.vec3), _wp(d_invs),
                   _wp(d_ir), _wp(d_ib), _wp(d_W.view(-1)), _wp(d_q, wp.vec3), _wp(d_e)]
        # Per-sample gradients are written by their ray's thread only; the shared parameters
        # (inv_s, i_r, i_b, proj_W) take atomics from every ray.
        _warp.launch_chunked(_render_bwd, inputs, outputs, sdf, _warp.ray_ranges(offsets, S, sdf, MIN_CHUNK_SAMPLES),
                             sliced_in=per_ray_in, shared={4: d_invs, 5: d_ir, 6: d_ib, 7: d_W.view(-1)})
        res = [d_sdf, d_grad, d_col, d_pos, d_invs, d_ir, d_ib, d_W, d_q, d_e]
        res = [g if n else None for g, n in zip(res, needs)]
        return tuple(res) + (None,) * 12


def check_projection(proj_K, proj_W, proj_pattern) -> tuple[int, int]:
    """Validate the projection table shapes; returns (F, P)."""
    if proj_W.ndim != 4 or tuple(proj_W.shape[2:]) != (3, 4):
        raise ValueError(f"proj_W must be [F, P, 3, 4], got {tuple(proj_W.shape)}")
    F, P = proj_W.shape[:2]
    if tuple(proj_K.shape) != (F, P, 3, 3) or tuple(proj_pattern.shape) != (F, P):
        raise ValueError(f"proj_K {tuple(proj_K.shape)} / proj_pattern {tuple(proj_pattern.shape)} do not match "
                         f"proj_W [F={F}, P={P}, 3, 4]")
    if P > MAX_PROJECTORS:
        raise ValueError(f"at most {MAX_PROJECTORS} projectors per frame are supported, got {P}")
    return F, P


def _check(sdf, offsets, proj_K, proj_W, proj_pattern, patterns) -> None:
    check_projection(proj_K, proj_W, proj_pattern)
    if patterns.buffer.device != sdf.device:
        raise ValueError(f"PatternStore is on {patterns.buffer.device} but the samples are on {sdf.device}; "
                         "move it once with patterns.to(device)")


def render_pattern(
    sdf: torch.Tensor,  # [S] float32
    grad: torch.Tensor,  # [S, 3] float32, SDF gradient (not normalised)
    color: torch.Tensor,  # [S, 3] float32, D (scene colour)
    pos: torch.Tensor,  # [S, 3] float32, sample positions (normalised space)
    t0: torch.Tensor,  # [S] float32
    t1: torch.Tensor,  # [S] float32
    ray_index: torch.Tensor,  # [S] int32 (unused by the kernel: samples are found through offsets/counts)
    offsets: torch.Tensor,  # [R] int32
    counts: torch.Tensor,  # [R] int32
    dirs: torch.Tensor,  # [R, 3] float32, unit ray directions
    ray_frame: torch.Tensor,  # [R] int32
    proj_K: torch.Tensor,  # [F, P, 3, 3] float32
    proj_W: torch.Tensor,  # [F, P, 3, 4] float32, normalised point -> projector camera coords
    proj_pattern: torch.Tensor,  # [F, P] int32, index into patterns, -1 = projector off
    patterns: PatternStore,
    inv_s: torch.Tensor,  # [1] float32
    cos_anneal: float | torch.Tensor,
    i_r: torch.Tensor,  # [1] float32
    i_b: torch.Tensor,  # [1] float32
    return_weights: bool = False,
    q_ext: torch.Tensor | None = None,  # [S, 3] float32: Q(P) computed elsewhere (project_pattern)
    spec: torch.Tensor | None = None,  # [S] float32: per-sample highlight e_i (added to i_b), >= 0
) -> dict:
    """NeuS rendering with pattern projection (Warp forward, hand-written Warp backward).

    One thread per ray scans its packed samples ``offsets[r] .. offsets[r] + counts[r]``
    (``ray_index`` is accepted for the common signature but not read). Computes in float32
    (other float inputs are cast). Differentiable in sdf, grad, color, pos, inv_s, i_r, i_b and proj_W; t0, t1, dirs,
    proj_K, patterns and the index tensors are constants. No host synchronisation; runs on
    torch's current stream of the inputs' device (cpu or cuda).

    Args:
        sdf, grad, color, pos, t0, t1: per-sample tensors, packed by ray.
        ray_index, offsets, counts: sample -> ray and ray -> sample range maps.
        dirs, ray_frame: per-ray direction and frame index.
        proj_K, proj_W, proj_pattern: per (frame, projector) intrinsics, world(normalised)->
            projector transform and pattern index (-1 = off).
        patterns: PatternStore on the samples' device.
        inv_s: NeuS sharpness s. cos_anneal: anneal ratio in [0, 1], a float or a [1] tensor on
            the device (what a captured step reads at replay).
        i_r, i_b: reflectance and bias of the projected light (used as given; keep them >= 0).
        return_weights: also return per-sample weights w_i (not differentiable).
        q_ext: when given, the projected light Q per sample is taken from it (differentiable)
            instead of being sampled from the patterns here; proj_W then gets no gradient.
        spec: when given, each sample's highlight e_i: the light's albedo-free part becomes
            i_b + e_i there (c_i = D_i + (i_r D_i + i_b + e_i) Q_i); differentiable.

    Returns:
        dict with color [R, 3], opacity [R], depth [R], texture [R, 3] (float32) and, if
        asked, weights [S].
    """
    _check(sdf, offsets, proj_K, proj_W, proj_pattern, patterns)
    meta = patterns.meta
    if meta.shape[0] == 0:  # Warp needs a non-empty array; no pattern index is valid anyway
        meta = torch.zeros((1, 3), dtype=torch.int32, device=sdf.device)
    out = _RenderPattern.apply(
        _f32(sdf), _f32(grad), _f32(color), _f32(pos), _f32(_param(inv_s, sdf)), _f32(_param(i_r, sdf)),
        _f32(_param(i_b, sdf)), _f32(proj_W), None if q_ext is None else _f32(q_ext),
        None if spec is None else _f32(spec).reshape(-1),
        _f32(t0), _f32(t1), _i32(offsets), _i32(counts), _f32(dirs), _i32(ray_frame), _f32(proj_K),
        _i32(proj_pattern), patterns.buffer.contiguous(), _i32(meta), cos_anneal, bool(return_weights))
    res = dict(color=out[0], opacity=out[1], depth=out[2], texture=out[3])
    if return_weights:
        res["weights"] = out[4]
    return res


# ----------------------------------------------------------------------------------------
# Pure torch twin
# ----------------------------------------------------------------------------------------
def _bilinear_torch(buf, off, w, h, valid, x, y, dtype):
    """Bilinear pattern samples [S, 3] at array coords (x, y) [S] (zeros outside), as the Warp ``_bilinear``.

    The (non-differentiable) cell corner is clamped before integer conversion; fx keeps x's gradient.
    """
    ch = torch.arange(3, device=x.device)
    xf = torch.floor(x.detach()).clamp(-2.0, 2.0**30)
    yf = torch.floor(y.detach()).clamp(-2.0, 2.0**30)
    fx, fy = (x - xf)[:, None], (y - yf)[:, None]
    x0, y0 = xf.long(), yf.long()
    vals = []
    for dy in (0, 1):
        for dx in (0, 1):
            xi, yi = x0 + dx, y0 + dy
            inb = valid & (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
            idx = off + (yi.clamp(min=0) * w + xi.clamp(min=0)) * 3
            idx = torch.where(inb, idx, torch.zeros_like(idx))
            vals.append(buf[idx[:, None] + ch].to(dtype) / 255.0 * inb[:, None].to(dtype))
    v00, v10, v01, v11 = vals
    return (v00 * (1.0 - fx) + v10 * fx) * (1.0 - fy) + (v01 * (1.0 - fx) + v11 * fx) * fy


def _pattern_sum_torch(pos, frame_s, proj_K, proj_W, proj_pattern, patterns):
    """Q(P) summed over the projectors of each sample's frame; [S, 3] in pos's dtype."""
    S, dtype = pos.shape[0], pos.dtype
    q = torch.zeros((S, 3), dtype=dtype, device=pos.device)
    buf = patterns.buffer
    meta = patterns.meta.long()
    if meta.shape[0] == 0 or buf.numel() == 0:
        return q
    for k in range(proj_W.shape[1]):
        pid = proj_pattern.long()[frame_s, k]  # [S]
        Wk = proj_W[frame_s, k].to(dtype)  # [S, 3, 4]
        Kk = proj_K[frame_s, k].to(dtype)  # [S, 3, 3]
        # Same operation order as the Warp kernel (keeps floor() decisions identical).
        X = (Wk[:, :, 0] * pos[:, 0:1] + Wk[:, :, 1] * pos[:, 1:2] + Wk[:, :, 2] * pos[:, 2:3]) + Wk[:, :, 3]
        z = X[:, 2]
        valid = (pid >= 0) & (z > _Z_MIN)
        zs = torch.where(valid, z, torch.ones_like(z))  # safe divisor: no inf/NaN gradients
        u = (Kk * X[:, None, :]).sum(-1)  # [S, 3]
        x = u[:, 0] / zs - 0.5
        y = u[:, 1] / zs - 0.5
        m = meta[pid.clamp(min=0)]  # [S, 3]
        qk = _bilinear_torch(buf, m[:, 0], m[:, 1], m[:, 2], valid, x, y, dtype)
        q = q + qk * valid[:, None].to(dtype)
    return q


def render_pattern_torch(
    sdf: torch.Tensor,  # [S]
    grad: torch.Tensor,  # [S, 3]
    color: torch.Tensor,  # [S, 3]
    pos: torch.Tensor,  # [S, 3]
    t0: torch.Tensor,  # [S]
    t1: torch.Tensor,  # [S]
    ray_index: torch.Tensor,  # [S] int32
    offsets: torch.Tensor,  # [R] int32
    counts: torch.Tensor,  # [R] int32
    dirs: torch.Tensor,  # [R, 3]
    ray_frame: torch.Tensor,  # [R] int32
    proj_K: torch.Tensor,  # [F, P, 3, 3]
    proj_W: torch.Tensor,  # [F, P, 3, 4]
    proj_pattern: torch.Tensor,  # [F, P] int32
    patterns: PatternStore,
    inv_s: torch.Tensor,  # [1]
    cos_anneal: float | torch.Tensor,
    i_r: torch.Tensor,  # [1]
    i_b: torch.Tensor,  # [1]
    return_weights: bool = False,
    q_ext: torch.Tensor | None = None,  # [S, 3]
    spec: torch.Tensor | None = None,  # [S]
) -> dict:
    """Pure-torch twin of :func:`render_pattern` (same maths; differentiable by autograd).

    Works in the dtype of ``sdf`` (float32 or float64, for gradcheck). Segment operations use
    ``ray_index``; samples must be packed by ray in order (``offsets`` = exclusive cumsum of
    ``counts``). The exclusive transmittance is ``exp`` of a per-ray exclusive cumsum of
    ``log(1 - alpha)``, accumulated in float64 so long batches keep full precision. Weights,
    when returned, are detached (as in the Warp op).
    """
    _check(sdf, offsets, proj_K, proj_W, proj_pattern, patterns)
    dtype, dev = sdf.dtype, sdf.device
    R = offsets.shape[0]
    ri = ray_index.long()
    inv_s, i_r, i_b = (_param(x, sdf).to(dtype) for x in (inv_s, i_r, i_b))
    d = dirs.to(dtype)[ri]
    cos = (d * grad).sum(-1)
    a = _param(cos_anneal, sdf).to(dtype)
    ic = -(torch.relu(-cos * 0.5 + 0.5) * (1.0 - a) + torch.relu(-cos) * a)
    dt = t1 - t0
    prev = sdf - ic * dt * 0.5
    nxt = sdf + ic * dt * 0.5
    sp = torch.sigmoid(prev * inv_s)
    sn = torch.sigmoid(nxt * inv_s)
    alpha = ((sp - sn + _EPS) / (sp + _EPS)).clamp(0.0, _ALPHA_MAX)
    log1m = torch.log1p(-alpha.double())
    excl = torch.cumsum(log1m, 0) - log1m  # global exclusive prefix
    start = offsets.long()[ri]  # first sample of each sample's ray
    T = torch.exp(excl - excl[start]).to(dtype)  # per-ray exclusive transmittance
    w = T * alpha
    if q_ext is not None:
        q = q_ext.to(dtype)
    else:
        q = _pattern_sum_torch(pos, ray_frame.long()[ri], proj_K, proj_W, proj_pattern, patterns)
    b = i_b if spec is None else i_b + spec.to(dtype).reshape(-1, 1)
    c = color + (i_r * color + b) * q
    mid = (t0 + t1) * 0.5

    def seg(x):
        return torch.zeros((R,) + x.shape[1:], dtype=dtype, device=dev).index_add(0, ri, x)

    res = dict(color=seg(w[:, None] * c), opacity=seg(w), depth=seg(w * mid), texture=seg(w[:, None] * color))
    if return_weights:
        res["weights"] = w.detach()
    return res


# ----------------------------------------------------------------------------------------
# Each ray's smallest sample (the mask's silhouette term, fastneus.train.losses.mask_silhouette)
# ----------------------------------------------------------------------------------------
@wp.kernel
def _ray_argmin(values: wp.array(dtype=float), offsets: wp.array(dtype=wp.int32), counts: wp.array(dtype=wp.int32),
                arg: wp.array(dtype=wp.int32)):
    r = wp.tid()
    a = int(offsets[r])
    best = float(0.0)
    bi = int(-1)
    for i in range(a, a + int(counts[r])):
        v = values[i]
        if bi < 0 or v < best:
            best = v
            bi = i
    arg[r] = wp.int32(bi)


def ray_argmin(values: torch.Tensor, ray_index: torch.Tensor, offsets: torch.Tensor,
               counts: torch.Tensor) -> torch.Tensor:
    """Index of each ray's smallest value over its samples (Warp, one thread per ray).

    Only the samples ``offsets[r] .. offsets[r] + counts[r]`` of each ray are read, so samples
    past every ray (a captured step's padding, whose ``ray_index`` is stale) are left out; the
    first of equal values wins. Not differentiable (an index); no host synchronisation.

    Args:
        values: [S] float32; ray_index: [S] int32 (unused here: the common signature with the
            twin); offsets, counts: [R] int32, samples packed by ray.
    Returns:
        [R] int32: the sample index of each ray's minimum, -1 for a ray without samples.
    """
    v, o, c = _f32(values.detach()), _i32(offsets), _i32(counts)
    arg = torch.empty(o.shape[0], dtype=torch.int32, device=v.device)
    _warp.launch_chunked(_ray_argmin, [_wp(v), _wp(o), _wp(c)], [_wp(arg)], v,
                         _warp.ray_ranges(o, int(v.shape[0]), v, MIN_CHUNK_SAMPLES),
                         sliced_in={1: (o, None), 2: (c, None)}, sliced_out={0: (arg, None)})
    return arg


def ray_argmin_torch(values: torch.Tensor, ray_index: torch.Tensor, offsets: torch.Tensor,
                     counts: torch.Tensor) -> torch.Tensor:
    """Pure-torch twin of :func:`ray_argmin` (same arguments and result): the minimum by a
    scatter over ``ray_index`` with the samples outside their ray's range left out, then the
    first sample that equals it."""
    v = values.detach().float()
    S, R, dev = v.shape[0], offsets.shape[0], v.device
    if S == 0:
        return torch.full((R,), -1, dtype=torch.int32, device=dev)
    ri = ray_index.long()
    i = torch.arange(S, device=dev)
    lo = offsets.long()[ri]
    live = (i >= lo) & (i < lo + counts.long()[ri])
    big = torch.finfo(torch.float32).max
    m = torch.full((R,), big, device=dev).scatter_reduce(0, ri, torch.where(live, v, big), "amin", include_self=True)
    first = torch.where(live & (v == m[ri]), i, S)
    arg = torch.full((R,), S, device=dev, dtype=torch.long).scatter_reduce(0, ri, first, "amin", include_self=True)
    return torch.where((counts > 0) & (arg < S), arg, -1).to(torch.int32)
