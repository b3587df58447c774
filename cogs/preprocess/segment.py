"""2D segmentation primitives for the object tracker: a colour model, GrabCut variants and
mask helpers. Pure functions of images and masks; the tracker (``tracking.py``) decides
which to use where.

Conventions: images are [H, W, 3] uint8 RGB, masks [H, W] bool, probability maps
[H, W] float in [0, 1], pixel centres at (x + 0.5, y + 0.5).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

BINS = 32  # colour histogram bins per channel


# -- colour model ---------------------------------------------------------------------


def _bin_index(rgb: np.ndarray) -> np.ndarray:
    q = (rgb.astype(np.int32) * BINS) // 256
    return (q[..., 0] * BINS + q[..., 1]) * BINS + q[..., 2]


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
        n = BINS**3
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

    return uniform_filter(h.reshape(BINS, BINS, BINS), size=3, mode="nearest").reshape(-1)


# -- mask helpers ---------------------------------------------------------------------


def mask_stats(mask: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(centre [2] pixels, bounding-box size [2] width, height), or (None, None) if empty."""
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return None, None
    centre = np.array([xs.mean() + 0.5, ys.mean() + 0.5])
    size = np.array([xs.max() - xs.min() + 1, ys.max() - ys.min() + 1], dtype=np.float64)
    return centre, size


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.logical_and(a, b).sum() / max(np.logical_or(a, b).sum(), 1))


def window(mask: np.ndarray, margin: float) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1): a non-empty mask's bounding box grown by ``margin`` x its size
    + 16 px on each side, clipped to the frame."""
    H, W = mask.shape
    c, s = mask_stats(mask)
    r = (0.5 + margin) * s + 16
    return int(max(0, c[0] - r[0])), int(max(0, c[1] - r[1])), int(min(W, c[0] + r[0] + 1)), int(min(H, c[1] + r[1] + 1))


def largest_component_near(mask: np.ndarray, point: tuple[float, float]) -> np.ndarray:
    """The connected component that is large and near ``point`` (x, y)."""
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


def fill_holes(mask: np.ndarray) -> np.ndarray:
    from scipy.ndimage import binary_fill_holes

    return binary_fill_holes(mask)


# Discs up to this radius are OpenCV's digital ellipse (what the tracker's constants were
# measured with); larger ones the exact Euclidean disc of a distance transform. A dilation's
# cost grows with the disc's area (0.19 s a 960 px frame at radius 100, 7 s at 490: a guitar
# as wide as the frame kept the tracker at minutes a frame), a distance transform's does not.
# The two discs differ by a few pixels along the outline, which the tracker can amplify (the
# exact disc at every size moved the bottle clip's track onto the floor, trusted, at 23-30;
# from radius 100 on, variant 7 of the synthetic video lost 0.03 object IoU), so discs up to
# 128 px, more than any object of the synthetic benchmark or the development clips but the
# guitar and the backpack spans, stay as measured (the demo scene runs no preprocessing;
# docs/experiments/2026-12-02-discs-the-size-of-a-guitar.md).
LARGE_DISC = 128
# The frame size the masks step's pixel lengths were chosen at (the development clips at
# --max-side 384): a length there covers SCALE_SIDE / side as much of a larger frame, so it
# is scaled up with the frame (``at_size``). The tracker's own few fixed lengths (5x5 and
# 15x15 rings, the keypoints' 1 and 3 px still and moving bounds) were scaled the same way:
# no mask of the synthetic video at 960 px (two settings) or the basketball clip at 960
# changed, and the bottle's track at 960 took both forearms, trusted, at frame 53; the static
# scene's 2 px colour tolerance, scaled, cost the synthetic video 0.016 and 0.012 object IoU
# at 960: neither is scaled
# (docs/experiments/2026-12-02-d-pixel-lengths-on-larger-frames.md).
SCALE_SIDE = 384


def at_size(px: float, shape: tuple[int, ...]) -> float:
    """``px`` pixels of a frame whose longer side is ``SCALE_SIDE`` -> pixels of a frame of
    ``shape`` (H, W, ...): as much of the frame, never fewer than ``px``."""
    return px * max(1.0, max(shape[0], shape[1]) / SCALE_SIDE)


def disk(r: int) -> np.ndarray:
    """OpenCV's digital ellipse of radius ``r``: a (2r + 1)-square uint8 structuring element."""
    import cv2

    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def grown(mask: np.ndarray, r: int) -> np.ndarray:
    """``mask`` [H, W] bool grown by a disc of radius ``r`` pixels -> [H, W] bool (the
    digital ellipse up to ``LARGE_DISC``, the pixels within r of the mask beyond)."""
    import cv2

    mask, r = np.asarray(mask, bool), int(r)
    if r <= LARGE_DISC:
        return cv2.dilate(mask.astype(np.uint8), disk(r)) > 0
    if not mask.any():
        return mask.copy()
    return cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE) <= r


def shrunk(mask: np.ndarray, r: int) -> np.ndarray:
    """``mask`` [H, W] bool shrunk by a disc of radius ``r`` -> [H, W] bool (the digital
    ellipse up to ``LARGE_DISC``; beyond, its pixels farther than r from any pixel outside
    it). The image's border does not count as outside."""
    import cv2

    mask, r = np.asarray(mask, bool), int(r)
    if r <= LARGE_DISC:
        return cv2.erode(mask.astype(np.uint8), disk(r)) > 0
    if mask.all():
        return mask.copy()
    return cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE) > r


def solidity(mask: np.ndarray) -> float:
    """Area over convex-hull area: 1 for a convex silhouette. A handled object is nearly
    convex; a piece of background that GrabCut cut out rarely is."""
    import cv2

    pts = cv2.findNonZero(mask.astype(np.uint8))
    if pts is None:
        return 0.0
    return float(mask.sum()) / max(cv2.contourArea(cv2.convexHull(pts)), 1.0)


def convex_hull(mask: np.ndarray) -> np.ndarray:
    """The convex hull of a mask's pixels -> [H, W] bool (empty for an empty mask)."""
    import cv2

    out = np.zeros(mask.shape, np.uint8)
    pts = cv2.findNonZero(mask.astype(np.uint8))
    if pts is not None:
        cv2.fillConvexPoly(out, cv2.convexHull(pts), 1)
    return out > 0


# -- edges ----------------------------------------------------------------------------

EDGE_RADIUS = 1.2
"""The guided filter's radius in `align_to_edges`, in cells of MediaPipe's segmentation
(the frame's longer side / 256, the grid its person mask is predicted on before it is
upsampled). Chosen on the synthetic video benchmark at seven settings (reference, variants
1-5, 60 frames seed 7), where 0.8 / 1.2 / 1.6 cells raise the final human IoU by
0.007-0.009 / 0.009-0.012 / 0.009-0.012 (eps 1e-3); the largest was not taken, for real
frames' clutter (a larger box reaches further onto other edges). On the real development
clips (2 px at 384 px) the basketball's and loading's strips were looked at, and the
basketball's, loading's and guitar's held-out PSNR measured with it
(docs/experiments/2026-11-29-outlines-and-somebody-elses-face.md).
The demo scene runs no preprocessing."""
EDGE_EPS = 1e-3  # the guided filter's regularisation (colours in [0, 1]): 1e-2 gave the same within 0.001


def guided_filter(rgb: np.ndarray, p: np.ndarray, radius: int, eps: float) -> np.ndarray:
    """He, Sun and Tang's guided filter with a colour guide: ``p`` [H, W] float smoothed
    within boxes of side 2 * radius + 1 so that its output is locally an affine function of
    the colours of ``rgb`` [H, W, 3] uint8 -> [H, W] float32. Edges of the image stay edges;
    a step in ``p`` that lies between two of them moves onto the nearest."""
    import cv2

    guide = rgb.astype(np.float32) / 255.0
    p = p.astype(np.float32)
    k = (2 * radius + 1,) * 2

    def mean(x):
        return cv2.boxFilter(x, -1, k, borderType=cv2.BORDER_REFLECT)

    mu = np.stack([mean(guide[..., c]) for c in range(3)], -1)
    mp = mean(p)
    cov = np.stack([mean(guide[..., c] * p) - mu[..., c] * mp for c in range(3)], -1)
    var = np.empty(p.shape + (3, 3), np.float32)
    for a in range(3):
        for b in range(a, 3):
            var[..., a, b] = var[..., b, a] = mean(guide[..., a] * guide[..., b]) - mu[..., a] * mu[..., b]
    var += eps * np.eye(3, dtype=np.float32)
    a = np.linalg.solve(var, cov[..., None])[..., 0]
    b = mp - (a * mu).sum(-1)
    return (np.stack([mean(a[..., c]) for c in range(3)], -1) * guide).sum(-1) + mean(b)


def align_to_edges(rgb: np.ndarray, mask: np.ndarray, radius: float | None = None, eps: float = EDGE_EPS,
                   keep_thin: bool = True) -> np.ndarray:
    """A mask's outline moved onto the image's edges nearby: the mask guided-filtered by the
    frame (`guided_filter`), kept where the result is at least a half -> [H, W] bool. A mask
    predicted on a coarser grid than the frame (MediaPipe's person mask) is off the true
    outline by up to a cell either way; this moves it by at most ``radius`` pixels
    (default `EDGE_RADIUS` cells of MediaPipe's grid). With ``keep_thin`` the parts
    narrower than the filter's box are kept as they are: averaged over the box they fall
    under a half whatever the edges say (a racket's handle, a small object's top; on the
    bottle development clip the bottle's top at 40 and 49 lost 30-60 % of its pixels).
    A person's mask does without: MediaPipe's has no part that thin but the bleed along
    the outline (on the synthetic benchmark's reference video, keeping thin parts gives
    back 0.003 of the 0.012 the filter gains on the person, 0.005 of 0.015 on the object)."""
    import cv2

    if not mask.any():
        return mask
    H, W = mask.shape
    r = max(1, int(round((EDGE_RADIUS * max(H, W) / 256) if radius is None else radius)))
    ys, xs = np.nonzero(mask)
    y0, y1 = max(0, ys.min() - 3 * r), min(H, ys.max() + 3 * r + 1)
    x0, x1 = max(0, xs.min() - 3 * r), min(W, xs.max() + 3 * r + 1)
    m = mask[y0:y1, x0:x1]
    aligned = guided_filter(rgb[y0:y1, x0:x1], m, r, eps) >= 0.5
    if keep_thin:
        aligned |= m & ~(cv2.morphologyEx(m.astype(np.uint8), cv2.MORPH_OPEN, disk(r)) > 0)
    out = np.zeros_like(mask)
    out[y0:y1, x0:x1] = aligned
    return out


# -- GrabCut --------------------------------------------------------------------------


def grabcut(img_bgr: np.ndarray, labels: np.ndarray, rect, iterations: int, mode: int) -> None:
    """``cv2.grabCut`` on ``labels`` (in place), with OpenCV's random generator reset: its
    colour models start from k-means, which draws from the global generator, so without
    this the same frames can give different masks from run to run."""
    import cv2

    cv2.setRNGSeed(0)
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    cv2.grabCut(img_bgr, labels, rect, bgd, fgd, iterations, mode)


def _foreground(labels: np.ndarray) -> np.ndarray:
    import cv2

    return (labels == cv2.GC_FGD) | (labels == cv2.GC_PR_FGD)


def grabcut_box(rgb: np.ndarray, box: np.ndarray, iterations: int = 5) -> tuple[np.ndarray, bool]:
    """GrabCut initialised with a rectangle -> ([H, W] bool: the component at the box
    centre, guessed: True where GrabCut kept under 5 % of the box and the box's inscribed
    ellipse stands in for the object: nothing in the box stood out from around it)."""
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
    labels = np.zeros(crop.shape[:2], np.uint8)
    rect = (x0 - cx0, y0 - cy0, max(bw, 2), max(bh, 2))
    if rect[0] == 0 and rect[1] == 0 and rect[2] >= crop.shape[1] and rect[3] >= crop.shape[0]:
        # The box fills the image: GrabCut needs some background; shrink by a pixel.
        rect = (1, 1, crop.shape[1] - 2, crop.shape[0] - 2)
    grabcut(crop, labels, rect, iterations, cv2.GC_INIT_WITH_RECT)
    out = np.zeros((H, W), bool)
    out[cy0:cy1, cx0:cx1] = _foreground(labels)
    out = largest_component_near(out, (0.5 * (x0 + x1), 0.5 * (y0 + y1)))
    guessed = bool(out.sum() < 0.05 * bw * bh)
    if guessed:
        # GrabCut found nothing convincing: the inscribed ellipse of the box is the best guess.
        yy, xx = np.mgrid[:H, :W]
        out = ((xx + 0.5 - 0.5 * (x0 + x1)) / (0.5 * bw)) ** 2 + ((yy + 0.5 - 0.5 * (y0 + y1)) / (0.5 * bh)) ** 2 <= 1
    return fill_holes(out), guessed


def grabcut_at(rgb: np.ndarray, prob: np.ndarray, centre, size, human_prob: np.ndarray | None, iterations: int = 3,
               static: np.ndarray | None = None) -> np.ndarray:
    """GrabCut around an object located at ``centre`` with bounding ``size`` (w, h), seeded
    from the colour probability ``prob`` -> [H, W] bool. ``static`` [H, W] bool: pixels
    known to show the static scene, background whatever their colour."""
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
    labels = np.full(crop.shape[:2], cv2.GC_PR_BGD, np.uint8)
    labels[near & (p > 0.5)] = cv2.GC_PR_FGD
    labels[(ell <= 0.25) & (p > 0.8)] = cv2.GC_FGD
    labels[ell > 2.25] = cv2.GC_BGD
    if human_prob is not None:
        # Confident person pixels that do not look like the object are background.
        labels[(human_prob[y0:y1, x0:x1] > 0.9) & (p < 0.3)] = cv2.GC_BGD
    if static is not None:
        labels[static[y0:y1, x0:x1]] = cv2.GC_BGD
    if not _foreground(labels).any():
        return np.zeros((H, W), bool)
    if not ((labels == cv2.GC_PR_BGD) | (labels == cv2.GC_BGD)).any():
        labels[0, :] = cv2.GC_BGD
    try:
        grabcut(crop, labels, None, iterations, cv2.GC_INIT_WITH_MASK)
        fg = _foreground(labels)
    except cv2.error:
        fg = near & (p > 0.5)
    out = np.zeros((H, W), bool)
    out[y0:y1, x0:x1] = fg
    return out


def grabcut_from_seed(rgb: np.ndarray, prob: np.ndarray, seed: np.ndarray, human_prob: np.ndarray | None, iterations: int = 3,
                      static: np.ndarray | None = None) -> np.ndarray:
    """GrabCut around a predicted mask ``seed`` -> [H, W] bool.

    The seed's core (eroded by 15 % of its size) is object whatever its colour (a turning
    object shows faces the colour model has not seen), its ring (0.6 of its size) may go
    either way, and beyond that is background; confident person pixels that do not look
    like the object (``prob`` < 0.3) are background outside the core. ``static`` [H, W]
    bool: pixels known to show the static scene, background (probable background in the
    core: the seed may be off by a little).
    """
    import cv2

    H, W = seed.shape
    _, s = mask_stats(seed)
    size = float(max(s))
    r = int(0.6 * size) + 6
    ys, xs = np.nonzero(seed)
    x0, x1 = max(0, xs.min() - 2 * r), min(W, xs.max() + 2 * r + 1)
    y0, y1 = max(0, ys.min() - 2 * r), min(H, ys.max() + 2 * r + 1)
    sd = seed[y0:y1, x0:x1].astype(np.uint8)
    p = prob[y0:y1, x0:x1]
    near = grown(sd > 0, r)
    core = shrunk(sd > 0, max(1, int(0.15 * size)))
    labels = np.full(sd.shape, cv2.GC_BGD, np.uint8)
    labels[near] = cv2.GC_PR_BGD
    labels[(sd > 0) | (near & (p > 0.8))] = cv2.GC_PR_FGD
    labels[core] = cv2.GC_FGD
    if human_prob is not None:
        labels[(human_prob[y0:y1, x0:x1] > 0.9) & (p < 0.3) & ~core] = cv2.GC_BGD
    if static is not None:
        st = static[y0:y1, x0:x1]
        labels[st] = np.where(core[st], cv2.GC_PR_BGD, cv2.GC_BGD)
    if not _foreground(labels).any():
        return np.zeros((H, W), bool)
    if not ((labels == cv2.GC_BGD) | (labels == cv2.GC_PR_BGD)).any():
        labels[0, :] = cv2.GC_BGD
    try:
        grabcut(np.ascontiguousarray(rgb[y0:y1, x0:x1, ::-1]), labels, None, iterations, cv2.GC_INIT_WITH_MASK)
        fg = _foreground(labels)
    except cv2.error:
        fg = sd > 0
    out = np.zeros((H, W), bool)
    out[y0:y1, x0:x1] = fg
    return out


def grabcut_at_hand(rgb: np.ndarray, hand: np.ndarray, size: float, human_prob: np.ndarray | None, iterations: int = 4,
                    static: np.ndarray | None = None) -> np.ndarray:
    """The object held at pixel ``hand`` (x, y), its appearance unknown -> [H, W] bool
    (empty when nothing suitable touches the hand).

    GrabCut in a window around the hand: within 1.5 ``size`` of it (an object may be held
    by a corner) pixels may be object, the window's rim (another ``size`` out) is
    background and trains the background colours, and the person's confident pixels
    are background everywhere (with only a hand to go on, an object seen against the
    body cannot be told from it). ``static`` [H, W] bool: pixels known to show the static
    scene, background too. Of what GrabCut keeps, the piece of at least a fifth of
    ``size``^2 nearest the hand, within half a ``size`` of it.
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
    labels = np.where(inner, cv2.GC_PR_FGD, cv2.GC_BGD).astype(np.uint8)
    if human_prob is not None:
        labels[human_prob[y0:y1, x0:x1] > 0.5] = cv2.GC_BGD
    if static is not None:
        labels[static[y0:y1, x0:x1]] = cv2.GC_BGD
    if not (labels == cv2.GC_PR_FGD).any() or not (labels == cv2.GC_BGD).any():
        return np.zeros((H, W), bool)
    try:
        grabcut(np.ascontiguousarray(rgb[y0:y1, x0:x1, ::-1]), labels, None, iterations, cv2.GC_INIT_WITH_MASK)
    except cv2.error:
        return np.zeros((H, W), bool)
    n, comp, stats, _ = cv2.connectedComponentsWithStats(_foreground(labels).astype(np.uint8), connectivity=8)
    ys, xs = np.nonzero(comp)
    d = np.hypot(xs + x0 + 0.5 - hx, ys + y0 + 0.5 - hy)
    lab = comp[ys, xs]
    best, best_d = 0, 0.5 * size
    for k in range(1, n):
        if stats[k, cv2.CC_STAT_AREA] >= 0.2 * size * size:
            dk = float(d[lab == k].min())
            if dk <= best_d:
                best, best_d = k, dk
    out = np.zeros((H, W), bool)
    if best:
        out[y0:y1, x0:x1] = fill_holes(comp == best)
    return out


def grabcut_with_seeds(rgb: np.ndarray, mask: np.ndarray, keep: np.ndarray, drop: np.ndarray, iterations: int = 5) -> np.ndarray:
    """``mask`` [H, W] bool without what GrabCut, told that ``keep`` [H, W] bool is
    object and ``drop`` is not, gives to the background -> [H, W] bool (a subset of
    ``mask``: nothing is added). The rest of ``mask`` is probable object, a margin of a
    tenth of its size around it probable background, beyond that background: the seeds'
    colours decide which parts of the mask go with them."""
    import cv2

    ys, xs = np.nonzero(mask)
    if not len(ys):
        return mask.copy()
    H, W = mask.shape
    m = max(3, int(0.1 * max(np.ptp(xs), np.ptp(ys))))
    x0, y0, x1, y1 = max(0, xs.min() - 3 * m), max(0, ys.min() - 3 * m), min(W, xs.max() + 3 * m + 1), min(H, ys.max() + 3 * m + 1)
    crop = (slice(y0, y1), slice(x0, x1))
    near = cv2.dilate(mask[crop].astype(np.uint8), np.ones((2 * m + 1, 2 * m + 1), np.uint8)) > 0
    labels = np.where(near, cv2.GC_PR_BGD, cv2.GC_BGD).astype(np.uint8)
    labels[mask[crop]] = cv2.GC_PR_FGD
    labels[drop[crop]] = cv2.GC_BGD
    labels[keep[crop]] = cv2.GC_FGD
    if not ((labels == cv2.GC_BGD) | (labels == cv2.GC_PR_BGD)).any():
        return mask.copy()  # the mask fills the frame: nothing to tell it from
    try:
        grabcut(np.ascontiguousarray(rgb[crop][..., ::-1]), labels, None, iterations, cv2.GC_INIT_WITH_MASK)
    except cv2.error:
        return mask.copy()
    out = np.zeros_like(mask)
    out[crop] = _foreground(labels)
    return out & mask
