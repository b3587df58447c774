"""Step 6: an initial object trajectory from its masks (silhouette fitting).

The object's geometry is unknown before training, so it is stood in for by an ellipsoid
whose axis ratios are the masks' median second-moment ellipse and whose metric size comes
from depth. Per frame:

1. **Depth seed**: when the mask is near a hand (2D distance from the mask to a fitted
   wrist under two object radii) the object is about as far from the camera as that hand;
   the object's metric size is the median over those frames of
   ``equivalent radius in pixels x depth / f``. Every frame then gets the depth at which
   an object of that size has the observed area (a clear view), or the hand's depth
   (a partly hidden view), interpolated over frames without a mask.
2. **Translation** from the mask centroid back-projected at that depth.
3. **Rotation hypotheses**: a fixed set of rotations covering SO(3) (plus the previous
   frame's), each scored by the silhouette IoU of the projected ellipsoid against the mask
   and the mean distance between their boundaries; the best is refined together with the
   translation by a shrinking-step coordinate search on the same score.
4. **Smoothing**: cubic-Hermite/SLERP keyframes (``cogs.geometry.splines.fit_keyframes``)
   fitted robustly to the per-frame poses, weighted by mask confidence, then sampled at
   every frame.

A symmetric object (a ball) has no observable rotation; the hypotheses then tie and the
rotation stays at the previous frame's (identity from the start).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch

from cogs.data.scene import ObjectTrack

log = logging.getLogger(__name__)

HAND_BONES = ["wrist.L", "wrist.R", "finger3-1.L", "finger3-1.R"]


@dataclass
class ObjectFit:
    track: ObjectTrack
    radii_m: np.ndarray  # [3] ellipsoid semi-axes in canonical coordinates
    iou: np.ndarray  # [T] silhouette IoU of the smoothed pose (NaN where the mask is empty)
    depth_source: list[str]  # per frame: "size", "hand", "interpolated"


def ellipsoid_points(radii: np.ndarray, n: int = 300) -> np.ndarray:
    """[n, 3] points on the ellipsoid surface (Fibonacci sphere, scaled)."""
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5**0.5) * i
    s = np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], 1)
    return s * radii


def rotation_hypotheses(n: int = 48, seed: int = 0) -> np.ndarray:
    """[n, 3, 3] rotations spread over SO(3) (deterministic), the identity first."""
    from cogs.geometry.rotations import quat_to_rotmat, random_quat

    g = torch.Generator().manual_seed(seed)
    q = random_quat(n - 1, generator=g, dtype=torch.float64)
    R = quat_to_rotmat(q).numpy()
    return np.concatenate([np.eye(3)[None], R])


def silhouette(points_cam: np.ndarray, K: np.ndarray, shape: tuple[int, int]) -> np.ndarray | None:
    """Filled convex hull of the projected points -> [H, W] bool (None when behind the camera)."""
    import cv2

    z = points_cam[:, 2]
    if (z <= 1e-3).any():
        return None
    uv = points_cam[:, :2] / z[:, None] * [K[0, 0], K[1, 1]] + K[:2, 2]
    H, W = shape
    out = np.zeros((H, W), np.uint8)
    hull = cv2.convexHull((uv * 4).astype(np.int32))  # 2 bits of sub-pixel precision
    cv2.fillConvexPoly(out, hull, 1, lineType=cv2.LINE_8, shift=2)
    return out.astype(bool)


class _Scorer:
    """Silhouette score of a pose against one frame's mask, in a crop around the mask."""

    def __init__(self, mask: np.ndarray, K: np.ndarray, pts: np.ndarray, margin: int):
        import cv2

        ys, xs = np.nonzero(mask)
        H, W = mask.shape
        self.x0, self.y0 = max(0, xs.min() - margin), max(0, ys.min() - margin)
        self.x1, self.y1 = min(W, xs.max() + margin + 1), min(H, ys.max() + margin + 1)
        self.mask = mask[self.y0 : self.y1, self.x0 : self.x1]
        self.K = K.copy()
        self.K[0, 2] -= self.x0
        self.K[1, 2] -= self.y0
        self.pts = pts
        m8 = self.mask.astype(np.uint8)
        edge = m8 - cv2.erode(m8, np.ones((3, 3), np.uint8))
        self.dist = cv2.distanceTransform((1 - edge).astype(np.uint8), cv2.DIST_L2, 3)
        self.size = max(1.0, np.sqrt(mask.sum() / np.pi))

    def render(self, R: np.ndarray, t: np.ndarray) -> np.ndarray | None:
        return silhouette(self.pts @ R.T + t, self.K, self.mask.shape)

    def __call__(self, R: np.ndarray, t: np.ndarray) -> tuple[float, float]:
        """(score to minimise, IoU)."""
        import cv2

        sil = self.render(R, t)
        if sil is None or not sil.any():
            return 2.0, 0.0
        inter = np.logical_and(sil, self.mask).sum()
        union = np.logical_or(sil, self.mask).sum()
        iou = inter / max(union, 1)
        s8 = sil.astype(np.uint8)
        edge = (s8 - cv2.erode(s8, np.ones((3, 3), np.uint8))).astype(bool)
        bd = float(self.dist[edge].mean()) / self.size if edge.any() else 1.0
        return (1.0 - iou) + 0.5 * min(bd, 2.0), float(iou)


def _mask_geometry(mask: np.ndarray):
    ys, xs = np.nonzero(mask)
    c = np.array([xs.mean() + 0.5, ys.mean() + 0.5])
    cov = np.cov(np.stack([xs, ys])) if len(xs) > 2 else np.eye(2)
    ev = np.sort(np.linalg.eigvalsh(cov))[::-1]
    axes = 2.0 * np.sqrt(np.maximum(ev, 1e-6))  # semi-axes of the equal-moment ellipse
    return c, axes, float(len(xs))


def _touches(mask: np.ndarray, other: np.ndarray | None) -> float:
    """Fraction of the mask's boundary that borders ``other`` (occlusion indicator)."""
    import cv2

    if other is None:
        return 0.0
    m8 = mask.astype(np.uint8)
    edge = (cv2.dilate(m8, np.ones((3, 3), np.uint8)) - m8).astype(bool)
    return float(other[edge].mean()) if edge.any() else 0.0


def fit_object(
    masks: np.ndarray,
    confidence: np.ndarray,
    K: np.ndarray,
    world_to_camera: np.ndarray,
    hand_points_world: np.ndarray,
    body_root_world: np.ndarray,
    human_masks: np.ndarray | None = None,
    ground: tuple[np.ndarray, float] | None = None,
    n_hypotheses: int = 48,
    refine_steps: int = 40,
    on_frame=None,
) -> ObjectFit:
    """Initial object poses for every frame.

    masks [T, H, W] bool; confidence [T] in [0, 1]; world_to_camera [T, 4, 4];
    hand_points_world [T, P, 3] fitted hand joints; body_root_world [T, 3];
    human_masks [T, H, W] flag frames where the object borders the person (partial views).
    """
    T, H, W = masks.shape
    f = float(K[0, 0])
    Kinv = np.linalg.inv(K)
    R_wc, t_wc = world_to_camera[:, :3, :3], world_to_camera[:, :3, 3]
    has = masks.reshape(T, -1).any(1)
    if not has.any():
        raise ValueError("fit_object: every object mask is empty")

    geo = [(_mask_geometry(masks[t]) if has[t] else None) for t in range(T)]
    hand_cam = np.einsum("tij,tpj->tpi", R_wc, hand_points_world) + t_wc[:, None]
    root_cam = np.einsum("tij,tj->ti", R_wc, body_root_world) + t_wc
    occl = np.array([_touches(masks[t], None if human_masks is None else human_masks[t]) if has[t] else 1.0 for t in range(T)])
    clear = has & (confidence >= 0.8) & (occl < 0.25)

    # 1. Metric size from frames where the object is at a hand.
    hand_depth = np.full(T, np.nan)
    for t in range(T):
        if not has[t]:
            continue
        c, axes, area = geo[t]
        r_px = np.sqrt(area / np.pi)
        hp = hand_cam[t]
        uv = hp[:, :2] / hp[:, 2:3] * f + K[:2, 2]
        d = np.linalg.norm(uv - c, axis=1)
        k = int(np.argmin(d))
        if d[k] < 2.0 * r_px + 0.02 * max(H, W) and hp[k, 2] > 0:
            hand_depth[t] = hp[k, 2]
    eq_r_px = np.array([np.sqrt(g[2] / np.pi) if g else np.nan for g in geo])
    sizes = eq_r_px * hand_depth / f
    use = np.isfinite(sizes) & clear
    if not use.any():
        use = np.isfinite(sizes)
    if use.any():
        R_eq = float(np.median(sizes[use]))
    else:  # never near a hand: assume the object is as far as the person
        ok = has & (root_cam[:, 2] > 0)
        R_eq = float(np.median(eq_r_px[ok] * root_cam[ok, 2] / f))
    ratios = np.median(np.stack([g[1] / np.sqrt(g[1][0] * g[1][1]) for g in geo if g is not None]), axis=0)
    radii = R_eq * np.array([ratios[0], ratios[1], ratios[1]])

    # 2. Depth per frame.
    depth = np.full(T, np.nan)
    source = ["interpolated"] * T
    for t in range(T):
        if not has[t]:
            continue
        z_size = f * R_eq / eq_r_px[t]
        if clear[t] or not np.isfinite(hand_depth[t]):
            depth[t], source[t] = z_size, "size"
        else:
            depth[t], source[t] = hand_depth[t], "hand"
    ok = np.isfinite(depth)
    depth = np.interp(np.arange(T), np.flatnonzero(ok), depth[ok])

    # Centroids, interpolated in the image over frames without a mask.
    cents = np.array([g[0] if g else [np.nan, np.nan] for g in geo])
    for k in range(2):
        cents[~has, k] = np.interp(np.flatnonzero(~has), np.flatnonzero(has), cents[has, k]) if (~has).any() else cents[~has, k]

    # 3. Per-frame silhouette fit.
    pts = ellipsoid_points(radii)
    hyps = rotation_hypotheses(n_hypotheses)
    R_obj_cam = np.zeros((T, 3, 3))
    t_obj_cam = np.zeros((T, 3))
    weight = np.zeros(T)
    prev_R_world = np.eye(3)
    for t in range(T):
        ray = Kinv @ np.array([cents[t, 0], cents[t, 1], 1.0])
        t0 = ray / ray[2] * depth[t]
        R_prev_cam = R_wc[t] @ prev_R_world
        if not has[t]:
            R_obj_cam[t], t_obj_cam[t] = R_prev_cam, t0
            if on_frame:
                on_frame(t + 1)
            continue
        scorer = _Scorer(masks[t], K, pts, margin=int(2 * eq_r_px[t]) + 4)
        best = (np.inf, None)
        for i, Rh in enumerate([R_prev_cam, *hyps]):
            s, _ = scorer(Rh, t0)
            s += 1e-3 * (i > 0)  # ties (symmetric objects) keep the previous rotation
            if s < best[0]:
                best = (s, Rh)
        R_best, t_best, s_best = best[1], t0.copy(), best[0]
        # Coordinate search on translation (fractions of the depth) and rotation (radians).
        step_t, step_r = 0.05 * depth[t], 0.3
        for _ in range(refine_steps):
            improved = False
            for axis in range(3):
                for sign in (-1.0, 1.0):
                    tc = t_best.copy()
                    tc[axis] += sign * step_t * (0.3 if axis < 2 else 1.0)
                    s, _ = scorer(R_best, tc)
                    if s < s_best - 1e-6:
                        s_best, t_best, improved = s, tc, True
                    Rc = _axis_rotation(axis, sign * step_r) @ R_best
                    s, _ = scorer(Rc, t_best)
                    if s < s_best - 1e-6:
                        s_best, R_best, improved = s, Rc, True
            if not improved:
                step_t *= 0.5
                step_r *= 0.5
                if step_r < 0.01:
                    break
        R_obj_cam[t], t_obj_cam[t] = R_best, t_best
        weight[t] = max(confidence[t], 0.05) * (1.0 if clear[t] else 0.5)
        prev_R_world = R_wc[t].T @ R_best
        if on_frame:
            on_frame(t + 1)

    # Camera -> world.
    R_world = np.einsum("tji,tjk->tik", R_wc, R_obj_cam)
    t_world = np.einsum("tji,tj->ti", R_wc, t_obj_cam - t_wc)
    if ground is not None:
        n, d = ground
        h = t_world @ n + d
        low = h < radii.min()
        t_world[low] += np.outer(radii.min() - h[low], n)

    # 4. Smoothing.
    from cogs.geometry.rotations import rotmat_to_quat
    from cogs.geometry.splines import fit_keyframes, sample_trajectory

    q = rotmat_to_quat(torch.tensor(R_world)).numpy()
    times = torch.arange(T, dtype=torch.float64)
    wts = torch.tensor(np.where(has, weight, 1e-3) + 1e-6)
    if T >= 3:
        n_key = max(2, min(T, (T + 1) // 2))
        p, v, qk = fit_keyframes(times, torch.tensor(t_world), torch.tensor(q), n_key, frame_weights=wts)
        tk = torch.linspace(0, T - 1, n_key, dtype=torch.float64)
        ts, qs = sample_trajectory(tk, p, v, qk, times)
        t_world, q = ts.numpy(), qs.numpy()
    q = q / np.linalg.norm(q, axis=1, keepdims=True)

    # Report the smoothed silhouettes' agreement.
    from cogs.geometry.rotations import quat_to_rotmat

    Rs = quat_to_rotmat(torch.tensor(q)).numpy()
    iou = np.full(T, np.nan)
    for t in range(T):
        if has[t]:
            scorer = _Scorer(masks[t], K, pts, margin=int(2 * eq_r_px[t]) + 4)
            Rc = R_wc[t] @ Rs[t]
            tc = R_wc[t] @ t_world[t] + t_wc[t]
            iou[t] = scorer(Rc, tc)[1]
    track = ObjectTrack(centre=np.zeros(3), quats=q, translations=t_world)
    return ObjectFit(track=track, radii_m=radii, iou=iou, depth_source=source)


def _axis_rotation(axis: int, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    if axis == 0:
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == 1:
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
