"""What rendering and export share: the world's up direction, skinning rotations
projected onto rotations, and a branch's splats posed for export.

Blended skinning matrices are not rotations (a blend of two bone rotations shrinks and
shears), so an exported Gaussian's orientation comes from the polar decomposition of its
blended 3x3 (`polar_rotation`), never from the blended matrix itself.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from cogs.body import blend_transforms
from cogs.geometry.rotations import quat_multiply, quat_to_rotmat, rotmat_to_quat
from cogs.render.sh import num_sh_bases, sh_basis

AXES = np.eye(3)


def polar_rotation(M: Tensor) -> Tensor:
    """[..., 3, 3] -> the nearest rotation (polar decomposition U V^T of M = U S V^T,
    with the sign of the smallest singular direction flipped where det < 0)."""
    U, _, Vh = torch.linalg.svd(M)
    d = torch.sign(torch.linalg.det(U @ Vh))
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], dim=-1))
    return U @ D @ Vh


def canonical_up(body, shape: Tensor | None = None) -> np.ndarray:
    """The body model's up direction in its canonical space: from the root towards the
    head bone (Anny: +z, SMPL: +y), snapped to the nearest axis."""
    joints = body.canonical(shape).joints.detach().cpu().double().numpy()
    head = body.bone_index("head") if "head" in body.bone_names else int(np.argmax(np.linalg.norm(joints - joints[0], axis=1)))
    return snap_axis(joints[head] - joints[0], 90.0)


def snap_axis(v: np.ndarray, within_deg: float = 10.0) -> np.ndarray:
    """`v` normalised, replaced by the nearest signed coordinate axis when it lies within
    `within_deg` of it."""
    v = np.asarray(v, np.float64)
    v = v / max(np.linalg.norm(v), 1e-12)
    k = int(np.argmax(np.abs(v)))
    axis = np.sign(v[k]) * AXES[k]
    return axis if float(axis @ v) >= np.cos(np.deg2rad(within_deg)) else v


def world_up(human) -> np.ndarray:
    """The world's up direction as the reconstruction sees it: the body's canonical up
    turned by the root rotation of every frame, averaged (people mostly stand), snapped to
    a world axis within 10 degrees. Synthetic and Anny-fitted scenes give +z."""
    up_c = torch.as_tensor(canonical_up(human.body, human.shape), dtype=torch.float32, device=human.device)
    with torch.no_grad():
        roots = torch.cat([human.frame_pose(t)[0][:, 0] for t in range(human.n_frames)])  # [T, 3]
        from cogs.geometry.rotations import axis_angle_to_rotmat

        ups = axis_angle_to_rotmat(roots) @ up_c
    return snap_axis(ups.mean(0).cpu().double().numpy())


def gltf_from_world(up: np.ndarray) -> np.ndarray:
    """A rotation [3, 3] taking the world's `up` to glTF's +Y (the smallest such turn;
    for z-up worlds, -90 degrees about x)."""
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    y = np.array([0.0, 1.0, 0.0])
    from cogs.geometry.rotations import rotmat_from_two_vectors

    if np.allclose(up, [0.0, 0.0, 1.0]):
        return np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    return rotmat_from_two_vectors(torch.from_numpy(up), torch.from_numpy(y)).numpy()


def posed_human_splats(human, pose: Tensor, transl: Tensor, state=None) -> dict[str, Tensor]:
    """The human skinned to one pose for export: means [N, 3] (cogs' own LBS), unit wxyz
    quats [N, 4] from the polar decomposition of each blended skinning matrix, linear
    scales, opacities and shaded colours [N, 3] (albedo x the irradiance of the posed
    normal, as rendered)."""
    state = human.decode() if state is None else state
    A, _ = human.body.bone_transforms(pose, transl, human.shape)
    B = blend_transforms(state.weights, A[0])  # [N, 3, 4]
    means = (B[:, :, :3] @ state.means[:, :, None])[:, :, 0] + B[:, :, 3]
    R = polar_rotation(B[:, :, :3])
    quats = quat_multiply(rotmat_to_quat(R), state.quats)
    colors = state.colors
    if human.cfg.shading:
        colors = colors * human.shading(quat_to_rotmat(quats)[:, :, 2])
    return {"means": means, "quats": quats, "scales": state.scales, "opacities": state.opacities,
            "colors": colors.clamp(0.0, 1.0)}


def _fibonacci_sphere(n: int, dtype, device) -> Tensor:
    i = torch.arange(n, dtype=dtype, device=device) + 0.5
    phi = torch.arccos(1 - 2 * i / n)
    theta = torch.pi * (1 + 5 ** 0.5) * i
    return torch.stack([torch.cos(theta) * torch.sin(phi), torch.sin(theta) * torch.sin(phi), torch.cos(phi)], -1)


def rotate_sh(coeffs: Tensor, R: Tensor, degree: int) -> Tensor:
    """SH coefficients [N, K, 3] of a colour field f(d) -> those of f(R^T d) (the field
    turned by R), exactly for band-limited fields: a least-squares fit on 64 directions."""
    K = num_sh_bases(degree)
    if K == 1:
        return coeffs
    d = _fibonacci_sphere(64, torch.float64, coeffs.device)
    Y = sh_basis(degree, d)  # [64, K]
    Yr = sh_basis(degree, d @ R.double())  # Y(R^T d) for row vectors d
    M = (torch.linalg.pinv(Y) @ Yr).to(coeffs.dtype)  # [K, K]
    return torch.einsum("kj,njc->nkc", M, coeffs[:, :K])
