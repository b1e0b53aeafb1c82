"""Which part of the volume the training cameras see.

Space that fewer than two cameras see cannot be triangulated: the photometric loss is
satisfied there by anything (a dark floater in front of a dark background, a shell
behind the object), so the occupancy grid never samples it and the exported mesh has
no surface in it. With a single viewpoint (one-shot) one camera is enough.
"""
from __future__ import annotations

import numpy as np
import torch



def _cell_centres(scene, resolution: int, device, dtype) -> tuple[torch.Tensor, float]:
    """World positions [R^3, 3] of the occupancy grid's cell centres (index x + y R + z R^2) and a
    cell's half-diagonal in world units."""
    r = int(resolution)
    lin = (torch.arange(r, dtype=dtype, device=device) + 0.5) * (2.0 / r) - 1.0
    z, y, x = torch.meshgrid(lin, lin, lin, indexing="ij")
    pts = torch.stack([x, y, z], -1).reshape(-1, 3)
    S = torch.as_tensor(scene.normalisation(), dtype=dtype, device=device)
    return pts @ S[:3, :3].T + S[:3, 3], float(scene.bounds.radius) * np.sqrt(3.0) / r


def _project(scene, i: int, world: torch.Tensor, half: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Frame ``i``'s pixel coordinates uv [N, 2] and depth z [N] of ``world`` points, and each point's
    projected ``half`` (a cell's half-diagonal) in pixels [N]."""
    cam = scene.frame_camera(i)
    dt, dev = world.dtype, world.device
    w2c = torch.as_tensor(scene.world_to_cam(i), dtype=dt, device=dev)
    K = torch.as_tensor(np.asarray(cam.K, dtype=np.float64), dtype=dt, device=dev)
    xc = world @ w2c[:3, :3].T + w2c[:3, 3]
    zc = xc[:, 2]
    uv = (xc @ K.T)[:, :2] / zc.clamp_min(1e-6)[:, None]
    kn = np.asarray(cam.K, dtype=np.float64)  # (no device sync for two numbers)
    return uv, zc, float(max(kn[0, 0], kn[1, 1])) * half / zc.clamp_min(1e-6)


def seen_cells(scene, frames: list[int], resolution: int, device, min_views: int = 2) -> torch.Tensor:
    """Cells of the [-1, 1]^3 occupancy grid inside the view frustums of at least ``min_views``
    distinct viewpoints (capped at the number of viewpoints), dilated by one cell.

    A cell counts as seen by a camera when its centre projects inside the image, widened by
    the cell's projected half-diagonal (conservative: a partly visible cell counts).

    Args:
        scene: a loaded :class:`fastneus.data.Scene`.
        frames: training frame indices; frames sharing a ``view`` count once.
        resolution: R, cells per axis (cell index x + y R + z R^2, as in ``OccupancyGrid``).
        device: where the result lives.
        min_views: distinct viewpoints required.
    Returns:
        [R^3] bool.
    """
    r = int(resolution)
    dev = torch.device(device)  # computed where it is used: R^3 x views float64 takes seconds on a host CPU
    world, half = _cell_centres(scene, r, dev, torch.float64)
    seen_views: dict[int, int] = {}
    for i in frames:
        seen_views.setdefault(scene.frames[i].view, i)
    count = torch.zeros(world.shape[0], dtype=torch.int32, device=dev)
    for i in seen_views.values():
        cam = scene.frame_camera(i)
        uv, zc, pad = _project(scene, i, world, half)
        inside = (zc > 1e-6) & (uv[:, 0] > -pad) & (uv[:, 0] < cam.width + pad) & (uv[:, 1] > -pad) & \
            (uv[:, 1] < cam.height + pad)
        count += inside.to(torch.int32)
    need = max(1, min(int(min_views), len(seen_views)))
    seen = (count >= need).reshape(1, 1, r, r, r).float()
    seen = torch.nn.functional.max_pool3d(seen, 3, stride=1, padding=1)  # one-cell dilation
    return seen.reshape(-1).bool().to(device)


def seen_fraction(mask: torch.Tensor) -> float:
    """Share of the grid's cells inside the unit sphere that are seen (for the run summary)."""
    r = round(mask.numel() ** (1 / 3))
    lin = (torch.arange(r, dtype=torch.float32) + 0.5) * (2.0 / r) - 1.0
    z, y, x = torch.meshgrid(lin, lin, lin, indexing="ij")
    inside = (x * x + y * y + z * z <= 1.0).reshape(-1).to(mask.device)
    return float((mask & inside).sum()) / max(1, int(inside.sum()))


def hull_cells(scene, frames: list[int], resolution: int, device, misses: int | None = None) -> torch.Tensor | None:
    """Cells of the [-1, 1]^3 occupancy grid inside the masks' visual hull, dilated by one cell.

    A cell is inside a view's mask when its centre projects within the cell's projected
    half-diagonal plus a pixel of a foreground pixel (mask >= 0.5): conservative, so a part one or
    two pixels wide, or a mask's anti-aliased edge, keeps its cells. A view says nothing about the
    cells that project outside its image or lie behind it, and an all-zero mask says nothing at all.
    A cell is in the hull when at most ``misses`` views put it outside their masks (a mask that
    misses a part in one view does not carve it from the volume).

    Args:
        scene: a loaded :class:`fastneus.data.Scene`.
        frames: training frame indices; frames sharing a ``view`` count once (the first one's mask).
        resolution: R, cells per axis (index x + y R + z R^2, as in ``OccupancyGrid``).
        device: where the result lives.
        misses: views allowed to disagree; None = a tenth of the masked views (at least 1 from
            3 views on, 0 below).
    Returns:
        [R^3] bool, or None when a view has no mask or no view has a non-empty one.
    """
    import cv2

    r = int(resolution)
    dev = torch.device(device)
    world, half = _cell_centres(scene, r, dev, torch.float32)
    views: dict[int, int] = {}
    for i in frames:
        views.setdefault(scene.frames[i].view, i)
    outside = torch.zeros(world.shape[0], dtype=torch.int32, device=dev)
    used = 0
    for i in views.values():
        m = scene.mask(i)
        if m is None:
            return None
        fg = m >= 0.5
        if not fg.any():
            continue
        used += 1
        # distance (px) from each pixel to the nearest foreground pixel
        dist = torch.from_numpy(cv2.distanceTransform((~fg).astype(np.uint8), cv2.DIST_L2, 5)).to(dev)
        uv, zc, pad = _project(scene, i, world, half)
        u, v = uv[:, 0].floor().long(), uv[:, 1].floor().long()
        h, w = dist.shape
        vis = (zc > 1e-6) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        d = torch.zeros_like(zc)
        d[vis] = dist[v[vis], u[vis]]
        outside += (vis & (d > pad + 1.0)).to(torch.int32)
    if used == 0:
        return None
    k = (0 if used < 3 else max(1, used // 10)) if misses is None else int(misses)
    hull = (outside <= k).reshape(1, 1, r, r, r).float()
    hull = torch.nn.functional.max_pool3d(hull, 3, stride=1, padding=1)  # one-cell dilation
    return hull.reshape(-1).bool()
