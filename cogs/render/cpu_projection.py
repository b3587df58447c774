"""The EWA projection of :mod:`cogs.render.projection`, fused into numba with a hand-written
backward, for the CPU backend.

The torch version is ~100 small tensor ops whose launch overhead and autograd bookkeeping
cost more than the whole pixel pass at training sizes; here one pass per Gaussian does the
same math in float64 registers. Same semantics (see projection.py); parity with the torch
version and with autograd is tested.

Gradients: means2d, conics and depths flow back to means, quats and scales. A culled
Gaussian (radius 0) still passes gradients from ``means2d`` and ``depths`` (which stay
defined for it), but none from its conic, which nothing can observe. Camera gradients are
not computed here: when ``viewmat`` or ``K`` requires grad the CPU backend uses the torch
projection instead (see cpu_backend.project).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from cogs.render._kernels import PARALLEL_MIN_N
from cogs.render.projection import EPS2D, Projected, _MAX_RADIUS

_QUAT_EPS = 1e-12  # as cogs.geometry.rotations.quat_normalize


@njit(cache=True, nogil=True)
def _rotmat(qw, qx, qy, qz):
    return (1.0 - 2.0 * (qy * qy + qz * qz), 2.0 * (qx * qy - qw * qz), 2.0 * (qx * qz + qw * qy),
            2.0 * (qx * qy + qw * qz), 1.0 - 2.0 * (qx * qx + qz * qz), 2.0 * (qy * qz - qw * qx),
            2.0 * (qx * qz - qw * qy), 2.0 * (qy * qz + qw * qx), 1.0 - 2.0 * (qx * qx + qy * qy))


@njit(cache=True, nogil=True)
def _unit_quat(q):
    n = math.sqrt(float(q[0]) ** 2 + float(q[1]) ** 2 + float(q[2]) ** 2 + float(q[3]) ** 2)
    if n > _QUAT_EPS:
        return q[0] / n, q[1] / n, q[2] / n, q[3] / n, n
    return 1.0, 0.0, 0.0, 0.0, 0.0


@njit(cache=True, nogil=True)
def _camera_terms(mean, V, K, width, height, near, far):
    """Camera-space point, depth flag, clamped normalised coordinates and limit flags."""
    x = V[0, 0] * mean[0] + V[0, 1] * mean[1] + V[0, 2] * mean[2] + V[0, 3]
    y = V[1, 0] * mean[0] + V[1, 1] * mean[1] + V[1, 2] * mean[2] + V[1, 3]
    z = V[2, 0] * mean[0] + V[2, 1] * mean[1] + V[2, 2] * mean[2] + V[2, 3]
    in_depth = (z > near) and (z < far)
    zs = z if in_depth else 1.0
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    tan_x = 0.5 * width / fx
    tan_y = 0.5 * height / fy
    lim_xp = (width - cx) / fx + 0.3 * tan_x
    lim_xn = cx / fx + 0.3 * tan_x
    lim_yp = (height - cy) / fy + 0.3 * tan_y
    lim_yn = cy / fy + 0.3 * tan_y
    u = x / zs
    v = y / zs
    uc = min(max(u, -lim_xn), lim_xp)
    vc = min(max(v, -lim_yn), lim_yp)
    u_free = (u > -lim_xn) and (u < lim_xp)
    v_free = (v > -lim_yn) and (v < lim_yp)
    return x, y, z, zs, in_depth, u, v, uc, vc, u_free, v_free


@njit(cache=True, nogil=True)
def _screen_terms(i, means, quats, scales, V, K, width, height, near, far, eps2d):
    """Everything the forward and backward share for Gaussian i (all scalars: no heap)."""
    x, y, z, zs, in_depth, u, v, uc, vc, u_free, v_free = _camera_terms(
        means[i], V, K, width, height, near, far)
    fx, fy = K[0, 0], K[1, 1]
    J00 = fx / zs
    J02 = -fx * uc / zs
    J11 = fy / zs
    J12 = -fy * vc / zs
    # A = J W (2x3)
    A = (J00 * V[0, 0] + J02 * V[2, 0], J00 * V[0, 1] + J02 * V[2, 1], J00 * V[0, 2] + J02 * V[2, 2],
         J11 * V[1, 0] + J12 * V[2, 0], J11 * V[1, 1] + J12 * V[2, 1], J11 * V[1, 2] + J12 * V[2, 2])
    qw, qx, qy, qz, qn = _unit_quat(quats[i])
    R = _rotmat(qw, qx, qy, qz)
    s0, s1, s2 = float(scales[i, 0]), float(scales[i, 1]), float(scales[i, 2])
    # M = R diag(s)
    M = (R[0] * s0, R[1] * s1, R[2] * s2, R[3] * s0, R[4] * s1, R[5] * s2,
         R[6] * s0, R[7] * s1, R[8] * s2)
    # B = A M (2x3), cov2d = B B^T
    B = (A[0] * M[0] + A[1] * M[3] + A[2] * M[6], A[0] * M[1] + A[1] * M[4] + A[2] * M[7],
         A[0] * M[2] + A[1] * M[5] + A[2] * M[8], A[3] * M[0] + A[4] * M[3] + A[5] * M[6],
         A[3] * M[1] + A[4] * M[4] + A[5] * M[7], A[3] * M[2] + A[4] * M[5] + A[5] * M[8])
    a = B[0] * B[0] + B[1] * B[1] + B[2] * B[2] + eps2d
    b = B[0] * B[3] + B[1] * B[4] + B[2] * B[5]
    c = B[3] * B[3] + B[4] * B[4] + B[5] * B[5] + eps2d
    det = a * c - b * b
    ok = in_depth and det > 0.0 and det < 1e300
    return (x, y, z, zs, in_depth, u, v, uc, vc, u_free, v_free, A, M, B, R,
            (qw, qx, qy, qz, qn), (s0, s1, s2), a, b, c, det, ok)


@njit(cache=True, nogil=True)
def _forward_one(i, means, quats, scales, V, K, width, height, near, far, eps2d,
                 means2d, conics, depths, radii):
    (x, y, z, zs, in_depth, u, v, uc, vc, u_free, v_free, A, M, B, R, q, sc,
     a, b, c, det, ok) = _screen_terms(i, means, quats, scales, V, K, width, height,
                                       near, far, eps2d)
    mx = K[0, 0] * u + K[0, 2]
    my = K[1, 1] * v + K[1, 2]
    means2d[i, 0] = mx
    means2d[i, 1] = my
    depths[i] = z
    ds = det if ok else 1.0
    conics[i, 0] = c / ds
    conics[i, 1] = -b / ds
    conics[i, 2] = a / ds
    radii[i] = 0
    if ok:
        hd = 0.5 * (a - c)
        lam = 0.5 * (a + c) + math.sqrt(hd * hd + b * b)
        r = min(math.ceil(3.0 * math.sqrt(max(lam, 0.0))), _MAX_RADIUS)
        if mx + r > 0 and mx - r < width and my + r > 0 and my - r < height:
            radii[i] = np.int32(r)


@njit(cache=True, nogil=True, parallel=True)
def _forward_parallel(means, quats, scales, V, K, width, height, near, far, eps2d, out):
    for i in prange(means.shape[0]):
        _forward_one(i, means, quats, scales, V, K, width, height, near, far, eps2d, *out)


@njit(cache=True, nogil=True)
def _forward_serial(means, quats, scales, V, K, width, height, near, far, eps2d, out):
    for i in range(means.shape[0]):
        _forward_one(i, means, quats, scales, V, K, width, height, near, far, eps2d, *out)


def project_forward(means, quats, scales, V, K, width, height, near, far, eps2d):
    n = means.shape[0]
    out = (np.empty((n, 2), np.float32), np.empty((n, 3), np.float32), np.empty(n, np.float32),
           np.zeros(n, np.int32))
    fn = _forward_parallel if n >= PARALLEL_MIN_N else _forward_serial
    fn(means, quats, scales, V, K, width, height, near, far, eps2d, out)
    return out


@njit(cache=True, nogil=True)
def _backward_one(i, means, quats, scales, V, K, width, height, near, far, eps2d,
                  v_means2d, v_conics, v_depths, v_means, v_quats, v_scales):
    fx, fy = K[0, 0], K[1, 1]
    (x, y, z, zs, in_depth, u, v, uc, vc, u_free, v_free, A, M, B, R, q, sc,
     a, b, c, det, ok) = _screen_terms(i, means, quats, scales, V, K, width, height,
                                       near, far, eps2d)
    # camera-space point gradient: means2d = (fx x/zs + cx, fy y/zs + cy), depth = z
    gmx = float(v_means2d[i, 0])
    gmy = float(v_means2d[i, 1])
    g_x = gmx * fx / zs
    g_y = gmy * fy / zs
    g_z = float(v_depths[i])
    if in_depth:
        g_z -= (gmx * fx * x + gmy * fy * y) / (zs * zs)
    if ok:
        g0 = float(v_conics[i, 0])
        g1 = float(v_conics[i, 1])
        g2 = float(v_conics[i, 2])
        d2 = det * det
        # conic = (c, -b, a) / det with det = a c - b^2
        v_a = g0 * (-c * c / d2) + g1 * (b * c / d2) + g2 * (1.0 / det - a * c / d2)
        v_b = (g0 * (2.0 * b * c / d2) + g1 * (-1.0 / det - 2.0 * b * b / d2)
               + g2 * (2.0 * a * b / d2))
        v_c = g0 * (1.0 / det - a * c / d2) + g1 * (a * b / d2) + g2 * (-a * a / d2)
        # a = |B0|^2 + eps, b = B0.B1, c = |B1|^2 + eps  (B0 = B[0:3], B1 = B[3:6])
        vB0 = 2.0 * v_a * B[0] + v_b * B[3]
        vB1 = 2.0 * v_a * B[1] + v_b * B[4]
        vB2 = 2.0 * v_a * B[2] + v_b * B[5]
        vB3 = 2.0 * v_c * B[3] + v_b * B[0]
        vB4 = 2.0 * v_c * B[4] + v_b * B[1]
        vB5 = 2.0 * v_c * B[5] + v_b * B[2]
        # B = A M: vA = vB M^T, vM = A^T vB
        vA0 = vB0 * M[0] + vB1 * M[1] + vB2 * M[2]
        vA1 = vB0 * M[3] + vB1 * M[4] + vB2 * M[5]
        vA2 = vB0 * M[6] + vB1 * M[7] + vB2 * M[8]
        vA3 = vB3 * M[0] + vB4 * M[1] + vB5 * M[2]
        vA4 = vB3 * M[3] + vB4 * M[4] + vB5 * M[5]
        vA5 = vB3 * M[6] + vB4 * M[7] + vB5 * M[8]
        vM0 = A[0] * vB0 + A[3] * vB3
        vM1 = A[0] * vB1 + A[3] * vB4
        vM2 = A[0] * vB2 + A[3] * vB5
        vM3 = A[1] * vB0 + A[4] * vB3
        vM4 = A[1] * vB1 + A[4] * vB4
        vM5 = A[1] * vB2 + A[4] * vB5
        vM6 = A[2] * vB0 + A[5] * vB3
        vM7 = A[2] * vB1 + A[5] * vB4
        vM8 = A[2] * vB2 + A[5] * vB5
        # M = R diag(s)
        s0, s1, s2 = sc
        v_scales[i, 0] = vM0 * R[0] + vM3 * R[3] + vM6 * R[6]
        v_scales[i, 1] = vM1 * R[1] + vM4 * R[4] + vM7 * R[7]
        v_scales[i, 2] = vM2 * R[2] + vM5 * R[5] + vM8 * R[8]
        r0, r1, r2 = vM0 * s0, vM1 * s1, vM2 * s2
        r3, r4, r5 = vM3 * s0, vM4 * s1, vM5 * s2
        r6, r7, r8 = vM6 * s0, vM7 * s1, vM8 * s2
        qw, qx, qy, qz, qn = q
        if qn > 0.0:
            gw = 2.0 * (-qz * r1 + qy * r2 + qz * r3 - qx * r5 - qy * r6 + qx * r7)
            gx = 2.0 * (qy * r1 + qz * r2 + qy * r3 - 2.0 * qx * r4 - qw * r5
                        + qz * r6 + qw * r7 - 2.0 * qx * r8)
            gy = 2.0 * (-2.0 * qy * r0 + qx * r1 + qw * r2 + qx * r3 + qz * r5
                        - qw * r6 + qz * r7 - 2.0 * qy * r8)
            gz = 2.0 * (-2.0 * qz * r0 - qw * r1 + qx * r2 + qw * r3
                        - 2.0 * qz * r4 + qy * r5 + qx * r6 + qy * r7)
            dot = qw * gw + qx * gx + qy * gy + qz * gz
            v_quats[i, 0] = (gw - qw * dot) / qn
            v_quats[i, 1] = (gx - qx * dot) / qn
            v_quats[i, 2] = (gy - qy * dot) / qn
            v_quats[i, 3] = (gz - qz * dot) / qn
        # A = J W
        vJ00 = vA0 * V[0, 0] + vA1 * V[0, 1] + vA2 * V[0, 2]
        vJ02 = vA0 * V[2, 0] + vA1 * V[2, 1] + vA2 * V[2, 2]
        vJ11 = vA3 * V[1, 0] + vA4 * V[1, 1] + vA5 * V[1, 2]
        vJ12 = vA3 * V[2, 0] + vA4 * V[2, 1] + vA5 * V[2, 2]
        # J00 = fx/z, J02 = -fx uc/z, J11 = fy/z, J12 = -fy vc/z, uc = clamp(x/z)
        zz = z * z
        g_z += -vJ00 * fx / zz - vJ11 * fy / zz + vJ02 * fx * uc / zz + vJ12 * fy * vc / zz
        if u_free:
            g_x += vJ02 * (-fx / zz)
            g_z += vJ02 * (fx * x / (zz * z))
        if v_free:
            g_y += vJ12 * (-fy / zz)
            g_z += vJ12 * (fy * y / (zz * z))
    for k in range(3):
        v_means[i, k] = V[0, k] * g_x + V[1, k] * g_y + V[2, k] * g_z


@njit(cache=True, nogil=True, parallel=True)
def _backward_parallel(means, quats, scales, V, K, width, height, near, far, eps2d, grads, out):
    for i in prange(means.shape[0]):
        _backward_one(i, means, quats, scales, V, K, width, height, near, far, eps2d, *grads, *out)


@njit(cache=True, nogil=True)
def _backward_serial(means, quats, scales, V, K, width, height, near, far, eps2d, grads, out):
    for i in range(means.shape[0]):
        _backward_one(i, means, quats, scales, V, K, width, height, near, far, eps2d, *grads, *out)


def project_backward(means, quats, scales, V, K, width, height, near, far, eps2d,
                     v_means2d, v_conics, v_depths):
    n = means.shape[0]
    out = (np.zeros((n, 3), np.float32), np.zeros((n, 4), np.float32), np.zeros((n, 3), np.float32))
    fn = _backward_parallel if n >= PARALLEL_MIN_N else _backward_serial
    fn(means, quats, scales, V, K, width, height, near, far, eps2d,
       (v_means2d, v_conics, v_depths), out)
    return out


def _np(t: Tensor, dtype=np.float32) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy().astype(dtype, copy=False))


class _Project(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, viewmat, K, width, height, near, far):
        args = (_np(means), _np(quats), _np(scales), _np(viewmat, np.float64), _np(K, np.float64),
                float(width), float(height), float(near), float(far), EPS2D)
        means2d, conics, depths, radii = project_forward(*args)
        ctx.args = args
        ctx.like = (means, quats, scales)
        radii_t = torch.from_numpy(radii).to(means.device)
        ctx.mark_non_differentiable(radii_t)
        to = dict(device=means.device, dtype=means.dtype)
        return (torch.from_numpy(means2d).to(**to), torch.from_numpy(conics).to(**to),
                torch.from_numpy(depths).to(**to), radii_t)

    @staticmethod
    def backward(ctx, v_means2d, v_conics, v_depths, _v_radii):
        grads = project_backward(*ctx.args, _np(v_means2d), _np(v_conics), _np(v_depths))
        out = [torch.from_numpy(g).to(device=like.device, dtype=like.dtype)
               for g, like in zip(grads, ctx.like)]
        return (*out, None, None, None, None, None, None)


def project_gaussians_fused(means, quats, scales, viewmat, K, width, height, near=0.01,
                            far=1e10) -> Projected:
    """numba twin of :func:`cogs.render.projection.project_gaussians` (no camera grads)."""
    means2d, conics, depths, radii = _Project.apply(means, quats, scales, viewmat, K, width,
                                                    height, near, far)
    return Projected(means2d=means2d, conics=conics, depths=depths, radii=radii, means_cam=None)
