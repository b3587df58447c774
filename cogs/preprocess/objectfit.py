"""Step 7: an initial object trajectory from its masks (silhouette fitting over the clip).

The object's geometry is unknown before training, so it is stood in for by a *proxy*: a
cuboid or an ellipsoid with three half-extents. A cuboid's silhouette (the hull of eight
projected corners) pins down its rotation up to the box's own symmetries; an ellipse, the
silhouette of an ellipsoid, leaves a one-parameter family of rotations open, so the
ellipsoid only wins for objects that really are round.

1. **Proxy** (``choose_proxy``): every candidate shape (kind x axis ratios, unit size) is
   scored on every frame with a mask (up to ``proxy_frames``, spread over the clip) by its
   best silhouette IoU over a coarse set of rotations, weighted as the frame's silhouette
   counts in step 2; the best fitting one is kept.
2. **Rotation hypotheses over the clip** (``silhouette_costs``, ``viterbi``): a fixed set
   of world rotations covering SO(3); in every frame each is placed where its silhouette
   has the mask's area and centroid, and scored by IoU. A dynamic programme picks one
   hypothesis per frame minimising the silhouette cost plus ``smooth_per_rad`` x the
   rotation between consecutive frames, in the world; the frames of a resting window
   (step 3) keep one hypothesis, refined on all of their silhouettes together (fitted one by
   one, each view turned the proxy its own way wherever the proxy's shape differs from the
   object's). One silhouette is ambiguous (a box
   and its mirror image through the image plane look alike, and symmetric views tie); the
   same object seen from a moving camera, or turning smoothly, is not.
3. **Metric size and depth from rest and from the hand** (``rest_positions``): where the
   object rests and the camera moves, the rays through its mask centroids meet at its
   position, which gives those frames' depth directly and the proxy's metric size (the
   ratio of that depth to the unit proxy's). Without a resting stretch the size comes from
   the hand: where the mask is near a fitted hand joint the object is about as far from
   the camera as that hand. Every other frame's depth is then the size's (a clear view) or
   the hand's (a view partly hidden by the person), interpolated over frames without a
   mask; a held object's is kept within reach of the holding hand (``HAND_LENGTH_M``). The
   body's metric scale carries over to all of them.
4. **Refinement**: rotation and translation together by a shrinking-step coordinate
   search on the full-resolution silhouette score, from the chosen hypothesis.
5. **Carried in a hand** (``carry_in_hand``): a stretch of frames held by a fitted hand
   that starts (or ends) at a frame whose rotation is known (at rest, or clearly seen and
   not held) turns with that hand's fitted forearm from there, the grasp keeping the object
   fixed on it: a person turning round with the object, or twisting it, turns it faster
   than the silhouettes can follow.
6. **Smoothing**: cubic-Hermite/SLERP keyframes (``cogs.geometry.splines.fit_keyframes``)
   fitted robustly to the per-frame poses, weighted by mask confidence, then sampled at
   every frame; carried frames keep the forearm's (already smooth) turn.

A symmetric object (a ball) has no observable rotation; the hypotheses then tie and the
smoothness term keeps the rotation constant.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch

from cogs.data.scene import ObjectTrack

log = logging.getLogger(__name__)

HAND_BONES = ["wrist.L", "wrist.R", "finger3-1.L", "finger3-1.R"]
PROXY_KINDS = ("cuboid", "ellipsoid")
HAND_LENGTH_M = 0.2
"""How much farther than its own length from the holding hand's fitted joints a held
object's centre may lie, in depth (``_poses``): about an adult hand's length, wrist to
fingertips (the joints are the wrist and the middle finger's base, and the grip can be at
the fingertips). A physical bound, not tuned; docs/experiments/2026-12-05-c-a-held-objects-depth-within-reach.md."""
PROXY_RATIOS = (1.0, 0.7, 0.45, 0.25)
"""Candidate ratios of the proxy's middle and smallest half-extent to its largest: from a
cube to a slab a quarter as thick. Set on the synthetic video benchmark (default clip and a
60-frame 512x384 one) without a sweep; finer grids were not tried."""


@dataclass
class ObjectFit:
    track: ObjectTrack
    radii_m: np.ndarray  # [3] the proxy's half-extents (semi-axes) in canonical coordinates, metres
    iou: np.ndarray  # [T] silhouette IoU of the smoothed pose (NaN where the mask is empty)
    depth_source: list[str]  # per frame: "rest", "size", "reach" (the size's, brought within reach of the hand), "hand", "interpolated"
    kind: str = "ellipsoid"  # the proxy: "cuboid" or "ellipsoid"
    carried: np.ndarray | None = None  # [T] bool: turned with a fitted forearm (``carry_in_hand``)


def ellipsoid_points(radii: np.ndarray, n: int = 300) -> np.ndarray:
    """[n, 3] points on the ellipsoid surface (Fibonacci sphere, scaled)."""
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5**0.5) * i
    s = np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], 1)
    return s * radii


def cuboid_points(half: np.ndarray) -> np.ndarray:
    """[8, 3] corners of the box with these half-extents (its silhouette is their hull)."""
    s = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
    return s * np.asarray(half, dtype=np.float64)


def proxy_points(kind: str, half: np.ndarray, n: int = 300) -> np.ndarray:
    """Points whose projected hull is the proxy's silhouette ([8, 3] corners or [n, 3] surface points)."""
    assert kind in PROXY_KINDS, kind
    return cuboid_points(half) if kind == "cuboid" else ellipsoid_points(np.asarray(half, dtype=np.float64), n)


def rotation_hypotheses(n: int = 48, seed: int = 0) -> np.ndarray:
    """[n, 3, 3] rotations spread over SO(3) (deterministic), the identity first."""
    from cogs.geometry.rotations import quat_to_rotmat, random_quat

    g = torch.Generator().manual_seed(seed)
    q = random_quat(n - 1, generator=g, dtype=torch.float64)
    R = quat_to_rotmat(q).numpy()
    return np.concatenate([np.eye(3)[None], R])


def rotation_distances(R: np.ndarray) -> np.ndarray:
    """[N, N] geodesic angles (radians) between every pair of rotations [N, 3, 3]."""
    tr = np.einsum("aij,bij->ab", R, R)  # trace(R_a^T R_b)
    return np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0))


def _slerp_rot(Ra: np.ndarray, Rb: np.ndarray, u: float) -> np.ndarray:
    """The rotation a fraction u of the way from Ra to Rb along the shorter arc."""
    from cogs.geometry.rotations import quat_to_rotmat, rotmat_to_quat, slerp

    q = rotmat_to_quat(torch.tensor(np.stack([Ra, Rb])))
    return quat_to_rotmat(slerp(q[0], q[1], torch.tensor(u, dtype=q.dtype))).numpy()


def fill_rotations(R: np.ndarray, has: np.ndarray, held: np.ndarray, carrier: np.ndarray | None) -> np.ndarray:
    """World rotations [T, 3, 3] with the frames without a mask filled in from the frames
    either side: where the object is held at both ends and a ``carrier`` [T, 3, 3] is given
    (the body part that holds it), the carrier's own turn with the object's rotation
    relative to it interpolated; otherwise the shorter arc; before the first and after the
    last mask, the nearest one's rotation."""
    R = R.copy()
    idx = np.flatnonzero(has)
    assert len(idx) > 0
    R[: idx[0]] = R[idx[0]]
    R[idx[-1] + 1 :] = R[idx[-1]]
    for a, b in zip(idx[:-1], idx[1:]):
        for t in range(a + 1, b):
            u = (t - a) / (b - a)
            if carrier is not None and held[a] and held[b]:
                R[t] = carrier[t] @ _slerp_rot(carrier[a].T @ R[a], carrier[b].T @ R[b], u)
            else:
                R[t] = _slerp_rot(R[a], R[b], u)
    return R


def carrying_side(frames: np.ndarray, side: np.ndarray, positions: np.ndarray | None = None, palms_world: np.ndarray | None = None,
                  forearm_world: np.ndarray | None = None) -> int:
    """The hand (0 left, 1 right) carrying the object over a held stretch's masked ``frames``.

    With the object's world ``positions`` [T, 3] and both hands' ``palms_world`` [T, 2, 3]
    and ``forearm_world`` [T, 2, 3, 3], over at least three frames: the hand the object stays
    fixed to, i.e. whose forearm frame holds the object at the steadiest offset from its
    palm (the grasp that ``carry_in_hand`` and ``carry_positions`` assume). Otherwise the
    hand ``side`` [T] finds nearest the mask in most of them. Nearest in the image is a weak
    cue where both hands are at the object (a box held against the body, the other hand
    steadying it): on the synthetic video benchmark's default clip it picked the free hand
    (10 of 18 frames), while the offsets' spreads (0.20 m left, 0.16 m right) pick the
    carrier there and on the 60- and 30-frame clips
    (docs/experiments/2026-11-28-carrying-hand.md)."""
    near = side[frames]
    near = near[near >= 0]
    votes = np.bincount(near, minlength=2)
    if positions is None or palms_world is None or forearm_world is None or len(frames) < 3:
        return int(votes.argmax())
    spread = []
    for s in (0, 1):
        o = np.einsum("tji,tj->ti", forearm_world[frames, s], positions[frames] - palms_world[frames, s])
        spread.append(float(np.linalg.norm(o - np.median(o, axis=0), axis=1).mean()))
    log.debug("carrying hand: offset spread left %.3f, right %.3f; nearest %s", *spread, votes.tolist())
    return int(np.argmin(spread))


def carry_in_hand(R_world: np.ndarray, has: np.ndarray, held: np.ndarray, side: np.ndarray, forearm_world: np.ndarray,
                  anchor: np.ndarray, positions: np.ndarray | None = None,
                  palms_world: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """World rotations [T, 3, 3] with each carried stretch turned with the forearm that
    holds it, and [T] int: the side (0 left, 1 right) carrying each frame so set, -1 elsewhere.

    A carried stretch is a run of masked frames ``held`` by a fitted hand (with the frames
    without a mask between them). Where the masked frame just before it, or just after it,
    is an ``anchor`` (a rotation to trust: the object resting or clearly seen, not in a
    hand), the grasp fixes the object to the forearm of the carrying hand
    (``carrying_side``: with the silhouettes' world ``positions`` [T, 3] and the
    ``palms_world`` [T, 2, 3], the one the object stays fixed to; otherwise the one ``side``
    [T] finds at it most often; ``forearm_world`` [T, 2, 3, 3], left and right): R(t) = F(t) G with the
    grasp offset G = F(a)^T R(a) at the anchor a before it, or at the one after it, or the
    two interpolated along the stretch where both exist (a regrasp in between). A stretch
    that ends at the last masked frame goes on to the clip's end with its last grasp (an
    object lost while carried is still in that hand; left at its last rotation, a box carried
    out of view as the person turns away was 89-175 degrees off on the synthetic video
    benchmark's variant 5, 19-58 with the hand: docs/experiments/2026-11-28-dev-clips-redrawn.md),
    and likewise one that starts at the first masked frame back to the clip's start. Stretches
    without an anchor are left as they are: their offset, and which of a box's symmetric
    twins it is, would be the silhouettes' guess. The silhouettes cannot follow a held
    object turning fast (a person turning round with it, a forearm twisting it: partial
    views, the object out of sight, twins that look alike), the forearm can; on the
    synthetic video benchmark the fitted forearm follows the box within about 30 degrees
    over its carried frames (docs/experiments/2026-11-27-carried-in-hand.md). The forearm
    (not the root, the spine, the upper arm or the wrist) was chosen there on the default
    clip and a 60-frame 512x384 one; none of the real development clips has an anchored
    held stretch, so real footage has not exercised it yet (their object step is
    unchanged), and ``cogs demo`` does not preprocess."""
    T = len(R_world)
    R = R_world.copy()
    carried = np.full(T, -1)
    idx = np.flatnonzero(has)
    k = 0
    while k < len(idx):
        if not held[idx[k]]:
            k += 1
            continue
        e = k
        while e + 1 < len(idx) and held[idx[e + 1]]:
            e += 1
        a, b = int(idx[k]), int(idx[e])
        stretch = idx[k : e + 1]
        before = int(idx[k - 1]) if k > 0 and anchor[idx[k - 1]] else None
        after = int(idx[e + 1]) if e + 1 < len(idx) and anchor[idx[e + 1]] else None
        k = e + 1
        if not (side[stretch] >= 0).any() or (before is None and after is None):
            continue
        by = carrying_side(stretch, side, positions, palms_world, forearm_world)
        F = forearm_world[:, by]
        G0 = F[before].T @ R_world[before] if before is not None else None
        G1 = F[after].T @ R_world[after] if after is not None else None
        for t in range(a, b + 1):
            if G0 is not None and G1 is not None and b > a:
                G = _slerp_rot(G0, G1, (t - a) / (b - a))
            else:
                G = G0 if G0 is not None else G1
            R[t] = F[t] @ G
        carried[a : b + 1] = by
        # Lost for good while carried (or first seen carried): it stays in that hand, with
        # the grasp of the last (first) frame it was seen in, to the clip's end (start).
        if b == idx[-1]:
            R[b + 1 :] = F[b + 1 :] @ (F[b].T @ R[b])
            carried[b + 1 :] = by
        if a == idx[0]:
            R[:a] = F[:a] @ (F[a].T @ R[a])
            carried[:a] = by
    return R, carried


def carry_positions(t_world: np.ndarray, has: np.ndarray, carried_by: np.ndarray, palms_world: np.ndarray,
                    forearm_world: np.ndarray) -> np.ndarray:
    """World positions [T, 3] with the frames of a carried stretch that have no mask moved
    with the carrying hand: t(t) = P(t) + F(t) o(t), the grasp offset o = F^T (t - P) taken at
    the stretch's masked frames either side and interpolated, or at the one sighting where
    the stretch runs to the clip's start or end (P: the palm of the carrying side in
    ``palms_world`` [T, 2, 3], F: its forearm in ``forearm_world`` [T, 2, 3, 3]).
    Elsewhere positions are unchanged. Interpolating the position itself through a gap lets
    an object that a person brings towards the camera lag behind the hand (on the 60-frame
    synthetic clip, 12 frames unmasked: 18-29 % of the depth off)."""
    out = t_world.copy()
    T = len(t_world)
    t = 0
    while t < T:
        if has[t] or carried_by[t] < 0:
            t += 1
            continue
        b = t
        while b + 1 < T and not has[b + 1] and carried_by[b + 1] == carried_by[t]:
            b += 1
        p, n, s = t - 1, b + 1, int(carried_by[t])
        P, F = palms_world[:, s], forearm_world[:, s]
        # carry_in_hand begins and ends a stretch on masked frames of the same side, or at
        # the clip's start or end (the offset of the one sighting then holds throughout)
        assert (p < 0 or (has[p] and carried_by[p] == s)) and (n >= T or (has[n] and carried_by[n] == s)) and (p >= 0 or n < T)
        offset = {q: F[q].T @ (t_world[q] - P[q]) for q in (p, n) if 0 <= q < T}
        o_p, o_n = offset.get(p, offset.get(n)), offset.get(n, offset.get(p))
        for k in range(t, b + 1):
            u = (k - p) / (n - p)
            out[k] = P[k] + F[k] @ ((1 - u) * o_p + u * o_n)
        t = b + 1
    return out


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


class _CoarseMask:
    """One frame's mask in a small crop (longer side <= ``side`` pixels) for scoring many
    hypotheses: each is placed where its silhouette has the mask's area and centroid."""

    def __init__(self, mask: np.ndarray, K: np.ndarray, side: int = 64):
        import cv2

        ys, xs = np.nonzero(mask)
        self.area_px = float(len(xs))
        self.centroid = np.array([xs.mean() + 0.5, ys.mean() + 0.5])  # full-frame pixels
        r = np.sqrt(self.area_px / np.pi)
        # The crop holds the mask and room for a silhouette somewhat larger than it.
        x0, x1 = xs.min() - 0.5 * r - 2, xs.max() + 1 + 0.5 * r + 2
        y0, y1 = ys.min() - 0.5 * r - 2, ys.max() + 1 + 0.5 * r + 2
        self.scale = min(1.0, side / max(x1 - x0, y1 - y0))
        self.origin = np.array([x0, y0])
        H, W = mask.shape
        w, h = int(np.ceil((x1 - x0) * self.scale)), int(np.ceil((y1 - y0) * self.scale))
        # Resample the mask into the crop (areas outside the frame are empty).
        A = np.array([[self.scale, 0.0, -x0 * self.scale], [0.0, self.scale, -y0 * self.scale]])
        m = cv2.warpAffine(mask.astype(np.float32), A, (w, h), flags=cv2.INTER_AREA if self.scale < 1 else cv2.INTER_LINEAR)
        self.mask = (m >= 0.5).astype(np.uint8)
        self.mask_sum = int(self.mask.sum())
        self.K = K
        self.Kinv = np.linalg.inv(K)

    def place(self, R_cam: np.ndarray, pts: np.ndarray) -> np.ndarray:
        """Translations [N, 3] that give each rotation [N, 3, 3] of the proxy ``pts`` the
        mask's area and centroid (to first order: weak perspective)."""
        import cv2

        N = len(R_cam)
        f = float(self.K[0, 0])
        z0 = f / max(np.sqrt(self.area_px / np.pi), 1.0)  # a unit sphere's depth for this area
        ray = self.Kinv @ np.array([self.centroid[0], self.centroid[1], 1.0])
        t0 = ray / ray[2] * z0
        P = np.einsum("nij,mj->nmi", R_cam, pts) + t0  # [N, M, 3]
        uv = P[..., :2] / P[..., 2:3] * f + self.K[:2, 2]
        t = np.empty((N, 3))
        for n in range(N):
            hull = cv2.convexHull(uv[n].astype(np.float32))
            mo = cv2.moments(hull)
            a = max(mo["m00"], 1e-9)
            c = np.array([mo["m10"] / a, mo["m01"] / a])
            z1 = z0 * np.sqrt(a / self.area_px)
            p1 = self.centroid - (c - self.centroid) * (z0 / z1)
            t[n] = self.Kinv @ np.array([p1[0], p1[1], 1.0]) * z1
        return t

    def iou(self, R_cam: np.ndarray, t: np.ndarray, pts: np.ndarray) -> np.ndarray:
        """[N] silhouette IoU of the unit proxy at each rotation [N, 3, 3] and translation [N, 3]."""
        import cv2

        P = np.einsum("nij,mj->nmi", R_cam, pts) + t[:, None]
        z = P[..., 2]
        uv = P[..., :2] / np.maximum(z, 1e-6)[..., None] * self.K[0, 0] + self.K[:2, 2]
        uv = (uv - self.origin) * self.scale
        out = np.zeros(len(R_cam))
        canvas = np.zeros_like(self.mask)
        for n in range(len(R_cam)):
            if (z[n] <= 1e-3).any():
                continue
            canvas[:] = 0
            cv2.fillConvexPoly(canvas, cv2.convexHull((uv[n] * 4).astype(np.int32)), 1, lineType=cv2.LINE_8, shift=2)
            inter = np.count_nonzero(canvas & self.mask)
            out[n] = inter / max(int(canvas.sum()) + self.mask_sum - inter, 1)
        return out


def silhouette_costs(frames: list, R_wc: np.ndarray, hyps_world: np.ndarray, pts: np.ndarray, on_frame=None) -> tuple[np.ndarray, np.ndarray]:
    """Cost 1 - IoU [T, N] of every world rotation hypothesis in every frame (0 where the
    frame has no mask) and the unit proxy's placed translation [T, N, 3] in camera coordinates."""
    T, N = len(frames), len(hyps_world)
    cost = np.zeros((T, N))
    trans = np.zeros((T, N, 3))
    for t, fm in enumerate(frames):
        if fm is not None:
            R_cam = np.einsum("ij,njk->nik", R_wc[t], hyps_world)
            trans[t] = fm.place(R_cam, pts)
            cost[t] = 1.0 - fm.iou(R_cam, trans[t], pts)
        if on_frame:
            on_frame(t + 1)
    return cost, trans


def viterbi(unary: np.ndarray, pairwise) -> np.ndarray:
    """Index [T] per frame minimising sum_t unary[t, i_t] + sum_t pairwise(t)[i_t, i_{t+1}]
    (``pairwise``: one [N, N] array for every step, or a function of the step t -> t + 1)."""
    T, N = unary.shape
    acc = unary[0].copy()
    back = np.zeros((T, N), np.int64)
    for t in range(1, T):
        P = pairwise(t - 1) if callable(pairwise) else pairwise
        assert P.shape == (N, N)
        total = acc[:, None] + P  # [from, to]
        back[t] = np.argmin(total, axis=0)
        acc = total[back[t], np.arange(N)] + unary[t]
    path = np.zeros(T, np.int64)
    path[-1] = int(np.argmin(acc))
    for t in range(T - 1, 0, -1):
        path[t - 1] = back[t, path[t]]
    return path


def choose_proxy(frames: list, R_wc: np.ndarray, hyps_world: np.ndarray, sample: list[int],
                 weight: np.ndarray | None = None) -> tuple[str, np.ndarray, float]:
    """(kind, unit half-extents [3] (largest 1), mean best IoU) of the candidate proxy whose
    silhouettes fit the sampled frames best, each frame at its best hypothesis; the mean is
    weighted by ``weight`` [len(sample)] where given."""
    views = [frames[t] for t in sample]
    best = ("ellipsoid", np.ones(3), -1.0)
    for kind in PROXY_KINDS:
        for i, b in enumerate(PROXY_RATIOS):
            for c in PROXY_RATIOS[i:]:
                half = np.array([1.0, b, c])
                cost = silhouette_costs(views, R_wc[sample], hyps_world, proxy_points(kind, half, 60))[0]
                score = float(np.average(1.0 - cost.min(axis=1), weights=weight))
                if score > best[2] + 1e-9:
                    best = (kind, half, score)
    return best


def ray_hits(kind: str, half: np.ndarray, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Distance [N] along each ray (origin [3], dirs [N, 3], object coordinates) to the
    proxy's near surface; NaN where the ray misses it."""
    if kind == "cuboid":
        with np.errstate(divide="ignore", invalid="ignore"):
            a = (-half - origin) / dirs
            b = (half - origin) / dirs
        near = np.nanmax(np.minimum(a, b), axis=1)
        far = np.nanmin(np.maximum(a, b), axis=1)
        return np.where((near <= far) & (near > 0), near, np.nan)
    o, d = origin / half, dirs / half  # the ellipsoid as the unit sphere
    A, B, C = (d * d).sum(1), 2 * (d @ o), o @ o - 1.0
    disc = B * B - 4 * A * C
    with np.errstate(invalid="ignore"):
        s = (-B - np.sqrt(disc)) / (2 * A)
    return np.where((disc >= 0) & (s > 0), s, np.nan)


class _Features:
    """SIFT keypoints of the object inside each frame's mask, matched between frames."""

    def __init__(self, images: np.ndarray, masks: np.ndarray):
        import cv2

        self.sift = cv2.SIFT_create(contrastThreshold=0.02)
        self.matcher = cv2.BFMatcher(cv2.NORM_L2)
        self.images, self.masks = images, masks
        self.cache: dict[int, tuple[np.ndarray, np.ndarray | None]] = {}

    def of(self, t: int) -> tuple[np.ndarray, np.ndarray | None]:
        import cv2

        if t not in self.cache:
            m = cv2.dilate(self.masks[t].astype(np.uint8), np.ones((5, 5), np.uint8))
            kp, desc = self.sift.detectAndCompute(cv2.cvtColor(self.images[t], cv2.COLOR_RGB2GRAY), m)
            self.cache[t] = (np.array([k.pt for k in kp], dtype=np.float64).reshape(-1, 2), desc)
        return self.cache[t]

    def matches(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        """Matched pixel positions [M, 2] in frame a and in frame b (Lowe's ratio test)."""
        (pa, da), (pb, db) = self.of(a), self.of(b)
        if da is None or db is None or len(da) < 2 or len(db) < 2:
            return np.zeros((0, 2)), np.zeros((0, 2))
        good = [m[0] for m in self.matcher.knnMatch(da, db, k=2) if len(m) == 2 and m[0].distance < 0.8 * m[1].distance]
        return pa[[m.queryIdx for m in good]], pb[[m.trainIdx for m in good]]


def relative_rotation(feats: _Features, a: int, b: int, kind: str, half: np.ndarray, R_a: np.ndarray, t_a: np.ndarray, K: np.ndarray,
                      min_inliers: int = 8) -> np.ndarray | None:
    """The object's rotation from frame a to frame b in camera coordinates (R_b = D R_a), from
    its features: those of frame a lifted onto the proxy posed at (R_a, t_a), then posed in
    frame b (PnP, RANSAC). None with fewer than ``min_inliers`` consistent matches (or under
    40 % of the lifted ones): 8 was chosen on the synthetic video benchmark's two clips, where
    6 let through turns some 30 degrees off."""
    import cv2

    ua, ub = feats.matches(a, b)
    if len(ua) < min_inliers:
        return None
    rays = np.c_[ua, np.ones(len(ua))] @ np.linalg.inv(K).T  # camera coordinates, z = 1
    origin = -R_a.T @ t_a  # the camera centre in object coordinates
    dirs = rays @ R_a  # R_a^T ray
    s = ray_hits(kind, half, origin, dirs)
    ok = np.isfinite(s)
    if ok.sum() < min_inliers:
        return None
    X = origin + s[ok, None] * dirs[ok]
    rvec0, _ = cv2.Rodrigues(R_a)
    found, rvec, tvec, inl = cv2.solvePnPRansac(X, ub[ok], K, None, rvec=rvec0.copy(), tvec=t_a.reshape(3, 1).copy(), useExtrinsicGuess=True,
                                                reprojectionError=max(3.0, 0.08 * K[0, 0] * float(np.max(half)) / max(t_a[2], 1e-6)),
                                                iterationsCount=200, flags=cv2.SOLVEPNP_ITERATIVE)
    if not found or inl is None or len(inl) < min_inliers or len(inl) < 0.4 * ok.sum():
        return None
    R_b, _ = cv2.Rodrigues(rvec)
    return R_b @ R_a.T


def _touches(mask: np.ndarray, other: np.ndarray | None) -> float:
    """Fraction of the mask's boundary that borders ``other`` (occlusion indicator)."""
    import cv2

    if other is None:
        return 0.0
    m8 = mask.astype(np.uint8)
    edge = (cv2.dilate(m8, np.ones((3, 3), np.uint8)) - m8).astype(bool)
    return float(other[edge].mean()) if edge.any() else 0.0


def _hand_depth(hand_cam: np.ndarray, frames: list, K: np.ndarray, eq_r_px: np.ndarray,
                shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """[T] camera depth of the fitted hand joint nearest the mask where one is within two
    object radii of its centroid in the image (NaN elsewhere), and [T] that joint's side
    (0 left, 1 right: the joints alternate as ``HAND_BONES``; -1 where none is near)."""
    out = np.full(len(frames), np.nan)
    side = np.full(len(frames), -1)
    for t, fm in enumerate(frames):
        if fm is None:
            continue
        k, d = _nearest_hand_joint(hand_cam[t], fm, K)
        if d < 2.0 * eq_r_px[t] + 0.02 * max(shape) and hand_cam[t, k, 2] > 0:
            out[t], side[t] = hand_cam[t, k, 2], k % 2
    return out, side


def _nearest_hand_joint(hand_cam_t: np.ndarray, fm, K: np.ndarray) -> tuple[int, float]:
    """The fitted hand joint (index into ``hand_cam_t`` [P, 3], camera coordinates) whose
    image lies nearest the mask's centroid, and that distance in pixels."""
    uv = hand_cam_t[:, :2] / hand_cam_t[:, 2:3] * K[0, 0] + K[:2, 2]
    d = np.linalg.norm(uv - fm.centroid, axis=1)
    k = int(np.argmin(d))
    return k, float(d[k])


def _holding_hand_depth(hand_cam: np.ndarray, frames: list, K: np.ndarray, held: np.ndarray) -> np.ndarray:
    """[T] camera depth of the fitted hand holding the object in its ``held`` frames (NaN
    elsewhere): the joint nearest the mask's centroid in the image, the one ``_hand_depth``
    takes where it is at the mask (a long object's centroid lies far from the hand holding
    it, so here it need not be)."""
    out = np.full(len(frames), np.nan)
    for t in np.flatnonzero(held):
        z = hand_cam[t, _nearest_hand_joint(hand_cam[t], frames[t], K)[0], 2]
        out[t] = z if z > 0 else np.nan
    return out


def _doubted_away_from_hands(masks: np.ndarray, has: np.ndarray, confidence: np.ndarray, trusted: float,
                             hand_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """[T] bool: the frames whose mask is doubted (confidence under ``trusted``) and has no
    fitted hand at it (``_hand_depth``'s test); none when that would leave no mask at all."""
    T, H, W = masks.shape
    low = has & (confidence < trusted)
    if not low.any():
        return low
    coarse = [_CoarseMask(masks[t], K) if low[t] else None for t in range(T)]
    r_px = np.array([np.sqrt(fm.area_px / np.pi) if fm else np.nan for fm in coarse])
    doubted = low & ~np.isfinite(_hand_depth(hand_cam, coarse, K, r_px, (H, W))[0])
    return np.zeros(T, bool) if doubted[has].all() else doubted


def rest_positions(frames: list, world_to_camera: np.ndarray, K: np.ndarray, candidates: np.ndarray, min_frames: int = 3,
                   min_parallax_deg: float = 5.0, tol: float = 0.1, extend: np.ndarray | None = None) -> np.ndarray:
    """World position [T, 3] of the object in the frames where it rests (NaN elsewhere).

    A resting object seen from a moving camera is a fixed point: the rays through its mask
    centroids meet there, which measures its depth without knowing its size (the world's
    metric scale is the body's). Runs of consecutive ``candidates`` frames are cut greedily
    into the longest windows of at least ``min_frames`` frames whose rays meet within
    ``tol`` x the mask's radius (at least 1.5 px) in every frame and whose rays spread over
    ``min_parallax_deg`` or more (less leaves the depth undetermined). An object rising or
    falling, a still camera or a mask whose centroid wanders (a hand across it) fails the
    test; motion along the camera's own path can mimic parallax, so the candidates should be
    frames where nothing moves the object (no hand at it). A window found is then extended
    over the neighbouring ``extend`` frames (e.g. the hand reaching for the object before it
    lifts it) whose centroid still projects from the window's point within the tolerance:
    the point is already fixed by the window's parallax.
    ``tol`` and ``min_parallax_deg`` were set on the synthetic video benchmark's two clips
    (docs/experiments/2026-11-27-object-at-rest.md)."""
    T = len(frames)
    out = np.full((T, 3), np.nan)
    R_wc, t_wc = world_to_camera[:, :3, :3], world_to_camera[:, :3, 3]
    Kinv = np.linalg.inv(K)
    centre = -np.einsum("tji,tj->ti", R_wc, t_wc)
    rays = np.full((T, 3), np.nan)
    for t, fm in enumerate(frames):
        if fm is not None:
            d = R_wc[t].T @ (Kinv @ np.array([fm.centroid[0], fm.centroid[1], 1.0]))
            rays[t] = d / np.linalg.norm(d)
    cand = candidates & np.isfinite(rays).all(1)
    cent = np.array([fm.centroid if fm is not None else (np.nan, np.nan) for fm in frames])
    tol_px = np.array([max(1.5, tol * np.sqrt(fm.area_px / np.pi)) if fm is not None else np.nan for fm in frames])

    def meet(sel: np.ndarray) -> np.ndarray | None:
        P = np.eye(3)[None] - np.einsum("ti,tj->tij", rays[sel], rays[sel])
        A, b = P.sum(0), np.einsum("tij,tj->i", P, centre[sel])
        if np.linalg.cond(A) > 1e8:
            return None
        X = np.linalg.solve(A, b)
        cam = np.einsum("tij,j->ti", R_wc[sel], X) + t_wc[sel]
        if (cam[:, 2] <= 1e-3).any():
            return None
        uv = cam[:, :2] / cam[:, 2:3] * K[0, 0] + K[:2, 2]
        return None if (np.linalg.norm(uv - cent[sel], axis=1) > tol_px[sel]).any() else X

    t = 0
    while t < T:
        if not cand[t]:
            t += 1
            continue
        end = t
        while end + 1 < T and cand[end + 1]:
            end += 1
        s = t
        while s + min_frames - 1 <= end:
            best, whole = None, True
            for e in range(s + min_frames - 1, end + 1):
                sel = np.zeros(T, bool)
                sel[s : e + 1] = True
                X = meet(sel)
                if X is None:
                    whole = False
                    break
                spread = np.degrees(np.arccos(np.clip(rays[sel] @ rays[sel].T, -1.0, 1.0)).max())
                if spread >= min_parallax_deg:
                    best = (e, X)
            if best is None:
                if whole:  # the rest of the run meets in a point but with too little parallax
                    break
                s += 1
                continue
            out[s : best[0] + 1] = best[1]
            s = best[0] + 1
        t = end + 1
    if extend is not None:
        def holds(t: int, X: np.ndarray) -> bool:
            if not (extend[t] and np.isfinite(rays[t]).all()):
                return False
            cam = R_wc[t] @ X + t_wc[t]
            return cam[2] > 1e-3 and np.linalg.norm(cam[:2] / cam[2] * K[0, 0] + K[:2, 2] - cent[t]) <= tol_px[t]

        found = out.copy()
        for t in range(1, T):  # forwards from each window's last frame
            if np.isfinite(found[t - 1]).all() and not np.isfinite(out[t]).all() and holds(t, found[t - 1]):
                found[t] = found[t - 1]
        for t in range(T - 2, -1, -1):  # and backwards from its first
            if np.isfinite(found[t + 1]).all() and not np.isfinite(found[t]).all() and holds(t, found[t + 1]):
                found[t] = found[t + 1]
        out = found
    return out


def _poses(path, hyps, has, clear, R_wc, trans_unit, hand_depth, root_cam, half_unit, rest_cam, held_z):
    """Camera-frame poses of the chosen hypotheses with the proxy's metric size and each
    frame's depth: (R [T, 3, 3], t [T, 3], depth [T], depth source [T], half-extents [3]).

    Depth, best first: a resting object's triangulated position (``rest_cam`` [T, 3], NaN
    elsewhere), the hand's where the view is partly hidden, the proxy's metric size. The
    size is set by the resting frames where there are some, else by the hand's depth.

    A held object's depth from its size is kept within its length plus ``HAND_LENGTH_M`` of
    the holding hand's (``held_z`` [T], NaN where no hand holds it): the size's depth
    follows the chosen rotation, and a flat object's silhouette seen more face-on than it is
    puts it far behind the hand (the tennis racket 7-10 m behind the player at 6 m, and
    one changed stretch of masks moved it by up to 1.9 m elsewhere in the clip)."""
    T = len(path)
    R_obj_cam = np.einsum("tij,tjk->tik", R_wc, hyps[path])
    z_unit = trans_unit[np.arange(T), path, 2]
    rest = has & np.isfinite(rest_cam).all(1)
    size = None
    for z in (rest_cam[:, 2], hand_depth):
        ratio = z / np.where(has, z_unit, np.nan)
        use = np.isfinite(ratio) & clear
        if not use.any():
            use = np.isfinite(ratio)
        if use.any():
            size = float(np.median(ratio[use]))
            break
    if size is None:  # never resting, never near a hand: assume the object is as far as the person
        ok = has & (root_cam[:, 2] > 0)
        size = float(np.median(root_cam[ok, 2] / z_unit[ok]))
    depth = np.full(T, np.nan)
    source = ["interpolated"] * T
    reach = 2.0 * size * float(half_unit.max()) + HAND_LENGTH_M  # the object's length and a hand
    for t in range(T):
        if not has[t]:
            continue
        if rest[t]:
            depth[t], source[t] = rest_cam[t, 2], "rest"
        elif clear[t] or not np.isfinite(hand_depth[t]):
            depth[t], source[t] = size * z_unit[t], "size"
            if abs(depth[t] - held_z[t]) > reach:  # (False where no hand holds it: NaN)
                depth[t], source[t] = float(np.clip(depth[t], held_z[t] - reach, held_z[t] + reach)), "reach"
        else:
            depth[t], source[t] = hand_depth[t], "hand"
    ok = np.isfinite(depth)
    depth = np.interp(np.arange(T), np.flatnonzero(ok), depth[ok])
    # The placed centre's direction, interpolated over frames without a mask.
    dirs = np.full((T, 3), np.nan)
    for t in np.flatnonzero(has):
        dirs[t] = trans_unit[t, path[t]] / trans_unit[t, path[t], 2]
    for k in range(2):
        if (~has).any():
            dirs[~has, k] = np.interp(np.flatnonzero(~has), np.flatnonzero(has), dirs[has, k])
    dirs[:, 2] = 1.0
    return R_obj_cam, dirs * depth[:, None], depth, source, size * half_unit


def _pose_search(score, R: np.ndarray, t: np.ndarray, s_best: float, steps: int, step_t: np.ndarray, step_r: float,
                 min_step_r: float) -> tuple[np.ndarray, np.ndarray]:
    """A pose (R, t) improved by a shrinking-step coordinate search on ``score(R, t)``
    (lower is better; ``s_best`` its value at the start): a step of ``step_t[axis]`` along
    each axis and a turn of ``step_r`` about it, both halved when no move helps, until the
    turn is under ``min_step_r`` or ``steps`` rounds have passed."""
    step_t = np.asarray(step_t, dtype=np.float64).copy()
    for _ in range(steps):
        improved = False
        for axis in range(3):
            for sign in (-1.0, 1.0):
                tc = t.copy()
                tc[axis] += sign * step_t[axis]
                s = score(R, tc)
                if s < s_best - 1e-6:
                    s_best, t, improved = s, tc, True
                Rc = _axis_rotation(axis, sign * step_r) @ R
                s = score(Rc, t)
                if s < s_best - 1e-6:
                    s_best, R, improved = s, Rc, True
        if not improved:
            step_t *= 0.5
            step_r *= 0.5
            if step_r < min_step_r:
                break
    return R, t


def _refine(masks, K, kind, half, R_obj_cam, t_obj_cam, depth, source, eq_r_px, refine_steps):
    """Each frame's pose refined from its hypothesis on the full-resolution silhouette."""
    R_obj_cam, t_obj_cam = R_obj_cam.copy(), t_obj_cam.copy()
    pts = proxy_points(kind, half)
    for t in range(len(masks)):
        if not masks[t].any():
            continue
        scorer = _Scorer(masks[t], K, pts, margin=int(2 * eq_r_px[t]) + 4)
        R_best, t_best = R_obj_cam[t], t_obj_cam[t].copy()
        s_best, _ = scorer(R_best, t_best)
        R_best, t_best = _pose_search(lambda R, tt: scorer(R, tt)[0], R_best, t_best, s_best, refine_steps,
                                      step_t=0.03 * depth[t] * np.array([0.3, 0.3, 1.0]), step_r=0.12, min_step_r=0.01)
        if source[t] in ("hand", "rest", "reach"):  # depth measured otherwise (a partly hidden view's outline says little about it; the size's outruns the hand)
            t_best = t_best / t_best[2] * depth[t]
        R_obj_cam[t], t_obj_cam[t] = R_best, t_best
    return R_obj_cam, t_obj_cam


def rest_windows(rest_world: np.ndarray) -> np.ndarray:
    """Window index [T] of each frame in ``rest_positions``' output (consecutive frames at
    one point), -1 where the object does not rest."""
    out = np.full(len(rest_world), -1)
    k = -1
    for t in range(len(rest_world)):
        if not np.isfinite(rest_world[t]).all():
            continue
        if t == 0 or out[t - 1] < 0 or not np.array_equal(rest_world[t], rest_world[t - 1]):
            k += 1
        out[t] = k
    return out


def _refine_rest(masks, K, kind, half, R_obj_cam, t_obj_cam, world_to_camera, windows, eq_r_px, refine_steps):
    """One world pose per resting window, refined on the sum of its frames' silhouette
    scores from the window's middle frame (its frames were refined one by one before, each
    free to turn its own way where the proxy's shape differs from the object's)."""
    R_obj_cam, t_obj_cam = R_obj_cam.copy(), t_obj_cam.copy()
    R_wc, t_wc = world_to_camera[:, :3, :3], world_to_camera[:, :3, 3]
    pts = proxy_points(kind, half)
    for w in range(windows.max() + 1):
        sel = np.flatnonzero(windows == w)
        scorers = [_Scorer(masks[t], K, pts, margin=int(2 * eq_r_px[t]) + 4) for t in sel]

        def score(Rw: np.ndarray, tw: np.ndarray) -> float:
            return float(np.mean([sc(R_wc[t] @ Rw, R_wc[t] @ tw + t_wc[t])[0] for sc, t in zip(scorers, sel)]))

        m = sel[len(sel) // 2]
        R_best = R_wc[m].T @ R_obj_cam[m]
        t_best = R_wc[m].T @ (t_obj_cam[m] - t_wc[m])
        depth = float(np.median(t_obj_cam[sel, 2]))
        R_best, t_best = _pose_search(score, R_best, t_best, score(R_best, t_best), refine_steps,
                                      step_t=0.01 * depth * np.ones(3), step_r=0.06, min_step_r=0.005)
        R_obj_cam[sel] = np.einsum("tij,jk->tik", R_wc[sel], R_best)
        t_obj_cam[sel] = np.einsum("tij,j->ti", R_wc[sel], t_best) + t_wc[sel]
    return R_obj_cam, t_obj_cam


def fit_object(
    masks: np.ndarray,
    confidence: np.ndarray,
    K: np.ndarray,
    world_to_camera: np.ndarray,
    hand_points_world: np.ndarray,
    body_root_world: np.ndarray,
    human_masks: np.ndarray | None = None,
    ground: tuple[np.ndarray, float] | None = None,
    n_hypotheses: int = 1500,
    smooth_per_rad: float = 0.3,
    refine_steps: int = 40,
    proxy_frames: int = 120,
    images: np.ndarray | None = None,
    feature_per_rad: float = 1.0,
    carrier_world: np.ndarray | None = None,
    forearm_world: np.ndarray | None = None,
    held_reach: int = 2,
    trusted: float = 0.2,
    on_frame=None,
) -> ObjectFit:
    """Initial object poses for every frame.

    masks [T, H, W] bool; confidence [T] in [0, 1]; world_to_camera [T, 4, 4];
    hand_points_world [T, P, 3] fitted hand joints; body_root_world [T, 3];
    human_masks [T, H, W] flag frames where the object borders the person (partial views);
    carrier_world [T, 3, 3]: the world rotation of the body part that carries a held object
    across frames without a mask (the pipeline gives the fitted body's root), or None;
    forearm_world [T, 2, 3, 3]: the fitted left and right forearms' world rotations, which
    turn a carried object from a frame whose rotation is known (``carry_in_hand``), or None.
    hand_points_world's joints alternate left and right (``HAND_BONES``).

    ``n_hypotheses`` world rotations are scored per frame (about 15 degrees apart);
    ``smooth_per_rad`` is the cost of turning one radian between consecutive frames, in
    units of silhouette IoU, and ``feature_per_rad`` the cost of departing by one radian
    from a turn the object's features measured. ``images`` [T, H, W, 3] uint8 enables the
    feature-measured turns. The two costs were chosen on the synthetic video benchmark (the
    default 40-frame clip and a 60-frame 512x384 one;
    docs/experiments/2026-11-25-initial-object-pose.md): a weaker smoothness let
    mirror-image solutions through, a stronger one or a stronger feature term did no better
    on both. ``n_hypotheses`` was set there without a sweep.

    ``proxy_frames``: the proxy is chosen on every frame with a mask, or on this many spread
    evenly over them (about 0.3 s a frame at 384 px wide), each weighted by its confidence
    and by half where it is not a clear view. Candidate shapes nearly tie on real objects
    (mean IoU within 0.0002-0.005), so a choice on a few samples flips when one frame
    changes: six clear frames picked 3-4 shapes under one- and two-frame shifts on the
    tennis, basketball, backpack, bottle, guitar and loading clips, and the racket's proxy
    and its whole trajectory (up to 0.69 m) changed when one mask's confidence fell under
    0.8. Nor do clear views alone tell a flat object's thickness: the racket is clear
    face-on, and edge-on only where the person partly hides it; on clear views it became
    an ellipsoid 1 : 1 : 0.7, on every view 1 : 1 : 0.25, which fits the frames' smooth
    path better (mean silhouette IoU 0.48 against 0.57). Chosen on the seven development
    clips and the synthetic video at two settings:
    docs/experiments/2026-12-03-g-the-proxy-on-every-view.md.

    Frames without a mask take their rotation from the frames either side
    (``fill_rotations``): while the object is held at both ends (a fitted hand at its mask
    within ``held_reach`` masked frames) it turns with the carrier, so a person turning
    round with the object hidden in front of them turns it with them.

    ``trusted``: the confidence under which a mask does not supervise the object branch
    (``ObjectConfig.min_confidence``). Such a mask counts here only where a fitted hand is
    at it (a carried object's partial view, still where the object is); away from the
    hands it is left out like a lost frame: the tracker itself doubts it, and on the
    synthetic video benchmark's variant 14 those masks lay on a blue rug the box's faces
    resemble, 12 frames pulling the trajectory 0.5-1 depth off (rotation 48.6 -> 18.4
    degrees, centre 33.5 -> 9.1 % of the depth without them; variant 10 within 0.2, the
    other 19 settings of 21 the same; on the real clips only the basketball's shadow, the
    bottle's floor patch and one tennis frame are left out). From
    ``trusted`` on, a mask may show the object at rest (``rest_positions``; the rays must
    still meet in a point): on variant 1 the box on the table, re-found after the prompt's
    pass had lost it while carried, has confidence 0.37 (its faces are not the prompt's)
    at 0.97 IoU, and with a bar of 0.5 it was never at rest, nothing anchored its carry
    and its rotation followed a silhouette twin (55.6 -> 16.1 degrees; 16.3 -> 12.0 %).
    docs/experiments/2026-12-01-doubted-masks-and-the-object-pose.md.
    """
    T, H, W = masks.shape
    R_wc, t_wc = world_to_camera[:, :3, :3], world_to_camera[:, :3, 3]
    has = masks.reshape(T, -1).any(1)
    if not has.any():
        raise ValueError("fit_object: every object mask is empty")
    assert np.isfinite(world_to_camera).all() and np.isfinite(hand_points_world).all(), "fit_object: non-finite body or cameras"
    assert carrier_world is None or (carrier_world.shape == (T, 3, 3) and np.isfinite(carrier_world).all()), "fit_object: bad carrier"
    assert forearm_world is None or (forearm_world.shape == (T, 2, 3, 3) and np.isfinite(forearm_world).all()), "fit_object: bad forearms"

    hand_cam = np.einsum("tij,tpj->tpi", R_wc, hand_points_world) + t_wc[:, None]
    root_cam = np.einsum("tij,tj->ti", R_wc, body_root_world) + t_wc
    doubted = _doubted_away_from_hands(masks, has, confidence, trusted, hand_cam, K)
    if doubted.any():
        log.info("object pose: %d doubted masks (confidence under %.2f) away from the hands left out: frames %s",
                 int(doubted.sum()), trusted, np.flatnonzero(doubted).tolist())
        masks = masks & ~doubted[:, None, None]
        has = has & ~doubted
    occl = np.array([_touches(masks[t], None if human_masks is None else human_masks[t]) if has[t] else 1.0 for t in range(T)])
    clear = has & (confidence >= 0.8) & (occl < 0.25)
    frames = [_CoarseMask(masks[t], K) if has[t] else None for t in range(T)]
    eq_r_px = np.array([np.sqrt(fm.area_px / np.pi) if fm else np.nan for fm in frames])

    # 1. The proxy, on the views with a mask spread over the clip, the clear ones counting most.
    hyps = rotation_hypotheses(n_hypotheses)
    weight = np.where(has, np.maximum(confidence, 0.05) * np.where(clear, 1.0, 0.5), 0.0)
    pool = np.flatnonzero(has)
    sample = [int(s) for s in np.unique(pool[np.linspace(0, len(pool) - 1, min(proxy_frames, len(pool))).round().astype(int)])]
    kind, half_unit, proxy_iou = choose_proxy(frames, R_wc, hyps[:: max(1, n_hypotheses // 300)], sample, weight[sample])
    pts_unit = proxy_points(kind, half_unit)

    # 2. One rotation hypothesis per frame with a mask: silhouettes plus smooth turning in
    # the world; then again with the turning its features measure between those frames.
    cost, trans_unit = silhouette_costs(frames, R_wc, hyps, pts_unit, on_frame=on_frame)
    idx = np.flatnonzero(has)
    dist = rotation_distances(hyps)
    hyp_flat = hyps.reshape(len(hyps), 9)
    hand_depth, hand_side = _hand_depth(hand_cam, frames, K, eq_r_px, (H, W))
    # Not held (no fitted hand at the mask) and trusted: the object can only rest or fly, and
    # a flying one fails the fixed-point test.
    rest_world = rest_positions(frames, world_to_camera, K, has & (confidence >= trusted) & ~np.isfinite(hand_depth),
                                extend=has & (confidence >= trusted))
    rest_cam = np.einsum("tij,tj->ti", R_wc, rest_world) + t_wc
    windows = rest_windows(rest_world)
    held = np.zeros(T, bool)  # a partial mask's centroid can stray from the hand for a frame
    for k, t in enumerate(idx):
        held[t] = np.isfinite(hand_depth[idx[max(0, k - held_reach) : k + held_reach + 1]]).any()
    held_z = _holding_hand_depth(hand_cam, frames, K, held)
    # A resting object does not turn: consecutive frames of one window keep one hypothesis.
    same = np.array([windows[a] >= 0 and windows[a] == windows[b] for a, b in zip(idx[:-1], idx[1:])])
    tied = np.where(dist > 0, np.inf, 0.0)
    path = np.zeros(T, np.int64)
    path[idx] = viterbi(cost[idx] * weight[idx, None], lambda k: tied if same[k] else smooth_per_rad * dist)
    R_obj_cam, t_obj_cam, depth, source, half = _poses(path, hyps, has, clear, R_wc, trans_unit, hand_depth, root_cam, half_unit, rest_cam, held_z)
    R_obj_cam, t_obj_cam = _refine(masks, K, kind, half, R_obj_cam, t_obj_cam, depth, source, eq_r_px, refine_steps)
    R_obj_cam, t_obj_cam = _refine_rest(masks, K, kind, half, R_obj_cam, t_obj_cam, world_to_camera, windows, eq_r_px, refine_steps)
    n_measured = 0
    if images is not None and len(idx) >= 2:
        feats = _Features(images, masks)
        D = []
        for a, b in zip(idx[:-1], idx[1:]):
            Dc = relative_rotation(feats, int(a), int(b), kind, half, R_obj_cam[a], t_obj_cam[a], K)
            D.append(None if Dc is None else R_wc[b].T @ Dc @ R_wc[a])
        n_measured = sum(d is not None for d in D)

        def pairwise(k: int) -> np.ndarray:
            if same[k]:
                return tied
            if D[k] is None:
                return smooth_per_rad * dist
            tr = (np.einsum("ij,njk->nik", D[k], hyps).reshape(len(hyps), 9)) @ hyp_flat.T  # tr(R_j^T D R_i) at [i, j]
            return feature_per_rad * np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0))

        path[idx] = viterbi(cost[idx] * weight[idx, None], pairwise)
        R_obj_cam, t_obj_cam, depth, source, half = _poses(path, hyps, has, clear, R_wc, trans_unit, hand_depth, root_cam, half_unit, rest_cam, held_z)
        R_obj_cam, t_obj_cam = _refine(masks, K, kind, half, R_obj_cam, t_obj_cam, depth, source, eq_r_px, refine_steps)
        R_obj_cam, t_obj_cam = _refine_rest(masks, K, kind, half, R_obj_cam, t_obj_cam, world_to_camera, windows, eq_r_px, refine_steps)
    pts = proxy_points(kind, half)

    # Camera -> world; frames without a mask from the frames either side.
    R_world = np.einsum("tji,tjk->tik", R_wc, R_obj_cam)
    # 5. Carried in a hand, from a frame whose rotation is known.
    t_world = np.einsum("tji,tj->ti", R_wc, t_obj_cam - t_wc)
    palms = 0.5 * (hand_points_world[:, :2] + hand_points_world[:, 2:4])
    carried_by = np.full(T, -1)
    if forearm_world is not None:
        resting = windows >= 0  # a hand at a resting object does not carry it yet
        anchor = has & (resting | (clear & ~held))
        R_world, carried_by = carry_in_hand(R_world, has, held & ~resting, hand_side, forearm_world, anchor, t_world, palms)
    carried = carried_by >= 0
    R_world = fill_rotations(R_world, has | carried, held, carrier_world)
    if carried.any():
        t_world = carry_positions(t_world, has, carried_by, palms, forearm_world)
    if ground is not None:
        n, d = ground
        h = t_world @ n + d
        # Lifted onto the floor where it sinks into it by a depth error's worth (a tenth of
        # its distance from the camera). Deeper means the world's floor is not where the
        # object is (a shelf taken for the floor lifted the loading clip's box 4 m, off
        # screen): its masks are trusted over the floor there.
        away = np.linalg.norm(t_obj_cam, axis=1)  # (not `dist`: the hypotheses' distances above)
        low = (h < half.min()) & (half.min() - h <= 0.1 * away)
        t_world[low] += np.outer(half.min() - h[low], n)
        deep = int(((h < half.min()) & ~low & has).sum())
        if deep:
            log.warning("the object sits more than a tenth of its distance below the world's floor in %d frames; its "
                        "masks are trusted there (the floor may be a shelf or a table: see source.body_fit in scene.json)", deep)

    # 6. Smoothing. (Leaving the rotations unsmoothed followed the synthetic box's fast turns
    # a little better but let a round object's unobservable spin jitter by 8-35 degrees a
    # frame on the real clips: docs/experiments/2026-11-27-resting-rotation-and-twins.md.)
    from cogs.geometry.rotations import quat_sign_continuous, rotmat_to_quat
    from cogs.geometry.splines import fit_keyframes, sample_trajectory

    q = rotmat_to_quat(torch.tensor(R_world)).numpy()
    times = torch.arange(T, dtype=torch.float64)
    wts = torch.tensor(np.where(has, weight, 1e-3) + 1e-6)
    if T >= 3:
        n_key = max(2, min(T, (T + 1) // 2))
        p, v, qk = fit_keyframes(times, torch.tensor(t_world), torch.tensor(q), n_key, frame_weights=wts)
        if carried.any():  # their positions, not their rotations (those are set below), count as partly hidden views
            p, v, _ = fit_keyframes(times, torch.tensor(t_world), torch.tensor(q), n_key,
                                    frame_weights=torch.tensor(np.where(has, weight, np.where(carried, 0.25, 1e-3)) + 1e-6))
        tk = torch.linspace(0, T - 1, n_key, dtype=torch.float64)
        ts, qs = sample_trajectory(tk, p, v, qk, times)
        t_world, q = ts.numpy(), qs.numpy()
        # A carried object turns with the (already smooth) fitted forearm, as fast as the
        # person turns it: the smoother's keyframes would cut a fast turn short.
        q[carried] = rotmat_to_quat(torch.tensor(R_world[carried])).numpy()
        q = quat_sign_continuous(torch.tensor(q)).numpy()
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    assert np.isfinite(q).all() and np.isfinite(t_world).all(), "fit_object: non-finite trajectory"

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
    log.info("object proxy: %s, half-extents %s m (silhouette IoU %.2f on %d frames); features measured %d of %d turns; "
             "%d frames turned with a forearm", kind, np.round(half, 3), proxy_iou, len(sample), n_measured, max(len(idx) - 1, 0),
             int(carried.sum()))
    track = ObjectTrack(centre=np.zeros(3), quats=q, translations=t_world)
    return ObjectFit(track=track, radii_m=half, iou=iou, depth_source=source, kind=kind, carried=carried)


def _axis_rotation(axis: int, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    if axis == 0:
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == 1:
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
