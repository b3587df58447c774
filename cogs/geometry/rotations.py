"""Rotations: unit quaternions (w, x, y, z), axis-angle vectors and 3x3 matrices.

One place for every rotation helper in the project. All functions are pure, batched over
leading dimensions, differentiable, and work on float32 or float64 tensors. Quaternions
are scalar-first (wxyz), the convention of the 3DGS PLY layout and of gsplat; roma (used
where convenient) is scalar-last, so conversions live here and nowhere else.
"""

from __future__ import annotations

import torch
from torch import Tensor

_EPS = 1e-12


def quat_normalize(q: Tensor) -> Tensor:
    """Unit quaternion of the same rotation; a zero quaternion becomes the identity."""
    norm = q.norm(dim=-1, keepdim=True)
    identity = torch.zeros_like(q)
    identity[..., 0] = 1.0
    return torch.where(norm > _EPS, q / norm.clamp_min(_EPS), identity)


def quat_to_rotmat(q: Tensor) -> Tensor:
    """[..., 4] wxyz (need not be unit) -> [..., 3, 3]."""
    w, x, y, z = quat_normalize(q).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(q.shape[:-1] + (3, 3))


def rotmat_to_quat(R: Tensor) -> Tensor:
    """[..., 3, 3] rotation -> [..., 4] unit wxyz with w >= 0."""
    import roma

    xyzw = roma.rotmat_to_unitquat(R)
    q = torch.cat([xyzw[..., 3:], xyzw[..., :3]], dim=-1)
    return torch.where(q[..., :1] < 0, -q, q)


def quat_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product a * b (apply b first, then a)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


def quat_conjugate(q: Tensor) -> Tensor:
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def axis_angle_to_quat(v: Tensor) -> Tensor:
    """[..., 3] rotation vector (axis * angle, radians) -> [..., 4] unit wxyz."""
    angle = v.norm(dim=-1, keepdim=True)
    half = 0.5 * angle
    # sin(half)/angle, with its Taylor series near zero so gradients stay finite.
    small = angle < 1e-6
    safe = torch.where(small, torch.ones_like(angle), angle)
    k = torch.where(small, 0.5 - angle * angle / 48.0, torch.sin(half) / safe)
    return torch.cat([torch.cos(half), v * k], dim=-1)


def quat_to_axis_angle(q: Tensor) -> Tensor:
    """[..., 4] wxyz -> [..., 3] rotation vector with angle in [0, pi]."""
    q = quat_normalize(q)
    q = torch.where(q[..., :1] < 0, -q, q)
    xyz = q[..., 1:]
    s = xyz.norm(dim=-1, keepdim=True)
    angle = 2.0 * torch.atan2(s, q[..., :1])
    small = s < 1e-6
    safe = torch.where(small, torch.ones_like(s), s)
    k = torch.where(small, 2.0 / q[..., :1].clamp_min(_EPS), angle / safe)
    return xyz * k


def axis_angle_to_rotmat(v: Tensor) -> Tensor:
    return quat_to_rotmat(axis_angle_to_quat(v))


def rotmat_to_axis_angle(R: Tensor) -> Tensor:
    return quat_to_axis_angle(rotmat_to_quat(R))


def quat_geodesic_angle(a: Tensor, b: Tensor) -> Tensor:
    """Angle in radians of the rotation taking a to b, in [0, pi]; sign-invariant.

    Computed as 2 atan2(|v|, |w|) of the relative quaternion, which is accurate for small
    angles and has finite gradients everywhere except exactly at zero, where it is masked.
    """
    rel = quat_multiply(quat_conjugate(quat_normalize(a)), quat_normalize(b))
    w = rel[..., 0].abs()
    v = rel[..., 1:]
    sq = (v * v).sum(-1)
    # sqrt has an infinite slope at 0; where the rotations coincide the angle's
    # subgradient 0 is used.
    nz = sq > 1e-20
    vnorm = torch.sqrt(torch.where(nz, sq, torch.ones_like(sq)))
    vnorm = torch.where(nz, vnorm, torch.zeros_like(vnorm))
    return 2.0 * torch.atan2(vnorm, w)


def quat_sign_continuous(q: Tensor) -> Tensor:
    """Quaternions [T, ..., 4] along time, each q[k] flipped to the side of q[k-1]
    (elementwise over the middle dimensions): q and -q are one rotation, and blending or
    interpolating along T needs neighbours on the same side."""
    q = q.clone()
    for k in range(1, q.shape[0]):
        q[k] = torch.where((q[k] * q[k - 1]).sum(-1, keepdim=True) < 0, -q[k], q[k])
    return q


def rotmat_geodesic_angle(Ra: Tensor, Rb: Tensor) -> Tensor:
    """Angle in radians between two rotation matrices, in [0, pi]."""
    rel = Ra.transpose(-1, -2) @ Rb
    cos = ((rel.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0) * 0.5).clamp(-1.0, 1.0)
    return torch.arccos(cos)


def slerp(q0: Tensor, q1: Tensor, u: Tensor) -> Tensor:
    """Spherical linear interpolation along the shortest arc.

    q0, q1: [..., 4] unit wxyz; u: [...] in [0, 1]. Returns unit quaternions; constant
    angular speed in u. Falls back to normalised lerp when the endpoints nearly coincide.
    """
    q0 = quat_normalize(q0)
    q1 = quat_normalize(q1)
    dot = (q0 * q1).sum(-1, keepdim=True)
    q1 = torch.where(dot < 0, -q1, q1)  # shortest arc
    dot = dot.abs().clamp(max=1.0)
    u = u.unsqueeze(-1)
    theta = torch.arccos(dot.clamp(max=1.0 - 1e-7))
    sin_theta = torch.sin(theta)
    near = dot > 0.9995
    safe_sin = torch.where(near, torch.ones_like(sin_theta), sin_theta)
    w0 = torch.where(near, 1.0 - u, torch.sin((1.0 - u) * theta) / safe_sin)
    w1 = torch.where(near, u, torch.sin(u * theta) / safe_sin)
    return quat_normalize(w0 * q0 + w1 * q1)


def random_quat(n: int, generator: torch.Generator | None = None, dtype=torch.float32, device=None) -> Tensor:
    """n rotations uniform on SO(3) (normalised Gaussian 4-vectors), wxyz; drawn on the
    generator's device unless `device` is given."""
    device = device if device is not None else (generator.device if generator is not None else None)
    q = torch.randn(n, 4, generator=generator, dtype=dtype, device=device)
    return quat_normalize(q)


def rotmat_from_two_vectors(a: Tensor, b: Tensor) -> Tensor:
    """Smallest rotation taking unit vector a to unit vector b ([..., 3] each)."""
    a = a / a.norm(dim=-1, keepdim=True).clamp_min(_EPS)
    b = b / b.norm(dim=-1, keepdim=True).clamp_min(_EPS)
    v = torch.linalg.cross(a, b, dim=-1)
    c = (a * b).sum(-1, keepdim=True)
    # Quaternion (1 + c, v) normalised is the half-angle rotation; antipodal vectors
    # need an arbitrary perpendicular axis.
    q = torch.cat([1.0 + c, v], dim=-1)
    anti = (1.0 + c) < 1e-8
    perp = torch.linalg.cross(a, a.new_tensor([1.0, 0.0, 0.0]).expand_as(a), dim=-1)
    perp2 = torch.linalg.cross(a, a.new_tensor([0.0, 1.0, 0.0]).expand_as(a), dim=-1)
    perp = torch.where(perp.norm(dim=-1, keepdim=True) > 1e-6, perp, perp2)
    q_anti = torch.cat([torch.zeros_like(c), perp], dim=-1)
    return quat_to_rotmat(torch.where(anti, q_anti, q))
