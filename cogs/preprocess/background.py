"""The static scene behind the person and the object, seen from other frames of the video.

A pixel that looks the same as the static scene did there in another frame (once the
camera's motion is undone) is background; one that does not is something that moves: the
person or the object. The camera's motion between two frames is a homography of keypoints
matched off the person and the object (exact for a turning camera and for distant or
planar surfaces) plus a smooth field for the parallax of a moving camera; what is left is
absorbed by comparing each pixel with the range of colours the other frame shows in a
small neighbourhood.

Used by the object tracker (``tracking.py``): static-scene pixels are never object, and
"moving but not the person" is object evidence that needs no colour model (an object that
turns a face never seen before). The same camera motion, applied to keypoints instead of
colours (``StaticScene.point_motion``), tells which parts of a prompt's mask hold still
with the room while the rest moves (a blanket inside the box drawn around a guitar).
"""

from __future__ import annotations

import numpy as np

from cogs.preprocess.segment import disk, grown


def person_free(person_prob: np.ndarray, margin: int) -> np.ndarray:
    """Pixels clear of the person -> [H, W] bool: MediaPipe's probability ``person_prob``
    [H, W] uint8 at most 64 (of 255) everywhere within ``margin`` pixels (its mask is
    predicted at low resolution and misses limbs' edges)."""
    import cv2

    return ~(cv2.dilate((person_prob > 64).astype(np.uint8), disk(margin)) > 0)


def colour_residual(rgb: np.ndarray, ref: np.ndarray, tol: int) -> np.ndarray:
    """How far each pixel of ``rgb`` [H, W, 3] uint8 lies outside the colours that ``ref``
    (the same view, aligned) shows within ``tol`` pixels of it -> [H, W] float32 grey
    levels (the largest channel's excess; 0 when some colour nearby matches per channel).

    Comparing with a neighbourhood's range, not one pixel, forgives the misalignment that
    parallax and interpolation leave along edges and textures.
    """
    import cv2

    k = np.ones((2 * tol + 1, 2 * tol + 1), np.uint8)
    lo = cv2.erode(ref, k).astype(np.int16)
    hi = cv2.dilate(ref, k).astype(np.int16)
    x = rgb.astype(np.int16)
    return np.maximum(np.maximum(x - hi, lo - x), 0).max(-1).astype(np.float32)


def scene_warp(src: np.ndarray, dst: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray] | None:
    """Where each pixel of one frame showed in another, for the static scene -> (map_x,
    map_y) [H, W] float32 pixels of the other frame (``cv2.remap``'s maps), or None when
    too few keypoints match.

    ``src`` [N, 2]: keypoints of the static scene in the other frame, ``dst`` [N, 2] their
    matches in this one. A homography carries most of the motion (all of it for a turning
    camera); what it leaves, the parallax of a moving camera (a floor and a wall that no
    one homography fits), is a smooth field interpolated from the keypoints it misses
    (normalised convolution on a grid of cells a twentieth of the frame), fitted twice to
    drop the matches that disagree with their neighbours (on a moving thing the masks
    missed).
    """
    import cv2

    H, W = shape
    if len(src) < 8:
        return None
    side = max(H, W)
    Hm, inl = cv2.findHomography(dst, src, cv2.RANSAC, 0.02 * side)  # this frame -> the other
    if Hm is None or inl.sum() < 8:
        return None
    pred = cv2.perspectiveTransform(dst.reshape(-1, 1, 2).astype(np.float64), Hm).reshape(-1, 2)
    res = src - pred
    keep = np.linalg.norm(res, axis=1) <= 0.05 * side  # parallax is a few percent of the frame
    cell = max(4, side // 20)
    gh, gw = -(-H // cell), -(-W // cell)
    gx = np.clip((dst[:, 0] // cell).astype(int), 0, gw - 1)
    gy = np.clip((dst[:, 1] // cell).astype(int), 0, gh - 1)

    def field(sel: np.ndarray) -> np.ndarray:
        acc = np.zeros((gh, gw, 3), np.float64)
        np.add.at(acc, (gy[sel], gx[sel]), np.column_stack([np.ones(int(sel.sum())), res[sel]]))
        acc = cv2.GaussianBlur(acc, (0, 0), 1.5)
        # Shrink towards the homography alone where few keypoints support the field.
        return acc[..., 1:] / (acc[..., :1] + 0.2)

    f = field(keep)
    dev = np.linalg.norm(res - f[gy, gx], axis=1)
    f = field(keep & (dev <= max(3.0, 0.01 * side)))
    f = cv2.resize(f.astype(np.float32), (gw * cell, gh * cell), interpolation=cv2.INTER_LINEAR)[:H, :W]
    yy, xx = np.mgrid[:H, :W].astype(np.float32)
    base = cv2.perspectiveTransform(np.stack([xx, yy], -1).reshape(-1, 1, 2).astype(np.float64), Hm).reshape(H, W, 2)
    return (base[..., 0] + f[..., 0]).astype(np.float32), (base[..., 1] + f[..., 1]).astype(np.float32)


class StaticScene:
    """Per frame, the residual of each pixel against the static scene that other frames
    show there (``residual``).

    ``images`` [T, H, W, 3] uint8; ``person_probs`` [T, H, W] uint8 (MediaPipe's soft
    mask); ``matches(u, t, static_u[, most])`` -> keypoints of frame u on the pixels
    ``static_u`` [H, W] bool (at most ``most`` of them) and their matches in frame t, ([N,
    2], [N, 2]) pixels (``tracking.FeatureBank.static_matches``).
    """

    def __init__(self, images: np.ndarray, person_probs: np.ndarray, matches, tol: int = 2):
        self.images = images
        self.person_probs = person_probs
        self.matches = matches
        self.tol = tol
        H, W = images.shape[1:3]
        # MediaPipe's mask bleeds and misses by a few percent of the frame.
        self.margin = max(3, int(round(0.015 * max(H, W))))

    def static_pixels(self, u: int, object_mask: np.ndarray | None) -> np.ndarray:
        """Frame u's pixels that show the static scene as far as is known -> [H, W] bool:
        off the person and off the object (``object_mask``, where known), by the object's
        size: a tracked mask that missed a face of a resting object must not make that
        face static scene for every later frame."""
        free = person_free(self.person_probs[u], self.margin)
        if object_mask is not None and object_mask.any():
            H, W = object_mask.shape
            ys, xs = np.nonzero(object_mask)
            r = max(self.margin, int(1.0 * max(np.ptp(xs), np.ptp(ys))))
            # Within r of the object, in a window around it (``grown``: a disc as large as
            # a guitar across a 960 px frame is a distance transform, not a dilation).
            x0, y0 = max(0, xs.min() - r - 1), max(0, ys.min() - r - 1)
            x1, y1 = min(W, xs.max() + r + 2), min(H, ys.max() + r + 2)
            free[y0:y1, x0:x1] &= ~grown(object_mask[y0:y1, x0:x1], r)
        return free

    def residual(self, t: int, refs: list[tuple[int, np.ndarray | None]]) -> np.ndarray:
        """Frame t against the static scene of the frames ``refs`` [(u, object mask of
        frame u or None)] -> [H, W] float32 grey levels: the smallest residual
        (``colour_residual``) over the frames that see static scene at that pixel; NaN
        where none does (the person or the object covers it in all of them, or no
        camera motion could be fitted).

        The smallest: one frame showing the same colours there is enough to call the pixel
        background, so a person or object that a reference's masks missed costs little.
        """
        import cv2

        H, W = self.images.shape[1:3]
        out = np.full((H, W), np.inf, np.float32)
        for u, obj in refs:
            if u == t or not 0 <= u < len(self.images):
                continue
            static = self.static_pixels(u, obj)
            maps = scene_warp(*self.matches(u, t, static), (H, W))
            if maps is None:
                continue
            ref = cv2.remap(self.images[u], *maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            valid = cv2.remap(static.astype(np.uint8), *maps, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0) > 0
            r = colour_residual(self.images[t], ref, self.tol)
            np.minimum(out, np.where(valid, r, np.inf), out=out)
        out[~np.isfinite(out)] = np.nan
        return out

    def point_motion(self, t: int, mask: np.ndarray, refs: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """How far frame t's keypoints on ``mask`` [H, W] bool move off the static scene
        in the frames ``refs`` -> (xy [N, 2] pixels of frame t, [N, len(refs)] float64
        pixels: the distance between where each keypoint matched in that frame and where
        the camera's motion alone (``scene_warp``) would have taken it; NaN where it did
        not match or no camera motion could be fitted).

        Unlike ``residual`` this needs texture, not a static reference behind the thing:
        a keypoint on a blanket follows the room whatever covers the blanket in the other
        frames, while a uniform surface has no keypoint and so no verdict.
        """
        H, W = self.images.shape[1:3]
        cols: dict[tuple[float, float], dict[int, float]] = {}
        for j, u in enumerate(refs):
            if u == t or not 0 <= u < len(self.images):
                continue
            maps = scene_warp(*self.matches(u, t, self.static_pixels(u, None)), (H, W))  # where frame t's pixels were in u
            if maps is None:
                continue
            xy_t, xy_u = self.matches(t, u, mask, 2000)
            ix = np.clip(np.round(xy_t[:, 0]).astype(int), 0, W - 1)
            iy = np.clip(np.round(xy_t[:, 1]).astype(int), 0, H - 1)
            scene_xy = np.stack([maps[0][iy, ix], maps[1][iy, ix]], 1)
            for p, d in zip(map(tuple, xy_t), np.linalg.norm(xy_u - scene_xy, axis=1)):
                cols.setdefault(p, {})[j] = float(d)
        xy = np.array(list(cols), np.float64).reshape(-1, 2)
        dist = np.full((len(xy), len(refs)), np.nan)
        for i, row in enumerate(cols.values()):
            for j, d in row.items():
                dist[i, j] = d
        return xy, dist
