"""The EWA projection of :mod:`cogs.render.projection`, fused into numba with a hand-written
backward, for the CPU backend.

The torch version is ~100 small tensor ops whose launch overhead and autograd bookkeeping
cost more than the whole pixel pass at training sizes; here one loop over the Gaussians does
the same math in float64, vectorised across Gaussians (see ``_BLOCK``). Same semantics (see projection.py); parity with the torch
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
from numba import njit
from torch import Tensor

from cogs.parallel import parallel_for
from cogs.render.projection import EPS2D, Projected, _MAX_RADIUS

_QUAT_EPS = 1e-12  # as cogs.geometry.rotations.quat_normalize

# The per-Gaussian helpers are inlined into the loops by numba itself (as separate
# functions they stay calls, which LLVM cannot vectorise) and, like the loops, use numpy's
# error model: a division by zero gives inf/nan (guarded against by the math) instead of a
# branch to a Python exception in every iteration.
_LOOP = dict(cache=True, nogil=True, error_model="numpy")
_INLINE = dict(_LOOP, inline="always")


@njit(**_INLINE)
def _rotmat(qw, qx, qy, qz):
    return (1.0 - 2.0 * (qy * qy + qz * qz), 2.0 * (qx * qy - qw * qz), 2.0 * (qx * qz + qw * qy),
            2.0 * (qx * qy + qw * qz), 1.0 - 2.0 * (qx * qx + qz * qz), 2.0 * (qy * qz - qw * qx),
            2.0 * (qx * qz - qw * qy), 2.0 * (qy * qz + qw * qx), 1.0 - 2.0 * (qx * qx + qy * qy))


@njit(**_INLINE)
def _unit_quat(q0, q1, q2, q3):
    n = math.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
    if n > _QUAT_EPS:
        return q0 / n, q1 / n, q2 / n, q3 / n, n
    return 1.0, 0.0, 0.0, 0.0, 0.0


# The camera travels as a flat tuple of floats (a value, unlike an array argument, which
# costs reference-count traffic on every call of the per-Gaussian helpers):
# V row-major 3x4 (12), fx, fy, cx, cy, width, height, near, far, eps2d.
def camera_tuple(V: np.ndarray, K: np.ndarray, width, height, near, far, eps2d) -> tuple:
    return tuple(float(v) for v in V[:3, :4].reshape(-1)) + (
        float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), float(width),
        float(height), float(near), float(far), float(eps2d))


@njit(**_INLINE)
def _screen_terms(m0, m1, m2, q0, q1, q2, q3, s0, s1, s2, cam):
    """Everything the forward and backward share for one Gaussian (scalars only)."""
    (V00, V01, V02, V03, V10, V11, V12, V13, V20, V21, V22, V23,
     fx, fy, cx, cy, width, height, near, far, eps2d) = cam
    x = V00 * m0 + V01 * m1 + V02 * m2 + V03
    y = V10 * m0 + V11 * m1 + V12 * m2 + V13
    z = V20 * m0 + V21 * m1 + V22 * m2 + V23
    in_depth = (z > near) and (z < far)
    zs = z if in_depth else 1.0
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
    J00 = fx / zs
    J02 = -fx * uc / zs
    J11 = fy / zs
    J12 = -fy * vc / zs
    # A = J W (2x3)
    A = (J00 * V00 + J02 * V20, J00 * V01 + J02 * V21, J00 * V02 + J02 * V22,
         J11 * V10 + J12 * V20, J11 * V11 + J12 * V21, J11 * V12 + J12 * V22)
    qw, qx, qy, qz, qn = _unit_quat(q0, q1, q2, q3)
    R = _rotmat(qw, qx, qy, qz)
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
            (qw, qx, qy, qz, qn), a, b, c, det, ok)


@njit(**_INLINE)
def _forward_one(m0, m1, m2, q0, q1, q2, q3, s0, s1, s2, cam):
    """-> (means2d x, y, depth, conic a, b, c, radius)"""
    (x, y, z, zs, in_depth, u, v, uc, vc, u_free, v_free, A, M, B, R, q,
     a, b, c, det, ok) = _screen_terms(m0, m1, m2, q0, q1, q2, q3, s0, s1, s2, cam)
    fx, fy, cx, cy, width, height = cam[12], cam[13], cam[14], cam[15], cam[16], cam[17]
    mx = fx * u + cx
    my = fy * v + cy
    ds = det if ok else 1.0
    radius = 0
    if ok:
        hd = 0.5 * (a - c)
        lam = 0.5 * (a + c) + math.sqrt(hd * hd + b * b)
        r = min(math.ceil(3.0 * math.sqrt(max(lam, 0.0))), _MAX_RADIUS)
        if mx + r > 0 and mx - r < width and my + r > 0 and my - r < height:
            radius = int(r)
    return mx, my, z, c / ds, -b / ds, a / ds, radius


# The loops over Gaussians run in blocks of _BLOCK: the inputs are gathered into one flat
# structure-of-arrays float64 buffer (row c of Gaussian k at c * _BLOCK + k) and the results
# written to another. With one buffer read and one written at constant row distances, LLVM
# needs a single runtime overlap check and vectorises the per-Gaussian math across Gaussians
# (8 float64 lanes with AVX-512); reading the [N, 3] / [N, 4] inputs directly, it needs one
# check per pair of arrays and gives up (0.9 -> 0.35 ms forward for 20k Gaussians).
_BLOCK = 128
# Gaussians per thread's work item: vectorised, a pass costs ~20 ns (forward) to ~35 ns
# (backward) per Gaussian, so a second thread pays only from ~30k Gaussians on (at 20k
# two threads measured 0.6 / 1.1 ms against 0.45 / 0.9 ms serially, in a training step).
_MIN_CHUNK = 16384


@njit(**_INLINE)
def _gather(b0, n, means, quats, scales, P):
    """Gaussians b0..b0+n-1 into rows 0-9 of P: mean xyz, quat wxyz, scale xyz."""
    for k in range(n):
        i = b0 + k
        for c in range(3):
            P[c * _BLOCK + k] = means[i, c]
            P[(7 + c) * _BLOCK + k] = scales[i, c]
        for c in range(4):
            P[(3 + c) * _BLOCK + k] = quats[i, c]


@njit(**_LOOP)
def _forward_range(lo, hi, means, quats, scales, cam, means2d, conics, depths, radii):
    P = np.empty(10 * _BLOCK)
    O = np.empty(7 * _BLOCK)
    B = np.uint64(_BLOCK)
    for b0 in range(lo, hi, _BLOCK):
        n = min(_BLOCK, hi - b0)
        _gather(b0, n, means, quats, scales, P)
        for k in range(np.uint64(0), np.uint64(n)):
            (O[k], O[B + k], O[2 * B + k], O[3 * B + k], O[4 * B + k], O[5 * B + k],
             O[6 * B + k]) = _forward_one(P[k], P[B + k], P[2 * B + k], P[3 * B + k],
                                          P[4 * B + k], P[5 * B + k], P[6 * B + k],
                                          P[7 * B + k], P[8 * B + k], P[9 * B + k], cam)
        for k in range(n):
            i = b0 + k
            means2d[i, 0] = O[k]
            means2d[i, 1] = O[_BLOCK + k]
            depths[i] = O[2 * _BLOCK + k]
            for c in range(3):
                conics[i, c] = O[(3 + c) * _BLOCK + k]
            radii[i] = np.int32(O[6 * _BLOCK + k])


def project_forward(means, quats, scales, cam):
    n = means.shape[0]
    out = (np.empty((n, 2), np.float32), np.empty((n, 3), np.float32), np.empty(n, np.float32),
           np.zeros(n, np.int32))
    parallel_for(_forward_range, n, means, quats, scales, cam, *out, min_chunk=_MIN_CHUNK)
    return out


@njit(**_INLINE)
def _backward_one(m0, m1, m2, q0, q1, q2, q3, s0, s1, s2, cam, gmx, gmy, g0, g1, g2, gd):
    """Upstream (means2d, conic, depth) grads -> (mean xyz, quat wxyz, scale xyz) grads."""
    (x, y, z, zs, in_depth, u, v, uc, vc, u_free, v_free, A, M, B, R, q,
     a, b, c, det, ok) = _screen_terms(m0, m1, m2, q0, q1, q2, q3, s0, s1, s2, cam)
    (V00, V01, V02, V03, V10, V11, V12, V13, V20, V21, V22, V23, fx, fy) = cam[:14]
    # camera-space point gradient: means2d = (fx x/zs + cx, fy y/zs + cy), depth = z
    g_x = gmx * fx / zs
    g_y = gmy * fy / zs
    g_z = gd
    if in_depth:
        g_z -= (gmx * fx * x + gmy * fy * y) / (zs * zs)
    vq0 = vq1 = vq2 = vq3 = 0.0
    vs0 = vs1 = vs2 = 0.0
    if ok:
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
        vs0 = vM0 * R[0] + vM3 * R[3] + vM6 * R[6]
        vs1 = vM1 * R[1] + vM4 * R[4] + vM7 * R[7]
        vs2 = vM2 * R[2] + vM5 * R[5] + vM8 * R[8]
        r0, r1, r2 = vM0 * s0, vM1 * s1, vM2 * s2
        r3, r4, r5 = vM3 * s0, vM4 * s1, vM5 * s2
        r6, r7, r8 = vM6 * s0, vM7 * s1, vM8 * s2
        qw, qx, qy, qz, qn = q
        if qn > 0.0:  # a zero quaternion is the constant identity: no gradient
            gw = 2.0 * (-qz * r1 + qy * r2 + qz * r3 - qx * r5 - qy * r6 + qx * r7)
            gx = 2.0 * (qy * r1 + qz * r2 + qy * r3 - 2.0 * qx * r4 - qw * r5
                        + qz * r6 + qw * r7 - 2.0 * qx * r8)
            gy = 2.0 * (-2.0 * qy * r0 + qx * r1 + qw * r2 + qx * r3 + qz * r5
                        - qw * r6 + qz * r7 - 2.0 * qy * r8)
            gz = 2.0 * (-2.0 * qz * r0 - qw * r1 + qx * r2 + qw * r3
                        - 2.0 * qz * r4 + qy * r5 + qx * r6 + qy * r7)
            # through the normalisation q / |q|
            dot = qw * gw + qx * gx + qy * gy + qz * gz
            vq0 = (gw - qw * dot) / qn
            vq1 = (gx - qx * dot) / qn
            vq2 = (gy - qy * dot) / qn
            vq3 = (gz - qz * dot) / qn
        # A = J W
        vJ00 = vA0 * V00 + vA1 * V01 + vA2 * V02
        vJ02 = vA0 * V20 + vA1 * V21 + vA2 * V22
        vJ11 = vA3 * V10 + vA4 * V11 + vA5 * V12
        vJ12 = vA3 * V20 + vA4 * V21 + vA5 * V22
        # J00 = fx/z, J02 = -fx uc/z, J11 = fy/z, J12 = -fy vc/z, uc = clamp(x/z)
        zz = z * z
        g_z += -vJ00 * fx / zz - vJ11 * fy / zz + vJ02 * fx * uc / zz + vJ12 * fy * vc / zz
        if u_free:
            g_x += vJ02 * (-fx / zz)
            g_z += vJ02 * (fx * x / (zz * z))
        if v_free:
            g_y += vJ12 * (-fy / zz)
            g_z += vJ12 * (fy * y / (zz * z))
    # mean: t = W m + T
    vm0 = V00 * g_x + V10 * g_y + V20 * g_z
    vm1 = V01 * g_x + V11 * g_y + V21 * g_z
    vm2 = V02 * g_x + V12 * g_y + V22 * g_z
    return vm0, vm1, vm2, vq0, vq1, vq2, vq3, vs0, vs1, vs2


@njit(**_LOOP)
def _backward_range(lo, hi, means, quats, scales, cam, v_means2d, v_conics, v_depths, v_means,
                    v_quats, v_scales):
    P = np.empty(16 * _BLOCK)  # rows 10-15: upstream gradients of means2d xy, conic abc, depth
    O = np.empty(10 * _BLOCK)
    B = np.uint64(_BLOCK)
    for b0 in range(lo, hi, _BLOCK):
        n = min(_BLOCK, hi - b0)
        _gather(b0, n, means, quats, scales, P)
        for k in range(n):
            i = b0 + k
            P[10 * _BLOCK + k] = v_means2d[i, 0]
            P[11 * _BLOCK + k] = v_means2d[i, 1]
            for c in range(3):
                P[(12 + c) * _BLOCK + k] = v_conics[i, c]
            P[15 * _BLOCK + k] = v_depths[i]
        for k in range(np.uint64(0), np.uint64(n)):
            (O[k], O[B + k], O[2 * B + k], O[3 * B + k], O[4 * B + k], O[5 * B + k],
             O[6 * B + k], O[7 * B + k], O[8 * B + k], O[9 * B + k]) = _backward_one(
                P[k], P[B + k], P[2 * B + k], P[3 * B + k], P[4 * B + k], P[5 * B + k],
                P[6 * B + k], P[7 * B + k], P[8 * B + k], P[9 * B + k], cam,
                P[10 * B + k], P[11 * B + k], P[12 * B + k], P[13 * B + k], P[14 * B + k],
                P[15 * B + k])
        for k in range(n):
            i = b0 + k
            for c in range(3):
                v_means[i, c] = O[c * _BLOCK + k]
                v_scales[i, c] = O[(7 + c) * _BLOCK + k]
            for c in range(4):
                v_quats[i, c] = O[(3 + c) * _BLOCK + k]


def project_backward(means, quats, scales, cam, v_means2d, v_conics, v_depths):
    n = means.shape[0]
    out = (np.zeros((n, 3), np.float32), np.zeros((n, 4), np.float32), np.zeros((n, 3), np.float32))
    parallel_for(_backward_range, n, means, quats, scales, cam, v_means2d, v_conics, v_depths,
                 *out, min_chunk=_MIN_CHUNK)
    return out


def _np(t: Tensor, dtype=np.float32) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy().astype(dtype, copy=False))


class _Project(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, viewmat, K, width, height, near, far):
        cam = camera_tuple(_np(viewmat, np.float64), _np(K, np.float64), width, height, near,
                           far, EPS2D)
        args = (_np(means), _np(quats), _np(scales), cam)
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
