"""SDF -> mesh in world units: the field evaluated only near its zero level, marching cubes, PLY.

Pipeline of :func:`extract_mesh_arrays` (the fast path; ``extract_mesh`` wraps it in a trimesh):

1. Coarse pass: the SDF at the centre of every block of ``block^3`` cells of the
   ``resolution^3`` node grid over [-1, 1]^3. A block whose centre value exceeds
   ``lipschitz`` x its half-diagonal in magnitude cannot hold the zero level (for an SDF whose
   gradient stays below ``lipschitz``); neither can a block wholly outside ``allowed``
   (the SDF is lifted above zero there).
2. Fine pass: the SDF at the nodes of the other ("active") blocks, each node once. An active
   block whose boundary nodes have the opposite sign of an inactive neighbour's centre (the
   surface runs on, the bound was too tight there) activates that neighbour; repeat.
3. Marching cubes on the cells of active blocks that change sign: Warp's sparse extractor
   on CUDA (``fastneus.kernels.mesh``), scikit-image on the CPU (same vertices).
4. Map to world units, drop small connected pieces (floaters), write PLY without trimesh.

The clamps are those of :func:`sdf_grid` (the dense reference): outside the unit sphere
(``bound='sphere'``) the value is at least the distance to the sphere, outside ``allowed``
at least one occupancy cell. Faces are wound counter-clockwise seen from outside
(outward normals, positive volume for a closed surface).
"""
from __future__ import annotations

import dataclasses

import math
import time
from dataclasses import dataclass, field as dc_field
from pathlib import Path

import numpy as np
import torch

from fastneus.data.response import encode
from fastneus.errors import FastneusError
from fastneus.io import atomic_write

MC_METHODS = ("auto", "warp", "skimage")


# ----------------------------------------------------------------------------- checks and shared maths
def _check(resolution, bound: str, allowed, block: int = 4, lipschitz: float = 2.0, mc: str = "auto") -> int:
    """Validate the extraction arguments; returns the allowed-mask resolution (0 if none)."""
    if isinstance(resolution, bool) or not isinstance(resolution, (int, np.integer)) or not 2 <= resolution <= 4096:
        raise FastneusError(f"mesh resolution must be an integer in 2..4096, got {resolution!r}",
                            field="mesh_resolution")
    if bound not in ("sphere", "box"):
        raise FastneusError(f"unknown bound {bound!r}; use sphere or box", field="bound")
    if isinstance(block, bool) or not isinstance(block, (int, np.integer)) or block < 1:
        raise FastneusError(f"block must be a positive integer, got {block!r}", field="block")
    if not (isinstance(lipschitz, (int, float)) and math.isfinite(lipschitz) and lipschitz > 0):
        raise FastneusError(f"lipschitz must be a positive number, got {lipschitz!r}", field="lipschitz")
    if mc not in MC_METHODS:
        raise FastneusError(f"unknown marching-cubes method {mc!r}; use one of {', '.join(MC_METHODS)}", field="mc")
    if allowed is None:
        return 0
    ar = round(allowed.numel() ** (1 / 3))
    if allowed.dtype != torch.bool or ar < 1 or ar ** 3 != allowed.numel():
        raise FastneusError(f"allowed must be a bool mask of R^3 cells, got {tuple(allowed.shape)} {allowed.dtype}",
                            field="allowed")
    return ar


def _clamped_sdf(field, pts: torch.Tensor, bound: str, allowed: torch.Tensor | None, ar: int) -> torch.Tensor:
    """``field.sdf`` with the export clamps. pts: [M, 3] normalised -> [M] float32."""
    f = field.sdf(pts).float()
    if f.shape != pts.shape[:1]:
        raise FastneusError(f"field.sdf returned shape {tuple(f.shape)} for {pts.shape[0]} points; expected [N]",
                            field="field")
    if bound == "sphere":
        f = torch.maximum(f, pts.norm(dim=-1) - 1.0)
    if allowed is not None:
        c = ((pts + 1.0) * (0.5 * ar)).long().clamp_(0, ar - 1)
        ok = allowed[c[:, 0] + ar * (c[:, 1] + ar * c[:, 2])]
        f = torch.where(ok, f, f.clamp_min(2.0 / ar))
    return f


def _sync(device) -> None:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


# ----------------------------------------------------------------------------- dense reference
@torch.no_grad()
def sdf_grid(field, resolution: int, device, chunk: int = 2 ** 18, bound: str = "sphere",
             allowed: torch.Tensor | None = None) -> np.ndarray:
    """Evaluate the SDF on every node of a regular grid over [-1, 1]^3 (the dense reference).

    Outside the unit sphere (``bound='sphere'``) the field was never trained, so it is
    clamped to at least the distance to that sphere: no spurious surfaces in the corners.
    Likewise outside ``allowed`` ([R^3] bool cells of an occupancy-grid layout over [-1, 1]^3,
    index x + R y + R^2 z, e.g. the volume the training cameras see) the SDF is clamped to at
    least one cell size.

    Returns:
        [N, N, N] float32, indexed [x, y, z].
    """
    ar = _check(resolution, bound, allowed)
    lin = torch.linspace(-1.0, 1.0, resolution, device=device)
    out = np.empty((resolution,) * 3, dtype=np.float32)
    yz = torch.stack(torch.meshgrid(lin, lin, indexing="ij"), -1).reshape(-1, 2)   # [N^2, 2]
    per = max(1, chunk // yz.shape[0])
    if allowed is not None:
        allowed = allowed.reshape(-1).to(device)
    for a in range(0, resolution, per):
        xs = lin[a:a + per]
        pts = torch.cat([xs[:, None, None].expand(-1, yz.shape[0], 1), yz[None].expand(xs.shape[0], -1, -1)], -1)
        f = _clamped_sdf(field, pts.reshape(-1, 3), bound, allowed, ar)
        out[a:a + per] = f.reshape(xs.shape[0], resolution, resolution).cpu().numpy()
    return out


# ----------------------------------------------------------------------------- sparse evaluation
@dataclass
class SparseSDF:
    """The SDF on the nodes of the active blocks of an N^3 grid over [-1, 1]^3.

    Attributes:
        grid: [N, N, N] float32 on the device; exact at the nodes of active blocks, a positive
            placeholder elsewhere.
        active: [nb, nb, nb] bool, the blocks evaluated at full resolution.
        block: cells per block edge.
        stats: evaluated points, blocks, rounds.
    """
    grid: torch.Tensor
    active: torch.Tensor
    block: int
    stats: dict = dc_field(default_factory=dict)

    @property
    def resolution(self) -> int:
        return int(self.grid.shape[0])


def _allowed_prefix(allowed: torch.Tensor, ar: int) -> torch.Tensor:
    """3-D prefix sums of the allowed mask.

    Args:
        allowed: [R^3] bool, index x + R y + R^2 z.
    Returns:
        [R+1, R+1, R+1] int32 indexed [x, y, z]; s[i, j, k] counts allowed cells below (i, j, k).
    """
    a = allowed.reshape(ar, ar, ar).permute(2, 1, 0).to(torch.int32)
    s = torch.zeros(ar + 1, ar + 1, ar + 1, dtype=torch.int32, device=a.device)
    s[1:, 1:, 1:] = a.cumsum(0).cumsum(1).cumsum(2)
    return s


def _allowed_in_boxes(s: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> tuple:
    """Whether any / all occupancy cells of each box are allowed.

    Args:
        s: prefix sums from :func:`_allowed_prefix`.
        lo, hi: [K, 3] long, first and last occupancy cell of each box per axis (inclusive).
    Returns:
        (any_ok [K] bool, all_ok [K] bool).
    """
    x0, y0, z0 = lo.unbind(1)
    x1, y1, z1 = (hi + 1).unbind(1)
    cnt = (s[x1, y1, z1] - s[x0, y1, z1] - s[x1, y0, z1] - s[x1, y1, z0]
           + s[x0, y0, z1] + s[x0, y1, z0] + s[x1, y0, z0] - s[x0, y0, z0])
    return cnt > 0, cnt == (x1 - x0) * (y1 - y0) * (z1 - z0)


def _block_node_ids(blocks: torch.Tensor, block: int, n: int) -> torch.Tensor:
    """Linear node ids (x n^2 + y n + z) of blocks. blocks: [K, 3] long -> [K, b+1, b+1, b+1] long."""
    r = torch.arange(block + 1, device=blocks.device)
    idx = (blocks[:, :, None] * block + r[None, None, :]).clamp_(max=n - 1)             # [K, 3, b+1]
    return ((idx[:, 0, :, None, None] * n + idx[:, 1, None, :, None]) * n + idx[:, 2, None, None, :])


def _spill(grid: torch.Tensor, done: torch.Tensor, active: torch.Tensor, sign: torch.Tensor, block: int,
           per: int) -> torch.Tensor:
    """Inactive blocks that the surface runs into: an evaluated node of theirs has the other sign.

    The nodes of an inactive block that were evaluated are those it shares with active
    blocks; the coarse pass gave the block one sign, so a node of the other sign means the
    zero level enters it (the SDF is steeper there than ``lipschitz`` assumed).

    Args:
        grid, done: [N^3] node values and whether evaluated.
        active: [nb, nb, nb] bool; sign: [nb, nb, nb] int8 (+1 / -1 for inactive blocks).
    Returns:
        [M, 3] long block subscripts to activate.
    """
    n = round(grid.numel() ** (1 / 3))
    near = torch.nn.functional.max_pool3d(active[None, None].float(), 3, stride=1, padding=1)[0, 0] > 0
    cand = (near & ~active).nonzero()                                                   # [M, 3]
    out = []
    for k in range(0, cand.shape[0], per):
        c = cand[k:k + per]
        ids = _block_node_ids(c, block, n)                                              # [m, b+1, b+1, b+1]
        s = sign[c[:, 0], c[:, 1], c[:, 2]]
        wrong = done[ids] & ((grid[ids] < 0) != (s < 0)[:, None, None, None])
        out.append(c[wrong.flatten(1).any(1)])
    return torch.cat(out) if out else cand


def _block_state(blocks: torch.Tensor, g: torch.Tensor, size: int, h: float, lipschitz: float, lin: torch.Tensor,
                 n: int, prefix: torch.Tensor | None, ar: int) -> torch.Tensor:
    """Sign of blocks of ``size`` cells from their centre values: +1 / -1 (cannot hold the zero level), 0 (may).

    Args:
        blocks: [K, 3] long block subscripts; g: [K] their centre values (no allowed-mask clamp).
        lin: [n] node coordinates; prefix: allowed-mask prefix sums (None: no mask).
    Returns:
        [K] int8.
    """
    i0 = blocks * size
    i1 = (i0 + size).clamp(max=n - 1)                      # a last block may be cut by the grid's edge
    margin = lipschitz * h * 0.5 * (i1 - i0).double().norm(dim=1).float()   # [K] lipschitz x half-diagonal
    pos, neg = g > margin, g < -margin
    if prefix is not None:
        cell = lambda x: ((x + 1.0) * (0.5 * ar)).long().clamp_(0, ar - 1)  # noqa: E731 (as in _clamped_sdf)
        any_ok, all_ok = _allowed_in_boxes(prefix, cell(lin[i0]), cell(lin[i1]))
        pos |= ~any_ok        # lifted above zero everywhere in the block
        neg &= all_ok & ~pos  # a lifted node would border the negative ones
    return pos.to(torch.int8) - neg.to(torch.int8)


@torch.no_grad()
def sparse_sdf(field, resolution: int, device, bound: str = "sphere", allowed: torch.Tensor | None = None,
               block: int = 4, lipschitz: float = 2.0, chunk: int | None = None, max_rounds: int = 32) -> SparseSDF:
    """Evaluate the SDF only in the blocks of the grid that can hold its zero level.

    Blocks are found top-down (a Lipschitz octree): blocks of ``block * 2^k`` cells, starting
    with ~8 per axis, are split into 8 children wherever their centre value is within
    ``lipschitz`` x half-diagonal of zero, down to ``block`` cells (blocks cut by the grid's edge
    use their own centre and half-diagonal).

    Args:
        field: object with ``sdf(x [M, 3]) -> [M]`` in normalised units.
        resolution: N, nodes per axis of the grid over [-1, 1]^3 (node i at -1 + 2 i / (N - 1)).
        device: where to evaluate.
        bound, allowed: the clamps of :func:`sdf_grid`.
        block: cells per edge of the finest blocks.
        lipschitz: assumed bound on |grad sdf|; a block is skipped when its centre value exceeds
            lipschitz x its half-diagonal (2 = the block's full diagonal).
        chunk: points per field call (default 2^19 on CUDA, 2^18 on the CPU).
        max_rounds: cap on the neighbour-activation rounds.
    Returns:
        :class:`SparseSDF`.
    """
    ar = _check(resolution, bound, allowed, block, lipschitz)
    dev = torch.device(device)
    chunk = chunk or (2 ** 19 if dev.type == "cuda" else 2 ** 18)
    n, h = int(resolution), 2.0 / (resolution - 1)
    lin = torch.linspace(-1.0, 1.0, n, device=dev)
    if allowed is not None:
        allowed = allowed.reshape(-1).to(dev)

    def evaluate(pts: torch.Tensor, with_allowed: bool) -> torch.Tensor:
        return torch.cat([_clamped_sdf(field, pts[i:i + chunk], bound, allowed if with_allowed else None, ar)
                          for i in range(0, pts.shape[0], chunk)]) if pts.shape[0] else pts[:, 0]

    def centres(blocks: torch.Tensor, size: int) -> torch.Tensor:  # [K, 3] long -> [K, 3] float32, inside the grid
        i0 = blocks * size
        return (-1.0 + (i0 + (i0 + size).clamp(max=n - 1)).double() * (0.5 * h)).float()

    # 1. coarse passes, top-down: sign [nb, nb, nb] int8 per level, 0 = may hold the surface
    t = time.perf_counter()
    levels = 0
    while -(-(n - 1) // (block << levels)) > 8:
        levels += 1
    size = block << levels
    nb = -(-(n - 1) // size)
    coarse_pts = nb ** 3
    prefix = _allowed_prefix(allowed, ar) if allowed is not None else None
    allb = torch.stack(torch.meshgrid(*[torch.arange(nb, device=dev)] * 3, indexing="ij"), -1).reshape(-1, 3)
    g = evaluate(centres(allb, size), with_allowed=False)
    sign = _block_state(allb, g, size, h, lipschitz, lin, n, prefix, ar).reshape(nb, nb, nb)
    while size > block:
        size //= 2
        nb = -(-(n - 1) // size)
        sign = sign.repeat_interleave(2, 0).repeat_interleave(2, 1).repeat_interleave(2, 2)[:nb, :nb, :nb]
        kids = (sign == 0).nonzero()                                                  # children of open blocks
        coarse_pts += kids.shape[0]
        g = evaluate(centres(kids, size), with_allowed=False)
        sign[kids[:, 0], kids[:, 1], kids[:, 2]] = _block_state(kids, g, size, h, lipschitz, lin, n, prefix, ar)
    active = sign == 0
    # two touching blocks given opposite signs: the zero level runs between them, whatever the bound said
    for ax in range(3):
        a, b = sign.narrow(ax, 0, nb - 1), sign.narrow(ax, 1, nb - 1)
        both = (a.to(torch.int16) * b.to(torch.int16)) < 0
        active.narrow(ax, 0, nb - 1).logical_or_(both)
        active.narrow(ax, 1, nb - 1).logical_or_(both)
    margin = lipschitz * block * h * math.sqrt(3) / 2
    _sync(dev)
    t_coarse = time.perf_counter() - t

    # 2. fine pass, round by round while the surface spills into inactive neighbours
    t = time.perf_counter()
    grid = torch.full((n ** 3,), float(margin), device=dev)
    done = torch.zeros(n ** 3, dtype=torch.bool, device=dev)
    flag = torch.zeros(n ** 3, dtype=torch.bool, device=dev)
    todo = active.nonzero()
    per = max(1, 2 ** 22 // (block + 1) ** 3)          # blocks per batch: ~4 M node ids
    evaluated, rounds = 0, 0
    while todo.shape[0] and rounds < max_rounds:
        rounds += 1
        for k in range(0, todo.shape[0], per):
            flag[_block_node_ids(todo[k:k + per], block, n).reshape(-1)] = True
        flag &= ~done
        ids = flag.nonzero()[:, 0]
        done |= flag
        flag.zero_()
        evaluated += int(ids.numel())
        for k in range(0, ids.shape[0], chunk):
            j = ids[k:k + chunk]
            pts = torch.stack([lin[j // (n * n)], lin[(j // n) % n], lin[j % n]], -1)
            grid[j] = _clamped_sdf(field, pts, bound, allowed, ar)
        todo = _spill(grid, done, active, sign, block, per)
        active[todo[:, 0], todo[:, 1], todo[:, 2]] = True
    _sync(dev)
    stats = {"points": evaluated + coarse_pts, "coarse_points": coarse_pts, "dense_points": n ** 3,
             "blocks_active": int(active.sum()), "blocks": nb ** 3, "block": block, "rounds": rounds,
             "spill_left": int(todo.shape[0]),
             "coarse_s": round(t_coarse, 4), "fine_s": round(time.perf_counter() - t, 4)}
    return SparseSDF(grid.reshape(n, n, n), active, block, stats)


@torch.no_grad()
def surface_cells(sp: SparseSDF, per: int = 4096) -> torch.Tensor:
    """Cells of the active blocks whose 8 corner values change sign.

    Returns:
        [C, 3] int32 cell subscripts (minimum corner), on the grid's device.
    """
    n, b = sp.resolution, sp.block
    blocks = sp.active.nonzero()                                                        # [K, 3]
    flat = sp.grid.reshape(-1)
    r = torch.arange(b, device=blocks.device)
    out = []
    for k in range(0, blocks.shape[0], per):
        bl = blocks[k:k + per]
        neg = (flat[_block_node_ids(bl, b, n)] < 0).to(torch.uint8)                     # [K, b+1, b+1, b+1]
        cnt = sum(neg[:, dx:b + dx, dy:b + dy, dz:b + dz] for dx in (0, 1) for dy in (0, 1) for dz in (0, 1))
        cell = bl[:, :, None] * b + r[None, None, :]                                    # [K, 3, b] cell subscripts
        inside = ((cell[:, 0, :, None, None] < n - 1) & (cell[:, 1, None, :, None] < n - 1)
                  & (cell[:, 2, None, None, :] < n - 1))
        kk, a, c, d = ((cnt > 0) & (cnt < 8) & inside).nonzero(as_tuple=True)
        out.append(torch.stack([cell[kk, 0, a], cell[kk, 1, c], cell[kk, 2, d]], -1))
    return (torch.cat(out) if out else blocks.new_zeros(0, 3)).to(torch.int32)


# ----------------------------------------------------------------------------- meshes as arrays
@dataclass
class MeshArrays:
    """A triangle mesh as plain arrays (what the pipeline writes; no trimesh needed).

    Attributes:
        vertices: [V, 3] float64 world units.
        faces: [F, 3] int64, counter-clockwise seen from outside.
        stats: seconds per step and evaluation counts of the extraction.
        normals: [V, 3] float32 unit outward normals (the SDF gradient), or None.
        colors: [V, 3] uint8 pattern-free colour learned by the model, or None.
    """
    vertices: np.ndarray
    faces: np.ndarray
    stats: dict = dc_field(default_factory=dict)
    normals: np.ndarray | None = None
    colors: np.ndarray | None = None

    def to_trimesh(self):
        import trimesh

        if len(self.vertices) == 0:  # a run that lost its surface: trimesh rejects empty normals/colours
            return trimesh.Trimesh(vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), np.int64), process=False)
        return trimesh.Trimesh(vertices=self.vertices, faces=self.faces, vertex_normals=self.normals,
                               vertex_colors=self.colors, process=False)


def keep_large_components(vertices: np.ndarray, faces: np.ndarray, keep_fraction: float) -> tuple:
    """Drop connected pieces with fewer faces than ``keep_fraction`` of the largest (floaters).

    Pieces are vertex-connected components (for marching-cubes output, which is manifold, the
    same as trimesh's edge-adjacency split). Unreferenced vertices are dropped.

    Args:
        vertices: [V, 3]; faces: [F, 3] int.
    Returns:
        (vertices [V', 3], faces [F', 3] int64).
    """
    faces = np.asarray(faces, dtype=np.int64)
    if keep_fraction <= 0 or len(faces) == 0:
        return vertices, faces
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    nv = len(vertices)
    a = np.concatenate([faces[:, 0], faces[:, 1]])
    b = np.concatenate([faces[:, 1], faces[:, 2]])
    graph = coo_matrix((np.ones(len(a), dtype=np.int8), (a, b)), shape=(nv, nv)).tocsr()
    n_comp, label = connected_components(graph, directed=False)
    if n_comp > 1:
        fl = label[faces[:, 0]]
        size = np.bincount(fl, minlength=n_comp)
        faces = faces[size[fl] >= keep_fraction * size.max()]
    used = np.zeros(nv, dtype=bool)
    used[faces.reshape(-1)] = True
    if used.all():
        return vertices, faces
    remap = np.cumsum(used) - 1
    return vertices[used], remap[faces]


def component_labels(faces: torch.Tensor, n_vertices: int, max_iter: int = 10_000) -> torch.Tensor:
    """Connected-component label of each vertex (the smallest vertex id of its component), in torch.

    Min-label propagation with hooking of the labels themselves and pointer jumping (as in
    FastSV): a few iterations for a mesh; meant for the GPU (on a CPU scipy is much faster).

    Args:
        faces: [F, 3] long; n_vertices: V.
    Returns:
        [V] long.
    """
    a = torch.cat([faces[:, 0], faces[:, 1]])
    b = torch.cat([faces[:, 1], faces[:, 2]])
    lab = torch.arange(n_vertices, device=faces.device)
    for _ in range(max_iter):
        la, lb = lab[a], lab[b]
        m = torch.minimum(la, lb)
        new = lab.clone()
        for idx in (a, b, la, lb):
            new.scatter_reduce_(0, idx, m, "amin")
        new = new[new]
        new = new[new]
        if torch.equal(new, lab):
            return lab
        lab = new
    raise RuntimeError("connected components did not converge")  # cannot happen: labels only decrease


def keep_large_components_torch(vertices: torch.Tensor, faces: torch.Tensor, keep_fraction: float) -> tuple:
    """:func:`keep_large_components` on torch tensors (on the GPU: no host round trip, no scipy).

    Args:
        vertices: [V, 3]; faces: [F, 3] long.
    Returns:
        (vertices [V', 3], faces [F', 3] long), the same arrays as the numpy version.
    """
    if keep_fraction <= 0 or faces.shape[0] == 0:
        return vertices, faces
    nv = vertices.shape[0]
    fl = component_labels(faces, nv)[faces[:, 0]]
    size = torch.bincount(fl, minlength=nv)
    faces = faces[size[fl] >= keep_fraction * size.max()]
    used = torch.zeros(nv, dtype=torch.bool, device=faces.device)
    used[faces.reshape(-1)] = True
    remap = torch.cumsum(used, 0) - 1
    return vertices[used], remap[faces]


def _to_world(verts: np.ndarray, faces: np.ndarray, center, radius: float, keep_fraction: float) -> tuple:
    v = np.asarray(verts, dtype=np.float64) * float(radius) + np.asarray(center, dtype=np.float64)[None]
    return keep_large_components(v, faces, keep_fraction)


def mesh_from_grid(sdf: np.ndarray, center, radius: float, keep_fraction: float = 0.02):
    """Marching cubes (scikit-image) over a whole dense grid and the map to world units (the reference).

    Args:
        sdf: [N, N, N] grid over [-1, 1]^3 (normalised units).
        center, radius: the scene's normalisation (x_world = radius * x + center).
        keep_fraction: drop connected pieces with fewer faces than this fraction of the largest
            (floaters); 0 keeps everything.
    Returns:
        trimesh.Trimesh, outward normals.
    """
    from skimage.measure import marching_cubes

    n = sdf.shape[0]
    if not (sdf.min() < 0 < sdf.max()):
        return MeshArrays(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)).to_trimesh()
    verts, faces, _, _ = marching_cubes(sdf, level=0.0, spacing=(2.0 / (n - 1),) * 3)
    # skimage winds faces counter-clockwise seen from the higher values (outside an SDF)
    v, f = _to_world(verts - 1.0, faces, center, radius, keep_fraction)
    return MeshArrays(v, f).to_trimesh()


def extract_mesh_arrays(field, scene, resolution: int, device, bound: str = "sphere",
                        allowed: torch.Tensor | None = None, keep_fraction: float = 0.02, mc: str = "auto",
                        block: int = 4, lipschitz: float = 2.0) -> MeshArrays:
    """The field's zero level set as a mesh in world units (only inside ``allowed`` cells, if given).

    Args:
        field: object with ``sdf(x [M, 3]) -> [M]`` (normalised units).
        scene: supplies ``bounds.center`` [3] and ``bounds.radius`` (normalised -> world).
        resolution: N, grid nodes per axis over [-1, 1]^3.
        device: where the field is evaluated.
        bound, allowed: clamps, see :func:`sdf_grid`.
        keep_fraction: see :func:`mesh_from_grid`.
        mc: "warp" (``fastneus.kernels.mesh``), "skimage", or "auto" (Warp on CUDA, else skimage).
        block, lipschitz: see :func:`sparse_sdf`.
    Returns:
        :class:`MeshArrays` with ``stats`` (seconds per step, evaluated points, cells).
    """
    from fastneus.kernels import get_op

    _check(resolution, bound, allowed, block, lipschitz, mc)
    dev = torch.device(device)
    use_warp = mc == "warp" or (mc == "auto" and dev.type == "cuda")
    t0 = time.perf_counter()
    sp = sparse_sdf(field, resolution, dev, bound=bound, allowed=allowed, block=block, lipschitz=lipschitz)
    t = time.perf_counter()
    cells = surface_cells(sp)
    _sync(dev)
    t_cells = time.perf_counter() - t
    t = time.perf_counter()
    op = get_op("marching_cubes", "warp" if use_warp else "torch")
    v, f = op(sp.grid, cells, origin=-1.0, spacing=2.0 / (resolution - 1))
    _sync(dev)
    t_mc = time.perf_counter() - t
    t = time.perf_counter()
    if v.device.type == "cuda":  # floaters dropped on the GPU (~ms), then one copy to the host
        v, f = keep_large_components_torch(v, f, keep_fraction)
        keep_fraction = 0.0
    verts, faces = _to_world(v.cpu().numpy(), f.cpu().numpy(), scene.bounds.center, float(scene.bounds.radius),
                             keep_fraction)
    stats = dict(sp.stats, cells=int(cells.shape[0]), mc="warp" if use_warp else "skimage",
                 cells_s=round(t_cells, 4), mc_s=round(t_mc, 4), filter_s=round(time.perf_counter() - t, 4),
                 total_s=round(time.perf_counter() - t0, 4))
    del sp
    return MeshArrays(verts, faces, stats)


def extract_mesh(field, scene, resolution: int, device, bound: str = "sphere",
                 allowed: torch.Tensor | None = None, **kw):
    """:func:`extract_mesh_arrays` as a ``trimesh.Trimesh`` (world units, outward normals)."""
    return extract_mesh_arrays(field, scene, resolution, device, bound=bound, allowed=allowed, **kw).to_trimesh()


def shade_mesh(field, scene, mesh: MeshArrays, device, chunk: int = 1 << 15, response=None,
               scale: float = 1.0) -> MeshArrays:
    """Add vertex normals and colours: the SDF gradient and the learned pattern-free colour D.

    D is evaluated looking at each vertex head-on (view direction = -normal), the same
    colour as the pattern-free texture renders (i_r = i_b = 0), encoded in the photos' camera
    response (``response``: the model is linear; None = linear photos).

    Args:
        field: the trained :class:`fastneus.field.model.SDFField` (normalised units).
        scene: supplies ``bounds`` (world -> normalised).
        mesh: the extracted mesh (world units).
        device: where the field is evaluated.
        chunk: vertices per field evaluation (memory).
        response: the camera response the colours are encoded with (``fastneus.data.response``).
        scale: times the model's colour before encoding (``1 / Trainer.photo_gain``: back to the
            photos' units when a dim capture was trained brighter).
    Returns:
        ``mesh`` with ``normals`` [V, 3] float32 and ``colors`` [V, 3] uint8 set.
    """
    if len(mesh.vertices) == 0:
        return dataclasses.replace(mesh, normals=np.zeros((0, 3), np.float32), colors=np.zeros((0, 3), np.uint8))
    c, r = np.asarray(scene.bounds.center, dtype=np.float64), float(scene.bounds.radius)
    xs = torch.as_tensor((mesh.vertices - c) / r, dtype=torch.float32, device=device)
    normals, colors = [], []
    for x in xs.split(chunk):
        with torch.no_grad():  # sdf_and_grad computes the analytic gradient locally even so
            _, geo, grad, _ = field.sdf_and_grad(x)
            n = grad / grad.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            col = (field.color(x, grad, -n, geo) * scale).clamp(0, 1)
            if response is not None:
                col = encode(col, response)
            colors.append((col * 255 + 0.5).to(torch.uint8).cpu())
            normals.append(n.cpu())
    return dataclasses.replace(mesh, normals=torch.cat(normals).numpy().astype(np.float32),
                               colors=torch.cat(colors).numpy())


# ----------------------------------------------------------------------------- writing
def write_ply(path: str | Path, vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray | None = None,
              colors: np.ndarray | None = None) -> Path:
    """Binary little-endian PLY (float32 x y z [nx ny nz] [uchar red green blue]; uchar-count
    int32 faces), written atomically.

    Args:
        vertices: [V, 3]; faces: [F, 3] int, indices into vertices.
        normals: optional [V, 3] unit normals; colors: optional [V, 3] uint8.
    """
    v = np.ascontiguousarray(vertices, dtype="<f4").reshape(-1, 3)
    f = np.asarray(faces).reshape(-1, 3)
    if len(f) and (f.min() < 0 or f.max() >= len(v)):
        raise FastneusError("face indices out of range of the vertices", field=str(path))
    fields = [("p", "<f4", (3,))] + ([("n", "<f4", (3,))] if normals is not None else []) + \
        ([("c", "u1", (3,))] if colors is not None else [])
    vrec = np.empty(len(v), dtype=fields)
    vrec["p"] = v
    props = "property float x\nproperty float y\nproperty float z\n"
    if normals is not None:
        vrec["n"] = np.asarray(normals, dtype="<f4").reshape(-1, 3)
        props += "property float nx\nproperty float ny\nproperty float nz\n"
    if colors is not None:
        vrec["c"] = np.asarray(colors, dtype=np.uint8).reshape(-1, 3)
        props += "property uchar red\nproperty uchar green\nproperty uchar blue\n"
    rec = np.empty(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    rec["n"], rec["i"] = 3, f
    header = ("ply\nformat binary_little_endian 1.0\ncomment fastneus\n"
              f"element vertex {len(v)}\n{props}"
              f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n").encode("ascii")

    def w(tmp: str) -> None:
        with open(tmp, "wb") as fh:
            fh.write(header)
            fh.write(vrec.tobytes())
            fh.write(rec.tobytes())
    atomic_write(path, w)
    return Path(path)


MESH_SUFFIXES = (".ply", ".obj", ".glb", ".stl", ".off")


def save_mesh(mesh, path: str | Path) -> Path:
    """Write PLY (own writer), or OBJ, GLB, STL, OFF (trimesh) by suffix, atomically, with the
    vertex normals and colours where the format holds them (STL keeps faces only, OFF vertex
    colours without normals). ``mesh``: MeshArrays or trimesh."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise FastneusError(f"mesh output must end in {', '.join(MESH_SUFFIXES[:-1])} or {MESH_SUFFIXES[-1]}",
                            field=str(path))
    if suffix == ".ply":  # a trimesh goes through the same writer (positions and faces)
        return write_ply(path, mesh.vertices, mesh.faces, getattr(mesh, "normals", None), getattr(mesh, "colors", None))
    tm = mesh.to_trimesh() if isinstance(mesh, MeshArrays) else mesh
    atomic_write(path, lambda tmp: tm.export(tmp, file_type=suffix[1:]))
    return path
