"""Rigid transforms: SO(3) / SE(3) exponentials (torch, differentiable), inverses, pose errors."""
from __future__ import annotations

import math

import numpy as np
import torch


def so3_exp(omega: torch.Tensor) -> torch.Tensor:
    """Rotation matrices of rotation vectors (Rodrigues), smooth through 0.

    Args:
        omega: [N, 3] rotation vectors (radians), any float dtype.
    Returns:
        [N, 3, 3] rotation matrices.
    """
    th2 = (omega * omega).sum(-1, keepdim=True)[..., None]  # [N, 1, 1]
    small = th2 < 1e-8
    th2s = torch.where(small, torch.ones_like(th2), th2)
    th = th2s.sqrt()
    a = torch.where(small, 1 - th2 / 6, torch.sin(th) / th)
    b = torch.where(small, 0.5 - th2 / 24, (1 - torch.cos(th)) / th2s)
    x, y, z = omega.unbind(-1)
    o = torch.zeros_like(x)
    Kx = torch.stack([o, -z, y, z, o, -x, -y, x, o], -1).reshape(-1, 3, 3)
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device).expand_as(Kx)
    return eye + a * Kx + b * (Kx @ Kx)


def se3_matrix(xi: torch.Tensor, scale: float = 1.0) -> torch.Tensor:
    """[N, 6] (omega, v) -> [N, 4, 4] rigid transforms [[exp(omega), scale * v], [0, 1]]."""
    R = so3_exp(xi[:, :3])
    top = torch.cat([R, scale * xi[:, 3:, None]], -1)
    bottom = torch.zeros_like(top[:, :1, :])
    bottom[..., 3] = 1.0
    return torch.cat([top, bottom], 1)


def rigid_inverse_torch(T: torch.Tensor) -> torch.Tensor:
    """Inverse of [..., 4, 4] rigid transforms (batched, differentiable): the torch twin of
    :func:`fastneus.geometry.cameras.rigid_inverse` (numpy, one 4x4)."""
    R, t = T[..., :3, :3], T[..., :3, 3:]
    Rt = R.transpose(-1, -2)
    top = torch.cat([Rt, -Rt @ t], -1)
    return torch.cat([top, T[..., 3:, :]], -2)


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(rotation error in degrees, translation error in the poses' units) of two 4x4 poses."""
    R = T_est[:3, :3].T @ T_true[:3, :3]
    s = 0.5 * np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    ang = math.degrees(math.atan2(s, (np.trace(R) - 1) / 2))  # accurate at small angles too
    return ang, float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))
