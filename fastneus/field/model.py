"""The neural field: hash-grid SDF + small torch MLPs (geometry and colour D).

Geometry: f(x) = MLP([x, hash(x)]) with Softplus(beta=100) and a sphere initialisation.
Normals (``sdf_grad``): ``fd`` = finite differences through the hash grid (4-tap
tetrahedron), so the eikonal loss needs only first-order gradients through the Warp
kernels; ``analytic`` = the hash features' spatial Jacobian from one fused kernel
(``hash_encode_jac``) chained with the MLP's input gradient (torch double backward for
the MLP only), on 1x instead of 5x the points.
"""
from __future__ import annotations

import dataclasses
import math

import torch
import torch.nn as nn
import torch.nn.functional as F

from fastneus.field.sdf_mlp import fusable, mlp_and_input_grad, mlp_forward
from fastneus.kernels import get_op
from fastneus.kernels.hashgrid import HashGridConfig, init_table

# tetrahedron taps: grad f ~= sum_i v_i f(x + eps v_i) / (4 eps)
HIGHLIGHT_BIAS = -6.0  # the highlight output's starting bias: softplus(-6) = 0.0025, no glint yet
_TETRA = torch.tensor([[1.0, -1.0, -1.0], [-1.0, -1.0, 1.0], [-1.0, 1.0, -1.0], [1.0, 1.0, 1.0]])


# the smallest table fastneus' defaults choose (pixels_per_entry): the smallest one measured (H200, 0.8 M
# pixels; docs/benchmarks/short-budget-gpu.md, "The hash table's size")
MIN_AUTO_LOG2_TABLE = 17


def table_log2(hashgrid, pixels: int) -> int:
    """log2 of the table's entries per level: ``log2_table``, or with ``pixels_per_entry`` set, the
    largest power of two at most ``pixels / pixels_per_entry``, within [MIN_AUTO_LOG2_TABLE, log2_table].

    Args:
        hashgrid: the config's ``hashgrid`` section.
        pixels: pixels of the training photos' distinct viewpoints.
    """
    top = hashgrid.log2_table
    if hashgrid.pixels_per_entry <= 0 or pixels <= 0:
        return top
    want = int(math.floor(math.log2(max(1.0, pixels / hashgrid.pixels_per_entry))))
    return max(min(MIN_AUTO_LOG2_TABLE, top), min(top, want))


def table_choice(hashgrid, pixels: int, views: int) -> tuple[int, str]:
    """(:func:`table_log2`, the printed line saying how it was chosen).

    Args:
        hashgrid: the config's ``hashgrid`` section.
        pixels, views: pixels and count of the training photos' distinct viewpoints.
    """
    lt = table_log2(hashgrid, pixels)
    note = f"hash table: 2^{lt} entries per level"
    if hashgrid.pixels_per_entry > 0:
        note += (f" ({pixels / 1e6:.2f} M pixels in {views} viewpoint{'s' * (views != 1)}, one entry per "
                 f"{hashgrid.pixels_per_entry:g}, within 2^{min(MIN_AUTO_LOG2_TABLE, hashgrid.log2_table)}"
                 f"..2^{hashgrid.log2_table})")
    return lt, note


class SDFField(nn.Module):
    """Hash-grid SDF and colour networks in normalised space ([-1, 1]^3).

    Args:
        hashgrid: the config's ``hashgrid`` section (table sizes, coarse-to-fine schedule).
        network: the config's ``network`` section (MLP sizes, NeuS sharpness).
        device: torch device.
        backend: kernel backend, ``warp`` or ``torch`` (the twins).
        log2_table: the table's entries per level (log2), if chosen by the caller (:func:`table_log2`);
            default ``hashgrid.log2_table``.
    """

    def __init__(self, hashgrid, network, device: torch.device | str = "cpu", backend: str = "warp",
                 log2_table: int | None = None):
        super().__init__()
        self.hashgrid, self.network = hashgrid, network
        lt = hashgrid.log2_table if log2_table is None else int(log2_table)
        self.grid_cfg = HashGridConfig(levels=hashgrid.levels, features=hashgrid.features, log2_table=lt,
                                       base_res=hashgrid.base_res, finest_res=hashgrid.finest_res)
        self.resolutions = self.grid_cfg.resolutions()
        self.table = nn.Parameter(init_table(self.grid_cfg, device))
        self.encode = get_op("hash_encode", backend)
        self.encode_jac = get_op("hash_encode_jac", backend)
        self.grad_from_jac = get_op("grad_from_jac", backend)
        self.sdf_grad = network.sdf_grad
        if self.sdf_grad not in ("fd", "analytic"):
            raise ValueError(f"sdf_grad must be 'fd' or 'analytic', got {self.sdf_grad!r}")
        n_feat = hashgrid.levels * hashgrid.features

        # geometry MLP: [x (3), hash features] -> [sdf, geo features]
        layers: list[nn.Module] = []
        dims = [3 + n_feat] + [network.sdf_hidden] * network.sdf_layers + [1 + network.geo_features]
        for i in range(len(dims) - 1):
            lin = nn.Linear(dims[i], dims[i + 1])
            self._geometric_init(lin, i == 0, i == len(dims) - 2, dims[i], network.init_radius)
            layers.append(lin)
            if i < len(dims) - 2:
                layers.append(nn.Softplus(beta=100))
        self.sdf_net = nn.Sequential(*layers).to(device)
        # the analytic gradient's MLP part as one autograd node (sdf_mlp.py); False = autograd's
        # double backward, the reference the tests compare it with
        self.fused_mlp = fusable(self.sdf_net)

        # colour MLP: [x, normal, (view dir), geo features] -> D (sigmoid) and, with
        # network.highlight, a fourth output: the projected light's highlight e (softplus)
        c_in = 3 + 3 + (3 if network.view_dependent else 0) + network.geo_features
        self.highlight = bool(network.highlight)
        cdims = [c_in] + [network.color_hidden] * network.color_layers + [4 if self.highlight else 3]
        clayers: list[nn.Module] = []
        for i in range(len(cdims) - 1):
            clayers.append(nn.Linear(cdims[i], cdims[i + 1]))
            if i < len(cdims) - 2:
                clayers.append(nn.ReLU(inplace=True))
        self.color_net = nn.Sequential(*clayers).to(device)
        if self.highlight:  # no highlight at the start: softplus(-6) = 0.0025
            with torch.no_grad():
                self.color_net[-1].bias[3] = HIGHLIGHT_BIAS

        # NeuS variance: inv_s = exp(10 v)
        self.variance = nn.Parameter(torch.tensor([network.variance_init], device=device))
        self.active_levels = hashgrid.levels
        self.inv_s_floor = 0.0
        self.register_buffer("_tetra", _TETRA.to(device), persistent=False)
        # device-side schedule (a captured CUDA step): see enable_device_schedule
        self._dev_sched = False
        self._floor_t = self._levels_t = None

    @staticmethod
    def _geometric_init(lin: nn.Linear, first: bool, last: bool, d_in: int, radius: float) -> None:
        """SAL/NeuS geometric init so that f(x) ~= |x| - radius at the start."""
        d_out = lin.out_features
        if last:
            nn.init.normal_(lin.weight, mean=math.sqrt(math.pi) / math.sqrt(d_in), std=1e-4)
            nn.init.constant_(lin.bias, -radius)
        elif first:
            nn.init.constant_(lin.bias, 0.0)
            nn.init.normal_(lin.weight[:, :3], 0.0, math.sqrt(2) / math.sqrt(d_out))
            nn.init.constant_(lin.weight[:, 3:], 0.0)  # hash features start silent
        else:
            nn.init.constant_(lin.bias, 0.0)
            nn.init.normal_(lin.weight, 0.0, math.sqrt(2) / math.sqrt(d_out))

    # ------------------------------------------------------------------ geometry
    def floor_end(self, steps_total: float | None = None) -> float:
        """The sharpness floor's end: ``inv_s_floor_end``, capped at ``inv_s_floor_per_step`` times
        ``steps_total`` (the run's steps, or those expected) when both are set, never below the
        floor's start."""
        c = self.network
        end = c.inv_s_floor_end
        if c.inv_s_floor_per_step > 0 and steps_total and steps_total > 0:
            end = max(c.inv_s_floor_start, min(end, c.inv_s_floor_per_step * steps_total))
        return end

    def set_progress(self, progress: float, steps_total: float | None = None) -> None:
        """Coarse-to-fine levels and the sharpness floor at ``progress`` in [0, 1] of the run.

        Active levels rise linearly from ``c2f_start_levels`` to all levels at ``c2f_frac`` of the
        run; inv_s is kept above a floor rising log-linearly from ``inv_s_floor_start`` to
        :meth:`floor_end` over the first ``inv_s_floor_frac``: the learned NeuS variance alone
        sharpens too slowly for a budget of a few thousand steps. Both are fractions of the run,
        so a 5-s and a 10-min run pass through the same stages; ``steps_total`` (the run's step
        count, expected or set) lowers the floor's end of a short run (``inv_s_floor_per_step``).
        """
        c, g = self.network, self.hashgrid
        if c.inv_s_floor_end > 0:
            f = min(1.0, progress / c.inv_s_floor_frac) if c.inv_s_floor_frac > 0 else 1.0
            end = self.floor_end(steps_total)
            self.inv_s_floor = math.exp(math.log(c.inv_s_floor_start) * (1 - f) + math.log(end) * f)
        if g.c2f_start_levels <= 0 or g.c2f_frac <= 0 or g.c2f_start_levels >= g.levels:
            self.active_levels = g.levels
        else:
            f = min(1.0, progress / g.c2f_frac)
            self.active_levels = min(g.levels, g.c2f_start_levels + int(math.floor(f * (g.levels - g.c2f_start_levels) + 1e-9)))
        self._fill_schedule()

    def enable_device_schedule(self) -> None:
        """Keep the schedule's values where a captured CUDA graph reads them at replay: the
        sharpness floor and the number of active hash levels as device tensors (filled by
        :meth:`set_progress`); the hash kernels launch every level and read the count when they
        run (the inactive levels return at once: zero features and Jacobian, no gradient, as
        when only the active levels are launched)."""
        dev = self.table.device
        self._dev_sched = True
        self._floor_t = torch.zeros((), device=dev)
        self._levels_t = torch.zeros((1,), dtype=torch.int32, device=dev)
        self._fill_schedule()

    def _fill_schedule(self) -> None:
        if self._dev_sched:  # fill_: the value travels as a kernel argument (no copy, no sync)
            self._floor_t.fill_(max(1e-3, self.inv_s_floor))
            self._levels_t.fill_(self.active_levels)

    def _levels_arg(self):
        """The active-level count the hash ops get: the device tensor on the device-side
        schedule (the kernels read it when they run, so a captured graph follows it and the
        inactive levels cost nothing), else the int."""
        return self._levels_t if self._dev_sched else self.active_levels

    def _encode(self, u: torch.Tensor) -> torch.Tensor:
        """[N, L*F] hash features of u in [0, 1]^3 at the active levels (zero above them)."""
        return self.encode(u, self.table, self.grid_cfg, self._levels_arg())

    def _encode_jac(self, u: torch.Tensor):
        """Features [N, L*F] and d feats / d u [N, L*F, 3] at the active levels (zero above them)."""
        return self.encode_jac(u, self.table, self.grid_cfg, self._levels_arg())

    def normal_eps(self) -> float:
        """Finite-difference step tied to the finest active level (normalised units)."""
        res = self.resolutions[max(0, self.active_levels - 1)]
        return max(self.network.normal_eps_min, 2.0 / res)

    def geometry(self, x: torch.Tensor) -> torch.Tensor:
        """SDF network output for points.

        Args:
            x: [N, 3] float32 normalised positions.
        Returns:
            [N, 1 + geo_features]: sdf in column 0, geometric features after.
        """
        u = ((x + 1.0) * 0.5).clamp(0.0, 1.0)
        feats = self._encode(u.contiguous())
        return self.sdf_net(torch.cat([x, feats], dim=-1))

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        """[N, 3] -> [N] signed distance (normalised units)."""
        return self.geometry(x)[:, 0]

    def sdf_and_grad(self, x: torch.Tensor, with_curvature: bool = False):
        """SDF, geometric features and SDF gradient (``network.sdf_grad``: finite or analytic).

        ``fd``: the centre and 4 tetrahedron taps go through the hash grid and MLP in one call
        (5N points). ``analytic``: features and d feats / d u from one ``hash_encode_jac``
        call and the MLP on the N points, grad = d MLP / d x + 0.5 jac^T d MLP / d feats.
        In both, gradients reach the table, the MLP weights and (first-order) x from any
        loss on the returned grad. Under ``torch.no_grad()`` the analytic gradient is still
        computed (locally with grad enabled, no graph kept) and all outputs are detached.

        ``with_curvature=True`` (the one-shot smoothness prior) evaluates the 4 tetrahedron
        taps in either mode: the trilinear hash grid's analytic Laplacian is zero inside
        cells and undefined on faces, so it carries no useful smoothness signal. In
        ``analytic`` mode the returned grad is still the analytic one.

        Args:
            x: [N, 3] float32 normalised positions.
            with_curvature: also return a Laplacian-like residual for a smoothness prior.
        Returns:
            sdf [N], geo [N, G], grad [N, 3], (curv [N] or None)
        """
        if self.sdf_grad == "analytic":
            return self._sdf_and_grad_analytic(x, with_curvature)
        n = x.shape[0]
        eps = self.normal_eps()
        taps = x[None, :, :] + eps * self._tetra[:, None, :]          # [4, N, 3]
        out = self.geometry(torch.cat([x, taps.reshape(-1, 3)], 0))   # [5N, 1+G]
        sdf, geo = out[:n, 0], out[:n, 1:]
        f_taps = out[n:, 0].reshape(4, n)
        grad = (f_taps[:, :, None] * self._tetra[:, None, :]).sum(0) / (4.0 * eps)
        curv = None
        if with_curvature:
            # mean of the tetrahedron taps minus the centre ~ eps^2/2 * Laplacian / 3
            curv = (f_taps.mean(0) - sdf) / (eps * eps)
        return sdf, geo, grad, curv

    def geometry_and_grad(self, x: torch.Tensor):
        """SDF network output and the analytic SDF gradient (the ``analytic`` mode's core).

        The encoding takes u = (x + 1) / 2 unclamped: ``hash_encode_jac`` clamps it and
        zeroes the Jacobian on clamped axes (d u / d x = 0 outside the box), so only the
        MLP's direct x input contributes there. The MLP part is one autograd node
        (``fused_mlp``, :mod:`fastneus.field.sdf_mlp`) when the network has one hidden layer;
        otherwise autograd's double backward, which needs grad mode (see :meth:`sdf_and_grad`).

        Args:
            x: [N, 3] float32 normalised positions.
        Returns:
            out [N, 1 + G] (sdf in column 0), grad [N, 3] with a graph to the table, the MLP
            weights and x (create_graph), ready for the eikonal loss.
        """
        feats, jac = self._encode_jac(((x + 1.0) * 0.5).contiguous())  # [N, L*F], [N, L*F, 3]
        if self.fused_mlp:
            out, g = mlp_and_input_grad(self.sdf_net, x, feats)  # [N, 1+G], [N, 3 + L*F]
            return out, self.grad_from_jac(g, jac, 0.5)
        net_in = torch.cat([x, feats], dim=-1)
        if not net_in.requires_grad:  # frozen table and constant x: differentiate the MLP input anyway
            net_in = net_in.detach().requires_grad_()
        out = self.sdf_net(net_in)
        (g,) = torch.autograd.grad(out[:, 0].sum(), net_in, create_graph=True)  # [N, 3 + L*F]
        # grad = g[:, :3] + 0.5 jac^T g[:, 3:] (d feats / d x = 0.5 jac, u = (x + 1) / 2) in one
        # kernel each way (a bmm here was a batched cuBLAS gemv: 1.5 ms at 2^18 samples; entry 17)
        grad = self.grad_from_jac(g, jac, 0.5)
        return out, grad

    def _sdf_and_grad_analytic(self, x: torch.Tensor, with_curvature: bool):
        n = x.shape[0]
        if torch.is_grad_enabled() or self.fused_mlp:  # the fused node needs no graph
            out, grad = self.geometry_and_grad(x)
        else:
            # inference (mesh/normal renders under no_grad): autograd.grad needs a graph, so build
            # one locally and drop it; every output comes back detached, as under no_grad
            with torch.enable_grad():
                out, grad = self.geometry_and_grad(x.detach())
            out, grad = out.detach(), grad.detach()
        sdf, geo = out[:, 0], out[:, 1:]
        curv = None
        if with_curvature:
            eps = self.normal_eps()
            taps = x[None, :, :] + eps * self._tetra[:, None, :]      # [4, N, 3]
            f_taps = self.geometry(taps.reshape(-1, 3))[:, 0].reshape(4, n)
            curv = (f_taps.mean(0) - sdf) / (eps * eps)
        return sdf, geo, grad, curv

    # ------------------------------------------------------------------ colour
    def color(self, x: torch.Tensor, normal: torch.Tensor, dirs: torch.Tensor, geo: torch.Tensor) -> torch.Tensor:
        """Colour D of the scene itself (no pattern).

        Args:
            x: [N, 3] positions; normal: [N, 3] SDF gradients; dirs: [N, 3] unit view directions;
            geo: [N, G] geometric features.
        Returns:
            [N, 3] in (0, 1).
        """
        return self.shade(x, normal, dirs, geo)[0]

    def shade(self, x: torch.Tensor, normal: torch.Tensor, dirs: torch.Tensor,
              geo: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Colour D and the projected light's highlight e (``network.highlight``) from one MLP pass.

        e is the non-Lambertian share of the pattern's light at a sample, added to i_b there
        (``c = D + (i_r D + i_b + e) Q``): a shiny surface's glint of the projector, seen from
        this view direction. It is >= 0, so it can brighten where the pattern falls but never move
        or remove a line.

        Args: as :meth:`color`.
        Returns:
            (D [N, 3] in (0, 1), e [N] >= 0 or None without ``network.highlight``).
        """
        n = normal / normal.norm(dim=-1, keepdim=True).clamp_min(1e-6)
        parts = [x, n] + ([dirs] if self.network.view_dependent else []) + [geo]
        out = mlp_forward(self.color_net, torch.cat(parts, dim=-1))
        if not self.highlight:
            return torch.sigmoid(out), None
        return torch.sigmoid(out[:, :3]), F.softplus(out[:, 3])

    def inv_s(self) -> torch.Tensor:
        """[1] NeuS sharpness exp(10 v), at least the scheduled floor, at most 1e6."""
        if self._dev_sched:  # the floor from the device (a captured step reads it at replay)
            return torch.maximum(torch.exp(self.variance * 10.0).clamp(max=1e6), self._floor_t)
        return torch.exp(self.variance * 10.0).clamp(max(1e-3, self.inv_s_floor), 1e6)

    def init_color_bias(self, mean_rgb) -> None:
        """Start D at the images' mean colour (logit of it), not at sigmoid(0) = 0.5 grey.

        Args:
            mean_rgb: [3] mean training pixel colour in [0, 1].
        """
        m = torch.as_tensor(mean_rgb, dtype=torch.float32).clamp(0.02, 0.98)
        with torch.no_grad():
            self.color_net[-1].bias[:3].copy_(torch.log(m / (1 - m)).to(self.color_net[-1].bias.device))

    def without_coarse_to_fine(self) -> None:
        """All hash levels from now on (a fitted initial surface set the fine levels already)."""
        self.hashgrid = dataclasses.replace(self.hashgrid, c2f_start_levels=0)
        self.active_levels = self.hashgrid.levels
        self._fill_schedule()

    def param_groups(self, optim):
        """Adam parameter groups: geometry (hash table, SDF MLP), colour MLP, variance."""
        return [
            {"params": [self.table] + list(self.sdf_net.parameters()), "lr": optim.lr, "name": "geometry"},
            {"params": list(self.color_net.parameters()), "lr": optim.lr, "name": "color"},
            {"params": [self.variance], "lr": optim.lr_variance, "name": "variance"},
        ]
