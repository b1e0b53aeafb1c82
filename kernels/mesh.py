"""Marching cubes on a listed set of grid cells: Warp's sparse extractor and a scikit-image twin.

Both ops triangulate the level 0 of a scalar grid, but only in the cells they are given
(``cells``), so a caller that evaluated the field only near the surface passes the cells it
evaluated. Contract (both):

- ``grid[i, j, k]`` is the value at ``origin + spacing * (i, j, k)`` (x, y, z), one value per
  node; the cell ``(i, j, k)`` spans nodes ``(i..i+1, j..j+1, k..k+1)``.
- A vertex lies on every cell edge whose end values straddle 0 (one ``< 0``, one ``>= 0``),
  linearly interpolated; vertices are shared between the cells of an edge (a closed surface
  comes out watertight).
- Faces are wound counter-clockwise seen from the positive side: with an SDF (negative
  inside), normals point outward and a closed surface has positive signed volume.

The Warp op uses ``warp.geometry.sparse_marching_cubes_from_cells`` (the classic Lorensen
case table; vertices de-duplicated by a radix sort of corner codes) and runs wherever Warp
runs (CUDA, and the CPU on one core). The twin is scikit-image's Lewiner marching cubes on the
cells' bounding box, masked to the listed cells. Both place the same vertices (one per
crossed edge, same interpolation); triangulations differ only in ambiguous cells (Lewiner
resolves face saddles, the classic table does not), so face counts agree to a few per cent.
"""
from __future__ import annotations

import sys

import numpy as np
import torch
import warp as wp
import warp.geometry  # noqa: F401 (wp.geometry is a lazily imported subpackage)

from . import _warp

# corner c of a cell is at subscript (i, j, k) + _CORNERS[c] (Warp's CUBE_CORNER_OFFSETS order)
_CORNERS = ((0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1))


def warp_modules() -> list:
    """The Warp modules (``warp.Module``) of the kernels this op launches, for ``load_modules``.

    Found from the kernels defined next to ``sparse_marching_cubes_from_cells`` (Warp names
    that module ``warp.geometry.sparse_marching_cubes``, not after its Python module).
    """
    pm = sys.modules[wp.geometry.sparse_marching_cubes_from_cells.__module__]
    mods = {id(k.module): k.module for k in vars(pm).values() if isinstance(k, wp.Kernel)}
    return list(mods.values())


def _check(grid: torch.Tensor, cells: torch.Tensor, spacing: float) -> None:
    if grid.dim() != 3 or min(grid.shape) < 2:
        raise ValueError(f"grid must be [Nx, Ny, Nz] with N >= 2 per axis, got {tuple(grid.shape)}")
    if grid.dtype != torch.float32:
        raise ValueError(f"grid must be float32, got {grid.dtype}")
    if cells.dim() != 2 or cells.shape[1] != 3 or cells.dtype not in (torch.int32, torch.int64):
        raise ValueError(f"cells must be [C, 3] int32/int64, got {tuple(cells.shape)} {cells.dtype}")
    if not spacing > 0:
        raise ValueError(f"spacing must be positive, got {spacing}")
    if cells.numel():
        lo, hi = cells.min(0).values, cells.max(0).values
        top = torch.tensor(grid.shape, device=cells.device) - 2
        if bool((lo < 0).any()) or bool((hi > top).any()):
            raise ValueError(f"cells out of range: subscripts must lie in [0, N-2] per axis, grid {tuple(grid.shape)}")


def _empty(device) -> tuple[torch.Tensor, torch.Tensor]:
    return (torch.zeros(0, 3, dtype=torch.float32, device=device),
            torch.zeros(0, 3, dtype=torch.int64, device=device))


def corner_values(grid: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
    """The 8 corner values of each cell, in Warp's corner order.

    Args:
        grid: torch.Tensor  # [Nx, Ny, Nz] float32
        cells: torch.Tensor  # [C, 3] int32/int64 cell subscripts (minimum corner)
    Returns:
        [C, 8] float32.
    """
    c = cells.long()
    ny, nz = grid.shape[1], grid.shape[2]
    base = (c[:, 0] * ny + c[:, 1]) * nz + c[:, 2]                                     # [C]
    offs = torch.tensor([(a * ny + b) * nz + d for a, b, d in _CORNERS], device=grid.device)  # [8]
    return grid.reshape(-1)[base[:, None] + offs[None, :]]


def marching_cubes(grid: torch.Tensor, cells: torch.Tensor, origin: float = -1.0,
                   spacing: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Level-0 surface of ``grid`` inside ``cells`` (Warp sparse marching cubes).

    Args:
        grid: torch.Tensor  # [Nx, Ny, Nz] float32, cpu or cuda
        cells: torch.Tensor  # [C, 3] int32/int64 unique cell subscripts in [0, N-2]
        origin: position of node (0, 0, 0) on every axis.
        spacing: node spacing (> 0).
    Returns:
        (vertices [V, 3] float32, faces [F, 3] int64), on ``grid``'s device; faces wound so
        that normals point towards increasing values.
    """
    _check(grid, cells, spacing)
    if cells.shape[0] == 0:
        return _empty(grid.device)
    cv = corner_values(grid, cells).contiguous()                                       # [C, 8]
    ci = cells.to(device=grid.device, dtype=torch.int32).contiguous()                  # [C, 3]
    _warp.init()
    dev = _warp.device_of(grid)
    with wp.ScopedStream(_warp.stream_of(grid)):  # torch's stream (None on the CPU: no-op)
        verts, idx = wp.geometry.sparse_marching_cubes_from_cells(
            wp.from_torch(ci, dtype=wp.vec3i), wp.from_torch(cv), origin=(float(origin),) * 3,
            cell_width=float(spacing), threshold=0.0, device=dev)
    if verts.shape[0] == 0 or idx.shape[0] == 0:
        return _empty(grid.device)
    v = wp.to_torch(verts).reshape(-1, 3).clone()
    f = wp.to_torch(idx).reshape(-1, 3).long()
    return v, f


def marching_cubes_torch(grid: torch.Tensor, cells: torch.Tensor, origin: float = -1.0,
                         spacing: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Twin of :func:`marching_cubes`: scikit-image (Lewiner) on the cells' bounding box, on the CPU.

    Same arguments and returns. The grid is copied to host memory (only the bounding box).
    """
    from skimage.measure import marching_cubes as sk_marching_cubes

    _check(grid, cells, spacing)
    if cells.shape[0] == 0:
        return _empty(grid.device)
    c = cells.long().cpu()
    lo = c.min(0).values                                                               # [3]
    hi = c.max(0).values + 2                                                           # exclusive node bound
    sub = grid[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]].detach().cpu().numpy()
    if not (sub.min() < 0.0 <= sub.max()):
        return _empty(grid.device)
    # skimage processes the cell whose *upper* corner is marked: cell (i, j, k) <-> mask[i+1, j+1, k+1]
    mask = np.zeros(sub.shape, dtype=bool)
    rel = (c - lo + 1).numpy()
    mask[rel[:, 0], rel[:, 1], rel[:, 2]] = True
    try:
        verts, faces, _, _ = sk_marching_cubes(sub, level=0.0, spacing=(float(spacing),) * 3, mask=mask)
    except (ValueError, RuntimeError) as e:  # "No surface found at the given iso value."
        if "surface" in str(e).lower():
            return _empty(grid.device)
        raise
    verts = verts.astype(np.float32) + (lo.numpy().astype(np.float64) * spacing + origin).astype(np.float32)
    return (torch.from_numpy(np.ascontiguousarray(verts)).to(grid.device),
            torch.from_numpy(faces.astype(np.int64)).to(grid.device))
