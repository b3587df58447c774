"""Numba kernels of the CPU pixel pass: tile binning, forward compositing, backward.

Layout and ordering (shared with the torch reference so results match):

* Gaussians are binned into 16x16 tiles by their 3-sigma square (tile ranges computed in
  torch by :func:`cogs.render.projection.tile_ranges`) in a global front-to-back order,
  so each tile's list ``ids[offsets[t]:offsets[t+1]]`` is already depth sorted.
* ``prange`` runs over tiles: a tile owns its pixels and its slice of the intersection
  list, so there are no write races and no atomics.
* Inside a tile the loop is Gaussian-major: each Gaussian only visits the pixels of the
  tile inside the box where its alpha can reach 1/255 (the ellipse
  ``d^T conic d <= 2 ln(255 o)``, slightly enlarged), which is exact: outside it the
  reference computes alpha < 1/255 and skips the pair anyway.
* The backward replays each tile back to front from the per-pixel final transmittance and
  last contributor (3DGS), visiting exactly the pairs the forward composited. Gradients are
  accumulated per Gaussian over the tile's pixels in registers and written to one slot per
  (tile, Gaussian) intersection; slots are reduced per Gaussian in intersection order.
  Every sum has a fixed order, so results are bit-reproducible whatever the thread count.

Arithmetic is float32 in the same operation order as the torch reference (no fastmath: FMA
contraction would move pairs across the 1/255 and 1e-4 thresholds relative to it); the
support-box bound alone is float64.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

TILE = 16
TILE_PIX = TILE * TILE

_F32 = np.float32
ALPHA_MIN = _F32(1.0 / 255.0)
ALPHA_MAX = _F32(0.99)
T_MIN = _F32(1e-4)
_HALF = _F32(0.5)
_ONE = _F32(1.0)
_ZERO = _F32(0.0)


@njit(cache=True, nogil=True)
def bin_gaussians(ranges, order, tiles_x, n_tiles):
    """Counting sort of (tile, Gaussian) intersections in depth order.

    ranges [N, 4] int32 (tx0, tx1, ty0, ty1), order [N] int64 front to back.
    Returns offsets [n_tiles + 1] int64 and ids [n_isect] int32.
    """
    counts = np.zeros(n_tiles + 1, np.int64)
    for k in range(order.shape[0]):
        g = order[k]
        for ty in range(ranges[g, 2], ranges[g, 3]):
            for tx in range(ranges[g, 0], ranges[g, 1]):
                counts[ty * tiles_x + tx + 1] += 1
    for t in range(n_tiles):
        counts[t + 1] += counts[t]
    fill = counts[:-1].copy()
    ids = np.empty(counts[n_tiles], np.int32)
    for k in range(order.shape[0]):
        g = order[k]
        for ty in range(ranges[g, 2], ranges[g, 3]):
            for tx in range(ranges[g, 0], ranges[g, 1]):
                t = ty * tiles_x + tx
                ids[fill[t]] = g
                fill[t] += 1
    return counts, ids


@njit(cache=True, nogil=True)
def _support_box(mx, my, a, b, c, o, x0, x1, y0, y1):
    """Inclusive pixel box [c0, c1] x [r0, r1] within the tile [x0, x1) x [y0, y1) whose
    centres can see alpha >= 1/255 from this Gaussian; empty when c0 > c1 or r0 > r1."""
    det = float(a) * float(c) - float(b) * float(b)
    if det <= 0.0 or not (det < 1e300):
        return x0, x1 - 1, y0, y1 - 1
    # o >= 1/255 here, so the log is >= 0; margins cover float32 rounding of the exponent.
    k2 = 2.0 * math.log(255.0 * float(o)) * 1.001 + 1e-3
    hx = math.sqrt(k2 * float(c) / det) * 1.0001 + 1e-3
    hy = math.sqrt(k2 * float(a) / det) * 1.0001 + 1e-3
    fx0 = math.ceil(float(mx) - hx - 0.5)
    fx1 = math.floor(float(mx) + hx - 0.5)
    fy0 = math.ceil(float(my) - hy - 0.5)
    fy1 = math.floor(float(my) + hy - 0.5)
    c0 = x0 if fx0 < x0 else (x1 if fx0 > x1 else int(fx0))
    c1 = x1 - 1 if fx1 > x1 - 1 else (x0 - 1 if fx1 < x0 - 1 else int(fx1))
    r0 = y0 if fy0 < y0 else (y1 if fy0 > y1 else int(fy0))
    r1 = y1 - 1 if fy1 > y1 - 1 else (y0 - 1 if fy1 < y0 - 1 else int(fy1))
    return c0, c1, r0, r1


@njit(cache=True, nogil=True, parallel=True)
def forward(offsets, ids, means2d, conics, opacities, features, width, height, tiles_x, tile_order):
    """Front-to-back compositing.

    Returns feat [H, W, F] (sum_i f_i alpha_i T_i), T_final [H, W] and last [H, W] int32
    (global intersection index of the last composited Gaussian, -1 when none).
    """
    F = features.shape[1]
    out_feat = np.zeros((height, width, F), np.float32)
    out_T = np.ones((height, width), np.float32)
    out_last = np.full((height, width), -1, np.int32)
    n_tiles = offsets.shape[0] - 1
    for k in prange(n_tiles):
        t = tile_order[k]
        ty = t // tiles_x
        tx = t - ty * tiles_x
        x0 = tx * TILE
        y0 = ty * TILE
        x1 = min(x0 + TILE, width)
        y1 = min(y0 + TILE, height)
        n_pix = (x1 - x0) * (y1 - y0)
        T = np.ones(TILE_PIX, np.float32)
        acc = np.zeros((TILE_PIX, F), np.float32)
        last = np.full(TILE_PIX, -1, np.int32)
        done = np.zeros(TILE_PIX, np.bool_)
        n_done = 0
        for j in range(offsets[t], offsets[t + 1]):
            g = ids[j]
            o = opacities[g]
            if o < ALPHA_MIN:
                continue
            mx = means2d[g, 0]
            my = means2d[g, 1]
            a = conics[g, 0]
            b = conics[g, 1]
            c = conics[g, 2]
            c0, c1, r0, r1 = _support_box(mx, my, a, b, c, o, x0, x1, y0, y1)
            for py in range(r0, r1 + 1):
                dy = my - (_F32(py) + _HALF)
                row = (py - y0) * TILE - x0
                for px in range(c0, c1 + 1):
                    p = row + px
                    if done[p]:
                        continue
                    dx = mx - (_F32(px) + _HALF)
                    power = -_HALF * (a * dx * dx + c * dy * dy) - b * dx * dy
                    if power > _ZERO:
                        continue
                    alpha = min(ALPHA_MAX, o * math.exp(power))
                    if alpha < ALPHA_MIN:
                        continue
                    Tp = T[p]
                    next_T = Tp * (_ONE - alpha)
                    if next_T < T_MIN:
                        done[p] = True
                        n_done += 1
                        continue
                    w = alpha * Tp
                    for f in range(F):
                        acc[p, f] += w * features[g, f]
                    T[p] = next_T
                    last[p] = j
            if n_done == n_pix:
                break
        for py in range(y0, y1):
            for px in range(x0, x1):
                p = (py - y0) * TILE + (px - x0)
                out_T[py, px] = T[p]
                out_last[py, px] = last[p]
                for f in range(F):
                    out_feat[py, px, f] = acc[p, f]
    return out_feat, out_T, out_last


@njit(cache=True, nogil=True, parallel=True)
def backward(offsets, ids, means2d, conics, opacities, features, width, height, tiles_x,
             tile_order, T_final, last_ids, grad_feat, grad_alpha):
    """Back-to-front replay. Returns per-intersection gradient slots:
    means2d [M, 2], conics [M, 3], opacities [M], features [M, F]."""
    F = features.shape[1]
    M = ids.shape[0]
    g_mean = np.zeros((M, 2), np.float32)
    g_conic = np.zeros((M, 3), np.float32)
    g_opac = np.zeros(M, np.float32)
    g_feat = np.zeros((M, F), np.float32)
    n_tiles = offsets.shape[0] - 1
    for k in prange(n_tiles):
        t = tile_order[k]
        ty = t // tiles_x
        tx = t - ty * tiles_x
        x0 = tx * TILE
        y0 = ty * TILE
        x1 = min(x0 + TILE, width)
        y1 = min(y0 + TILE, height)
        T = np.ones(TILE_PIX, np.float32)
        R = np.zeros(TILE_PIX, np.float32)  # -dL/dT_final * T_final + sum_{later} (g.f) w
        last = np.full(TILE_PIX, -1, np.int32)
        gpix = np.zeros((TILE_PIX, F), np.float32)
        acc_f = np.zeros(F, np.float32)
        j_max = -1
        for py in range(y0, y1):
            for px in range(x0, x1):
                p = (py - y0) * TILE + (px - x0)
                Tf = T_final[py, px]
                T[p] = Tf
                R[p] = -grad_alpha[py, px] * Tf
                last[p] = last_ids[py, px]
                if last[p] > j_max:
                    j_max = last[p]
                for f in range(F):
                    gpix[p, f] = grad_feat[py, px, f]
        for j in range(j_max, offsets[t] - 1, -1):
            g = ids[j]
            o = opacities[g]
            if o < ALPHA_MIN:
                continue
            mx = means2d[g, 0]
            my = means2d[g, 1]
            a = conics[g, 0]
            b = conics[g, 1]
            c = conics[g, 2]
            c0, c1, r0, r1 = _support_box(mx, my, a, b, c, o, x0, x1, y0, y1)
            s_mx = _ZERO
            s_my = _ZERO
            s_a = _ZERO
            s_b = _ZERO
            s_c = _ZERO
            s_o = _ZERO
            for f in range(F):
                acc_f[f] = _ZERO
            touched = False
            for py in range(r0, r1 + 1):
                dy = my - (_F32(py) + _HALF)
                row = (py - y0) * TILE - x0
                for px in range(c0, c1 + 1):
                    p = row + px
                    if j > last[p]:
                        continue
                    dx = mx - (_F32(px) + _HALF)
                    power = -_HALF * (a * dx * dx + c * dy * dy) - b * dx * dy
                    if power > _ZERO:
                        continue
                    G = math.exp(power)
                    raw = o * G
                    alpha = min(ALPHA_MAX, raw)
                    if alpha < ALPHA_MIN:
                        continue
                    touched = True
                    one_m = _ONE - alpha
                    Ti = T[p] / one_m
                    w = alpha * Ti
                    gf = _ZERO
                    for f in range(F):
                        gp = gpix[p, f]
                        gf += gp * features[g, f]
                        acc_f[f] += w * gp
                    d_alpha = Ti * gf - R[p] / one_m
                    R[p] += gf * w
                    T[p] = Ti
                    if raw <= ALPHA_MAX:
                        d_pow = d_alpha * alpha
                        s_o += d_alpha * G
                        s_a += d_pow * (-_HALF * dx * dx)
                        s_c += d_pow * (-_HALF * dy * dy)
                        s_b += d_pow * (-dx * dy)
                        s_mx += d_pow * (-(a * dx + b * dy))
                        s_my += d_pow * (-(c * dy + b * dx))
            if touched:
                g_mean[j, 0] = s_mx
                g_mean[j, 1] = s_my
                g_conic[j, 0] = s_a
                g_conic[j, 1] = s_b
                g_conic[j, 2] = s_c
                g_opac[j] = s_o
                for f in range(F):
                    g_feat[j, f] = acc_f[f]
    return g_mean, g_conic, g_opac, g_feat


@njit(cache=True, nogil=True)
def reduce_slots(ids, n, g_mean, g_conic, g_opac, g_feat):
    """Sum intersection slots per Gaussian in intersection order (deterministic)."""
    F = g_feat.shape[1]
    o_mean = np.zeros((n, 2), np.float32)
    o_conic = np.zeros((n, 3), np.float32)
    o_opac = np.zeros(n, np.float32)
    o_feat = np.zeros((n, F), np.float32)
    for j in range(ids.shape[0]):
        g = ids[j]
        o_mean[g, 0] += g_mean[j, 0]
        o_mean[g, 1] += g_mean[j, 1]
        o_conic[g, 0] += g_conic[j, 0]
        o_conic[g, 1] += g_conic[j, 1]
        o_conic[g, 2] += g_conic[j, 2]
        o_opac[g] += g_opac[j]
        for f in range(F):
            o_feat[g, f] += g_feat[j, f]
    return o_mean, o_conic, o_opac, o_feat
