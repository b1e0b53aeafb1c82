"""SDF -> mesh in world units: chunked grid evaluation + scikit-image marching cubes."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import trimesh

from fastneus.errors import FastneusError
from fastneus.io import atomic_write


@torch.no_grad()
def sdf_grid(field, resolution: int, device, chunk: int = 2 ** 18, bound: str = "sphere",
             allowed: torch.Tensor | None = None) -> np.ndarray:
    """Evaluate the SDF on a regular grid over [-1, 1]^3.

    Outside the unit sphere (``bound='sphere'``) the field was never trained, so it is
    clamped to at least the distance to that sphere: no spurious surfaces in the corners.
    Likewise outside ``allowed`` ([R^3] bool cells of an occupancy-grid layout over [-1, 1]^3,
    e.g. the volume the training cameras see) the SDF is clamped to at least one cell size.

    Returns:
        [N, N, N] float32, indexed [x, y, z].
    """
    lin = torch.linspace(-1.0, 1.0, resolution, device=device)
    out = np.empty((resolution,) * 3, dtype=np.float32)
    yz = torch.stack(torch.meshgrid(lin, lin, indexing="ij"), -1).reshape(-1, 2)   # [N^2, 2]
    per = max(1, chunk // yz.shape[0])
    if allowed is not None:
        ar = round(allowed.numel() ** (1 / 3))
        allowed = allowed.reshape(-1).to(device)
    for a in range(0, resolution, per):
        xs = lin[a:a + per]
        pts = torch.cat([xs[:, None, None].expand(-1, yz.shape[0], 1), yz[None].expand(xs.shape[0], -1, -1)], -1)
        pts = pts.reshape(-1, 3)
        f = field.sdf(pts)
        if bound == "sphere":
            f = torch.maximum(f, pts.norm(dim=-1) - 1.0)
        if allowed is not None:
            c = ((pts + 1.0) * (0.5 * ar)).long().clamp_(0, ar - 1)
            ok = allowed[c[:, 0] + ar * (c[:, 1] + ar * c[:, 2])]
            f = torch.where(ok, f, f.clamp_min(2.0 / ar))
        out[a:a + per] = f.reshape(xs.shape[0], resolution, resolution).float().cpu().numpy()
    return out


def mesh_from_grid(sdf: np.ndarray, center, radius: float, keep_fraction: float = 0.02) -> trimesh.Trimesh:
    """Marching cubes at level 0 and the map to world units.

    Args:
        sdf: [N, N, N] grid over [-1, 1]^3 (normalised units).
        center, radius: the scene's normalisation (x_world = radius * x + center).
        keep_fraction: drop connected pieces with fewer faces than this fraction of the largest
            (floaters); 0 keeps everything.
    """
    from skimage.measure import marching_cubes

    n = sdf.shape[0]
    if not (sdf.min() < 0 < sdf.max()):
        return trimesh.Trimesh(vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), dtype=np.int64))
    verts, faces, normals, _ = marching_cubes(sdf, level=0.0, spacing=(2.0 / (n - 1),) * 3)
    verts = verts - 1.0
    # marching_cubes orients faces toward increasing values (outside); trimesh wants outward normals
    mesh = trimesh.Trimesh(vertices=verts * radius + np.asarray(center)[None], faces=faces[:, ::-1], process=True)
    if keep_fraction > 0 and len(mesh.faces):
        parts = mesh.split(only_watertight=False)
        if len(parts) > 1:
            big = max(len(p.faces) for p in parts)
            parts = [p for p in parts if len(p.faces) >= keep_fraction * big]
            mesh = trimesh.util.concatenate(parts)
    return mesh


def extract_mesh(field, scene, resolution: int, device, bound: str = "sphere",
                 allowed: torch.Tensor | None = None) -> trimesh.Trimesh:
    """The field's zero level set as a mesh in world units (only inside ``allowed`` cells, if given)."""
    grid = sdf_grid(field, resolution, device, bound=bound, allowed=allowed)
    return mesh_from_grid(grid, scene.bounds.center, float(scene.bounds.radius))


def save_mesh(mesh: trimesh.Trimesh, path: str | Path) -> Path:
    """Write PLY or OBJ (by suffix), atomically."""
    path = Path(path)
    if path.suffix.lower() not in (".ply", ".obj"):
        raise FastneusError("mesh output must end in .ply or .obj", field=str(path))
    atomic_write(path, lambda tmp: mesh.export(tmp, file_type=path.suffix[1:].lower()))
    return path
