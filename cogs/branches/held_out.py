"""Posing frames the training never fitted (held-out frames) from the fitted frames beside them.

A held-out frame t takes the Lagrange interpolation of its nearest fitted neighbours'
poses (`lagrange_neighbours`, `blend`), and a share of the frame's own *input* detail:
how the input estimate at t departs from the same interpolation of the inputs at those
neighbours (`detail`). The detail is the motion the interpolation misses (a swing, a
bounce between fitted frames) plus the estimator's jitter on that frame. Shared by the
human branch (per bone) and the object branch (one rigid pose: J = 1).
"""

from __future__ import annotations

import torch
from torch import Tensor

from cogs.geometry.rotations import quat_conjugate, quat_multiply, quat_to_axis_angle


def lagrange_neighbours(t: int, trained: list[bool], per_side: int, max_gap: int) -> tuple[list[int], list[float]] | None:
    """(frames [n], weights [n]) interpolating frame t from the nearest trained frames on
    each side (up to `per_side` each, at most `max_gap` away; the same number on both
    sides): the Lagrange polynomial through them evaluated at t. None without a trained
    frame on both sides."""
    T = len(trained)
    before = [k for k in range(t - 1, max(t - max_gap, 0) - 1, -1) if trained[k]][:per_side]
    after = [k for k in range(t + 1, min(t + max_gap, T - 1) + 1) if trained[k]][:per_side]
    n = min(len(before), len(after))
    if n == 0:
        return None
    xs = before[:n][::-1] + after[:n]
    w = []
    for i, xi in enumerate(xs):
        li = 1.0
        for j, xj in enumerate(xs):
            if j != i:
                li *= (t - xj) / (xi - xj)
        w.append(li)
    return xs, w


def blend(quats: Tensor, transl: Tensor, frames: Tensor, weights: Tensor) -> tuple[Tensor, Tensor]:
    """Weighted blend of per-frame rotations [T, J, 4] (sign-continuous, normalised after
    the weighted sum; fine for the small steps between nearby frames) and translations."""
    q = torch.nn.functional.normalize((weights[:, None, None] * quats[frames]).sum(0), dim=-1)
    return q, (weights[:, None] * transl[frames]).sum(0)


def as_tensors(nb: tuple[list[int], list[float]], like: Tensor) -> tuple[Tensor, Tensor]:
    """`lagrange_neighbours`' (frames, weights) as tensors on `like`'s device."""
    return (torch.tensor(nb[0], device=like.device),
            torch.tensor(nb[1], dtype=torch.float32, device=like.device))


def detail(quats: Tensor, transl: Tensor, t: int, nb: tuple[list[int], list[float]]) -> tuple[Tensor, Tensor]:
    """How frame t's pose departs from the interpolation of its neighbours `nb`: per-bone
    rotation [J, 3] (axis-angle of q_t q_interp^-1) and translation [3]."""
    q, tr = blend(quats, transl, *as_tensors(nb, transl))
    return quat_to_axis_angle(quat_multiply(quats[t], quat_conjugate(q))), transl[t] - tr
