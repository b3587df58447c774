"""The static scene branch: world-space Gaussians from sparse points, with planar priors.

Gaussians start at the sparse SfM points, each an isotropic blob whose size is the mean
distance to its nearest neighbours. Planes (floor, walls, table tops) come from
sequential RANSAC on the same points. After a warm-up the trainer assigns flat Gaussians
lying near a compatible plane (distance and normal gates) and pulls their centres onto it
with a robust point-to-plane penalty.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from cogs.branches.base import Branch, Splats, register
from cogs.branches.gaussians import GaussianSet, guard_set, set_param_groups
from cogs.branches.surgery import SetGaussians
from cogs.geometry.planes import Plane, assign_to_planes, planes_to_tensors, point_to_plane_loss, ransac_planes
from cogs.geometry.rotations import quat_to_rotmat
from cogs.render.sh import sh_to_color


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


@register
class SceneBranch(Branch):
    name = "scene"

    def __init__(self, gaussians: GaussianSet, planes: list[Plane], cfg: SceneConfig):
        super().__init__()
        self.cfg = cfg
        self.gaussians = gaussians
        self.planes = list(planes)
        dev = gaussians.means.device
        n, d = planes_to_tensors(self.planes, device=dev)
        self.register_buffer("plane_normals", n)
        self.register_buffer("plane_offsets", d)
        # The planes at full precision (assignment is decided in float64), to rebuild them.
        n64, d64 = planes_to_tensors(self.planes, dtype=torch.float64, device=dev)
        self.register_buffer("planes64", torch.cat([n64, d64[:, None]], dim=1))
        self.register_buffer("assignment", torch.full((len(gaussians),), -1, dtype=torch.long, device=dev))

    def __len__(self) -> int:
        return len(self.gaussians)

    @classmethod
    def from_points(
        cls, xyz: np.ndarray, rgb: np.ndarray, cfg: SceneConfig, planes: list[Plane] | None = None,
        device: torch.device | str = "cpu",
    ) -> "SceneBranch":
        scales = knn_scales(xyz, cfg.knn, cfg.max_init_scale_m)
        g = GaussianSet.from_points(
            torch.from_numpy(np.asarray(xyz, np.float32)).to(device),
            torch.from_numpy(np.asarray(rgb, np.float32) / (255.0 if np.asarray(rgb).dtype == np.uint8 else 1.0)).to(device),
            torch.from_numpy(scales.astype(np.float32)).to(device),
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

    @classmethod
    def from_state(cls, state: dict[str, Tensor], cfg, body=None) -> "SceneBranch":
        g = GaussianSet.from_state(state, "gaussians.params.")
        p64 = state["planes64"].cpu().numpy()
        planes = [Plane(p64[i, :3].copy(), float(p64[i, 3]), np.zeros(0, np.int64)) for i in range(len(p64))]
        scene = cls(g, planes, cfg.scene)
        scene.load_state_dict(state)
        return scene

    def splats(self, frame: int, campos: Tensor, pose=None, prepared=None) -> Splats:
        g = self.gaussians
        rgb = g.rgb if g.sh_degree == 0 else sh_to_color(g.sh_degree, g.means - campos, g.sh)
        return Splats(g.means, g.quats, g.scales, g.opacities, rgb)

    # -- training ------------------------------------------------------------------------
    def param_groups(self, lr, extent: float) -> list[dict]:
        return set_param_groups(self.gaussians, lr, "scene", extent)

    def density_adapter(self) -> SetGaussians:
        return SetGaussians(self.gaussians)

    def guard(self, extent: float) -> None:
        guard_set(self.gaussians, extent)

    def regularisers(self, weights, frames: Tensor, prepared=None) -> dict[str, Tensor]:
        if weights.get("plane", 0) > 0:
            return {"plane": weights["plane"] * self.plane_loss()}
        return {}

    def gaussian_normals(self) -> Tensor:
        """Each Gaussian's shortest axis (its normal when it is flat), [N, 3]."""
        R = quat_to_rotmat(self.gaussians.quats.detach())
        axis = self.gaussians.params["scales"].detach().argmin(dim=1)
        return R[torch.arange(len(self), device=R.device), :, axis]

    def assign_planes(self) -> int:
        """Recompute which Gaussians the plane term acts on; returns how many."""
        a = assign_to_planes(
            self.gaussians.means.detach(), self.gaussian_normals(), self.planes,
            self.cfg.plane_assign_distance_m, self.cfg.plane_assign_angle_deg,
        )
        self.assignment = a.to(torch.long)
        return int((a >= 0).sum())

    def clear_assignment(self) -> None:
        """No Gaussian assigned (after density control changed the set)."""
        self.assignment = torch.full((len(self),), -1, dtype=torch.long, device=self.gaussians.means.device)

    def plane_loss(self) -> Tensor:
        if len(self.planes) == 0 or self.assignment.shape[0] != len(self):
            return (self.gaussians.means * 0).sum()
        return point_to_plane_loss(
            self.gaussians.means, self.plane_normals, self.plane_offsets, self.assignment,
            kind=self.cfg.plane_loss_kind, scale=self.cfg.plane_loss_scale_m,
        )

    def export(self, folder: Path, n_frames: int) -> list[Path]:
        path = folder / "scene.ply"
        self.gaussians.save_ply(path)
        return [path]
