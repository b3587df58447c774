"""The scene's world frame: metric, z up, the ground plane at z = 0.

Structure from motion gives cameras and points in an arbitrary similarity frame; the
rotation-only fallback gives rotations only. The person fixes what is missing:

- **up**: the mean of the person's feet-to-shoulders direction (MediaPipe's 3D landmarks,
  rotated into the world by each camera);
- **ground**: among the RANSAC planes of the sparse points (``cogs.geometry.planes``),
  the one with the most inliers whose normal is within 30 degrees of up, that the feet
  rays hit in front of the camera and that gives the same scale in every frame (see
  ``MAX_SCALE_SPREAD``); without such a plane, the plane normal to up through the feet;
- **scale**: the person's metric size (the body-fit initialisation puts the feet at a
  metric depth; the ratio of that depth to the SfM distance along the same pixel ray to
  the ground, median over frames);
- **origin**: the ground point below the person in the first frame; the first camera
  looks along +y.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

log = logging.getLogger(__name__)

_L_SH, _R_SH, _L_HIP, _R_HIP, _L_ANKLE, _R_ANKLE = 11, 12, 23, 24, 27, 28
FOOT_LANDMARKS = [29, 30, 31, 32]  # heels and foot tips: the landmarks nearest the ground


MAX_SCALE_SPREAD = 0.15
"""Largest spread (standard deviation of the log) of the per-frame scales a ground plane may
give before it is refused as not the floor. The floor gave 0.034-0.042 (the synthetic
video benchmark's two clips, the backpack clip); a plane of the loading clip's shop
shelves or boxes, taken as the floor in two of its three runs, 0.23 and 0.30, and with it a
scale 7x off and the body fit 10x further from the keypoints
(docs/experiments/2026-11-27-a-shelf-taken-for-the-floor.md)."""


@dataclass
class Alignment:
    scale: float  # metres per SfM unit
    rotation: np.ndarray  # [3, 3]
    origin: np.ndarray  # [3] in SfM coordinates
    ground_source: str  # "points" | "feet"
    notes: dict = field(default_factory=dict)

    def points(self, x: np.ndarray) -> np.ndarray:
        """SfM points [N, 3] -> world."""
        return self.scale * (np.asarray(x) - self.origin) @ self.rotation.T

    def cameras(self, w2c: np.ndarray) -> np.ndarray:
        """SfM world_to_camera [T, 4, 4] -> world_to_camera of the metric world."""
        out = np.tile(np.eye(4), (len(w2c), 1, 1))
        R, t = w2c[:, :3, :3], w2c[:, :3, 3]
        out[:, :3, :3] = R @ self.rotation.T
        out[:, :3, 3] = self.scale * (np.einsum("tij,j->ti", R, self.origin) + t)
        return out


def up_in_camera(kp3d: np.ndarray) -> np.ndarray:
    """[T, 3] unit feet-to-shoulders direction per frame in camera axes (NaN if undetected).

    The line from between the ankles to between the shoulders, not the torso alone: a
    person bending over (dribbling, picking something up) keeps the shoulders roughly above
    the feet while the torso leans far forward.
    """
    up = 0.5 * (kp3d[:, _L_SH] + kp3d[:, _R_SH]) - 0.5 * (kp3d[:, _L_ANKLE] + kp3d[:, _R_ANKLE])
    return up / np.linalg.norm(up, axis=1, keepdims=True)


def estimate_up(w2c: np.ndarray, up_cam: np.ndarray) -> np.ndarray:
    """World up from the person's per-frame up (falls back on the cameras' -y axis)."""
    R = w2c[:, :3, :3]
    ok = np.isfinite(up_cam).all(axis=1)
    if ok.sum() >= 1:
        u = np.einsum("tji,tj->ti", R[ok], up_cam[ok]).mean(0)
    else:
        u = -R[:, 1, :].mean(0)  # camera y points down in the image
    return u / np.linalg.norm(u)


def _rotation_to_z(n: np.ndarray, forward: np.ndarray) -> np.ndarray:
    """Rotation taking n to +z and the ground projection of ``forward`` to +y."""
    z = n / np.linalg.norm(n)
    f = forward - z * (forward @ z)
    if np.linalg.norm(f) < 1e-6:
        f = np.cross(z, [1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.cross(z, [0.0, 1.0, 0.0])
    y = f / np.linalg.norm(f)
    x = np.cross(y, z)
    return np.stack([x, y, z])  # rows: new axes in old coordinates


def _rays(w2c: np.ndarray, K: np.ndarray, pix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera centres [T, 3] and unit world ray directions [T, 3] through pixels [T, 2]."""
    R, t = w2c[:, :3, :3], w2c[:, :3, 3]
    centres = -np.einsum("tji,tj->ti", R, t)
    d_cam = np.c_[pix, np.ones(len(pix))] @ np.linalg.inv(K).T
    d = np.einsum("tji,tj->ti", R, d_cam)
    return centres, d / np.linalg.norm(d, axis=1, keepdims=True)


def lowest_foot(kp2d: np.ndarray, feet_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per frame: the lowest-in-image confident foot landmark's pixel [T, 2], its metric
    camera-space position [T, 3], and a validity flag [T]."""
    T = len(kp2d)
    pix = np.full((T, 2), np.nan)
    pos = np.full((T, 3), np.nan)
    ok = np.zeros(T, bool)
    for t in range(T):
        k = kp2d[t, FOOT_LANDMARKS]
        if not np.isfinite(k).all() or not np.isfinite(feet_cam[t]).all():
            continue
        conf = k[:, 2] > 0.3
        if not conf.any():
            continue
        i = int(np.argmax(np.where(conf, k[:, 1], -np.inf)))
        pix[t], pos[t], ok[t] = k[i, :2], feet_cam[t, i], True
    return pix, pos, ok


def align_sfm(
    w2c: np.ndarray,
    registered: np.ndarray,
    points: np.ndarray,
    K: np.ndarray,
    kp2d: np.ndarray,
    up_cam: np.ndarray,
    feet_cam: np.ndarray,
    root_cam: np.ndarray,
) -> Alignment:
    """Similarity from an SfM reconstruction to the metric z-up world (see module docstring).

    feet_cam [T, 4, 3]: metric camera-space positions of FOOT_LANDMARKS; root_cam [T, 3]:
    metric camera-space pelvis.
    """
    from cogs.geometry.planes import ransac_planes

    up = estimate_up(w2c[registered], up_cam[registered])
    pix, foot_pos, fok = lowest_foot(kp2d, feet_cam)
    fok &= registered
    centres, rays = _rays(w2c, K, np.nan_to_num(pix))
    notes: dict = {}
    ground = None
    if len(points) >= 30 and fok.any():
        depth_scale = float(np.median(np.linalg.norm(points - centres[registered].mean(0), axis=1)))
        planes = ransac_planes(points, max_planes=5, threshold_m=0.01 * depth_scale, min_inliers=max(30, int(0.03 * len(points))), iterations=500, seed=0)
        best = None
        for pl in planes:
            n, d = pl.normal, pl.offset
            if n @ up < 0:
                n, d = -n, -d
            if n @ up < np.cos(np.radians(30)):
                continue
            denom = rays[fok] @ n
            lam = -(centres[fok] @ n + d) / np.where(np.abs(denom) > 1e-9, denom, np.nan)
            hit = np.isfinite(lam) & (lam > 0)
            if hit.mean() < 0.5:
                continue
            # Cameras must be above the ground.
            if np.median(centres[registered] @ n + d) <= 0:
                continue
            # The feet stand on the floor in every frame: their metric depth over the SfM
            # distance to the plane is one scale throughout. A shelf, a table top or a ramp
            # within 30 degrees of up gives a scale that wanders from frame to frame.
            ratio = np.linalg.norm(foot_pos[fok], axis=1)[hit] / lam[hit]
            spread = float(np.std(np.log(ratio)))
            if spread > MAX_SCALE_SPREAD:
                notes.setdefault("planes_refused", []).append({"inliers": int(len(pl.inliers)), "scale_spread": round(spread, 3)})
                log.info("a plane of %d points is not taken for the floor: the scale it gives varies by %.0f %% from frame "
                         "to frame (a shelf, table top or ramp)", len(pl.inliers), 100 * (np.exp(spread) - 1))
                continue
            if best is None or len(pl.inliers) > len(best[2]):
                best = (n, d, pl.inliers, ratio, spread)
        if best is not None:
            n, d, inl, ratio, spread = best
            scale = float(np.median(ratio))
            ground = (n, d)
            notes.update(ground_inliers=int(len(inl)), scale_spread=spread)
    if ground is None:
        # No ground plane among the points: scale from the points nearest the feet.
        scale = _scale_from_nearby_points(w2c, registered, points, K, pix, foot_pos, fok)
        if scale is None:
            scale, explained = scale_from_body_motion(w2c, registered, root_cam)
            if scale is not None:
                notes["scale"] = f"from the person's motion (explains {explained:.0%} of its apparent acceleration)"
                log.info("no ground plane and no points near the feet: the world's scale (%.3g m per SfM unit) is the "
                         "one at which the person moves most smoothly", scale)
        if scale is None:
            scale = 1.0
            notes["scale"] = "unknown: no ground plane, no points near the feet, a camera path too still to tell; SfM units kept"
            log.warning("the world's scale is unknown: no ground plane among the reconstructed points, none near the "
                        "person's feet, and the camera moves too little for the person's motion to tell it, so the "
                        "camera reconstruction's units are kept as metres. The metric body and the scene can then "
                        "disagree by a large factor and training fails; a clip showing the floor round the person's "
                        "feet gives the scale")
        # Ground through the feet, normal to up.
        feet_w = centres[fok] + rays[fok] * (np.linalg.norm(foot_pos[fok], axis=1) / scale)[:, None]
        n = up
        d = -float(np.percentile(feet_w @ n, 10)) if len(feet_w) else -float(np.median(centres @ n)) + 1.5 / scale
        ground = (n, d)
        source = "feet"
    else:
        source = "points"
    n, d = ground
    # Origin: the ground point below the person's root in the first frame with a person.
    idx = np.flatnonzero(np.isfinite(root_cam).all(axis=1) & registered)
    t0 = int(idx[0]) if len(idx) else int(np.flatnonzero(registered)[0])
    R0, tt0 = w2c[t0, :3, :3], w2c[t0, :3, 3]
    root_w = R0.T @ (np.nan_to_num(root_cam[t0]) / scale - tt0)
    origin = root_w - n * (root_w @ n + d)
    forward = R0[2]  # camera z axis in world
    rot = _rotation_to_z(n, forward)
    return Alignment(scale=scale, rotation=rot, origin=origin, ground_source=source, notes=notes)


MIN_EXPLAINED = 0.05
"""Share of the person's apparent world acceleration that the camera's motion must explain
for `scale_from_body_motion` to be used. On the scenes whose scale a ground plane gives
(the synthetic video at seven settings, backpack, loading) the camera explains 0.1-1.0 %
and the estimate is noise; on the guitar clip (floor out of view, hand-held) 14 %, 34 % and
72 % with three of COLMAP's solutions for its cameras. Below it the reconstruction's units
are kept, which are arbitrary: at 0.2, the 14 % solution put the world 40x too large and
training failed (held-out PSNR 17 dB against 29;
docs/experiments/2026-11-29-still-parts-of-a-mask.md)."""


def scale_from_body_motion(w2c: np.ndarray, registered: np.ndarray, root_cam: np.ndarray) -> tuple[float | None, float]:
    """(metres per SfM unit, share explained): the scale at which the person's world path is
    smoothest, or None when the camera's motion explains less than MIN_EXPLAINED of it.

    The person's metric camera-space root r_t (from its body size) sits in the metric world
    at R_t^T r_t - s R_t^T tau_t for the SfM camera (R_t, tau_t): a wrong s adds the camera's
    own jitter, scaled, to the person's path. Least squares of its second differences in s
    (closed form); people move smoothly, hand-held cameras do not."""
    R, tau = w2c[:, :3, :3], w2c[:, :3, 3]
    a = np.einsum("tji,tj->ti", R, root_cam)
    b = np.einsum("tji,tj->ti", R, tau)
    ok = registered & np.isfinite(root_cam).all(axis=1)
    run = ok[2:] & ok[1:-1] & ok[:-2]
    if run.sum() < 5:
        return None, 0.0
    da = (a[2:] - 2 * a[1:-1] + a[:-2])[run]
    db = (b[2:] - 2 * b[1:-1] + b[:-2])[run]
    bb = float((db * db).sum())
    if bb <= 0:
        return None, 0.0
    s = float((da * db).sum()) / bb
    explained = 1.0 - float(((da - s * db) ** 2).sum()) / max(float((da * da).sum()), 1e-12)
    if s <= 0 or explained < MIN_EXPLAINED:
        return None, explained
    return s, explained


def _scale_from_nearby_points(w2c, registered, points, K, pix, foot_pos, fok) -> float | None:
    if len(points) == 0:
        return None
    ratios = []
    for t in np.flatnonzero(fok):
        R, tt = w2c[t, :3, :3], w2c[t, :3, 3]
        pc = points @ R.T + tt
        front = pc[:, 2] > 0
        uv = pc[front, :2] / pc[front, 2:3] * [K[0, 0], K[1, 1]] + K[:2, 2]
        near = np.linalg.norm(uv - pix[t], axis=1) < 0.05 * 2 * K[0, 2]
        if near.sum() >= 3:
            ratios.append(foot_pos[t, 2] / np.median(pc[front][near, 2]))
    return float(np.median(ratios)) if ratios else None


def align_static(w2c: np.ndarray, kp2d: np.ndarray, up_cam: np.ndarray, feet_cam: np.ndarray, root_cam: np.ndarray) -> tuple[Alignment, float]:
    """World for cameras that only rotate (centres at the origin, already metric).

    Returns the alignment and the camera height above the ground (metres).
    """
    up = estimate_up(w2c, up_cam)
    pix, foot_pos, fok = lowest_foot(kp2d, feet_cam)
    R, t = w2c[:, :3, :3], w2c[:, :3, 3]
    centres = -np.einsum("tji,tj->ti", R, t)
    if fok.any():
        feet_w = np.einsum("tji,tj->ti", R[fok], foot_pos[fok] - t[fok])
        d = -float(np.percentile(feet_w @ up, 10))
    else:
        d = 1.5  # no feet seen: assume a camera at 1.5 m
    n = up
    idx = np.flatnonzero(np.isfinite(root_cam).all(axis=1))
    t0 = int(idx[0]) if len(idx) else 0
    root_w = R[t0].T @ (np.nan_to_num(root_cam[t0]) - t[t0])
    origin = root_w - n * (root_w @ n + d)
    rot = _rotation_to_z(n, R[t0, 2])
    cam_height = float(np.median(centres @ n + d))
    return Alignment(scale=1.0, rotation=rot, origin=origin, ground_source="feet"), cam_height
