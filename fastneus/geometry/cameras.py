"""Pinhole cameras and projectors: intrinsics, poses, rig placement (OpenCV convention,
x right, y down, z forward; 4x4 device-to-world poses)."""
from __future__ import annotations

import math

import numpy as np


def camera_intrinsics(width: int, height: int, focal: float | None = None) -> np.ndarray:
    """[3, 3] K: NeRF-Synthetic-like f = 1111.11 px at 800 px wide (~40 deg), centred."""
    f = focal if focal is not None else 1111.111 * width / 800.0
    return np.array([[f, 0, width / 2.0], [0, f, height / 2.0], [0, 0, 1.0]])


def projector_intrinsics(width: int, height: int, hfov_deg: float = 60.0) -> np.ndarray:
    """[3, 3] K of a projector with horizontal field of view ``hfov_deg``."""
    f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
    return np.array([[f, 0, width / 2.0], [0, f, height / 2.0], [0, 0, 1.0]])


def rig_proj_to_cam(baseline: float, toe_in_distance: float) -> np.ndarray:
    """[4, 4] projector->camera for a projector at (baseline, 0, 0) in camera coordinates,
    yawed so its optical axis passes through (0, 0, toe_in_distance) (the object centre)."""
    z = np.array([-baseline, 0.0, toe_in_distance])
    z /= np.linalg.norm(z)
    y = np.array([0.0, 1.0, 0.0])
    x = np.cross(y, z)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, (baseline, 0.0, 0.0)
    return T


def rigid_inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform (R^T, -R^T t), numpy; the batched, differentiable torch
    twin is :func:`fastneus.geometry.se3.rigid_inverse_torch`."""
    out = np.eye(4)
    R = T[:3, :3]
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """[4, 4] OpenCV cam_to_world at ``eye`` looking at ``target`` (x right, y down, z forward).

    ``up`` is the world up direction; the image's y axis points along -up.
    """
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    up = np.asarray(up, dtype=np.float64)
    x = np.cross(z, up)  # right = forward x up
    if np.linalg.norm(x) < 1e-8:  # looking along up: any perpendicular will do
        x = np.cross(z, np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T
