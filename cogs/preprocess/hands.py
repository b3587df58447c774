"""Where the hands are, from MediaPipe's pose landmarks: their points, the pixels the hands
and forearms may cover, and which hand holds a mask. The object tracker (``tracking.py``)
and the outline that bridges two prompts (``outline.py``) both ask."""

from __future__ import annotations

import numpy as np

from cogs.preprocess.segment import disk

# MediaPipe pose landmarks of each hand (left, right): elbow, wrist, pinky, index, thumb.
HAND_LANDMARKS = ((13, 15, 17, 19, 21), (14, 16, 18, 20, 22))


def hand_points(kp2d: np.ndarray | None) -> np.ndarray | None:
    """[T, 2, 3] per hand (left, right): mean pixel of wrist, pinky and index points, and
    the lowest of their visibilities; None without keypoints."""
    if kp2d is None:
        return None
    out = np.full((len(kp2d), 2, 3), np.nan)
    for h, (_, wrist, pinky, index, _) in enumerate(HAND_LANDMARKS):
        k = kp2d[:, [wrist, pinky, index]]
        out[:, h, :2] = k[..., :2].mean(1)
        out[:, h, 2] = k[..., 2].min(1)
    return out


def hand_regions(kp: np.ndarray, shape: tuple[int, int], min_visibility: float = 0.5, which: tuple[int, ...] = (0, 1)) -> np.ndarray:
    """Pixels the visible hands may cover -> [H, W] bool, from one frame's MediaPipe
    keypoints [33, 3] (x, y, visibility); ``which``: the hands (0 left, 1 right).

    A hand is the convex hull of its wrist, pinky, index and thumb points and the finger
    tips, taken one palm length (wrist to knuckles) past the knuckles, grown by a
    quarter of the palm length (the fingers' width).
    """
    import cv2

    H, W = shape
    out = np.zeros((H, W), bool)
    for _, wrist, pinky, index, thumb in (HAND_LANDMARKS[h] for h in which):
        k = kp[[wrist, pinky, index, thumb]]
        if not np.isfinite(k).all() or k[:, 2].min() < min_visibility:
            continue
        w, p, i, th = k[:, :2].astype(np.float64)
        palm = float(np.linalg.norm(0.5 * (p + i) - w))
        if palm < 1.0:
            continue
        hull = cv2.convexHull(np.array([w, p, i, th, 2 * p - w, 2 * i - w], np.float32).reshape(-1, 1, 2))
        out |= filled_and_grown(hull, 0.25 * palm, (H, W))
    return out


def forearm_regions(kp: np.ndarray, shape: tuple[int, int], min_visibility: float = 0.5, radius: float = 0.15) -> np.ndarray:
    """Pixels the visible forearms may cover -> [H, W] bool, from one frame's MediaPipe
    keypoints [33, 3]: the segment from each elbow to its wrist, grown by ``radius`` x its
    length (a forearm is about a third as wide as it is long; the hand beyond the wrist is
    ``hand_regions``')."""
    import cv2

    H, W = shape
    out = np.zeros((H, W), np.uint8)
    for elbow, wrist, *_ in HAND_LANDMARKS:
        k = kp[[elbow, wrist]]
        if not np.isfinite(k).all() or k[:, 2].min() < min_visibility:
            continue
        r = max(1, int(round(radius * float(np.linalg.norm(k[1, :2] - k[0, :2])))))
        a, b = (tuple(int(v) for v in np.round(p)) for p in k[:, :2])
        cv2.line(out, a, b, 1, 2 * r + 1)
    return out > 0


def filled_and_grown(polygon: np.ndarray, grow: float, shape: tuple[int, int]) -> np.ndarray:
    """[H, W] bool: the convex ``polygon`` (pixel vertices) filled, then grown by a disc of
    ``grow`` pixels (at least 1)."""
    import cv2

    one = np.zeros(shape, np.uint8)
    cv2.fillConvexPoly(one, np.round(polygon).astype(np.int32).reshape(-1, 1, 2), 1)
    r = max(1, int(round(grow)))
    return cv2.dilate(one, disk(r)) > 0


def holding_hand(kp2d: np.ndarray | None, t: int, mask: np.ndarray, share: float = 0.15, which: tuple[int, ...] = (0, 1)) -> int | None:
    """The visible hand (0 left, 1 right) whose fingers close over frame t's ``mask``: its
    region (``hand_regions``) covers at least ``share`` of the mask (the most covering
    hand of ``which``); None when none does, or without keypoints.

    ``share`` 0.15 is set, not swept: fingers wrapped round a held object cover a sixth of
    a palm-sized one and more of a smaller one, while a hand merely beside an object
    covers little of it. Measured on the development clips' prompts: the bottle's 0.54
    and 0.58 (in the grip); the juggled ball's 0.12, the guitar's 0.08, the loaded box's
    0.08 and 0.03 (a hand at its edge); the basketball's, the backpack's and the
    synthetic benchmark's (three settings) 0 or nearly.
    """
    if kp2d is None:
        return None
    n = max(1, int(mask.sum()))
    cover = {h: float((hand_regions(kp2d[t], mask.shape, which=(h,)) & mask).sum()) / n for h in which}
    h = max(cover, key=cover.get)
    return h if cover[h] >= share else None
