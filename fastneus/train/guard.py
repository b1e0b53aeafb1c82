"""NaN/Inf guard shared by fastneus's trainer and the baseline."""
from __future__ import annotations

import torch


def finite_flag(opt, loss: torch.Tensor) -> torch.Tensor:
    """[] bool on the loss's device: the loss and every gradient of ``opt``'s parameters are
    finite (one fused norm over all gradients; no host read)."""
    count = opt.nonfinite_count() if hasattr(opt, "nonfinite_count") else None
    if count is not None:  # the fused count: one read pass per gradient instead of a norm
        return torch.isfinite(loss.detach().float().reshape(())) & (count.reshape(()) == 0)
    grads = [p.grad for g in opt.param_groups for p in g["params"] if p.grad is not None]
    total = loss.detach().float().reshape(())
    if grads:
        total = total + torch.stack(torch._foreach_norm(grads)).float().sum()
    return torch.isfinite(total)


def finite_step(opt, loss: torch.Tensor) -> bool:
    """Step ``opt`` (fastneus.train.adam.Adam or a torch optimiser) unless the loss or any gradient is non-finite; then drop the gradients.

    One fused norm over all gradients (a NaN/Inf anywhere makes its norm non-finite) and a
    single host read, instead of one check per parameter: the training step is launch-bound.

    Returns:
        True if the optimiser stepped, False if the step was skipped.
    """
    if not bool(finite_flag(opt, loss)):
        opt.zero_grad(set_to_none=True)
        return False
    opt.step()
    return True
