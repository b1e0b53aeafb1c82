"""Which part of the volume the training cameras see.

Space that fewer than two cameras see cannot be triangulated: the photometric loss is
satisfied there by anything (a dark floater in front of a dark background, a shell
behind the object), so the occupancy grid never samples it and the exported mesh has
no surface in it. With a single viewpoint (one-shot) one camera is enough.
"""
from __future__ import annotations

import math

import numpy as np
import torch


def dilate_cells(cells: torch.Tensor, m: int = 1) -> torch.Tensor:
    """[R^3] bool grid cells grown by ``m`` cells in every direction (a (2m+1)^3 max filter)."""
    r = round(cells.numel() ** (1 / 3))
    grown = torch.nn.functional.max_pool3d(cells.reshape(1, 1, r, r, r).float(), 2 * m + 1, stride=1, padding=m)
    return grown.reshape(-1).bool()


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
    return dilate_cells(count >= need).to(device)


def seen_fraction(mask: torch.Tensor) -> float:
    """Share of the grid's cells inside the unit sphere that are seen (for the run summary)."""
    r = round(mask.numel() ** (1 / 3))
    lin = (torch.arange(r, dtype=torch.float32) + 0.5) * (2.0 / r) - 1.0
    z, y, x = torch.meshgrid(lin, lin, lin, indexing="ij")
    inside = (x * x + y * y + z * z <= 1.0).reshape(-1).to(mask.device)
    return float((mask & inside).sum()) / max(1, int(inside.sum()))


def _hull_masks(scene, frames: list[int], given: dict[int, np.ndarray] | None = None
                ) -> list[tuple[int, np.ndarray]] | None:
    """(frame, foreground [H, W] bool) per viewpoint with a non-empty mask (frames sharing a
    ``view`` once: the first one's), or None when a view has no mask. ``given`` ({frame: foreground
    [H, W] bool}) stands in for the scene's masks (the photos' own: :func:`fastneus.train.rays.photo_masks`)."""
    views: dict[int, int] = {}
    for i in frames:
        views.setdefault(scene.frames[i].view, i)
    out = []
    for i in views.values():
        if given is not None:
            fg = given.get(i)
        else:
            m = scene.mask(i)
            fg = None if m is None else m >= 0.5
        if fg is None:
            return None
        if fg.any():
            out.append((i, fg))
    return out


def _hull_excess(scene, masks: list[tuple[int, np.ndarray]], world: torch.Tensor, half: float,
                 misses: int | None) -> torch.Tensor | None:
    """Per cell of the grid, how far (px) beyond its conservative pad it falls outside the masks of
    the view that disagrees most after the ``misses`` tolerated ones: [R^3] float (the (k+1)-th
    largest excess over the masked views, -inf where fewer views than that put it outside), or None
    when no view has a non-empty mask. ``excess <= e`` is the hull widened by ``e`` px, so several
    widths cost one pass over the views."""
    import cv2

    if not masks:
        return None
    dev = world.device
    used = len(masks)
    k = (0 if used < 3 else max(1, used // 10)) if misses is None else int(misses)
    if k >= used:
        return torch.full((world.shape[0],), -math.inf, device=dev)
    top = torch.full((k + 1, world.shape[0]), -math.inf, device=dev)  # the k+1 largest excesses, any order
    for i, fg in masks:
        # distance (px) from each pixel to the nearest foreground pixel
        dist = torch.from_numpy(cv2.distanceTransform((~fg).astype(np.uint8), cv2.DIST_L2, 5)).to(dev)
        uv, zc, pad = _project(scene, i, world, half)
        u, v = uv[:, 0].floor().long(), uv[:, 1].floor().long()
        h, w = dist.shape
        vis = (zc > 1e-6) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        # clamped gather + where instead of boolean indexing: ~2x faster on a host CPU
        d = dist.reshape(-1)[v.clamp(0, h - 1) * w + u.clamp(0, w - 1)]
        ex = torch.where(vis, d - pad - 1.0, torch.full_like(d, -math.inf))
        top = torch.topk(torch.cat([top, ex[None]]), k + 1, dim=0).values if k > 0 else torch.maximum(top, ex[None])
    return top.min(0).values


def hull_cells(scene, frames: list[int], resolution: int, device, misses: int | None = None,
               extra_pad: float = 0.0) -> torch.Tensor | None:
    """Cells of the [-1, 1]^3 occupancy grid inside the masks' visual hull, dilated by one cell.

    A cell is inside a view's mask when its centre projects within the cell's projected
    half-diagonal plus a pixel (plus ``extra_pad`` px) of a foreground pixel (mask >= 0.5):
    conservative, so a part one or two pixels wide, or a mask's anti-aliased edge, keeps its
    cells. A view says nothing about the cells that project outside its image or lie behind it,
    and an all-zero mask says nothing at all. A cell is in the hull when at most ``misses`` views
    put it outside their masks (a mask that misses a part in one view does not carve it from the
    volume).

    Args:
        scene: a loaded :class:`fastneus.data.Scene`.
        frames: training frame indices; frames sharing a ``view`` count once (the first one's mask).
        resolution: R, cells per axis (index x + y R + z R^2, as in ``OccupancyGrid``).
        device: where the result lives.
        misses: views allowed to disagree; None = a tenth of the masked views (at least 1 from
            3 views on, 0 below).
        extra_pad: px added to every cell's pad (a calibration that is off: :func:`consistent_hull`).
    Returns:
        [R^3] bool, or None when a view has no mask or no view has a non-empty one.
    """
    masks = _hull_masks(scene, frames)
    if masks is None:
        return None
    excess = _hull_excess(scene, masks, *_cell_centres(scene, int(resolution), torch.device(device), torch.float32),
                          misses)
    return None if excess is None else dilate_cells(excess <= float(extra_pad))


def hull_uncovered(scene, frames: list[int], hull: torch.Tensor) -> list[float]:
    """Share of each masked view's foreground pixels that no hull cell projects onto (a cell
    covering about its projected half side): 0 wherever the poses and the masks agree, since the
    object itself lies in the hull (dilated by a cell). Views with an empty or no mask are left out.

    Args:
        scene, frames: as :func:`hull_cells`. hull: [R^3] bool (:func:`hull_cells`).
    Returns:
        One share in [0, 1] per masked view (frames sharing a ``view`` once).
    """
    masks = _hull_masks(scene, frames)
    if masks is None:
        return []
    return _uncovered(scene, masks, hull, *_cell_centres(scene, round(hull.numel() ** (1 / 3)), hull.device,
                                                         torch.float32))


def _uncovered(scene, masks: list[tuple[int, np.ndarray]], hull: torch.Tensor, world: torch.Tensor,
               half: float) -> list[float]:
    """:func:`hull_uncovered` on loaded masks and the grid's cell centres ``world`` [R^3, 3]."""
    import cv2

    world = world[hull]
    out = []
    for i, fg in masks:
        h, w = fg.shape
        uv, zc, pad = _project(scene, i, world, half)
        u, v = uv[:, 0].floor().long(), uv[:, 1].floor().long()
        ok = (zc > 1e-6) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        hit = np.zeros((h, w), np.uint8)
        hit[v[ok].cpu().numpy(), u[ok].cpu().numpy()] = 1
        # a cell's footprint: about its projected half side (0.6 of the half-diagonal), not the hull's
        # generous pad, or a hull that misses part of the object still covers the masks by its margin
        rad = int(round(0.6 * float(pad[ok].median()))) if bool(ok.any()) else 0
        covered = cv2.dilate(hit, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * rad + 1, 2 * rad + 1))) > 0
        out.append(float((fg & ~covered).sum()) / float(fg.sum()))
    return out


HULL_PADS = (0.0, 2.0, 4.0, 8.0, 16.0)  # px tried in turn by consistent_hull
HULL_TOLERANCE = 0.002  # share of a view's mask pixels the hull may leave uncovered


def consistent_hull(scene, frames: list[int], resolution: int, device, pads=HULL_PADS,
                    tol: float = HULL_TOLERANCE, masks: dict[int, np.ndarray] | None = None
                    ) -> tuple[torch.Tensor | None, float, float]:
    """The tightest hull of :func:`hull_cells` (widened by each of ``pads`` px in turn) that covers
    every masked view's foreground (:func:`hull_uncovered` at most ``tol`` in every view).

    With exact poses the first one does (the object is inside it). A calibration that is off (a
    degree and 2 cm at 4 m is 2-4 px at 128-200 px) or a mask with a blob the others do not share
    leaves foreground pixels that no hull cell projects onto: the hull built from them would carve
    the object (toy, ant: 1.7-16 % of the true surface outside the plain hull at 1 deg / 2 cm, none
    once it covers the masks), so it is widened until it covers them, and dropped when even the
    widest does not.

    Args:
        masks: {frame: foreground [H, W] bool} in place of the scene's masks (e.g. the photos'
            non-background pixels without masks: :func:`fastneus.train.rays.photo_masks`).
    Returns:
        (hull [R^3] bool or None, the extra pad used (px), the worst view's uncovered share at it).
    """
    masks = _hull_masks(scene, frames, masks)
    if masks is None:
        return None, 0.0, 0.0
    world, half = _cell_centres(scene, int(resolution), torch.device(device), torch.float32)  # once for every width
    excess = _hull_excess(scene, masks, world, half, None)
    if excess is None:
        return None, 0.0, 0.0
    worst = 0.0
    for e in pads:
        hull = dilate_cells(excess <= float(e))
        worst = max(_uncovered(scene, masks, hull, world, half) or [0.0])
        if worst <= tol:
            return hull, float(e), worst
    return None, float(pads[-1]), worst
