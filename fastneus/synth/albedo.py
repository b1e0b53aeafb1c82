"""Surface colours of synthetic scenes: uniform, checker, procedural (smooth value noise) or
the mesh's own vertex colours."""
from __future__ import annotations

import numpy as np
import torch
import trimesh

from fastneus.errors import FastneusError

ALBEDOS = ("uniform", "procedural", "checker", "vertex")


class Albedo:
    """Surface colour at world points, [N, 3] in [0, 1]."""

    def __init__(self, kind: str, mesh: trimesh.Trimesh, radius: float, seed: int, device):
        if kind not in ALBEDOS:
            raise FastneusError(f"unknown albedo {kind!r}; use one of {', '.join(ALBEDOS)}", field="--albedo")
        self.kind, self.radius, self.device = kind, radius, device
        if kind == "procedural":
            rng = np.random.default_rng((seed, 7))
            # two octaves of smooth value noise: random RGB lattices, trilinear interpolation
            self.lattices = [(torch.tensor(rng.uniform(0, 1, (1, 3, g, g, g)), dtype=torch.float32, device=device), w)
                             for g, w in ((6, 0.65), (17, 0.35))]
        elif kind == "vertex":
            vis = mesh.visual
            if vis.kind == "texture":
                vis = vis.to_color()
            if vis.kind != "vertex":
                raise FastneusError("the mesh has no vertex colours; use --albedo procedural or uniform",
                                    field="--albedo")
            self.vcol = torch.tensor(np.asarray(vis.vertex_colors)[:, :3] / 255.0, dtype=torch.float32, device=device)

    def __call__(self, P: torch.Tensor, face: torch.Tensor, V: torch.Tensor, F: torch.Tensor) -> torch.Tensor:
        if self.kind == "uniform":
            return torch.tensor([0.75, 0.7, 0.65], device=P.device).expand(P.shape[0], 3)
        if self.kind == "checker":
            s = self.radius / 4.0
            k = torch.floor(P / s).long().sum(dim=1) % 2
            return torch.where(k[:, None] == 1, torch.tensor([0.85, 0.8, 0.7], device=P.device),
                               torch.tensor([0.25, 0.3, 0.45], device=P.device))
        if self.kind == "procedural":
            g = (P / (1.1 * self.radius)).clamp(-1, 1).view(1, -1, 1, 1, 3)
            val = sum(w * torch.nn.functional.grid_sample(lat, g, mode="bilinear", align_corners=True).view(3, -1).T
                      for lat, w in self.lattices)
            return 0.3 + 0.65 * val
        # vertex colours, barycentric on the hit face
        f = F[face.long()].long()
        a, b, c = V[f[:, 0]], V[f[:, 1]], V[f[:, 2]]
        v0, v1, v2 = b - a, c - a, P - a
        d00, d01, d11 = (v0 * v0).sum(1), (v0 * v1).sum(1), (v1 * v1).sum(1)
        d20, d21 = (v2 * v0).sum(1), (v2 * v1).sum(1)
        den = (d00 * d11 - d01 * d01).clamp_min(1e-20)
        w1 = ((d11 * d20 - d01 * d21) / den).clamp(0, 1)
        w2 = ((d00 * d21 - d01 * d20) / den).clamp(0, 1)
        w0 = (1 - w1 - w2).clamp(0, 1)
        return w0[:, None] * self.vcol[f[:, 0]] + w1[:, None] * self.vcol[f[:, 1]] + w2[:, None] * self.vcol[f[:, 2]]
