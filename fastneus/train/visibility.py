"""Which part of the volume the training cameras see.

Space that fewer than two cameras see cannot be triangulated: the photometric loss is
satisfied there by anything (a dark floater in front of a dark background, a shell
behind the object), so the occupancy grid never samples it and the exported mesh has
no surface in it. With a single viewpoint (one-shot) one camera is enough.
"""
from __future__ import annotations

import numpy as np
import torch


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
    lin = (torch.arange(r, dtype=torch.float64, device=dev) + 0.5) * (2.0 / r) - 1.0
    z, y, x = torch.meshgrid(lin, lin, lin, indexing="ij")          # index x + y R + z R^2
    pts = torch.stack([x, y, z], -1).reshape(-1, 3)                  # [R^3, 3] normalised
    S = torch.as_tensor(scene.normalisation(), dtype=torch.float64, device=dev)
    world = pts @ S[:3, :3].T + S[:3, 3]
    half = float(scene.bounds.radius) * np.sqrt(3.0) / r           # cell half-diagonal (world)
    seen_views: dict[int, int] = {}
    for i in frames:
        seen_views.setdefault(scene.frames[i].view, i)
    count = torch.zeros(pts.shape[0], dtype=torch.int32, device=dev)
    for i in seen_views.values():
        cam = scene.frame_camera(i)
        w2c = torch.as_tensor(scene.world_to_cam(i), dtype=torch.float64, device=dev)
        K = torch.as_tensor(cam.K, dtype=torch.float64, device=dev)
        xc = world @ w2c[:3, :3].T + w2c[:3, 3]
        zc = xc[:, 2]
        front = zc > 1e-6
        uv = (xc @ K.T)[:, :2] / zc.clamp_min(1e-6)[:, None]
        kn = np.asarray(cam.K, dtype=np.float64)                          # (no device sync for two numbers)
        pad = float(max(kn[0, 0], kn[1, 1])) * half / zc.clamp_min(1e-6)
        inside = front & (uv[:, 0] > -pad) & (uv[:, 0] < cam.width + pad) & (uv[:, 1] > -pad) & \
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
