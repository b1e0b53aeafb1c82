"""Read the NeuS / IDR DTU format: ``cameras_sphere.npz`` (``world_mat_i``, ``scale_mat_i``),
``image/`` and ``mask/``. Passive scenes: no projectors.

``world_mat_i`` is the 3x4 (or 4x4 padded) projection P = K [R | t] from world to
pixels; it is decomposed with ``cv2.decomposeProjectionMatrix`` as NeuS does
(``load_K_Rt_from_P``: K normalised by K[2,2], camera centre from the homogeneous
vector). NeuS generates rays at integer pixel coordinates (pixel centres at integers),
so K's principal point is shifted by +0.5 to the fastneus convention.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from fastneus.data.images import image_size
from fastneus.data.scene import FORMAT, VERSION, Scene
from fastneus.errors import FastneusError
from fastneus.formats.activeneus import NPZ, npz_matrix, group_equal, image_files, rel_posix, open_npz_folder
from fastneus.formats.safe_npz import npz_array


def decompose_projection(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split P = K [R | t] into intrinsics and pose.

    Args:
        P: [3, 4] projection matrix (world -> homogeneous pixels).

    Returns:
        K: [3, 3] with K[2, 2] = 1 (integer-centre pixel convention of the source).
        cam_to_world: [4, 4] rigid pose.
    """
    import cv2

    K, R, c = cv2.decomposeProjectionMatrix(np.ascontiguousarray(P[:3, :4], dtype=np.float64))[:3]
    K = K / K[2, 2]
    pose = np.eye(4)
    pose[:3, :3] = R.T  # R maps world -> camera
    pose[:3, 3] = (c[:3] / c[3])[:, 0]
    return K, pose


def read_neus(path: str | os.PathLike) -> Scene:
    """Read a NeuS/DTU scene folder into an in-memory passive :class:`Scene`.

    Args:
        path: folder with ``cameras_sphere.npz``, ``image/`` and optionally ``mask/``.

    Returns:
        The scene (frame i = i-th sorted image, bounds from ``scale_mat_0``).

    Raises:
        FastneusError: one line naming the file and key of the first problem.
    """
    root = Path(path)
    npz_path, npz, images, masks = open_npz_folder(root)

    Ks, poses = [], []
    S = None
    for i in range(len(images)):
        key = f"world_mat_{i}"
        Wm = npz_array(npz, key, npz_path)
        if Wm.shape not in ((3, 4), (4, 4)):
            raise FastneusError(f"expected shape 3x4 or 4x4, got {'x'.join(map(str, Wm.shape)) or 'scalar'}",
                                file=npz_path, field=key)
        Wm = npz_matrix(npz, key, Wm.shape, npz_path)  # numeric and finite
        if abs(np.linalg.det(Wm[:3, :3])) < 1e-12:
            raise FastneusError("singular projection matrix", file=npz_path, field=key)
        K, pose = decompose_projection(Wm)
        K[0, 2] += 0.5
        K[1, 2] += 0.5
        Ks.append(K)
        poses.append(pose)
        Si = npz_matrix(npz, f"scale_mat_{i}", (4, 4), npz_path)
        if S is None:
            S = Si
            s = S[0, 0]
            if not (s > 0 and np.allclose(S[:3, :3], s * np.eye(3), rtol=1e-6, atol=1e-9)):
                raise FastneusError("expected [[s I, c], [0, 1]] with s > 0", file=npz_path, field="scale_mat_0")
        elif not np.allclose(Si, S, rtol=1e-6, atol=1e-9):
            raise FastneusError("differs from scale_mat_0; all frames must share one normalisation",
                                file=npz_path, field=f"scale_mat_{i}")

    cam_of = group_equal(Ks)
    cameras, frames = {}, []
    for i in range(len(images)):
        cid = f"cam{cam_of[i]:03d}"
        if cid not in cameras:
            wh = image_size(images[i])
            if wh is None:
                raise FastneusError("cannot read image", file=images[i])
            cameras[cid] = {"K": Ks[i].tolist(), "width": wh[0], "height": wh[1], "dist": [0.0] * 5}
        fr = {"image": rel_posix(images[i], root), "camera": cid, "cam_to_world": poses[i].tolist(), "view": i}
        if masks:
            fr["mask"] = rel_posix(masks[i], root)
        frames.append(fr)
    data = {"format": FORMAT, "version": VERSION, "units": "m", "name": root.resolve().name,
            "bounds": {"center": S[:3, 3].tolist(), "radius": float(S[0, 0])},
            "cameras": cameras, "projectors": {}, "patterns": {}, "frames": frames,
            "meta": {"source_format": "neus", "source": str(root.resolve())}}
    return Scene.from_dict(data, root=root, file=npz_path)
