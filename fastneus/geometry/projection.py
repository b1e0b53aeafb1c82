"""Camera/projector geometry in torch: point projection, pattern sampling, pixel rays.

All functions work on any device and on float32 or float64 (the dtype of the point /
pixel tensors; matrices are converted to it). Conventions (docs/INTERNALS.md): integer
pixel (u, v) is centred at (u + 0.5, v + 0.5); pattern pixel (j, i) is centred at
(j + 0.5, i + 0.5), so a projected point (p_x, p_y) is sampled bilinearly at array
coordinates (p_x - 0.5, p_y - 0.5) with zeros outside the array.
"""
from __future__ import annotations

import numpy as np
import torch

Z_MIN = 1e-6  # points with projector depth <= Z_MIN are behind the projector: Q = 0


def _as(t, like: torch.Tensor) -> torch.Tensor:
    return torch.as_tensor(np.asarray(t) if not isinstance(t, torch.Tensor) else t,
                           dtype=like.dtype, device=like.device)


def project_points(points: torch.Tensor, K, world_to_proj) -> tuple[torch.Tensor, torch.Tensor]:
    """Project points through a pinhole (camera or projector).

    Args:
        points: [N, 3] points in the space ``world_to_proj`` maps from.
        K: [3, 3] intrinsics (tensor or array).
        world_to_proj: [4, 4] (or [3, 4]) rigid transform into the device's frame.

    Returns:
        px: [N, 2] continuous pixel coordinates (u, v) (pixel centres at +0.5);
            finite but meaningless where ``z <= 1e-6``.
        z: [N] depth along the optical axis.
    """
    K = _as(K, points)
    W = _as(world_to_proj, points)
    X = points @ W[:3, :3].T + W[:3, 3]
    z = X[:, 2]
    # keep the division finite behind the projector; callers mask with z > Z_MIN
    zs = torch.where(z.abs() > Z_MIN, z, torch.full_like(z, Z_MIN))
    xy = X[:, :2] / zs[:, None]
    px = xy @ K[:2, :2].T + K[:2, 2]
    return px, z


def sample_pattern(pattern: torch.Tensor, px: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
    """Bilinearly sample a pattern at projector pixel coordinates.

    Args:
        pattern: [H, W, 3] uint8 (or float in [0, 1]) pattern image, RGB.
        px: [N, 2] continuous pixel coords (p_x, p_y); pattern pixel (j, i) is centred at
            (j + 0.5, i + 0.5).
        valid: [N] bool, False where the point is behind the projector (z <= 1e-6);
            those samples are 0. None = all valid.

    Returns:
        [N, 3] float (px's dtype) in [0, 1]; neighbours outside the array count as 0.
    """
    H, W = pattern.shape[:2]
    scale = 1.0 / 255.0 if pattern.dtype == torch.uint8 else 1.0
    flat = pattern.reshape(H * W, -1)
    x = px[:, 0] - 0.5
    y = px[:, 1] - 0.5
    # clamp far-away coords so floor() stays an exact small integer
    x = x.clamp(-2.0, W + 1.0)
    y = y.clamp(-2.0, H + 1.0)
    x0 = torch.floor(x)
    y0 = torch.floor(y)
    fx = x - x0
    fy = y - y0
    x0 = x0.long()
    y0 = y0.long()
    # the 4 neighbours at once: one gather, one dtype conversion
    xs = torch.stack([x0, x0 + 1, x0, x0 + 1])  # [4, N]
    ys = torch.stack([y0, y0, y0 + 1, y0 + 1])
    w = torch.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy])
    inside = (xs >= 0) & (xs < W) & (ys >= 0) & (ys < H)
    idx = ys.clamp(0, H - 1) * W + xs.clamp(0, W - 1)
    val = flat[idx.reshape(-1)].reshape(4, -1, flat.shape[1]).to(px.dtype)
    out = ((w * inside)[:, :, None] * val).sum(dim=0)
    out = out * scale
    if valid is not None:
        out = out * valid.to(px.dtype)[:, None]
    return out


def pattern_at_points(points: torch.Tensor, K, world_to_proj, pattern: torch.Tensor) -> torch.Tensor:
    """Q(P): the pattern value a projector casts on each point ([N, 3] -> [N, 3] in [0, 1])."""
    px, z = project_points(points, K, world_to_proj)
    return sample_pattern(pattern, px, z > Z_MIN)


def unit_sphere_chord(o: torch.Tensor, d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Entry and exit distances of rays (unit d) through the unit sphere (entry >= 0; exit < entry = miss)."""
    b = (o * d).sum(-1)
    c = (o * o).sum(-1) - 1.0
    disc = (b * b - c).clamp_min(0).sqrt()
    return (-b - disc).clamp_min(0), -b + disc


def pixel_rays(K, cam_to_world, uv: torch.Tensor, S=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays through continuous pixel coordinates, in normalised space.

    Args:
        K: [3, 3] camera intrinsics.
        cam_to_world: [4, 4] camera pose.
        uv: [N, 2] continuous pixel coords; the centre of integer pixel (u, v) is
            (u + 0.5, v + 0.5), so the caller passes ``u + 0.5``.
        S: [4, 4] normalised->world transform ``[[s I, c], [0, 1]]`` (None = identity).

    Returns:
        origins: [N, 3] camera centre in normalised space.
        dirs: [N, 3] unit directions in normalised space (t is in normalised units).
    """
    K = _as(K, uv)
    T = _as(cam_to_world, uv)
    ones = torch.ones_like(uv[:, :1])
    d_cam = torch.linalg.solve(K, torch.cat([uv, ones], dim=1).T).T
    d = d_cam @ T[:3, :3].T
    d = d / d.norm(dim=1, keepdim=True)  # a uniform scale keeps directions; just normalise
    o = T[:3, 3]
    if S is not None:
        S = _as(S, uv)
        o = (o - S[:3, 3]) / S[0, 0]
    return o.expand(uv.shape[0], 3).clone(), d


def refract_rays(d: torch.Tensor, port_row) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays from a device centre through its flat port into the water (device frame).

    Args:
        d: [N, 3] unit directions in air (device frame).
        port_row: [8] (unit normal n, d0, glass thickness, n_air/n_glass, n_air/n_water, flag),
            ``fastneus.kernels.project.port_row``.
    Returns:
        origins [N, 3]: where each ray leaves the glass into the water (device frame, world units);
        dirs [N, 3]: unit directions in the water. Snell at both faces:
        ``t = eta (d - (n.d) n) + sqrt(1 - eta^2 |d - (n.d) n|^2) n``.
    """
    pr = _as(port_row, d)
    n, d0, tg, kg, kw = pr[0:3], pr[3], pr[4], pr[5], pr[6]

    def refract(v, eta):
        tang = v - (v @ n)[:, None] * n
        return eta * tang + torch.sqrt((1 - eta * eta * (tang * tang).sum(-1)).clamp_min(0))[:, None] * n

    a = d * (d0 / (d @ n).clamp_min(1e-9))[:, None]
    g = refract(d, kg)
    b = a + g * (tg / (g @ n).clamp_min(1e-9))[:, None]
    w = refract(g, kw / kg)
    return b, w / w.norm(dim=-1, keepdim=True)


def normalised_world_to_proj(world_to_proj, S) -> np.ndarray:
    """[3, 4] float64 map from normalised points to projector camera coordinates (W @ S)."""
    return (np.asarray(world_to_proj, dtype=np.float64) @ np.asarray(S, dtype=np.float64))[:3]
