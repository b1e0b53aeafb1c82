"""What a real rig gets wrong, learned during training: pose corrections of cameras and
projectors, a per-projector pattern blur (defocus), and the water medium (attenuation and
back-scatter; the flat-port refraction itself is geometry from the scene, applied in
``fastneus.train.rays``).

The trainer owns one :class:`Rig`. It is inert unless a config key turns a part on
(``pose_refine``, ``projector_blur``, ``medium``), so the default step is unchanged. Hooks, all cheap when off:

- :meth:`Rig.rays` corrects a batch's camera rays (differentiable in the corrections);
- :meth:`Rig.projection` returns the per-frame projector data with corrected poses and the
  learned light model (blur kernels, sampled by ``fastneus.kernels.project``);
- :meth:`Rig.param_groups` / :meth:`Rig.lr_gate` give its Adam groups and their warm-ups.

Pose corrections (small-angle SE(3), ``xi = (omega, v)``: rotation vector in radians and
translation in normalised units) act in each device's own frame::

    cam_to_world'  = cam_to_world  @ E(xi_view)            (one correction per viewpoint)
    proj_to_world' = cam_to_world' @ proj_to_cam @ E(xi_proj)   (rigged projector)
    proj_to_world' = proj_to_world @ E(xi_proj)                  (free projector)

``E(xi) = [[exp(omega^), radius * v], [0, 1]]`` (world units). The first training viewpoint
is the anchor (``pose_anchor``): its camera stays fixed and defines the world frame, as the
reference camera of a calibrated rig does; without an anchor the whole reconstruction could
drift rigidly at no cost in the loss.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import torch

from fastneus.geometry.cameras import rigid_inverse
from fastneus.geometry.se3 import rigid_inverse_torch, se3_matrix
from fastneus.io import atomic_write_json
from fastneus.data.kinds import get_projector_kind


# --------------------------------------------------------------------------- the rig
class Rig(torch.nn.Module):
    """Learned rig corrections for one training run.

    Args:
        scene: the loaded scene.
        frames: training frame indices (rows of the ray bank and of ``proj``).
        bank: the trainer's :class:`fastneus.train.rays.RayBank` (camera rotations per row).
        proj: the trainer's :class:`fastneus.train.rays.Projection` (uncorrected).
        cfg: the config's ``rig`` section (which corrections, their learning rates and warm-ups).
        device: torch device.
        split_patterns: the renderer samples patterns in a separate pass
            (:func:`fastneus.field.renderer.pattern_pass_split`), so the projection op is needed.
    """

    def __init__(self, scene, frames: list[int], bank, proj, cfg, device, split_patterns: bool = False):
        super().__init__()
        self.scene, self.frames, self.cfg = scene, list(frames), cfg
        self.split_patterns = split_patterns
        self.device = torch.device(device)
        self.radius = float(scene.bounds.radius)
        self.proj_ids = list(scene.projectors.keys())
        views = [scene.frames[i].view for i in self.frames]
        self.view_ids = list(dict.fromkeys(views))
        self.register_buffer("frame_view", torch.tensor([self.view_ids.index(v) for v in views],
                                                        dtype=torch.long, device=self.device), persistent=False)
        self.pose_on = bool(cfg.pose_refine)
        n_views, n_proj = len(self.view_ids), max(1, len(self.proj_ids))
        self.blur_n = int(cfg.projector_blur) if cfg.projector_blur > 1 else 0
        self.blur_on = self.blur_n > 0
        n = max(1, self.blur_n)
        raw = torch.zeros(n_proj, 2, n, device=self.device)  # separable: column (x) and row (y) profiles
        raw[:, :, n // 2] = 1.0  # identity
        self.blur_raw = torch.nn.Parameter(raw)
        self.cam_xi = torch.nn.Parameter(torch.zeros(n_views, 6, device=self.device))
        self.proj_xi = torch.nn.Parameter(torch.zeros(n_proj, 6, device=self.device))
        mask = torch.ones(n_views, 1, device=self.device)
        if cfg.pose_anchor:
            mask[0] = 0.0
        self.register_buffer("cam_mask", mask, persistent=False)
        self._bank, self._proj = bank, proj
        if self.pose_on:
            self._init_pose_data(scene)
        # water: attenuation beta_d and back-scatter beta_b (per channel, 1 / world unit), veiling light b_inf
        wet = any(c.port is not None for c in scene.cameras.values()) or \
            any(p.port is not None for p in scene.projectors.values())
        self.medium_on = cfg.medium == "on" or (cfg.medium == "auto" and wet)
        self.log_beta_d = torch.nn.Parameter(torch.full((3,), math.log(0.05), device=self.device))
        self.log_beta_b = torch.nn.Parameter(torch.full((3,), math.log(0.05), device=self.device))
        self.b_inf_raw = torch.nn.Parameter(torch.zeros(3, device=self.device))
        if self.medium_on:
            self._init_veiling_light(bank)

    # ------------------------------------------------------------------ setup
    def _init_pose_data(self, scene) -> None:
        F, P = len(self.frames), max(1, len(self.proj_ids))
        W4 = torch.zeros(F, P, 4, 4, dtype=torch.float64)
        W4[:, :, :3, :] = self._proj.W.detach().double().cpu()
        W4[:, :, 3, 3] = 1.0
        A = torch.eye(4, dtype=torch.float64).repeat(F, P, 1, 1)  # camera -> projector (world units)
        rigged = torch.zeros(F, P, dtype=torch.bool)
        for k, pid in enumerate(self.proj_ids):
            p2c = scene.projectors[pid].proj_to_cam
            if p2c is not None:
                A[:, k] = torch.as_tensor(rigid_inverse(p2c))
                rigged[:, k] = True
        self.register_buffer("W4", W4.float().to(self.device), persistent=False)
        self.register_buffer("cam_to_proj", A.float().to(self.device), persistent=False)
        self.register_buffer("rigged", rigged.to(self.device), persistent=False)
        g = self.scale_gauge(scene) if (self.cfg.pose_anchor and self.cfg.pose_fix_scale) else None
        self.register_buffer("gauge", None if g is None else g.float().to(self.device), persistent=False)

    def scale_gauge(self, scene) -> torch.Tensor | None:
        """Unit direction [V*3 + P*3] of the global-scale mode in the translation corrections.

        With the first camera anchored, scaling the whole rig about that camera's centre (the
        scene, every other camera centre, every projector position) leaves every image unchanged,
        so the joint problem has one free direction; on the GPU protocol the camera translations
        drifted along it (28 mm for a 10 mm perturbation). To first order it is
        ``v_view = R_c2w^T (c_view - c_anchor) / radius`` for the cameras (``cam_to_world @ E``
        moves the centre by ``R_c2w radius v``), ``v_p = R_p2c^T t_p / radius`` for a rigged
        projector (``t_p`` its position in the camera frame) and ``R_p2w^T (p - c_anchor) / radius``
        (mean over frames) for a free one. None when the rig has no such direction (one view and
        no projector translation).
        """
        frames_of = {v: [i for i in self.frames if scene.frames[i].view == v] for v in self.view_ids}
        c0 = scene.cam_to_world(frames_of[self.view_ids[0]][0])[:3, 3]
        parts = []
        for v in self.view_ids:
            T = scene.cam_to_world(frames_of[v][0])
            parts.append(T[:3, :3].T @ (T[:3, 3] - c0))
        for pid in self.proj_ids:
            pj = scene.projectors[pid]
            if pj.proj_to_cam is not None:
                T = np.asarray(pj.proj_to_cam)
                parts.append(T[:3, :3].T @ T[:3, 3])
            else:
                acc = [scene.frames[i].projectors[pid].proj_to_world for i in self.frames
                       if scene.frames[i].projectors.get(pid) is not None
                       and scene.frames[i].projectors[pid].proj_to_world is not None]
                parts.append(np.mean([a[:3, :3].T @ (a[:3, 3] - c0) for a in acc], 0) if acc else np.zeros(3))
        if not self.proj_ids:
            parts.append(np.zeros(3))
        g = torch.as_tensor(np.concatenate(parts) / self.radius, dtype=torch.float64)
        n = g.norm()
        return None if n < 1e-9 else g / n

    @torch.no_grad()
    def fix_gauge(self) -> None:
        """Remove the global-scale component from the translation corrections (after each step)."""
        if not self.pose_on or self.gauge is None:
            return
        V = self.cam_xi.shape[0]
        x = torch.cat([self.cam_xi[:, 3:].reshape(-1), self.proj_xi[:, 3:].reshape(-1)])
        x = x - (x @ self.gauge) * self.gauge
        self.cam_xi[:, 3:] = x[: V * 3].view(V, 3)
        self.proj_xi[:, 3:] = x[V * 3:].view(-1, 3)

    def _init_veiling_light(self, bank) -> None:
        """Start the veiling light at the colour of the background (pixels outside the masks,
        else the darkest 5% of pixels), where the far range makes back-scatter ~= b_inf."""
        g = torch.Generator(device=bank.rgb.device).manual_seed(0)
        idx = torch.randint(0, bank.n_pixels, (min(bank.n_pixels, 200_000),), device=bank.rgb.device, generator=g)
        rgb = bank.rgb[idx].float() / 255.0
        if bank.mask is not None and bool((bank.mask[idx] < 128).any()):
            bg = rgb[bank.mask[idx] < 128].mean(0)
        else:
            bright = rgb.sum(-1)
            bg = rgb[bright <= torch.quantile(bright, 0.05)].mean(0)
        bg = bg.clamp(0.01, 0.95) / (1 - math.exp(-0.05 * self.cfg.medium_far))
        with torch.no_grad():
            self.b_inf_raw.copy_(torch.logit(bg.clamp(0.01, 0.99)).to(self.device))

    def medium_params(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(beta_d [3], beta_b [3], b_inf [3]): attenuation and back-scatter coefficients (1 / world
        unit) and the veiling light colour."""
        return self.log_beta_d.exp(), self.log_beta_b.exp(), torch.sigmoid(self.b_inf_raw)

    def composite(self, color: torch.Tensor, out: dict, background: float) -> torch.Tensor:
        """Observed colour of rendered rays: ``color + background (1 - opacity)`` in air; in water

            C = color exp(-beta_d r) + b_inf (1 - exp(-beta_b r)),   r = R (depth + (1 - opacity) far)

        (r: expected range in the water along the camera ray, world units; R = bounds radius).

        Args:
            color: [B, 3] rendered colour (or texture), or [B, K, 3] for K shots per ray; out: the
                render dict (opacity [B], depth [B]).
        """
        shape = (-1,) + (1,) * (color.dim() - 1)  # [B, 1] or [B, 1, 1] for [B, K, 3] multi-shot colours
        op = out["opacity"].view(shape)
        if not self.medium_on:
            return color + background * (1.0 - op)
        bd, bb, binf = (x.to(color.device) for x in self.medium_params())
        r = out["depth"].view(shape) * self.radius + (1.0 - op) * self.cfg.medium_far
        return color * torch.exp(-bd * r) + binf * (1.0 - torch.exp(-bb * r))

    @property
    def active(self) -> bool:
        return self.pose_on or self.blur_on or self.medium_on

    def kernel_ops(self) -> tuple[str, ...]:
        """Extra kernel ops a training step uses (compiled before the clock starts)."""
        lights = getattr(self._proj, "lights", None) or {}  # emitter kinds (laser planes, ...)
        q_ext = self.blur_on or self.medium_on or bool(lights) or self._proj.port is not None or self.split_patterns
        ops = ("project_pattern",) if q_ext else ()
        return ops + tuple(op for op in (get_projector_kind(n).kernel_op() for n in lights) if op)

    def param_groups(self) -> list[dict]:
        """Adam groups of the enabled parts (names start with ``rig_``)."""
        groups = []
        if self.pose_on:
            groups.append({"params": [self.cam_xi, self.proj_xi], "lr": self.cfg.lr_pose, "name": "rig_pose"})
        if self.blur_on:
            groups.append({"params": [self.blur_raw], "lr": self.cfg.lr_blur, "name": "rig_blur"})
        if self.medium_on:
            groups.append({"params": [self.log_beta_d, self.log_beta_b, self.b_inf_raw], "lr": self.cfg.lr_medium,
                           "name": "rig_medium"})
        return groups

    def lr_gate(self, name: str, progress: float) -> float:
        """1 when group ``name`` learns at ``progress`` of the run, 0 during its warm-up."""
        if name == "rig_pose":
            return 0.0 if progress < self.cfg.pose_warmup_frac else 1.0
        if name == "rig_blur":
            return 0.0 if progress < self.cfg.blur_warmup_frac else 1.0
        return 1.0

    # ------------------------------------------------------------------ corrections
    def cam_correction(self) -> torch.Tensor:
        """[V, 4, 4] per-viewpoint camera correction E (world units; the anchor is identity)."""
        return se3_matrix(self.cam_xi * self.cam_mask, self.radius)

    def proj_correction(self) -> torch.Tensor:
        """[P, 4, 4] per-projector correction E (world units)."""
        return se3_matrix(self.proj_xi, self.radius)

    def blur_kernels(self) -> torch.Tensor:
        """[P, n*n] pattern blur taps ``k[a, b] = y[a] x[b]`` (row-major), identity at init.

        The kernel is separable: an x profile and a y profile per projector, each normalised
        to sum 1. A full n x n kernel is not identifiable from line patterns (a vertical laser
        line only sees the kernel's column sums), a separable one is, and defocus is close to
        a separable Gaussian. Plain normalisation (not softmax) keeps the identity init exact and
        every tap learnable; small negative taps are allowed (optics can also sharpen)."""
        prof = self.blur_raw / self.blur_raw.sum(-1, keepdim=True)  # [P, 2, n]
        return (prof[:, 1, :, None] * prof[:, 0, None, :]).reshape(prof.shape[0], -1)

    def light_model(self, proj):
        """``proj`` with the learned light model attached (blur, the medium's attenuation of the
        projected light), poses untouched."""
        kw = {}
        if self.blur_on:
            kw["blur"] = self.blur_kernels()
        if self.medium_on:
            kw["sigma"] = self.medium_params()[0]
        return dataclasses.replace(proj, **kw) if kw else proj

    def rays(self, batch: dict) -> dict:
        """Correct the camera rays of a :meth:`RayBank.sample` batch (a new dict; no-op when off).

        ``d' = R_c2w dR R_c2w^T d``, ``o' = o + R_c2w v`` with ``(dR, v)`` the frame's viewpoint
        correction (``v`` in normalised units).
        """
        if not self.pose_on:
            return batch
        f = batch["fidx"].long()
        E = self.cam_correction()[self.frame_view]           # [F, 4, 4]
        R = self._bank.rot                                    # [F, 3, 3] camera -> world
        M = R @ E[:, :3, :3] @ R.transpose(1, 2)              # [F, 3, 3]
        shift = (R @ E[:, :3, 3:]).squeeze(-1) / self.radius  # [F, 3] normalised
        out = dict(batch)
        out["dirs"] = torch.einsum("bij,bj->bi", M[f], batch["dirs"]).contiguous()
        out["origins"] = (batch["origins"] + shift[f]).contiguous()
        return out

    def projection(self, proj=None):
        """The projector data with corrected poses (``proj`` unchanged when pose refinement is off).

        ``W' = E_p^-1 A E_c^-1 A^-1 W`` for a rigged projector (A = camera->projector),
        ``W' = E_p^-1 W`` for a free one; W maps normalised points to projector coordinates.
        """
        proj = self.light_model(self._proj if proj is None else proj)
        if not self.pose_on:
            return proj
        Ec_inv = rigid_inverse_torch(self.cam_correction())[self.frame_view]      # [F, 4, 4]
        Ep_inv = rigid_inverse_torch(self.proj_correction())                      # [P, 4, 4]
        A = self.cam_to_proj
        Ainv = rigid_inverse_torch(A)
        P = A.shape[1]
        Ec = Ec_inv[:, None].expand(-1, P, -1, -1)
        moved = torch.where(self.rigged[..., None, None], A @ Ec @ Ainv @ self.W4, self.W4)
        W = (Ep_inv[None, :P] @ moved)[..., :3, :]
        return dataclasses.replace(proj, W=W.contiguous())

    # ------------------------------------------------------------------ results
    @torch.no_grad()
    def refined_poses(self) -> dict:
        """Corrected poses as numpy float64: ``cam_to_world`` per training frame, and per
        projector ``proj_to_cam`` (rigged) or ``proj_to_world`` per training frame (free)."""
        Ec = self.cam_correction().double().cpu().numpy()
        Ep = self.proj_correction().double().cpu().numpy()
        cams = [self.scene.cam_to_world(i) @ Ec[int(self.frame_view[a])] for a, i in enumerate(self.frames)]
        projs = {}
        for k, pid in enumerate(self.proj_ids):
            p2c = self.scene.projectors[pid].proj_to_cam
            if p2c is not None:
                projs[pid] = {"proj_to_cam": p2c @ Ep[k]}
            else:
                projs[pid] = {"proj_to_world": [None if self.scene.frames[i].projectors.get(pid) is None
                                                or self.scene.frames[i].projectors[pid].proj_to_world is None
                                                else self.scene.frames[i].projectors[pid].proj_to_world @ Ep[k]
                                                for i in self.frames]}
        return {"cam_to_world": cams, "projectors": projs}

    def refined_scene(self):
        """A copy of the scene (training frames only) with the corrected poses."""
        import copy

        s = self.scene.subset(self.frames)
        s.projectors = copy.deepcopy(self.scene.projectors)
        r = self.refined_poses()
        for a, f in enumerate(s.frames):
            f.cam_to_world = r["cam_to_world"][a]
        for pid, e in r["projectors"].items():
            if "proj_to_cam" in e:
                s.projectors[pid].proj_to_cam = e["proj_to_cam"]
            else:
                for a, f in enumerate(s.frames):
                    if e["proj_to_world"][a] is not None:
                        f.projectors[pid].proj_to_world = e["proj_to_world"][a]
        return s

    def eval_scene(self):
        """The whole scene with what was learned about poses: training frames' cameras and every
        projector corrected (held-out frames keep their cameras). The scene itself when off."""
        if not self.pose_on:
            return self.scene
        import copy

        s = copy.deepcopy(self.scene)
        r = self.refined_poses()
        for a, i in enumerate(self.frames):
            s.frames[i].cam_to_world = r["cam_to_world"][a]
        Ep = self.proj_correction().detach().double().cpu().numpy()
        for k, pid in enumerate(self.proj_ids):
            if s.projectors[pid].proj_to_cam is not None:
                s.projectors[pid].proj_to_cam = s.projectors[pid].proj_to_cam @ Ep[k]
            else:
                for f in s.frames:
                    fp = f.projectors.get(pid)
                    if fp is not None and fp.proj_to_world is not None:
                        fp.proj_to_world = fp.proj_to_world @ Ep[k]
        return s

    def write_json(self, out: Path) -> None:
        """``rig.json`` in the run folder: what was learned (corrected poses, sizes of the
        corrections), for the user to feed back into the calibration."""
        if not self.active:
            return
        d: dict = {}
        if self.pose_on:
            r = self.refined_poses()
            xi_c = self.cam_xi.detach().double().cpu().numpy() * self.cam_mask.cpu().numpy()
            xi_p = self.proj_xi.detach().double().cpu().numpy()
            d["pose"] = {
                "anchor_view": self.view_ids[0] if self.cfg.pose_anchor else None,
                "camera_correction_deg": [math.degrees(float(np.linalg.norm(x[:3]))) for x in xi_c],
                "camera_correction_m": [float(np.linalg.norm(x[3:])) * self.radius for x in xi_c],
                "projector_correction_deg": {p: math.degrees(float(np.linalg.norm(xi_p[k, :3])))
                                             for k, p in enumerate(self.proj_ids)},
                "projector_correction_m": {p: float(np.linalg.norm(xi_p[k, 3:])) * self.radius
                                           for k, p in enumerate(self.proj_ids)},
                "frames": self.frames,
                "cam_to_world": [T.tolist() for T in r["cam_to_world"]],
                "projectors": {p: {k: (v.tolist() if isinstance(v, np.ndarray) else
                                       [None if x is None else x.tolist() for x in v]) for k, v in e.items()}
                               for p, e in r["projectors"].items()},
            }
        if self.medium_on:
            bd, bb, binf = (x.detach().double().cpu().tolist() for x in self.medium_params())
            d["medium"] = {"beta_d": bd, "beta_b": bb, "b_inf": binf, "far": self.cfg.medium_far,
                           "note": "per RGB channel; beta in 1 / world unit"}
        if self.blur_on:
            k = self.blur_kernels().detach().double().cpu().numpy()
            d["blur"] = {"size": self.blur_n,
                         "kernels": {p: k[i].reshape(self.blur_n, self.blur_n).tolist()
                                     for i, p in enumerate(self.proj_ids)}}
        atomic_write_json(Path(out) / "rig.json", d)


def state_of(rig: Rig) -> dict:
    """The rig's learned tensors for a checkpoint."""
    return {k: v.detach().cpu() for k, v in rig.named_parameters()}


def load_into(rig: Rig, st: dict | None) -> None:
    if not st:
        return
    with torch.no_grad():
        for k, v in rig.named_parameters():
            if k in st and st[k].shape == v.shape:
                v.copy_(st[k].to(v.device))
