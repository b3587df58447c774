"""Linear blend skinning as pure functions.

Transforms are the body model's skinning transforms: they map canonical (zero-pose)
space to posed world space, one 4x4 per bone. Weights are dense [N, J] rows summing to 1.
"""

from __future__ import annotations

import torch
from torch import Tensor

from cogs.geometry.rotations import quat_multiply, rotmat_to_quat


def blend_transforms(weights: Tensor, transforms: Tensor) -> Tensor:
    """weights [N, J], transforms [J, 4, 4] -> per-point blended [N, 3, 4]."""
    J = transforms.shape[-3]
    flat = transforms[..., :3, :].reshape(J, 12)
    return (weights @ flat).reshape(-1, 3, 4)


def lbs_points(points: Tensor, weights: Tensor, transforms: Tensor) -> Tensor:
    """Skin canonical points [N, 3] with weights [N, J] by transforms [J, 4, 4] -> [N, 3]."""
    A = blend_transforms(weights, transforms)
    return (A[:, :, :3] @ points[:, :, None])[:, :, 0] + A[:, :, 3]


def lbs_gaussians(
    means: Tensor, quats: Tensor, weights: Tensor, transforms: Tensor
) -> tuple[Tensor, Tensor]:
    """Skin Gaussian centres and orientations.

    Each Gaussian's orientation is rotated by its blended linear part, projected to the
    nearest rotation through the quaternion conversion (the blend of a few nearby bone
    rotations is close to a rotation, so this is accurate where it matters).
    Returns posed means [N, 3] and unit quaternions [N, 4] (wxyz).
    """
    A = blend_transforms(weights, transforms)
    posed = (A[:, :, :3] @ means[:, :, None])[:, :, 0] + A[:, :, 3]
    q_blend = rotmat_to_quat(A[:, :, :3])
    return posed, quat_multiply(q_blend, quats)
