"""EWA projection of 3D Gaussians to screen-space 2D Gaussians, in differentiable PyTorch.

Every backend except gsplat shares this module, so the torch reference and the numba
kernels see bit-identical 2D Gaussians, tile ranges and depth order; the parity tests then
exercise only the pixel pass. The semantics follow classic 3DGS as gsplat implements it:

* camera-space mean ``t = R m + T``; Gaussians whose centre depth is ``<= near`` or
  ``>= far`` are culled (a Gaussian straddling the near plane is kept or culled by its
  centre alone, like gsplat and 3DGS);
* 3D covariance ``Sigma = (R_q S)(R_q S)^T`` from the (unnormalised) quaternion and the
  activated scales, rotated into the camera frame;
* the Jacobian of the perspective projection is evaluated at the centre with ``x/z`` and
  ``y/z`` clamped to the image's half-extent plus 30 % (gsplat's ``lim_x_pos``/``lim_x_neg``,
  i.e. ``1.3 tan(fov/2)`` for a centred principal point) so off-screen Gaussians do not
  explode;
* ``cov2d = J Sigma_c J^T + 0.3 I`` (low-pass filter), ``conic = cov2d^-1``;
* ``radius = ceil(3 sqrt(lambda_max(cov2d)))`` pixels (the 3DGS square bound); a Gaussian is
  culled when its square misses the image.

Culled Gaussians get ``radius == 0``; everything computed for them stays finite (their
depth is replaced by 1 before dividing) so that no NaN can leak into gradients through
``torch.where``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from cogs.geometry.rotations import quat_to_rotmat

TILE_SIZE = 16
EPS2D = 0.3  # low-pass filter added to the 2D covariance diagonal, in px^2
_MAX_RADIUS = 1.0e7  # px; only keeps the int32 radius representable for absurd Gaussians


@dataclass
class Projected:
    """Screen-space Gaussians for one camera (N entries, culled ones have radii == 0)."""

    means2d: Tensor  # [N, 2] px, differentiable
    conics: Tensor  # [N, 3] (a, b, c) of the inverse 2D covariance [[a, b], [b, c]], differentiable
    depths: Tensor  # [N] camera-space z, differentiable
    radii: Tensor  # [N] int32, 0 = culled
    means_cam: Tensor | None  # [N, 3] camera-space centres (torch projection only)


def covariance_3d(quats: Tensor, scales: Tensor) -> Tensor:
    """[N,4] wxyz (any norm; zero -> identity), [N,3] activated scales -> [N,3,3]."""
    M = quat_to_rotmat(quats) * scales[:, None, :]
    return M @ M.transpose(-1, -2)


def project_gaussians(
    means: Tensor,  # [N, 3] world
    quats: Tensor,  # [N, 4] wxyz
    scales: Tensor,  # [N, 3]
    viewmat: Tensor,  # [4, 4] world -> camera (OpenCV)
    K: Tensor,  # [3, 3] px
    width: int,
    height: int,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = EPS2D,
) -> Projected:
    R = viewmat[:3, :3]
    t = viewmat[:3, 3]
    means_c = means @ R.T + t  # [N, 3]
    x, y, z = means_c.unbind(-1)
    in_depth = (z > near) & (z < far)
    z_safe = torch.where(in_depth, z, torch.ones_like(z))

    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    lim_x_pos = (width - cx) / fx + 0.3 * tan_fovx
    lim_x_neg = cx / fx + 0.3 * tan_fovx
    lim_y_pos = (height - cy) / fy + 0.3 * tan_fovy
    lim_y_neg = cy / fy + 0.3 * tan_fovy
    u = x / z_safe
    v = y / z_safe
    tx = z_safe * torch.maximum(torch.minimum(u, lim_x_pos), -lim_x_neg)
    ty = z_safe * torch.maximum(torch.minimum(v, lim_y_pos), -lim_y_neg)

    zeros = torch.zeros_like(z)
    J = torch.stack(
        [fx / z_safe, zeros, -fx * tx / (z_safe * z_safe),
         zeros, fy / z_safe, -fy * ty / (z_safe * z_safe)],
        dim=-1,
    ).reshape(-1, 2, 3)
    cov_c = R @ covariance_3d(quats, scales) @ R.T  # [N, 3, 3]
    cov2d = J @ cov_c @ J.transpose(-1, -2)  # [N, 2, 2]
    a = cov2d[:, 0, 0] + eps2d
    b = 0.5 * (cov2d[:, 0, 1] + cov2d[:, 1, 0])
    c = cov2d[:, 1, 1] + eps2d
    det = a * c - b * b
    ok = in_depth & (det > 0) & torch.isfinite(det)
    det_safe = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([c / det_safe, -b / det_safe, a / det_safe], dim=-1)

    means2d = torch.stack([fx * u + cx, fy * v + cy], dim=-1)

    with torch.no_grad():
        half_diff = 0.5 * (a - c)
        lam_max = 0.5 * (a + c) + torch.sqrt(half_diff * half_diff + b * b)
        radius = torch.ceil(3.0 * torch.sqrt(lam_max.clamp_min(0.0)))
        radius = torch.nan_to_num(radius, nan=0.0, posinf=_MAX_RADIUS).clamp(0.0, _MAX_RADIUS)
        mx, my = means2d.detach().unbind(-1)
        inside = (mx + radius > 0) & (mx - radius < width) & (my + radius > 0) & (my - radius < height)
        radii = torch.where(ok & inside, radius, torch.zeros_like(radius)).to(torch.int32)
    return Projected(means2d=means2d, conics=conics, depths=z, radii=radii, means_cam=means_c)


def tile_grid(width: int, height: int) -> tuple[int, int]:
    """Number of 16x16 tiles across and down."""
    return math.ceil(width / TILE_SIZE), math.ceil(height / TILE_SIZE)


@torch.no_grad()
def tile_ranges(means2d: Tensor, radii: Tensor, width: int, height: int) -> Tensor:
    """[N, 4] int32 (tx0, tx1, ty0, ty1): half-open tile ranges touched by each square
    ``[m - r, m + r]`` (gsplat's isect_tiles rule); empty (0, 0, 0, 0) when culled."""
    tiles_x, tiles_y = tile_grid(width, height)
    m = means2d.detach() / TILE_SIZE
    r = radii.to(m.dtype)[:, None] / TILE_SIZE
    lo = torch.floor(m - r)
    hi = torch.ceil(m + r)
    lim = m.new_tensor([tiles_x, tiles_y])
    lo = torch.minimum(torch.clamp_min(lo, 0.0), lim)
    hi = torch.minimum(torch.clamp_min(hi, 0.0), lim)
    out = torch.stack([lo[:, 0], hi[:, 0], lo[:, 1], hi[:, 1]], dim=-1).to(torch.int32)
    return torch.where((radii > 0)[:, None], out, torch.zeros_like(out))


@torch.no_grad()
def depth_order(depths: Tensor) -> Tensor:
    """Front-to-back order (stable, ties by index) used by every backend."""
    return torch.argsort(depths.detach(), stable=True)
