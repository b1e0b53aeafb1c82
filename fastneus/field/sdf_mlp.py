"""The SDF network's output and its input gradient in one autograd node (issue 22).

The analytic SDF gradient needs d f / d input of the one-hidden-layer Softplus MLP, and the
eikonal and normal losses need that gradient differentiable: with plain autograd this is a
forward, a ``torch.autograd.grad(create_graph=True)`` and, at ``backward``, the double backward
of every op (Softplus's second derivative alone is several elementwise kernels and autograd
nodes). Here the forward returns ``out`` and ``g`` together and the backward is written out by
hand, with the same maths:

    z = a W1^T + b1,  s = sigmoid(beta z) = softplus'(z),  h = softplus(z),  out = h W2^T + b2
    g = d out[:, 0] / d a = (s * w) W1,  w = W2[0]

    given L_out = dL/d out and L_g = dL/d g:
    P  = L_g W1^T                                  (dL / d(s * w))
    dz = s * (L_out W2 + beta * P * w * (1 - s))   (s' = beta s (1 - s))
    M  = s^T L_g                                   ([H, D])
    dL/da = dz W1,  dL/dW1 = dz^T a + w * M,  dL/db1 = sum dz
    dL/dW2 = L_out^T h,  dL/dW2[0] += sum_n P * s = rowsum(W1 * M),  dL/db2 = sum L_out

The output weights w are folded into [H, D] matrices (w W1, beta w W1) before the GEMMs, so no
[N, H] tensor is ever multiplied by a broadcast row (a non-vectorised kernel on CUDA) and the
only [N, H] passes are sigmoid, softplus and the three of dz.

Fewer kernels on the GPU (a captured step replays them: fewer passes over [N, H]) and fewer
autograd nodes and Python on the CPU, where the engine's per-node cost is serial. The backward
is first order only (nothing differentiates the eikonal loss twice). The autograd path stays
the reference: tests/test_sdf_mlp.py compares outputs and gradients and runs a float64
gradcheck.
"""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F


def colsum(x: torch.Tensor, gemm: bool | None = None) -> torch.Tensor:
    """``x.sum(0)`` of an [N, H] tensor as a [1, N] x [N, H] matrix product: the bias gradients
    of the small networks. On CUDA torch's column reduction over ~2^18 rows ran at ~1 TB/s (four
    of them: 0.24 ms of a 4.8-ms step on an H200); the product is cuBLAS's split-K GEMV.

    Args:
        x: [N, H]; gemm: the product (True) or ``sum(0)`` (False); None: the product on CUDA.
    Returns:
        [H] the column sums (same dtype and device).
    """
    if not (x.device.type == "cuda" if gemm is None else gemm):
        return x.sum(0)
    return (x.new_ones(1, x.shape[0]) @ x).view(-1)


class _Linear(torch.autograd.Function):
    """``F.linear(x, w, b)`` with the bias gradient from :func:`colsum` (else the same GEMMs)."""

    @staticmethod
    def forward(ctx, x, w, b):
        ctx.save_for_backward(x, w)
        return torch.addmm(b, x, w.t())

    @staticmethod
    def backward(ctx, g):
        x, w = ctx.saved_tensors
        gx = g @ w if ctx.needs_input_grad[0] else None
        return gx, g.t() @ x, colsum(g)


def mlp_forward(net: nn.Sequential, x: torch.Tensor) -> torch.Tensor:
    """``net(x)`` for a stack of Linear and ReLU modules, each Linear through :class:`_Linear`
    (the colour network; same parameters and maths as calling the module).

    Args:
        net: Linear / ReLU modules; x: [N, D_in].
    Returns:
        [N, D_out].
    """
    for m in net:
        if isinstance(m, nn.Linear) and m.bias is not None:
            x = _Linear.apply(x, m.weight, m.bias)
        elif isinstance(m, nn.ReLU):
            x = torch.relu(x)
        else:
            x = m(x)
    return x


class _SoftplusMLPWithGrad(torch.autograd.Function):
    @staticmethod
    def forward(ctx, beta: float, w1, b1, w2, b2, *parts):
        # the input's column blocks (x, hash features) multiply their slices of W1: no
        # concatenated [N, D] copy, and each block's gradient comes back contiguous (the hash
        # Jacobian's backward would copy a strided slice of a concatenated input's gradient);
        # the slices are copied (a few KB) so cuBLAS sees aligned, contiguous weights
        cols, c0 = [], 0
        for t in parts:
            cols.append((c0, c0 + t.shape[1]))
            c0 += t.shape[1]
        w1p = [w1[:, c:d].contiguous() for c, d in cols]
        z = torch.addmm(b1, parts[0], w1p[0].t())                         # [N, H]
        for t, w in zip(parts[1:], w1p[1:]):
            z.addmm_(t, w.t())
        h = F.softplus(z, beta)
        # softplus's derivative; above its threshold (20: the linear branch, derivative 1)
        # sigmoid(beta z) > sigmoid(20) rounds to 1 in float32, so no mask is needed for
        # autograd's values (float64 differs there by < 3e-9)
        s = torch.sigmoid(z.mul_(beta))
        out = torch.addmm(b2, h, w2.t())                     # [N, O]
        # g = (s * w) W1 = s (w[:, None] * W1): the output weights folded into a [H, D] matrix, so
        # no [N, H] broadcast product is made
        g = s @ (w2[0, :, None] * w1)                        # [N, D]
        ctx.save_for_backward(w1, w2, s, h, *parts)
        ctx.beta, ctx.w1p = beta, w1p
        return out, g

    @staticmethod
    def backward(ctx, l_out, l_g):
        w1, w2, s, h, *parts = ctx.saved_tensors
        beta, w1p, w = ctx.beta, ctx.w1p, w2[0]
        # beta * P * w with P = L_g W1^T, as one GEMM against the scaled weights
        pwb = l_g @ (w1 * (w * beta)[:, None]).t()           # [N, H]
        # s' = beta s (1 - s); on softplus's linear branch s = 1, so s' = 0 there as in autograd
        dz = (1.0 - s).mul_(pwb).addmm_(l_out, w2).mul_(s)   # (L_out W2 + beta P w (1 - s)) * s
        grad_parts = [dz @ wp if ctx.needs_input_grad[5 + i] else None for i, wp in enumerate(w1p)]
        m = s.t() @ l_g                                      # [H, D] = sum_n s_n L_g,n^T
        grad_w1 = torch.cat([dz.t() @ t for t in parts], 1).add_(m * w[:, None])  # + (s w)^T L_g
        grad_b1 = colsum(dz)
        grad_w2 = l_out.t() @ h
        grad_w2[0] += (m * w1).sum(1)                        # sum_n P * s = rowsum(W1 * s^T L_g)
        grad_b2 = colsum(l_out)
        return None, grad_w1, grad_b1, grad_w2, grad_b2, *grad_parts


def fusable(net: nn.Sequential) -> bool:
    """True for the shape this node handles: Linear, Softplus, Linear (``sdf_layers: 1``)."""
    return (len(net) == 3 and isinstance(net[0], nn.Linear) and isinstance(net[1], nn.Softplus)
            and isinstance(net[2], nn.Linear) and net[1].threshold == 20)


def mlp_and_input_grad(net: nn.Sequential, *parts: torch.Tensor):
    """Output of a Linear-Softplus-Linear ``net`` and d out[:, 0] / d input, differentiable.

    Args:
        net: a module for which :func:`fusable` holds.
        parts: the input's column blocks ([N, D1], [N, D2], ...; D1 + D2 + ... = D), as if
            concatenated (``net(torch.cat(parts, -1))``) but without the copy.
    Returns:
        out [N, O] and g [N, D] (the gradient for the concatenated input), both with
        first-order gradients to every part and the weights.
    """
    l1, act, l2 = net[0], net[1], net[2]
    return _SoftplusMLPWithGrad.apply(float(act.beta), l1.weight, l1.bias, l2.weight, l2.bias, *parts)
