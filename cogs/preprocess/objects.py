"""Step 3: the handled object's mask in every frame, propagated from one box prompt.

Two engines:

- **SAM2** (optional, when the ``sam2`` package is installed and a checkpoint is given): its
  video predictor propagates the box prompt forwards and backwards.
- **classical** (default, no weights): GrabCut inside the prompt box gives the object's
  first mask and a colour model (object vs. rest-of-frame histograms). Every other frame,
  walking away from the prompt frame in both directions, is handled by

  1. a per-pixel object probability from the colour model (damped on the person's head,
     the commonest look-alike of a held object, unless the object was last seen there);
  2. the previous mask carried over by dense optical flow; when the carried mask still
     looks like the object (mean probability at least 0.7 of the prompt's) and no
     better-looking window lies elsewhere, GrabCut around it segments the object (slow or
     multi-coloured objects);
  3. otherwise localisation by colour: the window of the object's size with the highest
     mean probability, weighted towards the constant-velocity prediction (a fast object
     such as a bounced ball, or one reappearing), then GrabCut seeded with the probable
     object pixels there;
  4. clean-up: the connected component at the located object, holes filled, area checked
     against the prompt mask.

The person's mask is a soft prior here, not a hard exclusion: MediaPipe's person mask often
swallows a held object, so skin and clothes are kept apart by colour. The returned object
masks and the person masks are made disjoint by the pipeline (object pixels win).

Masks can also be read ready-made from a folder (``read_mask_folder``).
"""

from __future__ import annotations

import copy
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cogs.errors import UserError

log = logging.getLogger(__name__)

_DEBUG = None
_BINS = 32  # colour histogram bins per channel


def scale_box(box: tuple[float, float, float, float], source_size: tuple[int, int], size: tuple[int, int]) -> np.ndarray:
    """A box (x0, y0, x1, y1) in source-video pixels -> pixels of the resized frames."""
    sx, sy = size[0] / source_size[0], size[1] / source_size[1]
    x0, y0, x1, y1 = box
    return np.array([x0 * sx, y0 * sy, x1 * sx, y1 * sy], dtype=np.float64)


def check_box(box, source_size: tuple[int, int], frame: int, n_frames: int) -> None:
    """UserError naming the option when the prompt box is unusable."""
    if not 0 <= frame < n_frames:
        raise UserError(f"--object-box-frame {frame} is outside the {n_frames} processed frames (0..{n_frames - 1})")
    x0, y0, x1, y1 = box
    W, H = source_size
    if not (x1 > x0 and y1 > y0):
        raise UserError(f"--object-box {x0:g} {y0:g} {x1:g} {y1:g} must be x0 y0 x1 y1 with x1 > x0 and y1 > y0")
    if x1 <= 0 or y1 <= 0 or x0 >= W or y0 >= H:
        raise UserError(
            f"--object-box {x0:g} {y0:g} {x1:g} {y1:g} lies outside the {W}x{H} frame "
            "(the box is given in pixels of the input video)"
        )
    if (min(x1, W) - max(x0, 0)) < 3 or (min(y1, H) - max(y0, 0)) < 3:
        raise UserError(f"--object-box {x0:g} {y0:g} {x1:g} {y1:g} covers less than 3x3 pixels of the frame")


# -- colour model ---------------------------------------------------------------------


def _bin_index(rgb: np.ndarray) -> np.ndarray:
    q = (rgb.astype(np.int32) * _BINS) // 256
    return (q[..., 0] * _BINS + q[..., 1]) * _BINS + q[..., 2]


@dataclass
class ColourModel:
    """Log-likelihood ratio of object vs. background per colour bin ([BINS^3])."""

    llr: np.ndarray

    @classmethod
    def fit(cls, rgb: np.ndarray, fg: np.ndarray, bg: np.ndarray, distractors: np.ndarray | None = None) -> "ColourModel":
        """Object colours ``rgb[fg]`` against background ``rgb[bg]``.

        ``distractors`` [N, 3] uint8 are colours (the person's, from every frame) that get as
        much background weight as the whole rest of the frame: the person is the one
        thing that is always near a handled object, and a small part of the frame.
        """
        idx = _bin_index(rgb)
        n = _BINS**3
        hf = np.bincount(idx[fg], minlength=n).astype(np.float64)
        hb = np.bincount(idx[bg], minlength=n).astype(np.float64)
        hb /= max(hb.sum(), 1.0)
        if distractors is not None and len(distractors):
            hd = np.bincount(_bin_index(distractors), minlength=n).astype(np.float64)
            hb = 0.5 * hb + 0.5 * hd / hd.sum()
        # Smooth over neighbouring bins so colours slightly off the prompt's still count.
        hf, hb = _smooth3(hf / max(hf.sum(), 1.0)), _smooth3(hb)
        pf = (hf + 1e-5) / (hf.sum() + 1e-5 * n)
        pb = (hb + 1e-5) / (hb.sum() + 1e-5 * n)
        return cls(np.log(pf) - np.log(pb))

    def blend(self, other: "ColourModel", w: float) -> "ColourModel":
        return ColourModel((1 - w) * self.llr + w * other.llr)

    def prob(self, rgb: np.ndarray) -> np.ndarray:
        """[H, W] object probability in [0, 1] (equal priors)."""
        return 1.0 / (1.0 + np.exp(-np.clip(self.llr[_bin_index(rgb)], -20, 20)))


def _smooth3(h: np.ndarray) -> np.ndarray:
    from scipy.ndimage import uniform_filter

    return uniform_filter(h.reshape(_BINS, _BINS, _BINS), size=3, mode="nearest").reshape(-1)


# -- segmentation helpers -------------------------------------------------------------


def _largest_component_near(mask: np.ndarray, point: tuple[float, float]) -> np.ndarray:
    import cv2

    n, labels, stats, cents = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 1:
        return mask.astype(bool)
    x, y = point
    best, best_score = 0, -np.inf
    for k in range(1, n):
        d = np.hypot(cents[k, 0] - x, cents[k, 1] - y)
        score = np.log(stats[k, cv2.CC_STAT_AREA] + 1.0) - d / max(np.sqrt(stats[k, cv2.CC_STAT_AREA]), 1.0)
        if score > best_score:
            best, best_score = k, score
    return labels == best


def _fill_holes(mask: np.ndarray) -> np.ndarray:
    from scipy.ndimage import binary_fill_holes

    return binary_fill_holes(mask)


def _grabcut(img, mask, rect, bgd, fgd, iterations, mode):
    """cv2.grabCut with OpenCV's random generator reset: its GMMs start from k-means,
    which draws from the global generator, so the same input gives the same mask."""
    import cv2

    cv2.setRNGSeed(0)
    cv2.grabCut(img, mask, rect, bgd, fgd, iterations, mode)


def grabcut_box(rgb: np.ndarray, box: np.ndarray, iterations: int = 5) -> np.ndarray:
    """GrabCut initialised with a rectangle -> [H, W] bool (the component at the box centre)."""
    import cv2

    H, W = rgb.shape[:2]
    x0, y0, x1, y1 = box
    x0, y0 = int(max(0, np.floor(x0))), int(max(0, np.floor(y0)))
    x1, y1 = int(min(W, np.ceil(x1))), int(min(H, np.ceil(y1)))
    bw, bh = x1 - x0, y1 - y0
    # Work in a crop around the box: faster, and the background model stays local.
    m = max(bw, bh)
    cx0, cy0 = max(0, x0 - m), max(0, y0 - m)
    cx1, cy1 = min(W, x1 + m), min(H, y1 + m)
    crop = np.ascontiguousarray(rgb[cy0:cy1, cx0:cx1, ::-1])
    mask = np.zeros(crop.shape[:2], np.uint8)
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    rect = (x0 - cx0, y0 - cy0, max(bw, 2), max(bh, 2))
    if rect[0] == 0 and rect[1] == 0 and rect[2] >= crop.shape[1] and rect[3] >= crop.shape[0]:
        # The box fills the image: GrabCut needs some background; shrink by a pixel.
        rect = (1, 1, crop.shape[1] - 2, crop.shape[0] - 2)
    _grabcut(crop, mask, rect, bgd, fgd, iterations, cv2.GC_INIT_WITH_RECT)
    fg = (mask == cv2.GC_FGD) | (mask == cv2.GC_PR_FGD)
    out = np.zeros((H, W), bool)
    out[cy0:cy1, cx0:cx1] = fg
    out = _largest_component_near(out, (0.5 * (x0 + x1), 0.5 * (y0 + y1)))
    if out.sum() < 0.05 * bw * bh:
        # GrabCut found nothing convincing: the inscribed ellipse of the box is the best guess.
        yy, xx = np.mgrid[:H, :W]
        out = ((xx + 0.5 - 0.5 * (x0 + x1)) / (0.5 * bw)) ** 2 + ((yy + 0.5 - 0.5 * (y0 + y1)) / (0.5 * bh)) ** 2 <= 1
    return _fill_holes(out)


def _grabcut_seeded(rgb: np.ndarray, prob: np.ndarray, centre, size, human_prob: np.ndarray | None, iterations: int = 3):
    """GrabCut in a region around a located object; seeds from the colour probability."""
    import cv2

    H, W = rgb.shape[:2]
    cx, cy = centre
    w, h = size
    r = 1.25 * max(w, h)
    x0, y0 = int(max(0, cx - r)), int(max(0, cy - r))
    x1, y1 = int(min(W, cx + r + 1)), int(min(H, cy + r + 1))
    if x1 - x0 < 4 or y1 - y0 < 4:
        return np.zeros((H, W), bool)
    crop = np.ascontiguousarray(rgb[y0:y1, x0:x1, ::-1])
    p = prob[y0:y1, x0:x1]
    yy, xx = np.mgrid[y0:y1, x0:x1]
    ell = ((xx + 0.5 - cx) / (0.5 * w + 1)) ** 2 + ((yy + 0.5 - cy) / (0.5 * h + 1)) ** 2
    near = ell <= 1.0
    mask = np.full(crop.shape[:2], cv2.GC_PR_BGD, np.uint8)
    mask[near & (p > 0.5)] = cv2.GC_PR_FGD
    mask[(ell <= 0.25) & (p > 0.8)] = cv2.GC_FGD
    mask[ell > 2.25] = cv2.GC_BGD
    if human_prob is not None:
        # Confident person pixels that do not look like the object are background.
        hp = human_prob[y0:y1, x0:x1]
        mask[(hp > 0.9) & (p < 0.3)] = cv2.GC_BGD
    if not ((mask == cv2.GC_PR_FGD) | (mask == cv2.GC_FGD)).any():
        return np.zeros((H, W), bool)
    if not ((mask == cv2.GC_PR_BGD) | (mask == cv2.GC_BGD)).any():
        mask[0, :] = cv2.GC_BGD
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    try:
        _grabcut(crop, mask, None, bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK)
    except cv2.error:
        fg = near & (p > 0.5)
    else:
        fg = (mask == cv2.GC_FGD) | (mask == cv2.GC_PR_FGD)
    out = np.zeros((H, W), bool)
    out[y0:y1, x0:x1] = fg
    return out


# -- motion cues ----------------------------------------------------------------------


def _window(mask: np.ndarray, margin: float) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1): the mask's bounding box grown by ``margin`` x its size + 16 px."""
    H, W = mask.shape
    c, s = _mask_stats(mask)
    r = (0.5 + margin) * s + 16
    return int(max(0, c[0] - r[0])), int(max(0, c[1] - r[1])), int(min(W, c[0] + r[0] + 1)), int(min(H, c[1] + r[1] + 1))


def warp_mask_by_flow(prev_rgb: np.ndarray, rgb: np.ndarray, prev_mask: np.ndarray, margin: float = 1.5) -> np.ndarray:
    """The previous frame's mask carried into this frame by dense optical flow, computed in a
    window around the mask -> [H, W] bool (empty when nothing lands).

    DIS flow (OpenCV's dense inverse search): coarse-to-fine patch matching follows a
    fast object much further than Farneback's polynomial expansion.
    """
    import cv2

    H, W = prev_mask.shape
    if not prev_mask.any():
        return np.zeros((H, W), bool)
    x0, y0, x1, y1 = _window(prev_mask, margin)
    a = cv2.cvtColor(np.ascontiguousarray(rgb[y0:y1, x0:x1]), cv2.COLOR_RGB2GRAY)
    b = cv2.cvtColor(np.ascontiguousarray(prev_rgb[y0:y1, x0:x1]), cv2.COLOR_RGB2GRAY)
    # Flow from this frame to the previous one: where each pixel here came from.
    flow = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM).calc(a, b, None)
    gy, gx = np.mgrid[0 : y1 - y0, 0 : x1 - x0].astype(np.float32)
    pm = prev_mask[y0:y1, x0:x1].astype(np.float32)
    warped = cv2.remap(pm, gx + flow[..., 0], gy + flow[..., 1], cv2.INTER_LINEAR, borderValue=0.0)
    out = np.zeros((H, W), bool)
    out[y0:y1, x0:x1] = warped > 0.5
    return out


def align_mask(mask: np.ndarray, prob: np.ndarray, margin: float = 1.0) -> tuple[np.ndarray | None, float]:
    """Move a mask rigidly (rotation and translation) onto where a probability map puts
    the object -> (moved mask [H, W] bool or None when the fit fails, correlation).

    ECC (``cv2.findTransformECC``) maximises the correlation between the blurred mask and
    the blurred probability map in a window around the mask, starting where the mask
    is: a template fit that keeps the object's shape and lets its whole outline vote,
    so a few look-alike pixels nearby or a few missing ones (a new face, a finger) move
    it little. The correlation (up to 1) says how well the shape explains the map.
    """
    import cv2

    H, W = mask.shape
    _, s = _mask_stats(mask)
    x0, y0, x1, y1 = _window(mask, margin)
    sigma = max(2.0, 0.06 * float(s.max()))
    tmpl = cv2.GaussianBlur(mask[y0:y1, x0:x1].astype(np.float32), (0, 0), sigma)
    img = cv2.GaussianBlur(prob[y0:y1, x0:x1].astype(np.float32), (0, 0), 0.7 * sigma)
    warp = np.eye(2, 3, dtype=np.float32)
    try:
        cc, warp = cv2.findTransformECC(tmpl, img, warp, cv2.MOTION_EUCLIDEAN,
                                        (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-5), None, 5)
    except cv2.error:
        return None, 0.0  # no convergence (a flat map: nothing object-like there)
    A = warp.astype(np.float64)
    A[:, 2] += np.array([x0, y0]) - A[:, :2] @ np.array([x0, y0])  # window -> frame pixels
    moved = cv2.warpAffine(mask.astype(np.uint8), A, (W, H), flags=cv2.INTER_NEAREST) > 0
    return moved, float(cc)


@dataclass
class _View:
    """The object's SIFT keypoints in one frame where its mask is known."""

    t: int
    xy: np.ndarray  # [N, 2] pixels
    desc: np.ndarray  # [N, 128] float32
    mask: np.ndarray  # [H, W] bool


class _FeatureBank:
    """Re-detection by local features: SIFT keypoints of the object in remembered views (the
    prompt's, pinned, and the last few accepted frames), matched into a new frame and
    verified by a RANSAC similarity transform. Unlike flow, this follows a large jump
    (a fast lift) and finds the object again after an occlusion, as long as a face seen
    before is in view; unlike the colour model, it ignores look-alike colours elsewhere,
    because the matches must agree on one rigid motion."""

    def __init__(self, images: np.ndarray, recent: int = 4, min_inliers: int = 5):
        import cv2

        self.images = images
        # A low contrast threshold: small, synthetic-smooth or blurred objects still get keypoints.
        self.sift = cv2.SIFT_create(contrastThreshold=0.02)
        self.matcher = cv2.BFMatcher(cv2.NORM_L2)
        self.frames: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.pinned: _View | None = None
        self.recent: list[_View] = []
        self.n_recent = recent
        self.min_inliers = min_inliers

    def _frame(self, t: int) -> tuple[np.ndarray, np.ndarray]:
        if t not in self.frames:
            import cv2

            kps, desc = self.sift.detectAndCompute(cv2.cvtColor(self.images[t], cv2.COLOR_RGB2GRAY), None)
            xy = np.array([k.pt for k in kps], np.float32).reshape(-1, 2)
            self.frames[t] = (xy, np.zeros((0, 128), np.float32) if desc is None else desc)
        return self.frames[t]

    def view(self, t: int, mask: np.ndarray) -> _View:
        xy, desc = self._frame(t)
        H, W = mask.shape
        xi, yi = np.clip(xy[:, 0].astype(int), 0, W - 1), np.clip(xy[:, 1].astype(int), 0, H - 1)
        inside = mask[yi, xi]
        return _View(t, xy[inside], desc[inside], mask)

    def pin(self, t: int, mask: np.ndarray) -> None:
        self.pinned = self.view(t, mask)

    def reset(self, views: list[_View]) -> None:
        self.recent = list(views[-self.n_recent :])

    def add(self, t: int, mask: np.ndarray) -> None:
        self.recent = [v for v in self.recent if v.t != t][-(self.n_recent - 1) :] + [self.view(t, mask)]

    def background_motion(self, t0: int, t1: int, static0: np.ndarray) -> np.ndarray | None:
        """[3, 3] homography taking frame t0's pixels where ``static0`` (no person, no
        object) to frame t1's, from matched keypoints; None when too few match."""
        import cv2

        xy0, d0 = self._frame(t0)
        xy1, d1 = self._frame(t1)
        H, W = static0.shape
        keep = static0[np.clip(xy0[:, 1].astype(int), 0, H - 1), np.clip(xy0[:, 0].astype(int), 0, W - 1)]
        if keep.sum() < 8 or len(d1) < 8:
            return None
        pairs = [m for m in self.matcher.knnMatch(d0[keep], d1, k=2) if len(m) == 2 and m[0].distance < 0.8 * m[1].distance]
        if len(pairs) < 8:
            return None
        src = xy0[keep][[m[0].queryIdx for m in pairs]]
        dst = xy1[[m[0].trainIdx for m in pairs]]
        Hm, inl = cv2.findHomography(src, dst, cv2.RANSAC, 3.0)
        return Hm if Hm is not None and inl.sum() >= 8 else None

    def match(self, t: int) -> tuple[np.ndarray, int] | None:
        """(the best view's mask warped into frame t, its inlier count), or None."""
        import cv2

        xy, desc = self._frame(t)
        if len(desc) < 2:
            return None
        best = None
        views = self.recent[::-1] + ([self.pinned] if self.pinned is not None and all(v.t != self.pinned.t for v in self.recent) else [])
        for v in views:
            if len(v.desc) < self.min_inliers:
                continue
            pairs = [m for m in self.matcher.knnMatch(v.desc, desc, k=2) if len(m) == 2 and m[0].distance < 0.8 * m[1].distance]
            if len(pairs) < self.min_inliers:
                continue
            src = v.xy[[m[0].queryIdx for m in pairs]]
            dst = xy[[m[0].trainIdx for m in pairs]]
            _, s = _mask_stats(v.mask)
            A, inl = cv2.estimateAffinePartial2D(src, dst, method=cv2.RANSAC, ransacReprojThreshold=max(3.0, 0.05 * float(s.max())))
            if A is None:
                continue
            n = int(inl.sum())
            scale = float(np.sqrt(abs(np.linalg.det(A[:, :2]))))
            # A view far back in time may legitimately differ more in size than the last one.
            lo, hi = (0.5, 2.0) if abs(v.t - t) > 2 else (0.67, 1.5)
            if n < self.min_inliers or not lo <= scale <= hi:
                continue
            # The inliers must span the object, not sit on one spot (a repeated texture).
            p = src[inl.ravel().astype(bool)]
            if float(np.ptp(p, axis=0).max()) < 0.25 * float(s.max()):
                continue
            if best is None or n > best[2]:
                best = (v, A, n)
        if best is None:
            return None
        v, A, n = best
        H, W = v.mask.shape
        warped = cv2.warpAffine(v.mask.astype(np.uint8), A, (W, H), flags=cv2.INTER_NEAREST) > 0
        if warped.sum() < 0.5 * v.mask.sum():
            return None  # mostly outside the frame
        return warped, n


def _hand_points(kp2d: np.ndarray | None) -> np.ndarray | None:
    """[T, 2, 3] per hand (left, right): mean pixel of wrist, index and pinky knuckles, and
    the lowest of their visibilities; None without keypoints."""
    if kp2d is None:
        return None
    out = np.full((len(kp2d), 2, 3), np.nan)
    for h, idx in enumerate(([15, 17, 19], [16, 18, 20])):
        k = kp2d[:, idx]
        out[:, h, :2] = k[..., :2].mean(1)
        out[:, h, 2] = k[..., 2].min(1)
    return out


def hand_regions(kp: np.ndarray, shape: tuple[int, int], min_visibility: float = 0.5) -> np.ndarray:
    """Pixels the visible hands may cover -> [H, W] bool, from MediaPipe's 33 keypoints
    [33, 3] (x, y, visibility).

    A hand is the convex hull of its wrist, its pinky, index and thumb points and the
    finger tips, taken one palm length (wrist to knuckles) past the knuckles, grown by a
    quarter of the palm length (the fingers' width).
    """
    import cv2

    H, W = shape
    out = np.zeros((H, W), np.uint8)
    for wrist, pinky, index, thumb in ((15, 17, 19, 21), (16, 18, 20, 22)):
        k = kp[[wrist, pinky, index, thumb]]
        if not np.isfinite(k).all() or k[:, 2].min() < min_visibility:
            continue
        w, p, i, th = k[:, :2]
        palm = float(np.linalg.norm(0.5 * (p + i) - w))
        if palm < 1.0:
            continue
        tips = [p + (p - w), i + (i - w)]
        hull = cv2.convexHull(np.array([w, p, i, th, *tips], np.float32).reshape(-1, 1, 2))
        cv2.fillConvexPoly(out, np.round(hull).astype(np.int32), 1)
        grow = max(1, int(round(0.25 * palm)))
        out = cv2.dilate(out, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * grow + 1,) * 2))
    return out.astype(bool)


def _visible(hands: np.ndarray | None, t: int, h: int) -> bool:
    return hands is not None and bool(np.isfinite(hands[t, h]).all()) and hands[t, h, 2] >= 0.5


def _carrying_hand(hands: np.ndarray | None, t_prev: int, t: int, prev_mask: np.ndarray, mask: np.ndarray,
                   touch: float = 0.2, moved_max: float = 1 / 3) -> int | None:
    """The hand that carries the object between two frames, or None.

    A hand carries the object when it touches the mask in both frames (within ``touch``
    x the object's size) and the object moved with it (the two displacements differ by
    less than ``moved_max`` x its size). A bounced ball touches the hand but moves on
    its own.
    """
    if hands is None:
        return None
    import cv2

    c0, s0 = _mask_stats(prev_mask)
    c1, s1 = _mask_stats(mask)
    size = float(max(s1.max(), 1.0))
    best, best_d = None, np.inf
    for h in range(2):
        if not (_visible(hands, t_prev, h) and _visible(hands, t, h)):
            continue
        d = []
        for tt, m in ((t_prev, prev_mask), (t, mask)):
            x0, y0, x1, y1 = _window(m, 0.5)
            dist = cv2.distanceTransform((~m[y0:y1, x0:x1]).astype(np.uint8), cv2.DIST_L2, 3)
            x, y = hands[tt, h, :2]
            xi, yi = int(round(x)) - x0, int(round(y)) - y0
            d.append(float(dist[yi, xi]) if 0 <= xi < x1 - x0 and 0 <= yi < y1 - y0 else np.inf)
        moved = np.linalg.norm((c1 - c0) - (hands[t, h, :2] - hands[t_prev, h, :2]))
        if max(d) <= touch * size and moved <= moved_max * size and max(d) < best_d:
            best, best_d = h, max(d)
    return best


def _solidity(mask: np.ndarray) -> float:
    """Area over convex-hull area (1 for a convex silhouette; a handled object is
    nearly convex, a piece of background cut out by GrabCut rarely is)."""
    import cv2

    pts = cv2.findNonZero(mask.astype(np.uint8))
    if pts is None:
        return 0.0
    return float(mask.sum()) / max(cv2.contourArea(cv2.convexHull(pts)), 1.0)


def _move_with_hand(mask: np.ndarray, kp_from: np.ndarray, kp_to: np.ndarray, hand: int) -> np.ndarray:
    """A mask carried by a hand between two frames: turned with the forearm (elbow to
    hand) and moved with the hand -> [H, W] bool."""
    import cv2

    idx = ([13, 15, 17, 19], [14, 16, 18, 20])[hand]  # elbow, wrist, pinky, index
    a, b = kp_from[idx, :2].astype(np.float64), kp_to[idx, :2].astype(np.float64)
    pa, pb = a[1:].mean(0), b[1:].mean(0)
    va, vb = pa - a[0], pb - b[0]
    ang = np.arctan2(vb[1], vb[0]) - np.arctan2(va[1], va[0])
    sc = float(np.clip(np.linalg.norm(vb) / max(np.linalg.norm(va), 1e-6), 0.8, 1.25))
    R = sc * np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    A = np.concatenate([R, (pb - R @ pa)[:, None]], 1)
    H, W = mask.shape
    return cv2.warpAffine(mask.astype(np.uint8), A, (W, H), flags=cv2.INTER_NEAREST) > 0


def _grabcut_at_hand(rgb: np.ndarray, hand: np.ndarray, size: float, human_prob: np.ndarray | None, iterations: int = 4) -> np.ndarray:
    """The object in a carrying hand, appearance unknown -> [H, W] bool (may be empty).

    GrabCut in a window around the hand: within 1.5 ``size`` of it (the hand may hold the
    object by a corner) the pixels may be object, the window's rim (another ``size``
    out) is background and trains the background
    colours, and the person's confident pixels are background everywhere (with only a
    hand to go on, an object seen against the body cannot be told from it). Returns the
    component that touches the hand.
    """
    import cv2

    H, W = rgb.shape[:2]
    hx, hy = hand
    r_in, r_out = 1.5 * size, 2.5 * size
    x0, y0 = int(max(0, hx - r_out)), int(max(0, hy - r_out))
    x1, y1 = int(min(W, hx + r_out + 1)), int(min(H, hy + r_out + 1))
    if x1 - x0 < 8 or y1 - y0 < 8:
        return np.zeros((H, W), bool)
    yy, xx = np.mgrid[y0:y1, x0:x1]
    inner = (np.abs(xx + 0.5 - hx) <= r_in) & (np.abs(yy + 0.5 - hy) <= r_in)
    gc = np.where(inner, cv2.GC_PR_FGD, cv2.GC_BGD).astype(np.uint8)
    if human_prob is not None:
        gc[human_prob[y0:y1, x0:x1] > 0.5] = cv2.GC_BGD
    if not (gc == cv2.GC_PR_FGD).any() or not (gc == cv2.GC_BGD).any():
        return np.zeros((H, W), bool)
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    try:
        _grabcut(np.ascontiguousarray(rgb[y0:y1, x0:x1, ::-1]), gc, None, bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK)
    except cv2.error:
        return np.zeros((H, W), bool)
    fg = (gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD)
    out = np.zeros((H, W), bool)
    out[y0:y1, x0:x1] = fg
    if not out.any():
        return out
    # The piece nearest the hand (GrabCut also keeps unrelated background blobs), which
    # must touch it.
    n, labels, stats, _ = cv2.connectedComponentsWithStats(out.astype(np.uint8), connectivity=8)
    ys, xs = np.nonzero(out)
    d = np.hypot(xs + 0.5 - hx, ys + 0.5 - hy)
    lab = labels[ys, xs]
    best, best_d = 0, 0.5 * size
    for k in range(1, n):
        if stats[k, cv2.CC_STAT_AREA] >= 0.2 * size * size:
            dk = float(d[lab == k].min())
            if dk <= best_d:
                best, best_d = k, dk
    return _fill_holes(labels == best) if best else np.zeros((H, W), bool)


def _grabcut_from_seed(rgb: np.ndarray, prob: np.ndarray, seed: np.ndarray, human_prob: np.ndarray | None, iterations: int = 3) -> np.ndarray:
    """GrabCut around a predicted mask (warped by flow or features): its core is object
    whatever its colour (a new face of a turning object), far away is not."""
    import cv2

    H, W = seed.shape
    c, s = _mask_stats(seed)
    size = float(max(s))
    r = int(0.6 * size) + 6
    ys, xs = np.nonzero(seed)
    x0, x1 = max(0, xs.min() - 2 * r), min(W, xs.max() + 2 * r + 1)
    y0, y1 = max(0, ys.min() - 2 * r), min(H, ys.max() + 2 * r + 1)
    sd = seed[y0:y1, x0:x1].astype(np.uint8)
    p = prob[y0:y1, x0:x1]
    k_out = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    k_in = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * max(1, int(0.15 * size)) + 1,) * 2)
    near = cv2.dilate(sd, k_out) > 0
    core = cv2.erode(sd, k_in) > 0
    gc = np.full(sd.shape, cv2.GC_BGD, np.uint8)
    gc[near] = cv2.GC_PR_BGD
    gc[(sd > 0) | (near & (p > 0.8))] = cv2.GC_PR_FGD
    gc[core] = cv2.GC_FGD
    if human_prob is not None:
        # Confident person pixels that do not look like the object are background.
        hp = human_prob[y0:y1, x0:x1]
        gc[(hp > 0.9) & (p < 0.3) & ~core] = cv2.GC_BGD
    if not ((gc == cv2.GC_BGD) | (gc == cv2.GC_PR_BGD)).any():
        gc[0, :] = cv2.GC_BGD
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    crop = np.ascontiguousarray(rgb[y0:y1, x0:x1, ::-1])
    try:
        _grabcut(crop, gc, None, bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK)
        fg = (gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD)
    except cv2.error:
        fg = sd > 0
    out = np.zeros((H, W), bool)
    out[y0:y1, x0:x1] = fg
    return out


# -- tracking -------------------------------------------------------------------------


@dataclass
class _State:
    centre: np.ndarray  # [2] pixels
    velocity: np.ndarray  # [2] pixels per frame
    size: np.ndarray  # [2] bbox width, height
    mask: np.ndarray  # [H, W] the object's extent in the last frame it was found (hands included)
    visible: np.ndarray  # [H, W] its visible part there
    t: int  # that frame
    colour: float = 0.0  # mean object probability of its visible part (global colour model)
    lost: int = 0  # frames since it was found
    carrier: int | None = None  # the hand carrying the object (0 left, 1 right)
    carried: int = 0  # consecutive frames it was seen carried by that hand
    by_hand: int = 0  # consecutive frames found by the hand cue alone
    area: float = 0.0  # the object's usual extent in pixels (clear views only)


def _mask_stats(mask: np.ndarray):
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return None, None
    centre = np.array([xs.mean() + 0.5, ys.mean() + 0.5])
    size = np.array([xs.max() - xs.min() + 1, ys.max() - ys.min() + 1], dtype=np.float64)
    return centre, size


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.logical_and(a, b).sum() / max(np.logical_or(a, b).sum(), 1))


def _locate(prob: np.ndarray, state: _State, ref_score: float, hands: np.ndarray | None = None) -> tuple[np.ndarray, float, float]:
    """Centre and mean probability of the object-sized window that best explains the frame.

    The whole frame is searched: a window's mean object probability is weighted by
    0.35 + 0.65 g, with g a Gaussian around the constant-velocity prediction (or around a
    visible hand, whichever is larger: handled objects stay near hands), so a
    clearly better-looking window anywhere wins over a mediocre one nearby (a fast or
    briefly hidden object is re-acquired), while near-ties go to the motion prediction.
    """
    import cv2

    H, W = prob.shape
    w, h = np.maximum(state.size, 3).astype(int)
    score = cv2.boxFilter(prob.astype(np.float32), -1, (int(w), int(h)), normalize=True, borderType=cv2.BORDER_CONSTANT)
    pred = state.centre + state.velocity
    diag = float(np.hypot(w, h))
    sigma = max(1.5 * diag, 2.0 * float(np.linalg.norm(state.velocity))) * (1.0 + 0.5 * state.lost)
    yy, xx = np.mgrid[:H, :W]
    d2 = (xx + 0.5 - pred[0]) ** 2 + (yy + 0.5 - pred[1]) ** 2
    g = np.exp(-0.5 * d2 / sigma**2)
    if hands is not None:
        # A handled object is likely at a hand: windows near a visible hand are as
        # plausible as the motion prediction.
        for hx, hy, hv in hands:
            if np.isfinite(hx) and hv >= 0.5:
                dh2 = (xx + 0.5 - hx) ** 2 + (yy + 0.5 - hy) ** 2
                g = np.maximum(g, np.exp(-0.5 * dh2 / (0.75 * diag) ** 2))
    total = score * (0.35 + 0.65 * g)
    i = int(np.argmax(total))
    y, x = divmod(i, W)
    return np.array([x + 0.5, y + 0.5]), float(score[y, x]), float(g[y, x])


def _suppress_head(prob: np.ndarray, kp: np.ndarray, last_centre: np.ndarray) -> None:
    """Damp the object probability on the person's head, in place.

    Skin is the commonest look-alike of a handled object's colours and the face is always
    in view; unless the object was last seen on the head, head pixels count 5x less.
    """
    face = kp[:11]  # nose, eyes, ears, mouth
    if not np.isfinite(face).all() or np.median(face[:, 2]) < 0.5:
        return
    c = face[:, :2].mean(0)
    r = 1.3 * float(np.linalg.norm(face[:, :2] - c, axis=1).max()) + 2.0
    if np.linalg.norm(last_centre - c) < r:
        return
    H, W = prob.shape
    x0, x1 = int(max(0, c[0] - r)), int(min(W, c[0] + r + 1))
    y0, y1 = int(max(0, c[1] - r)), int(min(H, c[1] + r + 1))
    if x1 <= x0 or y1 <= y0:
        return
    yy, xx = np.mgrid[y0:y1, x0:x1]
    inside = (xx + 0.5 - c[0]) ** 2 + (yy + 0.5 - c[1]) ** 2 <= r * r
    prob[y0:y1, x0:x1][inside] *= 0.2


class _Tracker:
    """The classical engine's state shared by every pass over the video (see
    ``propagate_masks``): the colour model, the feature bank and the per-frame inputs."""

    def __init__(self, images, prompt_mask, prompt_frame, human_probs, kp2d, min_score, adapt, max_hand_frames, min_align=0.5):
        import cv2

        self.min_align = min_align

        self.images = images
        self.human_probs = human_probs
        self.kp2d = kp2d
        self.hands = _hand_points(kp2d)
        self.min_score = min_score
        self.adapt = adapt
        self.max_hand_frames = max_hand_frames
        self.ref_area = float(prompt_mask.sum())
        _, self.s0 = _mask_stats(prompt_mask)
        ring = cv2.dilate(prompt_mask.astype(np.uint8), np.ones((5, 5), np.uint8), iterations=max(2, int(0.15 * self.s0.max() / 2))) > 0
        self.distractors = None
        if human_probs is not None:
            # The person's colours in every frame (a held object inside the person's mask
            # contaminates this a little; the object's own histogram is far more peaked).
            keep = human_probs > 127
            keep[prompt_frame] &= ~ring
            rng = np.random.default_rng(0)
            flat = np.flatnonzero(keep)
            if len(flat):
                pick = rng.choice(flat, size=min(len(flat), 400_000), replace=False)
                self.distractors = images.reshape(-1, 3)[pick]
        self.base_model = ColourModel.fit(images[prompt_frame], prompt_mask, ~ring, self.distractors)
        self.ref_score = float(self.base_model.prob(images[prompt_frame])[prompt_mask].mean())
        self.bank = _FeatureBank(images)
        self.bank.pin(prompt_frame, prompt_mask)

    def _adapted(self, t: int, mask: np.ndarray) -> ColourModel:
        """The prompt's colour model with a share of frame t's object colours (a turning
        object shows new faces)."""
        import cv2

        if self.adapt <= 0:
            return self.base_model
        ring = cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8), iterations=3) > 0
        return self.base_model.blend(ColourModel.fit(self.images[t], mask, ~ring, self.distractors), self.adapt)

    def run(self, start: int, direction: int, masks: np.ndarray, conf: np.ndarray, cues: list, fill: bool = False, on_frame=None) -> None:
        """Track from frame ``start`` (its mask known) towards ``direction``, writing
        ``masks``/``conf``/``cues`` in place. ``fill``: only into empty frames, stopping at
        the first frame already found or where the object is lost again."""
        T = len(self.images)
        m0 = masks[start]
        c0, s0 = _mask_stats(m0)
        model = self._adapted(start, m0)
        st = _State(c0.copy(), np.zeros(2), s0.copy(), m0, m0, start, colour=float(model.prob(self.images[start])[m0].mean()), area=float(m0.sum()))
        self.bank.reset([self.bank.view(start, m0)])
        # A find by the hand cue alone is tentative: the next frame found by another cue
        # must show the object carried by that hand, or both are undone (the hand cue
        # picked something static, e.g. the background beside a hand hiding the object).
        pending = None  # (frame, hand, state and model before it)
        t = start + direction
        while 0 <= t < T:
            if fill and masks[t].any():
                break
            mask, extent, cf, cue, score = self._step(t, st, direction, model, verify=pending is not None)
            if pending is not None and mask.any() and cue != "hand":
                t_h, hand, st_before, model_before = pending
                pending = None
                if st.t != t - direction or not self._confirms_carry(st.t, t, st.mask, extent, hand):
                    for u in range(t_h, t, direction):
                        masks[u], conf[u], cues[u] = False, 0.0, ""
                    self.bank.recent = [v for v in self.bank.recent if (v.t - t_h) * direction < 0]
                    st, model = st_before, model_before
                    st.lost += abs(t - t_h) + 1
                    mask, cf, cue = np.zeros_like(mask), 0.0, ""
                    extent = mask
            if fill and not mask.any():
                break
            masks[t], conf[t], cues[t] = mask, cf, cue
            if mask.any():
                if cue == "hand" and pending is None:
                    pending = (t, st.carrier, copy.deepcopy(st), model)
                c, s = _mask_stats(mask)
                carrier = _carrying_hand(self.hands, st.t, t, st.mask, extent) if st.t == t - direction else None
                if carrier is not None:
                    st.carried = st.carried + 1 if carrier == st.carrier else 1
                    st.carrier = carrier
                elif cf >= 0.8:
                    st.carrier, st.carried = None, 0  # clearly seen, and not in that hand
                st.by_hand = st.by_hand + 1 if cue == "hand" else 0
                v_new = (c - st.centre) / (st.lost + 1)
                st.velocity = 0.5 * st.velocity + 0.5 * v_new
                st.centre = c
                if cue != "hand" and (cue != "colour" or score >= 0.8 * self.ref_score):
                    # Only clear views update the size; occluded views would shrink it.
                    st.size = np.clip(0.7 * st.size + 0.3 * s, 0.5 * self.s0, 2.0 * self.s0)
                if cf >= 0.8:
                    st.area = 0.7 * st.area + 0.3 * float(extent.sum())
                st.lost = 0
                model = self._adapted(t, mask)
                st.mask, st.visible, st.t, st.colour = extent, mask, t, score
                self.bank.add(t, mask)
            else:
                st.centre = st.centre + st.velocity
                st.velocity = 0.5 * st.velocity  # a hidden object's motion is unknown
                st.lost += 1
            if on_frame:
                on_frame()
            t += direction

    def _confirms_carry(self, t0: int, t1: int, m0: np.ndarray, m1: np.ndarray, hand: int) -> bool:
        """Whether the object found by the hand cue in frame t0 (``m0``) and found again in
        frame t1 (``m1``) is carried by ``hand``: touching it and moving with it (loosely:
        an object turning in the hand moves its centre), and not staying put with the
        background while the hand moves on (a piece of background beside the hand)."""
        import cv2

        if _carrying_hand(self.hands, t0, t1, m0, m1, touch=0.35, moved_max=0.6) != hand:
            return False
        static0 = ~(cv2.dilate(m0.astype(np.uint8), np.ones((15, 15), np.uint8)) > 0)
        if self.human_probs is not None:
            static0 &= self.human_probs[t0] <= 127
        Hm = self.bank.background_motion(t0, t1, static0)
        if Hm is None:
            return True
        c0, _ = _mask_stats(m0)
        c1, _ = _mask_stats(m1)
        size = float(np.sqrt(m1.sum()))
        pts = np.array([c0, self.hands[t0, hand, :2]], np.float64).reshape(-1, 1, 2)
        c_bg, h_bg = cv2.perspectiveTransform(pts, Hm).reshape(2, 2)
        stays = np.linalg.norm(c1 - c_bg) < 0.2 * size
        hand_moves = np.linalg.norm(self.hands[t1, hand, :2] - h_bg) > 0.4 * size
        return not (stays and hand_moves)

    def _local_model(self, st: _State) -> ColourModel:
        """The object's colours against its surroundings (a band around it, hands and
        all) in the last frame it was found, the person's colours weighing in as usual."""
        import cv2

        r = max(8, int(0.4 * float(st.size.max())))
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        x0, y0, x1, y1 = _window(st.mask, 1.0)
        band = np.zeros_like(st.mask)
        band[y0:y1, x0:x1] = cv2.dilate(st.mask[y0:y1, x0:x1].astype(np.uint8), k) > 0
        return ColourModel.fit(self.images[st.t], st.visible, band & ~st.visible, self.distractors)

    def _hands_mask(self, t: int) -> np.ndarray:
        H, W = self.images.shape[1:3]
        if self.kp2d is None:
            return np.zeros((H, W), bool)
        return hand_regions(self.kp2d[t], (H, W))

    def _step(self, t: int, st: _State, direction: int, model: ColourModel, verify: bool = False) -> tuple[np.ndarray, np.ndarray, float, str, float]:
        """One frame: (visible mask, extent including the parts hands hide, confidence,
        cue that found it, colour score). ``verify``: the last find came from the hand
        cue alone, so this frame must find the object without the hand's help."""
        rgb = self.images[t]
        H, W = rgb.shape[:2]
        prob = model.prob(rgb)
        if self.kp2d is not None:
            _suppress_head(prob, self.kp2d[t], st.centre)
        hp = None if self.human_probs is None else self.human_probs[t].astype(np.float32) / 255.0
        empty = np.zeros((H, W), bool)
        # The hands are next to a handled object all the time and look like a
        # skin-coloured one: they count 5x less in the colour search and are never object.
        hands = self._hands_mask(t)
        prob_search = prob.copy()
        prob_search[hands] *= 0.2

        def colour_of(m):
            return float(prob[m].mean()) if m.any() else 0.0

        # 1. Motion. Candidate places for the last extent: where it was, where matched
        #    features or dense flow carry it, where the carrying hand takes it. Each is
        #    aligned (ECC) to this frame's likelihood under a colour model of the object
        #    against its own surroundings in the last frame; the best-aligned one wins
        #    if it aligns well enough (otherwise the object moved too far, was hidden or
        #    changed too much: the searches below take over).
        lp = self._local_model(st).prob(rgb)
        cands = [("stay", st.mask)]
        feat = self.bank.match(t)
        if feat is not None:
            cands.append(("features", feat[0]))
        if st.t == t - direction:
            flow = warp_mask_by_flow(self.images[st.t], rgb, st.mask)
            if flow.sum() >= 0.25 * st.mask.sum():
                cands.append(("flow", flow))
            h = st.carrier
            if not verify and h is not None and st.carried >= 2 and _visible(self.hands, st.t, h) and _visible(self.hands, t, h):
                cands.append(("carried", _move_with_hand(st.mask, self.kp2d[st.t], self.kp2d[t], h)))
        best = None
        for name, cand in cands:
            if not cand.any():
                continue
            aligned, cc = align_mask(cand, lp)
            if _DEBUG is not None:
                _DEBUG.append(dict(t=t, name=name, cand=cand, aligned=aligned, cc=cc))
            if aligned is not None and aligned.any() and (best is None or cc > best[2]):
                best = (name, aligned, cc)
        if best is not None and best[2] >= self.min_align:
            cue, pred, cc = best
            seg = _grabcut_from_seed(rgb, lp, pred, hp)
            c, _ = _mask_stats(pred)
            seg = _fill_holes(_largest_component_near(seg, tuple(c))) if seg.any() else seg
            if not (seg.any() and _iou(seg, pred) >= 0.5 and 0.5 <= seg.sum() / pred.sum() <= 2.0):
                seg = pred
            # Fingers in front of the object: its extent carries on to the next frame, the
            # returned mask holds its visible pixels. Mostly hand is not the object (a
            # skin-coloured object slid onto the hand holding it).
            visible = seg & ~(hands & (lp < 0.5))
            if (seg & ~hands).sum() < 0.25 * seg.sum():
                best = None
            # It must still look like the object: clearly (half the prompt's evidence), or
            # keeping most of the evidence it had (a turning object shows new faces
            # gradually; a fit that slid onto a hand or the background loses it at once).
        if best is not None and best[2] >= self.min_align:
            sc = colour_of(visible)
            # ... and no clearly better-looking place elsewhere (the fit held on to a
            # look-alike while the object moved away, e.g. a hand after a bounce).
            centre, score, _ = _locate(prob_search, st, self.ref_score, None if self.hands is None else self.hands[t])
            far = np.linalg.norm(centre - _mask_stats(visible)[0]) > 0.5 * float(np.hypot(*st.size))
            better = far and score > 1.3 * sc and score >= self.min_score * self.ref_score
            if not better and (sc >= self.min_score * self.ref_score or sc >= 0.6 * st.colour):
                cf = float(np.clip((cc - self.min_align) / (0.9 - self.min_align), 0.3, 1.0))
                return visible, seg, cf, cue, sc

        # 2. Colour: the best-looking object-sized window (see _locate), GrabCut seeded there.
        centre, score, plausible = _locate(prob_search, st, self.ref_score, None if self.hands is None else self.hands[t])
        # Evidence needed falls with prior plausibility: min_score at a moderately likely
        # place, 0.7x that where predicted or at a hand, 1.3x far from both.
        needed = self.min_score * self.ref_score * (1.3 - 0.6 * plausible)
        if score >= needed:
            seg = _grabcut_seeded(rgb, prob_search, centre, st.size, hp)
            seg = _fill_holes(_largest_component_near(seg, tuple(centre))) & ~hands if seg.any() else seg
            if 0.25 * self.ref_area <= seg.sum() <= 3.0 * self.ref_area:
                return seg, seg, min(1.0, score / self.ref_score), "colour", score
            # GrabCut leaked or collapsed: keep the probable pixels in the located window.
            yy, xx = np.mgrid[:H, :W]
            ell = ((xx + 0.5 - centre[0]) / (0.5 * st.size[0])) ** 2 + ((yy + 0.5 - centre[1]) / (0.5 * st.size[1])) ** 2
            fallback = (ell <= 1.0) & (prob_search > 0.5)
            if fallback.sum() >= 0.25 * self.ref_area:
                fallback = _fill_holes(_largest_component_near(fallback, tuple(centre))) & ~hands
                return fallback, fallback, min(1.0, score / self.ref_score), "colour", score

        # 3. The hand: an object carried for a while is still in that hand, whatever face
        #    it now shows (for a few frames; past them it may have been put down).
        h = st.carrier
        if h is not None and st.carried >= 2 and abs(t - st.t) <= self.max_hand_frames and _visible(self.hands, t, h):
            seg = _grabcut_at_hand(rgb, self.hands[t, h, :2], float(np.sqrt(st.area)), hp) & ~hands
            area = st.area
            if _DEBUG is not None:
                _DEBUG.append(dict(t=t, name="handsearch", cand=seg, aligned=seg, cc=seg.sum() / area))
            if 0.4 * area <= seg.sum() <= 2.5 * area and _solidity(seg) >= 0.8:
                return seg, seg, 0.3, "hand", colour_of(seg)
        return empty, empty, 0.0, "", 0.0


def propagate_masks(
    images: np.ndarray,
    prompt_mask: np.ndarray,
    prompt_frame: int,
    human_probs: np.ndarray | None = None,
    kp2d: np.ndarray | None = None,
    min_score: float = 0.5,
    adapt: float = 0.1,
    max_hand_frames: int = 4,
    on_frame=None,
) -> tuple[np.ndarray, np.ndarray]:
    """Propagate one frame's object mask through the video (classical engine).

    images [T, H, W, 3] uint8; prompt_mask [H, W] bool at frame ``prompt_frame``;
    human_probs [T, H, W] uint8 person probabilities (optional prior); kp2d [T, 33, 3]
    MediaPipe keypoints (optional: the hands).

    Each frame, walking away from the prompt in both directions, takes the first cue that
    holds:

    1. **motion**: the mask of a remembered view carried by the RANSAC similarity of
       matched SIFT keypoints, or the last mask carried by dense optical flow when it
       keeps at least 0.6 of its colour evidence; GrabCut then fits it to this frame's
       edges (its eroded core stays object whatever its colour);
    2. **colour**: the object-sized window with the best mean object probability (see
       ``_locate``); ``min_score``: a window below this fraction of the prompt mask's own
       probability counts as "object not visible" (scaled by 0.7 where the motion
       prediction or a hand puts the object, 1.3 far from both);
    3. **hand**: an object seen carried by a hand (moving with it, touching it) for two
       frames or more is segmented next to that hand, off the person, for at most
       ``max_hand_frames`` frames in a row;

    otherwise the object is hidden and the frame's mask is empty. ``adapt``: share of
    the last found mask's colours in the colour model. Then each run of empty frames that
    ends where the object was found again is tracked back into from there.
    Returns (masks [T, H, W] bool, confidence [T] in [0, 1]; 0 where the object was lost).
    """
    T, H, W, _ = images.shape
    if not prompt_mask.any():
        raise UserError(f"the object prompt on frame {prompt_frame} gave an empty mask")
    masks = np.zeros((T, H, W), bool)
    conf = np.zeros(T)
    cues = [""] * T
    masks[prompt_frame] = prompt_mask
    conf[prompt_frame] = 1.0
    cues[prompt_frame] = "prompt"
    tracker = _Tracker(images, prompt_mask, prompt_frame, human_probs, kp2d, min_score, adapt, max_hand_frames)
    done = [1]

    def tick():
        done[0] += 1
        if on_frame:
            on_frame(min(done[0], T))

    if on_frame:
        on_frame(1)
    for direction in (+1, -1):
        tracker.run(prompt_frame, direction, masks, conf, cues, on_frame=tick)
    # Backwards into each gap from where the object was found again (it reappeared with a
    # face or at a place the forward pass could not connect to).
    for direction in (+1, -1):
        order = range(prompt_frame + direction, T if direction > 0 else -1, direction)
        for t in order:
            if masks[t].any() and not masks[t - direction].any():
                tracker.run(t, -direction, masks, conf, cues, fill=True)
    log.debug("object cues per frame: %s", cues)
    if _DEBUG is not None:
        _DEBUG.append(dict(cues=cues))
    return masks, conf


def read_mask_folder(folder: str | Path, n_frames: int, size: tuple[int, int], source_indices: np.ndarray | None = None) -> np.ndarray:
    """Ready-made object masks: one image per frame (sorted by name), resized -> [T, H, W] bool.

    The folder may hold one mask per *source* frame (then ``source_indices`` picks the kept
    ones) or exactly one per processed frame.
    """
    import cv2
    from PIL import Image

    folder = Path(folder)
    if not folder.is_dir():
        raise UserError(f"--object-masks {folder} is not a folder")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"))
    if len(files) == n_frames:
        chosen = files
    elif source_indices is not None and len(files) > int(source_indices.max()):
        chosen = [files[i] for i in source_indices]
    else:
        raise UserError(f"--object-masks {folder} holds {len(files)} masks; expected {n_frames} (one per processed frame) or one per input frame")
    out = np.zeros((n_frames, size[1], size[0]), bool)
    for t, f in enumerate(chosen):
        try:
            with Image.open(f) as im:
                m = np.asarray(im.convert("L"))
        except OSError as e:
            raise UserError(f"cannot read mask {f}: {e}") from None
        out[t] = cv2.resize(m, size, interpolation=cv2.INTER_NEAREST) > 127
    return out


def propagate_masks_sam2(images: np.ndarray, box: np.ndarray, prompt_frame: int, checkpoint: Path, config: str, work_dir: Path, on_frame=None) -> np.ndarray:
    """SAM2 video propagation from a box prompt (optional engine) -> [T, H, W] bool."""
    if not Path(checkpoint).exists():
        raise UserError(f"--sam2-checkpoint {checkpoint} does not exist")
    try:
        import torch
        from sam2.build_sam import build_sam2_video_predictor
    except ImportError as e:
        raise UserError(f"--sam2-checkpoint needs the `sam2` package ({e}); install it or drop the option") from None
    from PIL import Image

    frames_dir = Path(work_dir) / "sam2_frames"
    frames_dir.mkdir(parents=True, exist_ok=True)
    for t, rgb in enumerate(images):  # SAM2 reads a folder of JPEGs named by index
        Image.fromarray(rgb).save(frames_dir / f"{t:05d}.jpg", quality=95)
    predictor = build_sam2_video_predictor(config, str(checkpoint), device="cpu")
    T, H, W, _ = images.shape
    out = np.zeros((T, H, W), bool)
    done = 0
    with torch.inference_mode():
        state = predictor.init_state(video_path=str(frames_dir))
        predictor.add_new_points_or_box(state, frame_idx=prompt_frame, obj_id=1, box=box.astype(np.float32))
        for reverse in (False, True):
            for t, _, logits in predictor.propagate_in_video(state, start_frame_idx=prompt_frame, reverse=reverse):
                out[t] = (logits[0, 0] > 0).cpu().numpy()
                done += 1
                if on_frame:
                    on_frame(min(done, T))
    return out
