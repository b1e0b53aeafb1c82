"""Mesh ray casting for synthetic data: Warp BVH (``raycast_mesh``) and a brute-force torch twin.

Both return the closest hit of each ray with a triangle mesh: distance ``t`` (in
multiples of ``|dir|``; inf on a miss), the face index (-1 on a miss) and the unit
geometric face normal turned to face against the ray (zero on a miss).
"""
from __future__ import annotations

import math

import torch
import warp as wp

from . import _warp

# wp.Mesh objects keyed by the vertex/face tensors: the BVH is built once per mesh.
_MESH_CACHE: dict[tuple, tuple] = {}
_MESH_CACHE_MAX = 4
MIN_CHUNK_RAYS = 1024  # rays per CPU chunk at least (a BVH query is a few microseconds)


@wp.kernel
def _raycast_kernel(mesh: wp.uint64, origins: wp.array(dtype=wp.vec3), dirs: wp.array(dtype=wp.vec3),
                    max_t: wp.array(dtype=wp.float32), t_out: wp.array(dtype=wp.float32),
                    face_out: wp.array(dtype=wp.int32), n_out: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    d = dirs[i]
    q = wp.mesh_query_ray(mesh, origins[i], d, max_t[i])
    if q.result:
        n = q.normal
        if wp.dot(n, d) > 0.0:
            n = -n
        t_out[i] = q.t
        face_out[i] = q.face
        n_out[i] = n
    else:
        t_out[i] = wp.inf
        face_out[i] = -1
        n_out[i] = wp.vec3(0.0, 0.0, 0.0)


def _mesh_for(vertices: torch.Tensor, faces: torch.Tensor):
    """The cached wp.Mesh for these tensors (rebuilt if they changed in place)."""
    key = (vertices.data_ptr(), faces.data_ptr(), tuple(vertices.shape), tuple(faces.shape),
           str(vertices.device), vertices._version, faces._version)
    hit = _MESH_CACHE.get(key)
    if hit is not None:
        return hit[0]
    _warp.init()
    v = vertices.detach().to(torch.float32).contiguous()
    f = faces.detach().to(torch.int32).contiguous().reshape(-1)
    pts = wp.from_torch(v, dtype=wp.vec3)
    idx = wp.from_torch(f, dtype=wp.int32)
    mesh = wp.Mesh(points=pts, indices=idx)
    if len(_MESH_CACHE) >= _MESH_CACHE_MAX:
        _MESH_CACHE.pop(next(iter(_MESH_CACHE)))
    # keep the tensors alive: the wp arrays are zero-copy views of them
    _MESH_CACHE[key] = (mesh, v, f, vertices, faces)
    return mesh


def _max_t_tensor(max_t, n: int, ref: torch.Tensor) -> torch.Tensor:
    if isinstance(max_t, torch.Tensor):
        return max_t.to(device=ref.device, dtype=torch.float32).expand(n).contiguous()
    return torch.full((n,), float(max_t), dtype=torch.float32, device=ref.device)


def raycast_mesh(vertices: torch.Tensor, faces: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor,
                 max_t=1.0e6) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Closest ray-mesh hits with Warp's BVH (``wp.mesh_query_ray``), on CPU or CUDA.

    Args:
        vertices: [V, 3] float32 mesh vertices.
        faces: [F, 3] int32 triangle vertex indices.
        origins: [R, 3] ray origins (same space as the mesh).
        dirs: [R, 3] ray directions (need not be unit; t is in multiples of |dir|).
        max_t: float or [R] tensor: hits at t >= max_t are ignored.

    Returns:
        t: [R] float32 hit distance, inf on a miss.
        face: [R] int32 hit face, -1 on a miss.
        normal: [R, 3] float32 unit geometric normal facing against the ray (0 on a miss).
    """
    R = origins.shape[0]
    dev = origins.device
    t = torch.empty(R, dtype=torch.float32, device=dev)
    face = torch.empty(R, dtype=torch.int32, device=dev)
    normal = torch.empty(R, 3, dtype=torch.float32, device=dev)
    if R == 0:
        return t, face, normal
    mesh = _mesh_for(vertices, faces)
    o = origins.detach().to(torch.float32).contiguous()
    d = dirs.detach().to(torch.float32).contiguous()
    mt = _max_t_tensor(max_t, R, o)
    # one thread per ray, writing only its own hit; the BVH is only read
    _warp.launch_chunked(_raycast_kernel, [mesh.id, _warp.to_wp(o, wp.vec3), _warp.to_wp(d, wp.vec3), _warp.to_wp(mt)],
                         [_warp.to_wp(t), _warp.to_wp(face), _warp.to_wp(normal, wp.vec3)], o,
                         _warp.item_ranges(R, o, MIN_CHUNK_RAYS),
                         sliced_in={1: (o, wp.vec3), 2: (d, wp.vec3), 3: (mt, None)},
                         sliced_out={0: (t, None), 1: (face, None), 2: (normal, wp.vec3)})
    return t, face, normal


def raycast_mesh_torch(vertices: torch.Tensor, faces: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor,
                       max_t=1.0e6, chunk: int | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Torch twin of :func:`raycast_mesh`: brute-force Moller-Trumbore over all faces.

    Same arguments and returns; O(R * F) work, chunked over rays so memory stays bounded
    (``chunk`` rays at a time; default keeps ~2^24 ray-face pairs per chunk). For small meshes.
    """
    R = origins.shape[0]
    dt = origins.dtype if origins.dtype == torch.float64 else torch.float32
    o_all = origins.to(dt)
    d_all = dirs.to(dt)
    v = vertices.to(device=origins.device, dtype=dt)
    f = faces.to(device=origins.device).long()
    v0, v1, v2 = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    e1, e2 = v1 - v0, v2 - v0
    fn = torch.linalg.cross(e1, e2)
    fn = fn / fn.norm(dim=1, keepdim=True).clamp_min(1e-30)
    mt_all = _max_t_tensor(max_t, R, o_all).to(dt)
    chunk = chunk or max(1, (1 << 24) // max(1, f.shape[0]))
    t_out = torch.full((R,), math.inf, dtype=torch.float32, device=origins.device)
    face_out = torch.full((R,), -1, dtype=torch.int32, device=origins.device)
    n_out = torch.zeros(R, 3, dtype=torch.float32, device=origins.device)
    eps = 1e-12 if dt == torch.float64 else 1e-9
    for s in range(0, R, chunk):
        o, d, mt = o_all[s:s + chunk], d_all[s:s + chunk], mt_all[s:s + chunk]
        p = torch.linalg.cross(d[:, None, :], e2[None], dim=-1)  # [r, F, 3]
        det = (e1[None] * p).sum(-1)
        ok = det.abs() > eps
        inv = 1.0 / torch.where(ok, det, torch.ones_like(det))
        tv = o[:, None, :] - v0[None]
        u = (tv * p).sum(-1) * inv
        q = torch.linalg.cross(tv, e1[None].expand_as(tv), dim=-1)
        w = (d[:, None, :] * q).sum(-1) * inv
        t = (e2[None] * q).sum(-1) * inv
        hit = ok & (u >= 0) & (w >= 0) & (u + w <= 1) & (t >= 0) & (t < mt[:, None])
        t = torch.where(hit, t, torch.full_like(t, math.inf))
        tmin, fi = t.min(dim=1)
        got = torch.isfinite(tmin)
        n = fn[fi]
        n = torch.where(((n * d).sum(-1, keepdim=True) > 0), -n, n)
        t_out[s:s + chunk] = tmin.to(torch.float32)
        face_out[s:s + chunk] = torch.where(got, fi.to(torch.int32), torch.full_like(fi, -1, dtype=torch.int32))
        n_out[s:s + chunk] = torch.where(got[:, None], n, torch.zeros_like(n)).to(torch.float32)
    return t_out, face_out, n_out
