"""The synthetic underwater capture: flat ports in front of cameras and projectors, and the
water's attenuation and back-scatter (a coastal-water-like medium)."""
from __future__ import annotations

import numpy as np
import torch


WATER_PORT = dict(normal=np.array([0.0, 0.0, 1.0]), distance=0.03, thickness=0.01, n_air=1.0, n_glass=1.5,
                  n_water=1.333)
# coastal-water-like: red fades first; per RGB channel, 1 / m; far = range of rays that hit nothing
WATER = {"beta_d": [0.30, 0.10, 0.06], "beta_b": [0.25, 0.12, 0.08], "b_inf": [0.02, 0.12, 0.18], "far": 20.0}


class Water:
    """Attenuation and back-scatter along the camera rays of one view (see ``synthesize``)."""

    def __init__(self, t_hit: torch.Tensor, hidx: torch.Tensor, n_pix: int, device):
        self.r = t_hit[:, None]  # the rays start on the port's outer face: all of t is in the water
        self.bd, self.bb, self.binf = (torch.tensor(WATER[k], device=device) for k in ("beta_d", "beta_b", "b_inf"))
        self.n_pix = n_pix

    def seen(self, c: torch.Tensor) -> torch.Tensor:
        return c * torch.exp(-self.bd * self.r) + self.binf * (1 - torch.exp(-self.bb * self.r))

    def background(self) -> torch.Tensor:
        far = WATER["far"]
        return (self.binf * (1 - torch.exp(-self.bb * far))).expand(self.n_pix, 3)


def port_exit(X: torch.Tensor, V: torch.Tensor, port_row: torch.Tensor) -> torch.Tensor:
    """[N, 3] point (device frame) where the light toward X leaves the port's outer face."""
    n, d0, tg, kg, kw = port_row[0:3], port_row[3], port_row[4], port_row[5], port_row[6]
    h = X @ n
    r = X - h[:, None] * n
    e = r / r.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    s = (V * e).sum(-1)
    sw = kw * s
    cw = torch.sqrt(1 - sw * sw)
    hw = (h - d0 - tg).clamp_min(0)
    wdir = cw[:, None] * n + sw[:, None] * e
    return X - (hw / cw)[:, None] * wdir
