"""SSIM fused into numba kernels with a hand-written backward: the D-SSIM training loss on
the CPU (`cogs.ssim.ssim`).

The torch version (`cogs.ssim.ssim_torch`, the reference) blurs five maps with ten
depthwise convolutions and combines them in a dozen image-sized ops, each with its
backward. On the CPU the depthwise convolutions run at ~1 GFLOP/s: at 960x540 the loss
cost ~0.2 s of a ~0.9 s training step. Here two separable passes do the five blurs
(horizontal into [C, H, W-10] maps, vertical into the valid [C, H-10, W-10] region, where
the SSIM map and its three partial derivatives are formed at once), and the backward is
the transposed pair of passes. Rows are spread over `cogs.parallel`'s threads. Float32
maps, float64 row sums; same semantics as the reference (scikit-image's Gaussian SSIM,
mean over the valid region), parity tested to float32 precision.

Gradient (per valid window centre, S = A1 A2 / (B1 B2) with A1 = 2 mu_x mu_y + c1,
A2 = 2 s_xy + c2, B1 = mu_x^2 + mu_y^2 + c1, B2 = s_xx + s_yy + c2, and the blurred
moments mu_x = w*x, E_xx = w*x^2, E_xy = w*xy):

    dS/dmu_x = 2 mu_y (A2 - A1) / (B1 B2) + 2 mu_x S (1/B2 - 1/B1)
    dS/dE_xx = -S / B2
    dS/dE_xy = 2 A1 / (B1 B2)

and dx = w^T * dS/dmu_x + 2 x (w^T * dS/dE_xx) + y (w^T * dS/dE_xy), w^T the transposed
(full) blur. Only the first image gets a gradient (the training's target is constant).
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit
from torch import Tensor

from cogs.parallel import parallel_for

_OPTS = dict(cache=True, nogil=True, error_model="numpy", fastmath={"contract", "reassoc"})
_MIN_ROWS = 32  # rows per work item: a row of 1000 pixels costs ~2 us a pass


@njit(**_OPTS)
def _horizontal(lo, hi, x, y, w, hx, hy, hxx, hyy, hxy):
    """Rows lo..hi of the flattened [C*H] rows: the five moments blurred along x (valid)."""
    C, H, W = x.shape
    K = w.shape[0]
    Wv = W - K + 1
    for rr in range(lo, hi):
        c, r = rr // H, rr % H
        xr, yr = x[c, r], y[c, r]
        ox, oy, oxx, oyy, oxy = hx[c, r], hy[c, r], hxx[c, r], hyy[c, r], hxy[c, r]
        for j in range(Wv):
            ox[j] = 0.0
            oy[j] = 0.0
            oxx[j] = 0.0
            oyy[j] = 0.0
            oxy[j] = 0.0
        for k in range(K):
            wk = w[k]
            for j in range(Wv):
                a = xr[j + k]
                b = yr[j + k]
                ox[j] += wk * a
                oy[j] += wk * b
                oxx[j] += wk * a * a
                oyy[j] += wk * b * b
                oxy[j] += wk * a * b


@njit(**_OPTS)
def _vertical(lo, hi, hx, hy, hxx, hyy, hxy, w, c1, c2, rowsum, g_mu, g_xx, g_xy):
    """Valid rows lo..hi of the flattened [C*Hv] rows: the blur along y, the SSIM map's row
    sum and its partial derivatives with respect to mu_x, E_xx and E_xy."""
    C, H, Wv = hx.shape
    K = w.shape[0]
    Hv = H - K + 1
    mx = np.empty(Wv, np.float32)
    my = np.empty(Wv, np.float32)
    exx = np.empty(Wv, np.float32)
    eyy = np.empty(Wv, np.float32)
    exy = np.empty(Wv, np.float32)
    for rr in range(lo, hi):
        c, i = rr // Hv, rr % Hv
        mx[:] = 0.0
        my[:] = 0.0
        exx[:] = 0.0
        eyy[:] = 0.0
        exy[:] = 0.0
        for k in range(K):
            wk = w[k]
            ax, ay, axx, ayy, axy = hx[c, i + k], hy[c, i + k], hxx[c, i + k], hyy[c, i + k], hxy[c, i + k]
            for j in range(Wv):
                mx[j] += wk * ax[j]
                my[j] += wk * ay[j]
                exx[j] += wk * axx[j]
                eyy[j] += wk * ayy[j]
                exy[j] += wk * axy[j]
        total = 0.0
        gm, gx, gy = g_mu[c, i], g_xx[c, i], g_xy[c, i]
        for j in range(Wv):
            ux, uy = mx[j], my[j]
            sxx = exx[j] - ux * ux
            syy = eyy[j] - uy * uy
            sxy = exy[j] - ux * uy
            a1 = 2.0 * ux * uy + c1
            a2 = 2.0 * sxy + c2
            b1 = ux * ux + uy * uy + c1
            b2 = sxx + syy + c2
            inv = 1.0 / (b1 * b2)
            s = a1 * a2 * inv
            total += s
            gm[j] = 2.0 * uy * (a2 - a1) * inv + 2.0 * ux * s * (1.0 / b2 - 1.0 / b1)
            gx[j] = -s / b2
            gy[j] = 2.0 * a1 * inv
        rowsum[rr] = total


@njit(**_OPTS)
def _vertical_t(lo, hi, g_mu, g_xx, g_xy, w, scale, vm, vx, vy):
    """Rows lo..hi of the flattened [C*H] rows: the transposed blur along y of the three
    derivative maps (times the upstream `scale`), valid [Hv] rows spread onto [H]."""
    C, Hv, Wv = g_mu.shape
    K = w.shape[0]
    H = Hv + K - 1
    # Accumulated in the thread's own rows (LLVM vectorises loops over arrays it knows
    # apart), then copied out.
    tm = np.empty(Wv, np.float32)
    tx = np.empty(Wv, np.float32)
    ty = np.empty(Wv, np.float32)
    for rr in range(lo, hi):
        c, q = rr // H, rr % H
        tm[:] = 0.0
        tx[:] = 0.0
        ty[:] = 0.0
        for k in range(max(0, q - Hv + 1), min(K, q + 1)):
            wk = w[k] * scale
            am, ax, ay = g_mu[c, q - k], g_xx[c, q - k], g_xy[c, q - k]
            for j in range(Wv):
                tm[j] += wk * am[j]
                tx[j] += wk * ax[j]
                ty[j] += wk * ay[j]
        vm[c, q, :] = tm
        vx[c, q, :] = tx
        vy[c, q, :] = ty


@njit(**_OPTS)
def _horizontal_t(lo, hi, vm, vx, vy, x, y, w, dx):
    """Rows lo..hi of the flattened [C*H] rows: the transposed blur along x, combined into
    the gradient of the first image."""
    C, H, W = x.shape
    K = w.shape[0]
    Wv = W - K + 1
    tm = np.empty(W, np.float32)
    tx = np.empty(W, np.float32)
    ty = np.empty(W, np.float32)
    for rr in range(lo, hi):
        c, r = rr // H, rr % H
        am, ax, ay, xr, yr, out = vm[c, r], vx[c, r], vy[c, r], x[c, r], y[c, r], dx[c, r]
        tm[:] = 0.0
        tx[:] = 0.0
        ty[:] = 0.0
        for k in range(K):  # output q = j + k for every valid j
            wk = w[k]
            for j in range(Wv):
                tm[j + k] += wk * am[j]
                tx[j + k] += wk * ax[j]
                ty[j + k] += wk * ay[j]
        for q in range(W):
            out[q] = tm[q] + 2.0 * xr[q] * tx[q] + yr[q] * ty[q]


def ssim_forward(x: np.ndarray, y: np.ndarray, w: np.ndarray, c1: float, c2: float):
    """x, y [C, H, W] float32 -> (mean SSIM over the valid region, the three derivative
    maps [C, H-K+1, W-K+1] the backward needs)."""
    C, H, W = x.shape
    K = w.shape[0]
    Hv, Wv = H - K + 1, W - K + 1
    h = [np.empty((C, H, Wv), np.float32) for _ in range(5)]
    parallel_for(_horizontal, C * H, x, y, w, *h, min_chunk=_MIN_ROWS)
    rowsum = np.empty(C * Hv, np.float64)
    g = [np.empty((C, Hv, Wv), np.float32) for _ in range(3)]
    parallel_for(_vertical, C * Hv, *h, w, np.float32(c1), np.float32(c2), rowsum, *g, min_chunk=_MIN_ROWS)
    return float(rowsum.sum() / (C * Hv * Wv)), g


def ssim_backward(x: np.ndarray, y: np.ndarray, w: np.ndarray, g: list[np.ndarray], scale: float) -> np.ndarray:
    """d(scale * mean SSIM)/dx [C, H, W] from the forward's derivative maps."""
    C, H, W = x.shape
    Wv = g[0].shape[2]
    v = [np.empty((C, H, Wv), np.float32) for _ in range(3)]
    parallel_for(_vertical_t, C * H, *g, w, np.float32(scale), *v, min_chunk=_MIN_ROWS)
    dx = np.empty((C, H, W), np.float32)
    parallel_for(_horizontal_t, C * H, *v, x, y, w, dx, min_chunk=_MIN_ROWS)
    return dx


class FusedSSIM(torch.autograd.Function):
    """Mean SSIM of two [H, W, C] float32 CPU images; gradient to the first only."""

    @staticmethod
    def forward(ctx, pred: Tensor, gt: Tensor, w: np.ndarray, c1: float, c2: float) -> Tensor:
        x = np.ascontiguousarray(pred.detach().permute(2, 0, 1).numpy())
        y = np.ascontiguousarray(gt.detach().permute(2, 0, 1).numpy())
        value, g = ssim_forward(x, y, w, c1, c2)
        ctx.saved = (x, y, w, g)
        return pred.new_tensor(value)

    @staticmethod
    def backward(ctx, grad_out: Tensor):
        x, y, w, g = ctx.saved
        C, Hv, Wv = g[0].shape
        dx = ssim_backward(x, y, w, g, float(grad_out) / (C * Hv * Wv))
        return torch.from_numpy(dx).permute(1, 2, 0), None, None, None, None
