"""The static scene branch: world-space Gaussians from sparse points, with planar priors.

Gaussians start at the sparse SfM points, each an isotropic blob whose size is the mean
distance to its nearest neighbours. Planes (floor, walls, table tops) come from
sequential RANSAC on the same points. After a warm-up the trainer assigns flat Gaussians
lying near a compatible plane (distance and normal gates) and pulls their centres onto it
with a robust point-to-plane penalty.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from cogs.branches.gaussians import GaussianSet
from cogs.geometry.planes import Plane, assign_to_planes, planes_to_tensors, point_to_plane_loss, ransac_planes
from cogs.geometry.rotations import quat_to_rotmat


@dataclass
class SceneConfig:
    """Scene-branch hyper-parameters."""

    knn: int = 3
    """Neighbours whose mean distance sets each initial Gaussian's size (3DGS)."""
    init_opacity: float = 0.1
    max_init_scale_m: float = 0.1
    sh_degree: int = 0
    """View-dependent colour degree (0 = Lambertian; 3 in the paper preset)."""
    max_planes: int = 6
    plane_threshold_m: float = 0.02
    plane_min_inliers: int = 150
    plane_assign_distance_m: float = 0.05
    plane_assign_angle_deg: float = 20.0
    plane_loss_kind: str = "huber"
    plane_loss_scale_m: float = 0.01


def knn_scales(xyz: np.ndarray, k: int, max_scale: float) -> np.ndarray:
    """Mean distance to the k nearest other points, clipped to (1e-4, max_scale)."""
    from scipy.spatial import cKDTree

    if len(xyz) < 2:
        return np.full(len(xyz), 0.01)
    k = min(k, len(xyz) - 1)
    d, _ = cKDTree(xyz).query(xyz, k=k + 1)
    return np.clip(d[:, 1:].mean(1), 1e-4, max_scale)


class SceneBranch(torch.nn.Module):
    def __init__(self, gaussians: GaussianSet, planes: list[Plane], cfg: SceneConfig):
        super().__init__()
        self.cfg = cfg
        self.gaussians = gaussians
        self.planes = list(planes)
        n, d = planes_to_tensors(self.planes)
        self.register_buffer("plane_normals", n)
        self.register_buffer("plane_offsets", d)
        self.register_buffer("assignment", torch.full((len(gaussians),), -1, dtype=torch.long))

    def __len__(self) -> int:
        return len(self.gaussians)

    @classmethod
    def from_points(
        cls, xyz: np.ndarray, rgb: np.ndarray, cfg: SceneConfig, planes: list[Plane] | None = None
    ) -> "SceneBranch":
        scales = knn_scales(xyz, cfg.knn, cfg.max_init_scale_m)
        g = GaussianSet.from_points(
            torch.from_numpy(np.asarray(xyz, np.float32)),
            torch.from_numpy(np.asarray(rgb, np.float32) / (255.0 if np.asarray(rgb).dtype == np.uint8 else 1.0)),
            torch.from_numpy(scales.astype(np.float32)),
            opacity=cfg.init_opacity,
            sh_degree=cfg.sh_degree,
        )
        if planes is None:
            planes = ransac_planes(
                np.asarray(xyz, np.float64),
                max_planes=cfg.max_planes,
                threshold_m=cfg.plane_threshold_m,
                min_inliers=cfg.plane_min_inliers,
            )
        return cls(g, planes, cfg)

    def gaussian_normals(self) -> Tensor:
        """Each Gaussian's shortest axis (its normal when it is flat), [N, 3]."""
        R = quat_to_rotmat(self.gaussians.quats.detach())
        axis = self.gaussians.params["scales"].detach().argmin(dim=1)
        return R[torch.arange(len(self)), :, axis]

    def assign_planes(self) -> int:
        """Recompute which Gaussians the plane term acts on; returns how many."""
        a = assign_to_planes(
            self.gaussians.means.detach(), self.gaussian_normals(), self.planes,
            self.cfg.plane_assign_distance_m, self.cfg.plane_assign_angle_deg,
        )
        self.assignment = a.to(torch.long)
        return int((a >= 0).sum())

    def plane_loss(self) -> Tensor:
        if len(self.planes) == 0 or self.assignment.shape[0] != len(self):
            return (self.gaussians.means * 0).sum()
        return point_to_plane_loss(
            self.gaussians.means, self.plane_normals, self.plane_offsets, self.assignment,
            kind=self.cfg.plane_loss_kind, scale=self.cfg.plane_loss_scale_m,
        )
