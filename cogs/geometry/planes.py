"""Planar primitives for the static scene branch: sequential RANSAC, assignment, robust loss.

A plane is ``n . x + d = 0`` with a unit normal n; the signed distance of a point x is
``n . x + d``. ``ransac_planes`` finds the dominant planes in the sparse SfM points (floor,
walls, table tops); after a warm-up the trainer assigns flat scene Gaussians to them with
``assign_to_planes`` and pulls their centres onto them with ``point_to_plane_loss``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "Plane",
    "fit_plane_lstsq",
    "ransac_planes",
    "planes_to_tensors",
    "assign_to_planes",
    "point_to_plane_loss",
]


@dataclass
class Plane:
    """One plane ``normal . x + offset = 0``.

    normal: [3] unit float64; offset: d in metres; inliers: int64 indices into the point array
    given to ``ransac_planes`` (sorted). The normal points to the side holding the centroid of
    all input points (for a room: into the room), so signs are stable across runs.
    """

    normal: np.ndarray
    offset: float
    inliers: np.ndarray = field(repr=False)

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """[P, 3] -> [P] metres."""
        return np.asarray(points, dtype=np.float64) @ self.normal + self.offset


def fit_plane_lstsq(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Total-least-squares plane through >= 3 points: (unit normal [3], offset d).

    The normal is the right singular vector of the centred points with the smallest
    singular value (it minimises the sum of squared orthogonal distances).
    """
    pts = np.asarray(points, dtype=np.float64)
    c = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - c, full_matrices=False)
    n = vt[-1]
    n = n / np.linalg.norm(n)
    return n, float(-n @ c)


def ransac_planes(
    points: np.ndarray,
    max_planes: int = 6,
    threshold_m: float = 0.02,
    min_inliers: int | None = None,
    iterations: int = 500,
    seed: int = 0,
    batch: int = 64,
) -> list[Plane]:
    """Sequential RANSAC: find a plane, remove its inliers, repeat.

    points: [P, 3] metres (numpy or torch). Each round scores ``iterations`` three-point
    hypotheses (evaluated ``batch`` at a time as one matrix product), keeps the one with the
    most points within ``threshold_m``, refits it by SVD on those inliers, and re-collects the
    inliers of the refitted plane among the remaining points (twice). Rounds stop after
    ``max_planes`` planes or when the best plane has fewer than ``min_inliers`` points
    (default: max(30, 2 % of P)). Deterministic for a given seed.
    """
    pts = points.detach().cpu().numpy() if isinstance(points, Tensor) else np.asarray(points)
    pts = pts.astype(np.float64, copy=False)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"ransac_planes: points must be [P, 3], got shape {pts.shape}")
    finite = np.isfinite(pts).all(axis=1)
    n_total = pts.shape[0]
    if min_inliers is None:
        min_inliers = max(30, int(math.ceil(0.02 * n_total)))
    min_inliers = max(3, int(min_inliers))
    rng = np.random.default_rng(seed)
    centroid = pts[finite].mean(axis=0) if finite.any() else np.zeros(3)

    remaining = np.flatnonzero(finite)
    planes: list[Plane] = []
    while len(planes) < max_planes and remaining.size >= min_inliers:
        sub = pts[remaining]
        best_count, best = -1, None
        for start in range(0, iterations, batch):
            m = min(batch, iterations - start)
            idx = rng.integers(0, sub.shape[0], size=(m, 3))
            a, b, c = sub[idx[:, 0]], sub[idx[:, 1]], sub[idx[:, 2]]
            nrm = np.cross(b - a, c - a)
            length = np.linalg.norm(nrm, axis=1)
            ok = length > 1e-12
            if not ok.any():
                continue
            nrm = nrm[ok] / length[ok, None]
            d = -(nrm * a[ok]).sum(axis=1)
            counts = (np.abs(sub @ nrm.T + d) < threshold_m).sum(axis=0)  # [m]
            j = int(np.argmax(counts))
            if counts[j] > best_count:
                best_count, best = int(counts[j]), (nrm[j], d[j])
        if best is None or best_count < min_inliers:
            break
        n, d = best
        mask = np.abs(sub @ n + d) < threshold_m
        for _ in range(2):
            n, d = fit_plane_lstsq(sub[mask])
            mask = np.abs(sub @ n + d) < threshold_m
        if mask.sum() < min_inliers:
            break
        if n @ centroid + d < 0:
            n, d = -n, -d
        planes.append(Plane(normal=n, offset=float(d), inliers=np.sort(remaining[mask])))
        remaining = remaining[~mask]
    return planes


def planes_to_tensors(planes: Sequence[Plane], dtype=torch.float32, device=None) -> tuple[Tensor, Tensor]:
    """Stack planes into (normals [J, 3], offsets [J]) tensors."""
    if len(planes) == 0:
        return torch.zeros(0, 3, dtype=dtype, device=device), torch.zeros(0, dtype=dtype, device=device)
    n = torch.as_tensor(np.stack([p.normal for p in planes]), dtype=dtype, device=device)
    d = torch.as_tensor(np.array([p.offset for p in planes]), dtype=dtype, device=device)
    return n, d


def assign_to_planes(
    means: Any,
    normals: Any | None,
    planes: Sequence[Plane],
    max_distance_m: float,
    max_angle_deg: float,
) -> Any:
    """Plane index per point, or -1 where no plane is compatible.

    means: [N, 3]; normals: [N, 3] per-point normals (e.g. a flat Gaussian's shortest axis;
    need not be unit; the sign is ignored) or None to gate on distance only. A point may join
    plane j when |n_j . x + d_j| <= max_distance_m and, with normals, the angle between the
    lines of its normal and n_j is <= max_angle_deg; among the compatible planes the nearest
    wins. Returns a torch long tensor on the means' device if means is a tensor, else an
    int64 numpy array. Not differentiable (assignment is a discrete decision).
    """
    is_torch = isinstance(means, Tensor)
    x = means.detach().cpu().double().numpy() if is_torch else np.asarray(means, dtype=np.float64)
    n_pts = x.shape[0]
    if len(planes) == 0 or n_pts == 0:
        out = np.full(n_pts, -1, dtype=np.int64)
    else:
        pn = np.stack([p.normal for p in planes])  # [J, 3]
        pd = np.array([p.offset for p in planes])  # [J]
        dist = np.abs(x @ pn.T + pd)  # [N, J]
        ok = dist <= max_distance_m
        if normals is not None:
            if isinstance(normals, Tensor):
                nv = normals.detach().cpu().double().numpy()
            else:
                nv = np.asarray(normals, dtype=np.float64)
            nv = nv / np.maximum(np.linalg.norm(nv, axis=1, keepdims=True), 1e-12)
            cos = np.abs(nv @ pn.T)
            ok &= cos >= math.cos(math.radians(max_angle_deg)) - 1e-12
        dist = np.where(ok, dist, np.inf)
        out = np.where(ok.any(axis=1), dist.argmin(axis=1), -1).astype(np.int64)
    if is_torch:
        return torch.as_tensor(out, device=means.device)
    return out


PLANE_LOSS_KINDS = ("huber", "cauchy")


def point_to_plane_loss(
    means: Tensor,
    plane_normals: Tensor,
    plane_offsets: Tensor,
    assignment: Tensor,
    kind: str = "huber",
    scale: float = 0.01,
) -> Tensor:
    """Mean robust penalty rho(n_j . mu_i + d_j) over the points assigned to a plane.

    means [N, 3] (Gaussian centres, metres), plane_normals [J, 3] unit, plane_offsets [J],
    assignment [N] long (-1 = unassigned). ``scale`` s in metres:

    - "huber":  r^2 / 2 for |r| <= s, else s (|r| - s / 2)  (quadratic near the plane, linear
      growth beyond s, so a misassigned Gaussian pulls with bounded force s);
    - "cauchy": s^2 / 2 * log(1 + (r / s)^2)  (logarithmic growth, pull fades with distance).

    Differentiable w.r.t. means and the plane parameters. Returns 0 (still attached to the
    graph of ``means``) when no point is assigned.
    """
    assignment = torch.as_tensor(assignment, device=means.device).long()
    sel = assignment >= 0
    if not bool(sel.any()):
        return (means * 0).sum()
    j = assignment[sel]
    r = (means[sel] * plane_normals[j]).sum(-1) + plane_offsets[j]
    if kind == "huber":
        a = r.abs()
        rho = torch.where(a <= scale, 0.5 * r * r, scale * (a - 0.5 * scale))
    elif kind == "cauchy":
        rho = 0.5 * scale * scale * torch.log1p((r / scale) ** 2)
    else:
        raise ValueError(f"kind must be one of {PLANE_LOSS_KINDS}, got {kind!r}")
    return rho.mean()
