"""Projected light at sample points, Q(P): pattern blur, flat-port refraction, attenuation.

``project_pattern`` is the Warp op (forward and backward one thread per sample; the shared
blur, attenuation and pose gradients are added into striped buffers, see ``_stripes``);
``project_pattern_torch`` is its pure-torch twin (same signature and maths). The
render op takes the result as ``q_ext`` instead of sampling the patterns itself. See
docs/INTERNALS.md, section "project_pattern".

For sample P of a ray of frame f, projector k showing pattern pid (``proj_pattern[f, k]``,
-1 = off), X = W[f, k] [P, 1] (projector coordinates, world units)::

    V = X                    (in air), or the air-side direction of the refracted ray
        port_dir(X)          from the projector centre to X through a flat port (below)
    (p_x, p_y) = (K V / V.z)[:2]   (only where V.z > 1e-6)
    Q(P) = sum_k a_k * sum_{a, b = 0..n-1} blur[k, a n + b]
                 * bilinear(pattern_pid, p_x - 0.5 + b - h, p_y - 0.5 + a - h),   h = (n - 1) / 2
    a_k  = exp(-sigma * |X|)   per channel (the projector light's attenuation in the medium)

i.e. the pattern correlated with the n x n kernel (zero outside the pattern, so light blurs
past its edge), sampled bilinearly; ``blur`` rows are used as given (the caller normalises
them). n = 1 with weight 1, no port and sigma = 0 is the plain pattern sample of the render op.

Flat port (``port[k]`` = unit normal n (3), d0 = distance from the centre to the glass,
t = glass thickness, k_g = n_air / n_glass, k_w = n_air / n_water, flag): with h = n.X,
rho = |X - h n|, e = (X - h n) / rho and h_w = max(h - d0 - t, 0), the air-side sine s solves

    f(s) = d0 tan(a_a) + t tan(a_g) + h_w tan(a_w) - rho = 0,   sin a_a = s, sin a_g = k_g s, sin a_w = k_w s

(10 bisection steps on [0, 1) bracket the root of this increasing convex f, then 6 Newton
steps from the bracket's right end fall monotonically onto it), and V = sqrt(1 - s^2) n + s e.
The backward uses the implicit derivative ds = (drho - tan(a_w) dh_w) / f'(s).
"""
from __future__ import annotations

from functools import partial

import torch
import warp as wp

from . import _warp
from .render import (_Z_MIN, PatternStore, _bilinear, _bilinear_torch, _bilinear_vg, _f32, _i32, _pixel_vjp,
                     _transform, _transform_vjp, check_projection, mat34)

_warp.init()
_wp = partial(_warp.to_wp, ctype=True)
wp.set_module_options({"enable_backward": False})

MAX_TAPS = 49  # n <= 7
PORT_FLOATS = 8  # normal (3), d0, thickness, n_air / n_glass, n_air / n_water, flag (1 = port)
BISECT_STEPS = wp.constant(10)
NEWTON_STEPS = wp.constant(6)
_S_MAX = wp.constant(0.999999)


@wp.func
def _scatter_dW(d_W: wp.array2d(dtype=float), row: int, base: int, gX: wp.vec3, ph: wp.vec4):
    """Add gX [p, 1]^T (one sample's [3, 4] W gradient of one projector) at ``d_W[row, base:base + 12]``."""
    for j in range(4):
        wp.atomic_add(d_W, row, base + j, gX[0] * ph[j])
        wp.atomic_add(d_W, row, base + 4 + j, gX[1] * ph[j])
        wp.atomic_add(d_W, row, base + 8 + j, gX[2] * ph[j])


@wp.func
def _port_f(s: float, d0: float, tg: float, kg: float, kw: float, hw: float, rho: float):
    return (d0 * s / wp.sqrt(1.0 - s * s) + tg * kg * s / wp.sqrt(1.0 - kg * kg * s * s)
            + hw * kw * s / wp.sqrt(1.0 - kw * kw * s * s) - rho)


@wp.func
def _port_solve(X: wp.vec3, n: wp.vec3, d0: float, tg: float, kg: float, kw: float):
    """(s, e, rho, h_w, clamp flag) of the refracted path from the origin to X (see module doc)."""
    h = wp.dot(n, X)
    r = X - h * n
    rho = wp.length(r)
    e = wp.vec3(0.0)
    if rho > 1e-12:
        e = r / rho
    hw = h - d0 - tg
    inside = float(1.0)
    if hw < 0.0:
        hw = 0.0
        inside = 0.0
    lo = float(0.0)
    hi = float(_S_MAX)
    for it in range(BISECT_STEPS):  # f(0) = -rho <= 0 <= f(S_MAX): bracket the root first
        mid = 0.5 * (lo + hi)
        if _port_f(mid, d0, tg, kg, kw, hw, rho) > 0.0:
            hi = mid
        else:
            lo = mid
    s = hi  # right of the root of an increasing convex f: Newton falls monotonically onto it
    for it in range(NEWTON_STEPS):
        ca = wp.sqrt(1.0 - s * s)
        cg = wp.sqrt(1.0 - kg * kg * s * s)
        cw = wp.sqrt(1.0 - kw * kw * s * s)
        fp = d0 / (ca * ca * ca) + tg * kg / (cg * cg * cg) + hw * kw / (cw * cw * cw)
        s = wp.clamp(s - _port_f(s, d0, tg, kg, kw, hw, rho) / fp, lo, hi)
    return s, e, rho, hw, inside


@wp.func
def _port_dir(X: wp.vec3, pt: wp.array2d(dtype=float), k: int):
    n = wp.vec3(pt[k, 0], pt[k, 1], pt[k, 2])
    s, e, rho, hw, inside = _port_solve(X, n, pt[k, 3], pt[k, 4], pt[k, 5], pt[k, 6])
    return wp.sqrt(1.0 - s * s) * n + s * e


@wp.func
def _port_vjp(X: wp.vec3, pt: wp.array2d(dtype=float), k: int, gV: wp.vec3):
    """d <gV, V(X)> / dX by the implicit function theorem."""
    n = wp.vec3(pt[k, 0], pt[k, 1], pt[k, 2])
    d0 = pt[k, 3]
    tg = pt[k, 4]
    kg = pt[k, 5]
    kw = pt[k, 6]
    s, e, rho, hw, inside = _port_solve(X, n, d0, tg, kg, kw)
    ca = wp.sqrt(1.0 - s * s)
    cg = wp.sqrt(1.0 - kg * kg * s * s)
    cw = wp.sqrt(1.0 - kw * kw * s * s)
    fp = d0 / (ca * ca * ca) + tg * kg / (cg * cg * cg) + hw * kw / (cw * cw * cw)
    if rho <= 1e-12:
        return (gV - wp.dot(gV, n) * n) / fp
    tw = kw * s / cw * inside
    gs = wp.dot(gV, e - (s / ca) * n)
    perp = gV - wp.dot(gV, e) * e - wp.dot(gV, n) * n
    return gs * (e - tw * n) / fp + (s / rho) * perp


@wp.kernel
def _project_fwd(pos: wp.array(dtype=wp.vec3), ray_index: wp.array(dtype=wp.int32), ray_frame: wp.array(dtype=wp.int32),
                 K: wp.array2d(dtype=wp.mat33), W: wp.array2d(dtype=mat34), proj_pattern: wp.array2d(dtype=wp.int32),
                 pat: wp.array(dtype=wp.uint8), meta: wp.array(dtype=wp.vec3i), blur: wp.array2d(dtype=float),
                 n: int, port: wp.array2d(dtype=float), sigma: wp.array(dtype=wp.vec3), use_att: int,
                 out_q: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    f = ray_frame[ray_index[i]]
    p = pos[i]
    h = float(n - 1) * 0.5
    q = wp.vec3(0.0)
    for k in range(proj_pattern.shape[1]):
        pid = proj_pattern[f, k]
        if pid >= 0:
            X = _transform(W[f, k], p)
            V = X
            if port[k, 7] != 0.0:
                V = _port_dir(X, port, k)
            if V[2] > 1e-6:
                u = K[f, k] * V
                m = meta[pid]
                x = u[0] / V[2] - 0.5 - h
                y = u[1] / V[2] - 0.5 - h
                qk = wp.vec3(0.0)
                for a in range(n):
                    for b in range(n):
                        qk += blur[k, a * n + b] * _bilinear(pat, m[0], m[1], m[2], x + float(b), y + float(a))
                if use_att != 0:
                    L = wp.length(X)
                    sg = sigma[0]
                    qk = wp.cw_mul(qk, wp.vec3(wp.exp(-sg[0] * L), wp.exp(-sg[1] * L), wp.exp(-sg[2] * L)))
                q += qk
    out_q[i] = q


@wp.kernel
def _project_bwd(pos: wp.array(dtype=wp.vec3), ray_index: wp.array(dtype=wp.int32), ray_frame: wp.array(dtype=wp.int32),
                 K: wp.array2d(dtype=wp.mat33), W: wp.array2d(dtype=mat34), proj_pattern: wp.array2d(dtype=wp.int32),
                 pat: wp.array(dtype=wp.uint8), meta: wp.array(dtype=wp.vec3i), blur: wp.array2d(dtype=float), n: int,
                 port: wp.array2d(dtype=float), sigma: wp.array(dtype=wp.vec3), use_att: int,
                 g_q: wp.array(dtype=wp.vec3), need_pos: int, need_W: int, need_blur: int, need_sigma: int,
                 stripes_W: int, stripes_B: int, d_pos: wp.array(dtype=wp.vec3), d_W: wp.array2d(dtype=float),
                 d_blur: wp.array2d(dtype=float), d_sigma: wp.array2d(dtype=float)):
    # One thread per sample, like the forward. The shared gradients go to row i % stripes of
    # their striped buffers (see _stripes); zero contributions (dark or off-pattern taps) skip
    # their atomic.
    i = wp.tid()
    f = ray_frame[ray_index[i]]
    sW = i % stripes_W
    sB = i % stripes_B
    P = proj_pattern.shape[1]
    h = float(n - 1) * 0.5
    T = n * n
    sg = sigma[0]
    p = pos[i]
    ph = wp.vec4(p[0], p[1], p[2], 1.0)
    gq = g_q[i]
    gp = wp.vec3(0.0)
    accS = wp.vec3(0.0)
    for k in range(P):
        pid = proj_pattern[f, k]
        if pid >= 0:
            Wf = W[f, k]
            X = _transform(Wf, p)
            V = X
            has_port = port[k, 7] != 0.0
            if has_port:
                V = _port_dir(X, port, k)
            z = V[2]
            if z > 1e-6:
                Kf = K[f, k]
                m = meta[pid]
                L = float(0.0)
                att = wp.vec3(1.0)
                if use_att != 0:
                    L = wp.length(X)
                    att = wp.vec3(wp.exp(-sg[0] * L), wp.exp(-sg[1] * L), wp.exp(-sg[2] * L))
                gqk = wp.cw_mul(gq, att)  # gradient reaching the unattenuated light of projector k
                u = Kf * V
                px = u[0] / z
                py = u[1] / z
                g2 = wp.vec2(0.0)
                qk = wp.vec3(0.0)
                for a in range(n):
                    for b in range(n):
                        t = a * n + b
                        v, gt = _bilinear_vg(pat, m[0], m[1], m[2], px - 0.5 - h + float(b),
                                             py - 0.5 - h + float(a), gqk)
                        gb = wp.dot(gqk, v)
                        if need_blur != 0 and gb != 0.0:
                            wp.atomic_add(d_blur, sB, k * T + t, gb)
                        qk += blur[k, t] * v
                        g2 += blur[k, t] * gt
                gX = _pixel_vjp(Kf, g2, px, py, z)
                if has_port:
                    gX = _port_vjp(X, port, k, gX)
                if use_att != 0:
                    # q = att * qk: d/dsigma_c = -L q_c; d/dX through L = |X|
                    gl = wp.cw_mul(wp.cw_mul(gq, att), qk)
                    accS -= L * gl
                    if L > 0.0:
                        gX = gX - (wp.dot(gl, sg) / L) * X
                gp += _transform_vjp(Wf, gX)
                if need_W != 0 and (gX[0] != 0.0 or gX[1] != 0.0 or gX[2] != 0.0):
                    _scatter_dW(d_W, sW, (f * P + k) * 12, gX, ph)
    if need_pos != 0:
        d_pos[i] = gp
    if need_sigma != 0 and (accS[0] != 0.0 or accS[1] != 0.0 or accS[2] != 0.0):
        for c in range(3):
            wp.atomic_add(d_sigma, sB, c, accS[c])


def _check(pos, proj_K, proj_W, proj_pattern, patterns, blur, port) -> int:
    F, P = check_projection(proj_K, proj_W, proj_pattern)
    if blur.ndim != 2 or blur.shape[0] != P:
        raise ValueError(f"blur must be [P={P}, n*n], got {tuple(blur.shape)}")
    n = int(round(blur.shape[1] ** 0.5))
    if n * n != blur.shape[1] or n % 2 == 0 or n * n > MAX_TAPS:
        raise ValueError(f"blur rows must hold n*n taps with n odd and n*n <= {MAX_TAPS}, got {blur.shape[1]}")
    if port is not None and tuple(port.shape) != (P, PORT_FLOATS):
        raise ValueError(f"port must be [P={P}, {PORT_FLOATS}], got {tuple(port.shape)}")
    if patterns.buffer.device != pos.device:
        raise ValueError(f"PatternStore is on {patterns.buffer.device} but the samples are on {pos.device}")
    return n


# Shared gradients (d_W [F, P, 12], d_blur [P, n*n], d_sigma [3]) of the per-sample backward.
# All samples of a frame add into the same 12 + n*n addresses per projector: ~S / F same-address
# atomics each (~2e4 at S = 3e5, F = 12), which serialise. Per-sample partials reduced by torch
# would avoid atomics but cost S x P x (12 + n*n) floats (~0.6 GB at S = 3e5, P = 8, 7x7 taps).
# So: striped buffers [stripes, ...], sample i adding into row i % stripes (the consecutive
# samples of one ray land on different rows), summed over the rows by torch afterwards: the
# contention drops by `stripes` for stripes x (F P 12 + P n*n + 3) floats. Warp's CPU backend
# runs one thread, nothing contends there: one row, and the sum is a view. (Tests set other
# counts on CPU to exercise the wrap-around.)
STRIPES = {"cuda": 128, "cpu": 1}  # by torch device type
STRIPE_FLOATS_W = 1 << 20  # cap of the striped d_W (4 MiB): many frames x projectors get fewer rows


def _stripes(device: torch.device, S: int, w_floats: int) -> tuple[int, int]:
    """(rows of the striped d_W, rows of the striped d_blur / d_sigma) for S samples on ``device``."""
    rows = max(1, min(STRIPES.get(device.type, 1), S))
    return max(1, min(rows, STRIPE_FLOATS_W // max(w_floats, 1))), rows


def _striped(need: bool, rows: int, size: int, device) -> torch.Tensor:
    """Zeroed [rows, size] float32 accumulator, or a [1, 1] dummy the kernel never touches."""
    if not need:
        return _warp.dummy((1, 1), device, "project.striped")
    return torch.zeros((rows, size), dtype=torch.float32, device=device)


def _unstripe(buf: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """Sum of the stripes of ``buf`` [rows, numel] shaped as ``like``."""
    return (buf[0] if buf.shape[0] == 1 else buf.sum(0)).view(like.shape)


class _ProjectPattern(torch.autograd.Function):
    @staticmethod
    def forward(ctx, pos, proj_W, blur, sigma, ray_index, offsets, counts, ray_frame, proj_K, proj_pattern, pat_buf,
                pat_meta, n, port, use_att):
        S = pos.shape[0]
        out = torch.zeros((S, 3), dtype=torch.float32, device=pos.device)
        _warp.launch(_project_fwd, S, [_wp(pos, wp.vec3), _wp(ray_index), _wp(ray_frame), _wp(proj_K, wp.mat33),
                                       _wp(proj_W, mat34), _wp(proj_pattern), _wp(pat_buf), _wp(pat_meta, wp.vec3i),
                                       _wp(blur), int(n), _wp(port), _wp(sigma.view(1, 3), wp.vec3), int(use_att)],
                     pos, outputs=[_wp(out, wp.vec3)])
        ctx.save_for_backward(pos, proj_W, blur, sigma, ray_index, ray_frame, proj_K, proj_pattern, pat_buf,
                              pat_meta, port)
        ctx.n, ctx.use_att = int(n), int(use_att)
        return out

    @staticmethod
    def backward(ctx, g_q):
        pos, proj_W, blur, sigma, ray_index, ray_frame, proj_K, proj_pattern, pat_buf, pat_meta, port = \
            ctx.saved_tensors
        need = ctx.needs_input_grad[:4]
        if not any(need):
            return (None,) * 15
        dev = pos.device
        S, (F, P) = pos.shape[0], proj_W.shape[:2]
        need_sigma = bool(need[3] and ctx.use_att)
        sW, sB = _stripes(dev, S, F * P * 12)
        d_pos = torch.empty_like(pos) if need[0] else _warp.dummy((1, 3), dev, "project.d_pos")  # every row is written
        d_W = _striped(need[1], sW, proj_W.numel(), dev)
        d_blur = _striped(need[2], sB, blur.numel(), dev)
        d_sigma = _striped(need_sigma, sB, 3, dev)
        _warp.launch(_project_bwd, S,
                     [_wp(pos, wp.vec3), _wp(ray_index), _wp(ray_frame), _wp(proj_K, wp.mat33), _wp(proj_W, mat34),
                      _wp(proj_pattern), _wp(pat_buf), _wp(pat_meta, wp.vec3i), _wp(blur), ctx.n, _wp(port),
                      _wp(sigma.view(1, 3), wp.vec3), ctx.use_att, _wp(_f32(g_q), wp.vec3),
                      int(need[0]), int(need[1]), int(need[2]), int(need_sigma), sW, sB],
                     pos, outputs=[_wp(d_pos, wp.vec3), _wp(d_W), _wp(d_blur), _wp(d_sigma)])
        return (d_pos if need[0] else None, _unstripe(d_W, proj_W) if need[1] else None,
                _unstripe(d_blur, blur) if need[2] else None,
                (_unstripe(d_sigma, sigma) if need_sigma else torch.zeros_like(sigma)) if need[3] else None) \
            + (None,) * 11


def _port_or_none(port, P, device):
    if port is None:
        return torch.zeros((P, PORT_FLOATS), dtype=torch.float32, device=device)
    return _f32(port)


def project_pattern(
    pos: torch.Tensor,  # [S, 3] float32, sample positions (normalised space)
    ray_index: torch.Tensor,  # [S] int32, sample -> ray
    offsets: torch.Tensor,  # [R] int32, first sample of each ray (samples packed by ray)
    counts: torch.Tensor,  # [R] int32
    ray_frame: torch.Tensor,  # [R] int32
    proj_K: torch.Tensor,  # [F, P, 3, 3] float32
    proj_W: torch.Tensor,  # [F, P, 3, 4] float32, normalised point -> projector coords (world units)
    proj_pattern: torch.Tensor,  # [F, P] int32, -1 = off
    patterns: PatternStore,
    blur: torch.Tensor,  # [P, n*n] float32 tap weights (n odd), row-major over (a = row, b = column)
    port: torch.Tensor | None = None,  # [P, 8] flat port per projector (flag column 0 = none)
    sigma: torch.Tensor | None = None,  # [3] per-channel attenuation of the projected light (1 / world unit)
) -> torch.Tensor:
    """Q(P): projected light at each sample, through a per-projector n x n pattern blur, an
    optional flat port (refraction) and an optional attenuation of the medium.

    Differentiable in ``pos``, ``proj_W``, ``blur`` and ``sigma`` (Warp forward and hand-written
    Warp backward); the rest are constants. Float32; no host synchronisation.

    Returns:
        [S, 3] float32 (RGB, in [0, 1] per projector when the blur rows are non-negative and sum to 1).
    """
    n = _check(pos, proj_K, proj_W, proj_pattern, patterns, blur, port)
    meta = patterns.meta
    if meta.shape[0] == 0:
        meta = torch.zeros((1, 3), dtype=torch.int32, device=pos.device)
    use_att = sigma is not None
    sig = _f32(sigma.reshape(3)) if use_att else torch.zeros(3, dtype=torch.float32, device=pos.device)
    return _ProjectPattern.apply(_f32(pos), _f32(proj_W), _f32(blur), sig, _i32(ray_index), _i32(offsets),
                                 _i32(counts), _i32(ray_frame), _f32(proj_K), _i32(proj_pattern),
                                 patterns.buffer.contiguous(), _i32(meta), n,
                                 _port_or_none(port, proj_W.shape[1], pos.device), use_att)


def port_dir_torch(X: torch.Tensor, port_row: torch.Tensor) -> torch.Tensor:
    """Air-side unit direction [N, 3] of the refracted path from the origin to points X [N, 3]
    through the flat port ``port_row`` [8] (Newton as in the kernel; differentiable by autograd)."""
    dtype = X.dtype
    pr = port_row.to(dtype)
    n, d0, tg, kg, kw = pr[0:3], pr[3], pr[4], pr[5], pr[6]
    h = X @ n
    r = X - h[:, None] * n
    rho = r.norm(dim=-1)
    safe = torch.where(rho > 1e-12, rho, torch.ones_like(rho))
    e = torch.where((rho > 1e-12)[:, None], r / safe[:, None], torch.zeros_like(r))
    hw = (h - d0 - tg).clamp(min=0.0)
    def f_of(s):
        return (d0 * s / torch.sqrt(1 - s * s) + tg * kg * s / torch.sqrt(1 - kg * kg * s * s)
                + hw * kw * s / torch.sqrt(1 - kw * kw * s * s) - rho)

    with torch.no_grad():  # the bracket only picks the start; the gradient flows through Newton
        lo = torch.zeros_like(rho)
        hi = torch.full_like(rho, float(_S_MAX))
        for _ in range(int(BISECT_STEPS)):
            mid = 0.5 * (lo + hi)
            pos = f_of(mid) > 0
            hi = torch.where(pos, mid, hi)
            lo = torch.where(pos, lo, mid)
    s = hi
    for _ in range(int(NEWTON_STEPS)):
        ca = torch.sqrt(1 - s * s)
        cg = torch.sqrt(1 - kg * kg * s * s)
        cw = torch.sqrt(1 - kw * kw * s * s)
        fp = d0 / ca ** 3 + tg * kg / cg ** 3 + hw * kw / cw ** 3
        s = torch.minimum(torch.maximum(s - f_of(s) / fp, lo), hi)
    return torch.sqrt(1 - s * s)[:, None] * n + s[:, None] * e


def project_pattern_torch(
    pos: torch.Tensor,  # [S, 3]
    ray_index: torch.Tensor,  # [S] int32
    offsets: torch.Tensor,  # [R] int32
    counts: torch.Tensor,  # [R] int32
    ray_frame: torch.Tensor,  # [R] int32
    proj_K: torch.Tensor,  # [F, P, 3, 3]
    proj_W: torch.Tensor,  # [F, P, 3, 4]
    proj_pattern: torch.Tensor,  # [F, P] int32
    patterns: PatternStore,
    blur: torch.Tensor,  # [P, n*n]
    port: torch.Tensor | None = None,  # [P, 8]
    sigma: torch.Tensor | None = None,  # [3]
) -> torch.Tensor:
    """Pure-torch twin of :func:`project_pattern` (works in ``pos``'s dtype, for gradcheck)."""
    n = _check(pos, proj_K, proj_W, proj_pattern, patterns, blur, port)
    dtype = pos.dtype
    S = pos.shape[0]
    q = torch.zeros((S, 3), dtype=dtype, device=pos.device)
    meta = patterns.meta.long()
    if meta.shape[0] == 0 or patterns.buffer.numel() == 0:
        return q
    frame_s = ray_frame.long()[ray_index.long()]
    h = (n - 1) * 0.5
    for k in range(proj_W.shape[1]):
        pid = proj_pattern.long()[frame_s, k]
        Wk = proj_W[frame_s, k].to(dtype)
        Kk = proj_K[frame_s, k].to(dtype)
        X = (Wk[:, :, 0] * pos[:, 0:1] + Wk[:, :, 1] * pos[:, 1:2] + Wk[:, :, 2] * pos[:, 2:3]) + Wk[:, :, 3]
        V = X
        if port is not None and float(port[k, 7]) != 0.0:
            V = port_dir_torch(X, port[k])
        z = V[:, 2]
        valid = (pid >= 0) & (z > _Z_MIN)
        zs = torch.where(valid, z, torch.ones_like(z))
        u = (Kk * V[:, None, :]).sum(-1)
        x = u[:, 0] / zs - 0.5 - h
        y = u[:, 1] / zs - 0.5 - h
        m = meta[pid.clamp(min=0)]
        qk = torch.zeros_like(q)
        for a in range(n):
            for b in range(n):
                qk = qk + blur[k, a * n + b].to(dtype) * _bilinear_torch(patterns.buffer, m[:, 0], m[:, 1], m[:, 2],
                                                                          valid, x + b, y + a, dtype)
        if sigma is not None:
            qk = qk * torch.exp(-sigma.to(dtype).reshape(1, 3) * X.norm(dim=-1, keepdim=True))
        q = q + qk * valid[:, None].to(dtype)
    return q


def identity_blur(n_proj: int, n: int = 1, device="cpu") -> torch.Tensor:
    """[P, n*n] kernels that leave the pattern unchanged (1 at the centre tap)."""
    b = torch.zeros(n_proj, n * n, device=device)
    b[:, (n * n) // 2] = 1.0
    return b


def port_row(normal, distance: float, thickness: float = 0.0, n_air: float = 1.0, n_glass: float = 1.5,
             n_water: float = 1.333) -> list[float]:
    """One row of the ``port`` array from physical parameters (device frame, world units)."""
    import math

    nn = [float(v) for v in normal]
    ln = math.sqrt(sum(v * v for v in nn))
    return [v / ln for v in nn] + [float(distance), float(thickness), n_air / n_glass, n_air / n_water, 1.0]


# ----------------------------------------------------------------------------------------
# Laser-plane projectors: light evaluated from the planes, no pattern image
# ----------------------------------------------------------------------------------------
PLANE_FLOATS = 12  # per plane: normal (3), offset, fan axis in the plane (3, unit), cos(fan/2), colour (3), sigma


@wp.func
def _laser_plane(pl: wp.array3d(dtype=float), k: int, l: int, X: wp.vec3):
    """(light value without colour, d value / d X) of plane l of laser k at projector point X."""
    n = wp.vec3(pl[k, l, 0], pl[k, l, 1], pl[k, l, 2])
    sig = pl[k, l, 11]
    if sig <= 0.0:
        return float(0.0), wp.vec3(0.0)
    nx = wp.dot(n, X)
    v = X - nx * n
    u = wp.vec3(pl[k, l, 4], pl[k, l, 5], pl[k, l, 6])
    vn = wp.length(v)
    if vn <= 0.0 or wp.dot(v, u) < pl[k, l, 7] * vn:
        return float(0.0), wp.vec3(0.0)
    dist = nx - pl[k, l, 3]
    g = wp.exp(-0.5 * dist * dist / (sig * sig))
    return g, (-g * dist / (sig * sig)) * n


@wp.kernel
def _laser_fwd(pos: wp.array(dtype=wp.vec3), ray_index: wp.array(dtype=wp.int32), ray_frame: wp.array(dtype=wp.int32),
               W: wp.array2d(dtype=mat34), laser_on: wp.array2d(dtype=wp.int32), planes: wp.array3d(dtype=float),
               out_q: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    f = ray_frame[ray_index[i]]
    p = pos[i]
    q = wp.vec3(0.0)
    for k in range(laser_on.shape[1]):
        if laser_on[f, k] != 0:
            X = _transform(W[f, k], p)
            for l in range(planes.shape[1]):
                g, gX = _laser_plane(planes, k, l, X)
                q += g * wp.vec3(planes[k, l, 8], planes[k, l, 9], planes[k, l, 10])
    out_q[i] = q


@wp.kernel
def _laser_bwd(pos: wp.array(dtype=wp.vec3), ray_index: wp.array(dtype=wp.int32), ray_frame: wp.array(dtype=wp.int32),
               W: wp.array2d(dtype=mat34), laser_on: wp.array2d(dtype=wp.int32), planes: wp.array3d(dtype=float),
               g_q: wp.array(dtype=wp.vec3), need_pos: int, need_W: int, stripes_W: int,
               d_pos: wp.array(dtype=wp.vec3), d_W: wp.array2d(dtype=float)):
    # One thread per sample; d_W striped as in _project_bwd.
    i = wp.tid()
    f = ray_frame[ray_index[i]]
    sW = i % stripes_W
    P = laser_on.shape[1]
    p = pos[i]
    ph = wp.vec4(p[0], p[1], p[2], 1.0)
    gq = g_q[i]
    gp = wp.vec3(0.0)
    for k in range(P):
        if laser_on[f, k] != 0:
            Wf = W[f, k]
            X = _transform(Wf, p)
            gX = wp.vec3(0.0)
            for l in range(planes.shape[1]):
                g, dg = _laser_plane(planes, k, l, X)
                gX += wp.dot(gq, wp.vec3(planes[k, l, 8], planes[k, l, 9], planes[k, l, 10])) * dg
            gp += _transform_vjp(Wf, gX)
            if need_W != 0 and (gX[0] != 0.0 or gX[1] != 0.0 or gX[2] != 0.0):
                _scatter_dW(d_W, sW, (f * P + k) * 12, gX, ph)
    if need_pos != 0:
        d_pos[i] = gp


def _check_laser(pos, proj_W, laser_on, planes) -> None:
    if proj_W.ndim != 4 or tuple(proj_W.shape[2:]) != (3, 4):
        raise ValueError(f"proj_W must be [F, P, 3, 4], got {tuple(proj_W.shape)}")
    F, P = proj_W.shape[:2]
    if tuple(laser_on.shape) != (F, P):
        raise ValueError(f"laser_on must be [F={F}, P={P}], got {tuple(laser_on.shape)}")
    if planes.ndim != 3 or planes.shape[0] != P or planes.shape[2] != PLANE_FLOATS:
        raise ValueError(f"planes must be [P={P}, L, {PLANE_FLOATS}], got {tuple(planes.shape)}")


class _LaserLight(torch.autograd.Function):
    @staticmethod
    def forward(ctx, pos, proj_W, ray_index, offsets, counts, ray_frame, laser_on, planes):
        out = torch.zeros((pos.shape[0], 3), dtype=torch.float32, device=pos.device)
        _warp.launch(_laser_fwd, pos.shape[0], [_wp(pos, wp.vec3), _wp(ray_index), _wp(ray_frame),
                                                _wp(proj_W, mat34), _wp(laser_on), _wp(planes)],
                     pos, outputs=[_wp(out, wp.vec3)])
        ctx.save_for_backward(pos, proj_W, ray_index, ray_frame, laser_on, planes)
        return out

    @staticmethod
    def backward(ctx, g_q):
        pos, proj_W, ray_index, ray_frame, laser_on, planes = ctx.saved_tensors
        need = ctx.needs_input_grad[:2]
        if not any(need):
            return (None,) * 8
        dev = pos.device
        S, (F, P) = pos.shape[0], proj_W.shape[:2]
        sW, _ = _stripes(dev, S, F * P * 12)
        d_pos = torch.empty_like(pos) if need[0] else _warp.dummy((1, 3), dev, "project.d_pos")  # every row is written
        d_W = _striped(need[1], sW, proj_W.numel(), dev)
        _warp.launch(_laser_bwd, S,
                     [_wp(pos, wp.vec3), _wp(ray_index), _wp(ray_frame), _wp(proj_W, mat34), _wp(laser_on),
                      _wp(planes), _wp(_f32(g_q), wp.vec3), int(need[0]), int(need[1]), sW],
                     pos, outputs=[_wp(d_pos, wp.vec3), _wp(d_W)])
        return (d_pos if need[0] else None, _unstripe(d_W, proj_W) if need[1] else None) + (None,) * 6


def laser_light(
    pos: torch.Tensor,  # [S, 3] float32, normalised space
    ray_index: torch.Tensor,  # [S] int32
    offsets: torch.Tensor,  # [R] int32
    counts: torch.Tensor,  # [R] int32
    ray_frame: torch.Tensor,  # [R] int32
    proj_W: torch.Tensor,  # [F, P, 3, 4] float32, normalised point -> projector coords (world units)
    laser_on: torch.Tensor,  # [F, P] int32, 1 where projector k is a laser lit in frame f
    planes: torch.Tensor,  # [P, L, 12] float32 (see PLANE_FLOATS; sigma 0 = padding)
) -> torch.Tensor:
    """Light of laser-plane projectors at each sample, evaluated from the planes.

    For laser k lit in frame f, X = W[f, k] [P, 1] and each plane (unit n, offset d, unit
    in-plane fan axis u, c = cos(fan / 2), colour rgb, sigma)::

        v = X - (n.X) n;   inside = |v| > 0 and u.v >= c |v|
        Q += rgb * inside * exp(-(n.X - d)^2 / (2 sigma^2))

    Differentiable in ``pos`` and ``proj_W`` (the fan edge is a hard cut, like a pattern's
    border). Warp forward and backward per sample.

    Returns:
        [S, 3] float32.
    """
    _check_laser(pos, proj_W, laser_on, planes)
    return _LaserLight.apply(_f32(pos), _f32(proj_W), _i32(ray_index), _i32(offsets), _i32(counts), _i32(ray_frame),
                             _i32(laser_on), _f32(planes))


def laser_light_torch(
    pos: torch.Tensor,  # [S, 3]
    ray_index: torch.Tensor,  # [S] int32
    offsets: torch.Tensor,  # [R] int32
    counts: torch.Tensor,  # [R] int32
    ray_frame: torch.Tensor,  # [R] int32
    proj_W: torch.Tensor,  # [F, P, 3, 4]
    laser_on: torch.Tensor,  # [F, P] int32
    planes: torch.Tensor,  # [P, L, 12]
) -> torch.Tensor:
    """Pure-torch twin of :func:`laser_light` (in ``pos``'s dtype, for gradcheck)."""
    _check_laser(pos, proj_W, laser_on, planes)
    dtype = pos.dtype
    frame_s = ray_frame.long()[ray_index.long()]
    q = torch.zeros((pos.shape[0], 3), dtype=dtype, device=pos.device)
    pl = planes.to(dtype)
    for k in range(proj_W.shape[1]):
        on = laser_on.long()[frame_s, k] != 0  # [S]
        Wk = proj_W[frame_s, k].to(dtype)
        X = (Wk[:, :, 0] * pos[:, 0:1] + Wk[:, :, 1] * pos[:, 1:2] + Wk[:, :, 2] * pos[:, 2:3]) + Wk[:, :, 3]
        for l in range(pl.shape[1]):
            n, d, u, c, rgb, sig = pl[k, l, 0:3], pl[k, l, 3], pl[k, l, 4:7], pl[k, l, 7], pl[k, l, 8:11], pl[k, l, 11]
            if float(sig) <= 0:
                continue
            nx = X @ n
            v = X - nx[:, None] * n
            vn = v.norm(dim=-1)
            inside = on & (vn > 0) & ((v @ u) >= c * vn)
            dist = nx - d
            g = torch.exp(-0.5 * dist * dist / (sig * sig))
            q = q + (g * inside.to(dtype))[:, None] * rgb
    return q


def pack_planes(planes_per_projector, device="cpu") -> torch.Tensor:
    """[P, L, 12] float32 from, per projector, a list of planes (objects with normal, offset,
    colour, width (FWHM), fan_deg, axis) or None (a pattern projector: an all-padding row)."""
    import math

    L = max([len(p) for p in planes_per_projector if p] or [1])
    out = torch.zeros(len(planes_per_projector), L, PLANE_FLOATS, dtype=torch.float64)
    for k, pls in enumerate(planes_per_projector):
        for l, p in enumerate(pls or []):
            n = torch.as_tensor(p.normal, dtype=torch.float64)
            n = n / n.norm()
            a = torch.as_tensor(p.axis, dtype=torch.float64)
            u = a - (a @ n) * n
            u = u / u.norm()
            out[k, l, 0:3], out[k, l, 3], out[k, l, 4:7] = n, float(p.offset), u
            out[k, l, 7] = math.cos(math.radians(p.fan_deg) / 2)
            out[k, l, 8:11] = torch.as_tensor(p.colour, dtype=torch.float64)
            out[k, l, 11] = float(p.width) / (2 * math.sqrt(2 * math.log(2)))  # FWHM -> sigma
    return out.to(torch.float32).to(device)
