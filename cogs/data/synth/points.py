"""SfM-like sparse points of the static scene.

A structure-from-motion run on the video would triangulate points where the image is
textured (corners), only on the static scene (people and moving objects are masked out
or fail to triangulate consistently), only where training frames see the surface, with
errors of about a centimetre. This module imitates that from the ground truth: corners
(Shi-Tomasi) of each training image inside the static region, lifted to 3D with the exact
depth through the pixel centre, de-duplicated on a voxel grid, coloured from the image,
then perturbed.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.ndimage import binary_erosion

from cogs.data.synth.mesh import STATIC


def frame_points(rgb: np.ndarray, centre_label: np.ndarray, label: np.ndarray, depth: np.ndarray,
                 K: np.ndarray, world_to_camera: np.ndarray, max_corners: int = 160):
    """Corner points of one frame on static surfaces -> (xyz [P, 3] world, rgb [P, 3] uint8).

    Only pixels whose centre sample and whole 5x5 neighbourhood are static qualify, so no
    point sits on a silhouette or on the person or object.
    """
    static = (label == STATIC) & (centre_label == STATIC) & (depth > 0)
    static = binary_erosion(static, np.ones((5, 5), dtype=bool))
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    corners = cv2.goodFeaturesToTrack(gray, maxCorners=max_corners, qualityLevel=0.02, minDistance=5,
                                      mask=static.astype(np.uint8) * 255, blockSize=5)
    if corners is None:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.uint8)
    ij = np.rint(corners[:, 0, ::-1]).astype(np.int64)  # (row, col)
    ij = ij[static[ij[:, 0], ij[:, 1]]]
    z = depth[ij[:, 0], ij[:, 1]].astype(np.float64)
    u, v = ij[:, 1] + 0.5, ij[:, 0] + 0.5
    x_cam = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=1)
    R, t = world_to_camera[:3, :3], world_to_camera[:3, 3]
    return (x_cam - t) @ R, rgb[ij[:, 0], ij[:, 1]]


def voxel_dedup(xyz: np.ndarray, rgb: np.ndarray, voxel: float):
    """Keep the first point in each voxel (input order, so the result is deterministic)."""
    keys = np.floor(xyz / voxel).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    first = np.sort(first)
    return xyz[first], rgb[first]


def perturb(xyz: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """Isotropic Gaussian error, std `sigma` per axis, displacement length capped at 3 sigma."""
    d = rng.standard_normal(xyz.shape) * sigma
    n = np.linalg.norm(d, axis=1, keepdims=True)
    cap = 3.0 * sigma
    d = np.where(n > cap, d * cap / np.maximum(n, 1e-12), d)
    return xyz + d
