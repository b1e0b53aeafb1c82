"""Adam without torch.optim: the same update as ``torch.optim.Adam`` (foreach), no TorchDynamo.

Every ``torch.optim.Optimizer`` imports ``torch._dynamo`` when its first parameter group is
added (``add_param_group`` is wrapped in ``torch._disable_dynamo``). That import took 4.1 s
of a 20-s GPU run's wall clock on the H100 machine (1.3 s on the 2-core CPU), more than the
whole start-up budget of issue 10, for a compiler fastneus never uses. This class keeps the
interface the trainer relies on (``param_groups`` dicts with a mutable ``lr``, ``step``,
``zero_grad``, ``state_dict`` / ``load_state_dict``, and the state layout of torch's Adam, so
checkpoints written by either load in both) and does the arithmetic with ``torch._foreach_*``
ops, as torch's multi-tensor Adam does. tests/test_adam.py checks it step by step against
``torch.optim.Adam``.
"""
from __future__ import annotations

import math

import torch


# the group options torch.optim.Adam expects in a state it loads (all off here)
_TORCH_KEYS = {"weight_decay": 0.0, "amsgrad": False, "maximize": False, "foreach": None, "capturable": False,
               "differentiable": False, "fused": None, "decoupled_weight_decay": False}


class Adam:
    """Adam (Kingma & Ba) with bias correction; no weight decay, no amsgrad.

    Args:
        params: an iterable of tensors, or of dicts with ``params`` and per-group options
            (``lr``, ``betas``, ``eps``; any other keys are kept, e.g. ``name``, ``base_lr``).
        lr, betas, eps: defaults for groups that do not set them.
    """

    def __init__(self, params, lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8):
        params = list(params)
        if not params:
            raise ValueError("Adam got an empty parameter list")
        groups = params if isinstance(params[0], dict) else [{"params": params}]
        self.defaults = {"lr": lr, "betas": tuple(betas), "eps": eps}
        self.param_groups: list[dict] = []
        self.state: dict[torch.Tensor, dict] = {}
        for g in groups:
            g = dict(g)
            g["params"] = list(g["params"])
            for k, v in self.defaults.items():
                g.setdefault(k, v)
            self.param_groups.append(g)
        self.fused = None  # (update op, non-finite count op): see use_fused

    def use_fused(self, backend: str = "warp") -> None:
        """Do the guarded update (:meth:`gated_step`, :meth:`device_update`) with fused kernels
        (``fastneus.kernels.adam``'s multi-tensor ops; ``backend`` "warp" or their "torch" twins:
        one launch for the hash table, one for all the small tensors) and the NaN/Inf guard with a
        count of non-finite gradient entries (one read pass, launched the same way), instead of ~14
        foreach passes and a norm: ~1.2 ms of a 10-ms captured GPU step went there for the 67-MB
        hash table, and one launch per tensor cost 30 launches a step (perf note 39). float32
        parameters only (others keep the foreach path).
        """
        from fastneus.kernels import get_op

        # the per-tensor ops (adam_update, adam_nonfinite) stay: the multi-tensor ops use them for large tensors
        self.fused = (get_op("adam_update_multi", backend), get_op("adam_nonfinite_multi", backend))

    def _state(self, p: torch.Tensor) -> dict:
        """``p``'s step count and moments, created (zero) on its first update."""
        st = self.state.get(p)
        if st is None:
            st = self.state[p] = {"step": 0, "exp_avg": torch.zeros_like(p), "exp_avg_sq": torch.zeros_like(p)}
        return st

    def zero_grad(self, set_to_none: bool = True) -> None:
        for g in self.param_groups:
            for p in g["params"]:
                if p.grad is None:
                    continue
                if set_to_none:
                    p.grad = None
                else:
                    p.grad.detach_().zero_()

    @torch.no_grad()
    def step(self) -> None:
        """One Adam update of every parameter that has a gradient (host arithmetic only: no sync)."""
        for g in self.param_groups:
            b1, b2 = g["betas"]
            # parameters with the same step count share one foreach call (all of them, normally)
            by_step: dict[int, tuple[list, list, list, list]] = {}
            for p in g["params"]:
                if p.grad is None:
                    continue
                st = self._state(p)
                st["step"] += 1
                lists = by_step.setdefault(st["step"], ([], [], [], []))
                lists[0].append(p)
                lists[1].append(p.grad)
                lists[2].append(st["exp_avg"])
                lists[3].append(st["exp_avg_sq"])
            for t, (ps, gs, ms, vs) in by_step.items():
                torch._foreach_lerp_(ms, gs, 1 - b1)
                torch._foreach_mul_(vs, b2)
                torch._foreach_addcmul_(vs, gs, gs, 1 - b2)
                bc1 = 1 - b1 ** t
                bc2_sqrt = math.sqrt(1 - b2 ** t)
                denom = torch._foreach_sqrt(vs)
                torch._foreach_div_(denom, bc2_sqrt)
                torch._foreach_add_(denom, g["eps"])
                torch._foreach_addcdiv_(ps, ms, denom, -g["lr"] / bc1)

    @torch.no_grad()
    def gated_step(self, ok: torch.Tensor) -> None:
        """The update of :meth:`step`, applied only where the device flag ``ok`` is true, with no
        host read of it (the NaN guard of a CUDA step without a host sync).

        Non-finite gradients are zeroed first (0 * NaN is NaN), then the moments and parameters
        move by ``ok`` times their Adam increment; so a step with ``ok`` false leaves parameters
        and moments exactly as they were, and one with ``ok`` true matches :meth:`step` up to
        rounding. Every group's tensors go through one set of ``_foreach`` calls (the per-group
        learning rate is a per-tensor scalar): ~10 launches for the whole model instead of ~7
        per group. The step count (bias correction) still advances on a gated-off step, as in
        torch's capturable Adam; a skipped step is rare and its effect on the correction tiny.

        Args:
            ok: [] or [1] bool/float tensor on the parameters' device.
        """
        if self.fused is not None and self._fusable():
            self.prepare_device_step()  # advances the steps and writes this step's scalars
            self.device_update(ok)
            return
        okf = ok.to(torch.float32).reshape(())
        buckets: dict[tuple, tuple[list, list, list, list, list]] = {}
        for g in self.param_groups:
            b1, b2 = g["betas"]
            for p in g["params"]:
                if p.grad is None:
                    continue
                st = self._state(p)
                st["step"] += 1
                t = st["step"]
                # -lr / bc1 and 1 / bc2_sqrt per tensor; eps and the betas are shared by a bucket
                lists = buckets.setdefault((b1, b2, g["eps"], p.dtype), ([], [], [], [], []))
                lists[0].append(p)
                lists[1].append(p.grad)
                lists[2].append(st["exp_avg"])
                lists[3].append(st["exp_avg_sq"])
                lists[4].append((-g["lr"] / (1 - b1 ** t), 1.0 / math.sqrt(1 - b2 ** t)))
        for (b1, b2, eps, dtype), (ps, gs, ms, vs, sc) in buckets.items():
            _masked_update(ps, gs, ms, vs, okf.to(dtype), b1, b2, eps, [s[1] for s in sc], [s[0] for s in sc])

    # ---------------------------------------------------------------- a captured update
    def prepare_device_step(self) -> None:
        """The host half of a captured update (:meth:`device_update`): moment buffers created,
        step counts advanced, and each group's ``-lr / bc1`` and ``1 / sqrt(bc2)`` written to a
        device tensor with ``fill_`` (a kernel argument: no copy, no sync), so a replayed graph
        reads this step's learning rate. Every parameter of a group must have a gradient (the
        caller checks :meth:`uniform_steps`)."""
        dev = self.param_groups[0]["params"][0].device
        if getattr(self, "_scal", None) is None or self._scal.device != dev:
            self._scal = torch.zeros(len(self.param_groups), 2, device=dev)
        vals = []
        for g in self.param_groups:
            b1, b2 = g["betas"]
            t = 0
            for p in g["params"]:
                st = self._state(p)
                st["step"] += 1
                t = st["step"]
            vals += [-g["lr"] / (1 - b1 ** t), 1.0 / math.sqrt(1 - b2 ** t)]
        if dev.type == "cuda":
            # one copy from page-locked memory instead of a fill per value: this runs between the
            # march's count read and the replay, while the device waits for the host's launches
            # (10 fills: 0.28 ms of idle device per step on an H200; a fresh pinned tensor per
            # step: 0.15 ms). Two pinned buffers in turn, each reused once its last copy has run.
            if getattr(self, "_pinned", None) is None or self._pinned[0].numel() != len(vals):
                self._pinned = [torch.empty(len(vals), dtype=self._scal.dtype, pin_memory=True) for _ in range(2)]
                self._copied = [torch.cuda.Event(), torch.cuda.Event()]  # not recorded yet: no wait
                self._turn = 0
            i = self._turn = 1 - self._turn
            if not self._copied[i].query():  # its copy of two steps back: waits only if the host ran that far ahead
                self._copied[i].synchronize()
            self._pinned[i].copy_(torch.tensor(vals, dtype=self._scal.dtype))
            self._scal.view(-1).copy_(self._pinned[i], non_blocking=True)
            self._copied[i].record(torch.cuda.current_stream(dev))  # the copy's stream (cuda:N too)
        else:
            self._scal.view(-1).copy_(torch.tensor(vals, dtype=self._scal.dtype))

    def _fusable(self) -> bool:
        """Every parameter float32 with a gradient and one step count per group (the fused
        update's per-group scalars hold then)."""
        return all(p.grad is not None and p.dtype == torch.float32 for g in self.param_groups for p in g["params"]) \
            and self.uniform_steps()

    def nonfinite_count(self) -> torch.Tensor | None:
        """[1] float32 device count of non-finite gradient entries (fused op), or None when
        the fused ops are off or a gradient is not float32."""
        if self.fused is None:
            return None
        grads = [p.grad for g in self.param_groups for p in g["params"] if p.grad is not None]
        if not grads or any(x.dtype != torch.float32 for x in grads):
            return None
        count = torch.zeros(1, device=grads[0].device)
        self.fused[1](grads, count)
        return count

    def uniform_steps(self) -> bool:
        """Whether every parameter of each group has the same step count (one bias correction
        per group, as :meth:`prepare_device_step` assumes)."""
        for g in self.param_groups:
            steps = {self.state[p]["step"] if p in self.state else 0 for p in g["params"]}
            if len(steps) > 1:
                return False
        return True

    @torch.no_grad()
    def device_update(self, ok: torch.Tensor) -> None:
        """The device half of a captured update: :meth:`gated_step`'s arithmetic with the
        learning rates and bias corrections read from the tensor :meth:`prepare_device_step`
        filled. No host value is read, so the update can be captured in a CUDA graph.

        Args:
            ok: [] bool/float tensor: apply the update (False: parameters and moments unchanged).
        """
        okf = ok.to(torch.float32).reshape(())
        # fused: the groups' float32 tensors with the same constants go in one launch
        multi: dict[tuple, tuple[list, list, list, list, list]] = {}
        for gi, g in enumerate(self.param_groups):
            ps = [p for p in g["params"] if p.grad is not None]
            if not ps:
                continue
            b1, b2 = g["betas"]
            dt = ps[0].dtype
            if self.fused is not None and all(p.dtype == torch.float32 for p in ps) and self._scal.dtype == torch.float32:
                lists = multi.setdefault((b1, b2, g["eps"]), ([], [], [], [], []))
                for p in ps:
                    st = self.state[p]
                    for lst, x in zip(lists, (p.detach(), p.grad, st["exp_avg"], st["exp_avg_sq"], gi)):
                        lst.append(x)
                continue
            _masked_update(ps, [p.grad for p in ps], [self.state[p]["exp_avg"] for p in ps],
                           [self.state[p]["exp_avg_sq"] for p in ps], okf.to(dt), b1, b2, g["eps"],
                           self._scal[gi, 1].to(dt), self._scal[gi, 0].to(dt))
        for (b1, b2, eps), (ps, gs, ms, vs, rows) in multi.items():
            self.fused[0](ps, gs, ms, vs, self._scal, rows, okf.reshape(1), b1, b2, eps)

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict:
        """torch.optim's layout: ``state`` keyed by parameter index, groups with index lists."""
        index, i = {}, 0
        groups = []
        for g in self.param_groups:
            ids = []
            for p in g["params"]:
                index[p] = i
                ids.append(i)
                i += 1
            groups.append({**_TORCH_KEYS, **{k: v for k, v in g.items() if k != "params"}, "params": ids})
        state = {index[p]: {"step": torch.tensor(float(st["step"])), "exp_avg": st["exp_avg"],
                            "exp_avg_sq": st["exp_avg_sq"]} for p, st in self.state.items() if p in index}
        return {"state": state, "param_groups": groups}

    def load_state_dict(self, sd: dict) -> None:
        """Load a :meth:`state_dict` of this class or of ``torch.optim.Adam`` (same layout)."""
        groups = sd["param_groups"]
        if len(groups) != len(self.param_groups) or any(
                len(a["params"]) != len(b["params"]) for a, b in zip(groups, self.param_groups)):
            raise ValueError("optimizer state does not match the parameter groups")
        by_index = {}
        for saved, g in zip(groups, self.param_groups):
            for i, p in zip(saved["params"], g["params"]):
                by_index[i] = p
            for k, v in saved.items():
                if k != "params":
                    g[k] = tuple(v) if k == "betas" else v
        self.state = {}
        for i, st in sd["state"].items():
            p = by_index.get(int(i))
            if p is None:
                continue
            step = st["step"]
            self.state[p] = {"step": int(step.item() if torch.is_tensor(step) else step),
                             "exp_avg": st["exp_avg"].to(device=p.device, dtype=p.dtype).clone(),
                             "exp_avg_sq": st["exp_avg_sq"].to(device=p.device, dtype=p.dtype).clone()}


def _masked_update(ps: list, gs: list, ms: list, vs: list, w: torch.Tensor, b1: float, b2: float, eps: float,
                   inv_bc2_sqrt, step_scale) -> None:
    """Adam's arithmetic moved by ``w`` (0 or 1, a device scalar): non-finite gradients zeroed
    (0 * NaN is NaN), m += w (1 - b1) (g - m), v += w (1 - b2) (g^2 - v), p += w * step_scale *
    m / (sqrt(v) inv_bc2_sqrt + eps). ``inv_bc2_sqrt`` and ``step_scale`` (-lr / bc1) are a list
    of floats (one per tensor) or a device scalar (a captured step reads it at replay)."""
    gs = [torch.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0) for x in gs]
    d = torch._foreach_sub(gs, ms)
    torch._foreach_mul_(d, w * (1 - b1))
    torch._foreach_add_(ms, d)
    d = torch._foreach_mul(gs, gs)
    torch._foreach_sub_(d, vs)
    torch._foreach_mul_(d, w * (1 - b2))
    torch._foreach_add_(vs, d)
    denom = torch._foreach_sqrt(vs)
    torch._foreach_mul_(denom, inv_bc2_sqrt)
    torch._foreach_add_(denom, eps)
    upd = torch._foreach_div(ms, denom)
    torch._foreach_mul_(upd, step_scale)
    torch._foreach_mul_(upd, w)
    torch._foreach_add_(ps, upd)
