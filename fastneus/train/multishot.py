"""Multi-shot training: every pattern shown at one viewpoint trains through one ray per pixel.

A multi-shot capture (e.g. 20 Gray-code patterns per viewpoint) photographs the same pixels
under several patterns from one camera pose. :class:`ShotBank` groups the training frames by
viewpoint: a sampled ray is a (view, pixel) pair carrying the colours of ``shots`` of its
shots, so one march and one field evaluation serve all of them and only the pattern term is
rendered per shot (``fastneus.field.renderer.render_rays`` with a [B, K] frame index).

Memory is flat in the number of patterns apart from the photos themselves, kept once as uint8
([view pixels, shots, 3], 3 bytes per pixel and shot): the brightness distribution, background
flags and masks are per view pixel, and nothing is copied to float per shot. Patterns are the
shared uint8 :class:`fastneus.kernels.render.PatternStore`.
"""
from __future__ import annotations

import numpy as np
import torch

from fastneus.errors import FastneusError
from fastneus.train.rays import RayBank, background_codes, draw_pixels, lut_mean, normalised_camera, pixel_fields


def group_views(scene, frames: list[int]) -> list[list[int]]:
    """Positions in ``frames`` grouped by viewpoint (first-seen order), e.g. [[0..19], [20..39]].

    Raises:
        FastneusError: frames sharing a view id but not the camera or its pose.
    """
    groups: dict[int, list[int]] = {}
    for a, i in enumerate(frames):
        groups.setdefault(scene.frames[i].view, []).append(a)
    for g in groups.values():
        f0 = scene.frames[frames[g[0]]]
        for a in g[1:]:
            f = scene.frames[frames[a]]
            if f.camera != f0.camera or not np.allclose(f.cam_to_world, f0.cam_to_world, atol=1e-6):
                raise FastneusError(f"frames {frames[g[0]]} and {frames[a]} share view {f0.view} but not the "
                                    "camera pose; give them different view ids", field=f"frames[{frames[a]}].view")
    return list(groups.values())


def is_multishot(scene, frames: list[int]) -> bool:
    """True when some viewpoint of ``frames`` has more than one frame (shot)."""
    views = [scene.frames[i].view for i in frames]
    return len(set(views)) < len(views)


class ShotBank:
    """Training pixels grouped by viewpoint, each with the colours of all its shots (uint8).

    Same interface as :class:`fastneus.train.rays.RayBank` for the trainer (``sample``,
    ``mean_rgb``, ``bg_fraction``, ``has_masks``), but ``sample`` returns per ray a [n, k]
    frame index and [n, k, 3] colours.

    Args:
        scene: a loaded scene; frames: training frame indices (into ``scene.frames``).
        device: where the store lives.
        shots: shots per ray and step: 0 or >= the most shots of a view = all of them, in order
            (views with fewer shots repeat theirs cyclically); else that many drawn per ray at random.
        load_masks, brightness_cdf, background, bg_tolerance, lut: as for ``RayBank`` (the fixed
            tolerance: multi-shot captures project onto a lit scene, never a dark room; no
            foreground flags, the trainer thresholds each batch); a pixel is
            background when it is in every shot, its brightness is its brightest shot's, its mask
            is the first shot's.
    """

    def __init__(self, scene, frames: list[int], device, shots: int = 0, load_masks: bool = False,
                 brightness_cdf: bool = False, background: float | None = None, bg_tolerance: float = 2.0 / 255,
                 lut=None):
        self.frames = list(frames)
        self.device = torch.device(device)
        self.lut = None if lut is None else torch.as_tensor(lut, dtype=torch.float32, device=self.device)  # [256]
        hist = torch.zeros(3, 256, dtype=torch.int64) if lut is not None else None  # code histograms (mean)
        self.fg = None
        bg_code = background_codes(self.lut.cpu(), background, bg_tolerance) if lut is not None and \
            background is not None else None
        self.port = None  # rays in air only (make_bank sends ported cameras to RayBank)
        self.groups = group_views(scene, self.frames)
        V = len(self.groups)
        kmax = max(len(g) for g in self.groups)
        self.k = kmax if shots <= 0 or shots >= kmax else int(shots)
        self.all_shots = self.k == kmax
        sizes, kinv, rot, org = [], [], [], []
        for g in self.groups:
            cam = scene.frame_camera(self.frames[g[0]])
            sizes.append((cam.width, cam.height))
            ki, r, o = normalised_camera(scene, self.frames[g[0]])
            kinv.append(ki)
            rot.append(r)
            org.append(o)
        wh = torch.tensor(sizes, dtype=torch.int64)
        npx = (wh[:, 0] * wh[:, 1])
        self.n_pixels = int(npx.sum())
        offset = torch.cat([torch.zeros(1, dtype=torch.int64), torch.cumsum(npx, 0)[:-1]])
        # the photos: one uint8 block, filled frame by frame (no float copy, no per-shot list)
        rgb = torch.empty((self.n_pixels, kmax, 3), dtype=torch.uint8)
        total = torch.zeros(3, dtype=torch.float64)
        bright = torch.zeros(self.n_pixels, dtype=torch.uint8) if brightness_cdf else None
        bg = torch.ones(self.n_pixels, dtype=torch.bool) if background is not None else None
        bgv, tol = int(round(255 * (background or 0.0))), int(round(255 * bg_tolerance))
        masks = []
        for v, g in enumerate(self.groups):
            o, n = int(offset[v]), int(npx[v])
            for j in range(kmax):
                i = self.frames[g[j % len(g)]]
                if j < len(g):
                    img = torch.from_numpy(np.ascontiguousarray(scene.image(i).reshape(-1, 3)))
                    if img.shape[0] != n:
                        raise FastneusError(f"frame {i} is not the size of its view's camera", field=f"frames[{i}]")
                    rgb[o:o + n, j] = img
                    total += img.sum(0, dtype=torch.float64)
                    if hist is not None:
                        hist += torch.stack([torch.bincount(img[:, c].long(), minlength=256) for c in range(3)])
                    if bright is not None:
                        bright[o:o + n] = torch.maximum(bright[o:o + n], img.amax(1))
                    if bg is not None and bg_code is not None:  # linear background and tolerance
                        bg[o:o + n] &= bg_code[img.long()].all(1)
                    elif bg is not None:
                        bg[o:o + n] &= (img.to(torch.int16) - bgv).abs().amax(1) <= tol
                else:
                    rgb[o:o + n, j] = rgb[o:o + n, j % len(g)]
            if load_masks:
                m = scene.mask(self.frames[g[0]])
                masks.append(None if m is None else torch.from_numpy((np.clip(m, 0, 1) * 255).astype(np.uint8).reshape(-1)))
        n_real = sum(len(g) * int(npx[v]) for v, g in enumerate(self.groups))  # real (not repeated) shots
        self._mean = (total / (255.0 * n_real)).float() if hist is None else lut_mean(hist, self.lut, n_real)
        self.rgb = rgb.to(self.device)                                           # [N, kmax, 3] uint8
        self.has_masks = load_masks and all(m is not None for m in masks)
        self.mask = torch.cat(masks).to(self.device) if self.has_masks else None  # [N] uint8
        self.mask_core = None  # [N] bool, the masks' core (the trainer sets it: rays.mask_core), or None
        self.bg = bg.to(self.device) if bg is not None else None                  # [N] bool
        self.bg_fraction = float(bg.float().mean()) if bg is not None else 0.0
        # brightness-proportional pixel distribution over view pixels (not shots): flat in patterns
        self.cdf = torch.cumsum(bright.double() / 255.0 + 1e-3, 0).to(self.device) if bright is not None else None
        f32 = dict(dtype=torch.float32, device=self.device)
        self.wh = wh.to(self.device)                                              # [V, 2]
        self.offset = offset.to(self.device)                                      # [V]
        self.kinv = torch.tensor(np.stack(kinv), **f32)                          # [V, 3, 3]
        self.rot = torch.tensor(np.stack(rot), **f32)                            # [V, 3, 3]
        self.origin = torch.tensor(np.stack(org), **f32)                         # [V, 3]
        rows = torch.tensor([[g[j % len(g)] for j in range(kmax)] for g in self.groups], dtype=torch.int32)
        self.shot_row = rows.to(self.device)                                      # [V, kmax] row of proj
        self.n_shots = torch.tensor([len(g) for g in self.groups], dtype=torch.int64, device=self.device)  # [V]
        self.n_views = V

    def mean_rgb(self) -> torch.Tensor:
        """[3] mean colour of every stored photo in [0, 1] (for the colour network's bias)."""
        return self._mean

    def store_bytes(self) -> int:
        """Bytes of the photo store."""
        return self.rgb.numel() * self.rgb.element_size()

    rays = RayBank.rays  # (view index, u, v) -> origins, dirs: the same maths, indexed per view

    def sample(self, n: int, generator: torch.Generator | None = None, bright_fraction: float = 0.0,
               blur: float = 0.0, sub: int = 1):
        """``n`` random (view, pixel) rays, each with ``self.k`` of its shots.

        Returns:
            dict: fidx [n, k] int32 (rows of the projection table = positions in ``frames``),
            origins [n, 3], dirs [n, 3], rgb [n, k, 3] float in [0, 1] (linear), sat [n, k, 3] bool
            (saturated photo channels), mask [n] (if masks),
            bg [n] (if ``background``), pix [n] int64 flat view-pixel index. ``blur``/``sub`` (the
            camera's defocus as several rays per pixel) are for one-shot-per-ray banks only; the
            trainer refuses them here.
        """
        g = generator
        flat, view, col, row = draw_pixels(self, n, g, bright_fraction)
        o, d = self.rays(view, col.float() + 0.5, row.float() + 0.5)
        if self.all_shots:
            slot = torch.arange(self.k, device=self.device).expand(n, self.k)
        else:  # k distinct-in-expectation shots among the view's own
            u = torch.rand(n, self.k, device=self.device, generator=g)
            slot = (u * self.n_shots[view][:, None]).long().clamp_max(self.rgb.shape[1] - 1)
        return {"fidx": self.shot_row[view[:, None], slot], "origins": o, "dirs": d,
                **pixel_fields(self, flat, self.rgb[flat[:, None], slot])}


def make_bank(scene, frames: list[int], device, cfg, refraction: bool = True, **kw):
    """The trainer's pixel store: a :class:`ShotBank` when a viewpoint has several shots (and
    ``cfg.rays.group_shots``), else a :class:`RayBank` (one ray per frame pixel). Cameras behind a
    flat port (``refraction``) take the RayBank, which casts refracted rays, and so does pose
    refinement (its corrections index the bank's per-frame camera tables)."""
    ported = refraction and any(scene.frame_camera(i).port is not None for i in frames)
    if cfg.rays.group_shots and not ported and not cfg.rig.pose_refine and is_multishot(scene, frames):
        single_view_only = ("bg_noise_k", "bg_cap", "fg_relative")  # RayBank's noise floor and foreground flags
        return ShotBank(scene, frames, device, shots=cfg.rays.shots_per_ray,
                        **{k: v for k, v in kw.items() if k not in single_view_only})
    return RayBank(scene, frames, device, refraction=refraction, **kw)
