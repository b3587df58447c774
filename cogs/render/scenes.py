"""Synthetic Gaussian scenes for the renderer's tests and benchmark (not for training)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass
class SplatScene:
    means: Tensor  # [N, 3] world
    quats: Tensor  # [N, 4] wxyz, unnormalised
    scales: Tensor  # [N, 3]
    opacities: Tensor  # [N]
    colors: Tensor  # [N, D]
    viewmat: Tensor  # [4, 4]
    K: Tensor  # [3, 3]
    width: int
    height: int

    def gaussians(self) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        return self.means, self.quats, self.scales, self.opacities, self.colors

    def camera(self) -> tuple[Tensor, Tensor, int, int]:
        return self.viewmat, self.K, self.width, self.height


def look_at_viewmat(eye, target, dtype=torch.float32) -> Tensor:
    """OpenCV world->camera matrix of a camera at ``eye`` looking at ``target`` (y down)."""
    eye = torch.as_tensor(eye, dtype=torch.float64)
    target = torch.as_tensor(target, dtype=torch.float64)
    z = target - eye
    z = z / z.norm()
    down = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    if abs(float(z @ down)) > 0.99:
        down = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    x = torch.linalg.cross(down, z)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z])  # rows: camera axes in world coordinates
    V = torch.eye(4, dtype=torch.float64)
    V[:3, :3] = R
    V[:3, 3] = -R @ eye
    return V.to(dtype)


def splat_scene(n: int, width: int, height: int, *, channels: int = 3, seed: int = 0,
                sigma_px: tuple[float, float] = (0.5, 3.0), dtype=torch.float32) -> SplatScene:
    """A trained-scene-like cloud, entirely inside the frustum (the benchmark scene).

    Camera at the origin looking down +z with a ~59 deg horizontal field of view
    (fx = 0.9 W). Centres are uniform in depth z in [2, 6] and uniform across the frustum at
    that depth (95 % of the image). Per-axis scales are log-uniform such that each axis's
    on-screen standard deviation ``f s / z`` lies in ``sigma_px`` pixels, giving 3-sigma
    radii of ~2-10 px (mean ~6): the small, dense splats a trained 3DGS scene is made of.
    Random rotations; opacities uniform in [0.05, 0.95]; colours uniform in [0, 1].
    """
    g = torch.Generator().manual_seed(seed)
    f = 0.9 * width
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    z = 2.0 + 4.0 * torch.rand(n, generator=g)
    u = (torch.rand(n, generator=g) - 0.5) * 0.95 * width / f
    v = (torch.rand(n, generator=g) - 0.5) * 0.95 * height / f
    means = torch.stack([u * z, v * z, z], dim=-1)
    lo, hi = math.log(sigma_px[0]), math.log(sigma_px[1])
    sig = torch.exp(lo + (hi - lo) * torch.rand(n, 3, generator=g))
    scales = sig * z[:, None] / f
    quats = torch.randn(n, 4, generator=g)
    opacities = 0.05 + 0.9 * torch.rand(n, generator=g)
    colors = torch.rand(n, channels, generator=g)
    return SplatScene(*(t.to(dtype) for t in (means, quats, scales, opacities, colors,
                                               torch.eye(4), K)), width=width, height=height)


def random_scene(n: int, width: int, height: int, *, channels: int = 3, seed: int = 0,
                 dtype=torch.float32) -> SplatScene:
    """A harder test scene: a general camera pose, Gaussians of widely varying size and
    opacity, some anisotropic, some partly or wholly outside the frustum or behind the
    camera."""
    g = torch.Generator().manual_seed(seed)
    f = 0.8 * width
    K = torch.tensor([[f, 0.0, 0.5 * width + 1.3], [0.0, 1.1 * f, 0.5 * height - 0.7],
                      [0.0, 0.0, 1.0]])
    viewmat = look_at_viewmat([0.3, -0.4, -4.0], [0.1, 0.05, 0.2])
    means = (torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([4.5, 3.4, 6.0])
    means[:1] = torch.tensor([0.1, 0.05, 0.2])  # at least one Gaussian on screen
    log_s = -3.5 + 2.0 * torch.rand(n, 3, generator=g)
    log_s[:, 0] += torch.randn(n, generator=g)  # some elongated splats
    scales = torch.exp(log_s)
    quats = torch.randn(n, 4, generator=g)
    opacities = torch.rand(n, generator=g)
    opacities[:1] = 0.8
    colors = torch.rand(n, channels, generator=g)
    return SplatScene(*(t.to(dtype) for t in (means, quats, scales, opacities, colors,
                                               viewmat, K)), width=width, height=height)
