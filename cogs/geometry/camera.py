"""Pinhole cameras in the OpenCV convention.

x right, y down, z forward; `world_to_camera` is a 4x4 rigid transform, `K` a 3x3
intrinsic matrix in pixels, lengths in metres. Pixel centres sit at integer + 0.5 in the
image plane coordinates used by K (the 3DGS/gsplat convention: pixel (i, j) covers
[j, j+1) x [i, i+1)).

Functions accept numpy arrays or torch tensors alike (they use only operators both share),
so the synthetic generator (numpy) and the trainer (torch) project points the same way.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def intrinsics_from_fov(width: int, height: int, fov_y_deg: float) -> np.ndarray:
    """K for a centred principal point and a vertical field of view."""
    f = 0.5 * height / np.tan(0.5 * np.deg2rad(fov_y_deg))
    return np.array([[f, 0.0, 0.5 * width], [0.0, f, 0.5 * height], [0.0, 0.0, 1.0]])


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """world_to_camera 4x4 for a camera at `eye` looking at `target` (OpenCV axes).

    `up` is the world up direction; the camera's y axis (down in the image) points
    against it.
    """
    eye = np.asarray(eye, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    up = np.asarray(up, dtype=np.float64)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-8:  # looking straight along up
        x = np.cross(z, np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in world coordinates
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye
    return w2c


def camera_center(world_to_camera):
    """Camera position in world coordinates: -R^T t. Works batched ([..., 4, 4])."""
    R = world_to_camera[..., :3, :3]
    t = world_to_camera[..., :3, 3:4]
    return -(R.swapaxes(-1, -2) @ t)[..., 0] if isinstance(R, np.ndarray) else -(R.transpose(-1, -2) @ t)[..., 0]


def transform_points(T, points):
    """Apply a 4x4 rigid transform to [..., 3] points."""
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    return points @ R.T + t if R.ndim == 2 else (R @ points[..., None])[..., 0] + t


def project_points(points_world, world_to_camera, K):
    """World points [N, 3] -> (pixels [N, 2], depth [N]) under one camera.

    Depth is camera-space z; points with z <= 0 get meaningless pixels (callers mask by
    depth).
    """
    pc = transform_points(world_to_camera, points_world)
    z = pc[..., 2]
    zs = z + (z == 0) * 1e-12
    u = K[0, 0] * pc[..., 0] / zs + K[0, 1] * pc[..., 1] / zs + K[0, 2]
    v = K[1, 1] * pc[..., 1] / zs + K[1, 2]
    if isinstance(pc, np.ndarray):
        return np.stack([u, v], axis=-1), z
    import torch

    return torch.stack([u, v], dim=-1), z


def invert_rigid(T):
    """Inverse of a 4x4 rigid transform (numpy or torch, batched)."""
    R = T[..., :3, :3]
    t = T[..., :3, 3:4]
    if isinstance(T, np.ndarray):
        Rt = R.swapaxes(-1, -2)
        out = np.zeros_like(T)
    else:
        Rt = R.transpose(-1, -2)
        out = T.new_zeros(T.shape)
    out[..., :3, :3] = Rt
    out[..., :3, 3:4] = -(Rt @ t)
    out[..., 3, 3] = 1.0
    return out


@dataclass
class Camera:
    """One pinhole camera: intrinsics, extrinsics and image size."""

    K: np.ndarray  # [3, 3] pixels
    world_to_camera: np.ndarray  # [4, 4]
    width: int
    height: int

    @property
    def center(self) -> np.ndarray:
        return camera_center(self.world_to_camera)
