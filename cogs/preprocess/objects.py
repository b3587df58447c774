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

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cogs.errors import UserError

log = logging.getLogger(__name__)

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
    cv2.grabCut(crop, mask, rect, bgd, fgd, iterations, cv2.GC_INIT_WITH_RECT)
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
        cv2.grabCut(crop, mask, None, bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK)
    except cv2.error:
        fg = near & (p > 0.5)
    else:
        fg = (mask == cv2.GC_FGD) | (mask == cv2.GC_PR_FGD)
    out = np.zeros((H, W), bool)
    out[y0:y1, x0:x1] = fg
    return out


# -- optical flow ---------------------------------------------------------------------


def warp_mask_by_flow(prev_rgb: np.ndarray, rgb: np.ndarray, prev_mask: np.ndarray, margin: float = 1.0) -> np.ndarray:
    """The previous frame's mask carried into this frame by dense optical flow (Farneback),
    computed in a window around the mask -> [H, W] bool (empty when nothing lands)."""
    import cv2

    H, W = prev_mask.shape
    c, s = _mask_stats(prev_mask)
    if c is None:
        return np.zeros((H, W), bool)
    r = (0.5 + margin) * s + 16
    x0, x1 = int(max(0, c[0] - r[0])), int(min(W, c[0] + r[0] + 1))
    y0, y1 = int(max(0, c[1] - r[1])), int(min(H, c[1] + r[1] + 1))
    a = cv2.cvtColor(np.ascontiguousarray(rgb[y0:y1, x0:x1]), cv2.COLOR_RGB2GRAY)
    b = cv2.cvtColor(np.ascontiguousarray(prev_rgb[y0:y1, x0:x1]), cv2.COLOR_RGB2GRAY)
    # Flow from this frame to the previous one: where each pixel here came from.
    flow = cv2.calcOpticalFlowFarneback(a, b, None, 0.5, 4, 15, 3, 5, 1.2, 0)
    gy, gx = np.mgrid[0 : y1 - y0, 0 : x1 - x0].astype(np.float32)
    pm = prev_mask[y0:y1, x0:x1].astype(np.float32)
    warped = cv2.remap(pm, gx + flow[..., 0], gy + flow[..., 1], cv2.INTER_LINEAR, borderValue=0.0)
    out = np.zeros((H, W), bool)
    out[y0:y1, x0:x1] = warped > 0.5
    return out


def _grabcut_from_seed(rgb: np.ndarray, prob: np.ndarray, seed: np.ndarray, human_prob: np.ndarray | None, iterations: int = 3) -> np.ndarray:
    """GrabCut around a predicted mask (e.g. flow-warped): its core is object, far away is not."""
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
    gc[core & (p > 0.2)] = cv2.GC_FGD
    if human_prob is not None:
        hp = human_prob[y0:y1, x0:x1]
        gc[(hp > 0.9) & (p < 0.3) & ~core] = cv2.GC_BGD
    if not ((gc == cv2.GC_BGD) | (gc == cv2.GC_PR_BGD)).any():
        gc[0, :] = cv2.GC_BGD
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    crop = np.ascontiguousarray(rgb[y0:y1, x0:x1, ::-1])
    try:
        cv2.grabCut(crop, gc, None, bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK)
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
    lost: int = 0


def _mask_stats(mask: np.ndarray):
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return None, None
    centre = np.array([xs.mean() + 0.5, ys.mean() + 0.5])
    size = np.array([xs.max() - xs.min() + 1, ys.max() - ys.min() + 1], dtype=np.float64)
    return centre, size


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


def _hand_shift(hands: np.ndarray | None, t_from: int, t_to: int, mask: np.ndarray) -> np.ndarray | None:
    """Displacement of the hand holding the object (the visible hand within one object size
    of the mask's centre at ``t_from``) between two frames, or None."""
    if hands is None:
        return None
    c, s = _mask_stats(mask)
    if c is None:
        return None
    a, b = hands[t_from], hands[t_to]
    best, best_d = None, float(np.max(s))
    for h in range(2):
        if not (np.isfinite(a[h]).all() and np.isfinite(b[h]).all()) or min(a[h, 2], b[h, 2]) < 0.5:
            continue
        d = float(np.linalg.norm(a[h, :2] - c))
        if d <= best_d:
            best, best_d = b[h, :2] - a[h, :2], d
    return best


def _shift_mask(mask: np.ndarray, shift: np.ndarray) -> np.ndarray:
    import cv2

    H, W = mask.shape
    M = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])
    return cv2.warpAffine(mask.astype(np.uint8), M, (W, H), flags=cv2.INTER_NEAREST) > 0


def propagate_masks(
    images: np.ndarray,
    prompt_mask: np.ndarray,
    prompt_frame: int,
    human_probs: np.ndarray | None = None,
    kp2d: np.ndarray | None = None,
    hand_carry: bool = False,
    min_score: float = 0.5,
    adapt: float = 0.1,
    on_frame=None,
) -> tuple[np.ndarray, np.ndarray]:
    """Propagate one frame's object mask through the video (classical engine).

    images [T, H, W, 3] uint8; prompt_mask [H, W] bool at frame ``prompt_frame``;
    human_probs [T, H, W] uint8 person probabilities (optional prior); kp2d [T, 33, 3]
    MediaPipe keypoints (optional): with ``hand_carry`` an object seen at a hand is also
    predicted to move with it (off by default: it drags a dribbled ball along with the
    hand into skin-coloured distractors).
    ``min_score``: a located window whose mean object probability is below this fraction of
    the prompt mask's own counts as "object not visible" (occluded or out of frame); the
    fraction is scaled by 0.7 where the motion prediction or a hand puts the object and by
    1.3 far from both.
    Returns (masks [T, H, W] bool, confidence [T] in [0, 1]; 0 where the object was lost).
    """
    T, H, W, _ = images.shape
    masks = np.zeros((T, H, W), bool)
    conf = np.zeros(T)
    masks[prompt_frame] = prompt_mask
    conf[prompt_frame] = 1.0
    ref_area = float(prompt_mask.sum())
    c0, s0 = _mask_stats(prompt_mask)
    if c0 is None:
        raise UserError(f"the object prompt on frame {prompt_frame} gave an empty mask")
    import cv2

    ring = cv2.dilate(prompt_mask.astype(np.uint8), np.ones((5, 5), np.uint8), iterations=max(2, int(0.15 * s0.max() / 2))) > 0
    distractors = None
    if human_probs is not None:
        # The person's colours in every frame (a held object inside the person's mask
        # contaminates this a little; the object's own histogram is far more peaked).
        keep = human_probs > 127
        keep[prompt_frame] &= ~ring
        rng = np.random.default_rng(0)
        flat = np.flatnonzero(keep)
        if len(flat):
            pick = rng.choice(flat, size=min(len(flat), 400_000), replace=False)
            distractors = images.reshape(-1, 3)[pick]
    base_model = ColourModel.fit(images[prompt_frame], prompt_mask, ~ring, distractors)
    ref_score = float(base_model.prob(images[prompt_frame])[prompt_mask].mean())
    hands = _hand_points(kp2d)
    done = 1
    if on_frame:
        on_frame(done)
    for direction in (+1, -1):
        state = _State(c0.copy(), np.zeros(2), s0.copy())
        model = base_model
        t = prompt_frame + direction
        prev_mask, prev_t = prompt_mask, prompt_frame
        while 0 <= t < T:
            rgb = images[t]
            prob = model.prob(rgb)
            if kp2d is not None:
                _suppress_head(prob, kp2d[t], state.centre)
            hp = None if human_probs is None else human_probs[t].astype(np.float32) / 255.0
            mask = np.zeros((H, W), bool)
            # 1. Optical flow from the last frame with the object: right for slow, textured
            #    objects; a fast or reappearing object lands elsewhere and scores low.
            candidates = []
            if prev_t == t - direction:
                candidates.append(warp_mask_by_flow(images[prev_t], rgb, prev_mask))
            # 1b. An object held in a hand moves with that hand.
            shift = _hand_shift(hands, prev_t, t, prev_mask) if hand_carry else None
            if shift is not None:
                candidates.append(_shift_mask(prev_mask, shift))
            warped, flow_score = np.zeros((H, W), bool), 0.0
            for cand in candidates:
                sc = float(prob[cand].mean()) if cand.sum() >= 0.15 * ref_area else 0.0
                if sc > flow_score:
                    warped, flow_score = cand, sc
            if shift is not None:
                state.centre = _mask_stats(prev_mask)[0] + shift - state.velocity  # the prediction follows the hand
            # The carried mask must look clearly like the object (a drifting flow slides onto
            # similar-coloured skin or clothes); the colour search below needs less.
            use_flow = flow_score >= 0.7 * ref_score
            centre, score, plausible = _locate(prob, state, ref_score, None if hands is None else hands[t])
            # Evidence needed falls with prior plausibility: min_score at a moderately likely
            # place, 0.7x that where predicted or at a hand, 1.3x far from both.
            needed = min_score * ref_score * (1.3 - 0.6 * plausible)
            if use_flow:
                cw, _ = _mask_stats(warped)
                far = np.linalg.norm(centre - cw) > 0.5 * float(np.hypot(*state.size))
                if far and score > 1.3 * flow_score:
                    use_flow = False  # a better-looking window elsewhere: the flow drifted
            if use_flow:
                seg = _grabcut_from_seed(rgb, prob, warped, hp)
                cw, _ = _mask_stats(warped)
                seg = _fill_holes(_largest_component_near(seg, tuple(cw))) if seg.any() else seg
                agree = np.logical_and(seg, warped).sum() / max(np.logical_or(seg, warped).sum(), 1)
                prev_area = float(prev_mask.sum())
                seg_ok = 0.25 * ref_area <= seg.sum() <= 3.0 * ref_area
                if seg_ok and (agree >= 0.7 or (agree >= 0.3 and abs(np.log(seg.sum() / prev_area)) <= abs(np.log(warped.sum() / prev_area)))):
                    mask, score = seg, max(flow_score, float(prob[seg].mean()))
                else:
                    use_flow = False  # GrabCut and the motion disagree: search by colour instead
            if not use_flow and score >= needed:
                # 2. Colour search (see _locate) and GrabCut seeded from the colour model.
                seg = _grabcut_seeded(rgb, prob, centre, state.size, hp)
                seg = _fill_holes(_largest_component_near(seg, tuple(centre))) if seg.any() else seg
                area = float(seg.sum())
                if 0.25 * ref_area <= area <= 3.0 * ref_area:
                    mask = seg
                else:
                    # GrabCut leaked or collapsed: keep the probable pixels in the located window.
                    yy, xx = np.mgrid[:H, :W]
                    ell = ((xx + 0.5 - centre[0]) / (0.5 * state.size[0])) ** 2 + ((yy + 0.5 - centre[1]) / (0.5 * state.size[1])) ** 2
                    fallback = (ell <= 1.0) & (prob > 0.5)
                    if fallback.sum() >= 0.25 * ref_area:
                        mask = _fill_holes(_largest_component_near(fallback, tuple(centre)))
            if mask.any():
                prev_mask, prev_t = mask, t
            if mask.any():
                c, s = _mask_stats(mask)
                v_new = c - state.centre if state.lost == 0 else (c - state.centre) / (state.lost + 1)
                state.velocity = 0.5 * state.velocity + 0.5 * v_new
                state.centre = c
                if score >= 0.8 * ref_score:
                    # Only clear views update the size; occluded views would shrink it.
                    state.size = np.clip(0.7 * state.size + 0.3 * s, 0.6 * s0, 1.7 * s0)
                state.lost = 0
                conf[t] = min(1.0, score / ref_score)
                if adapt > 0:
                    ring_t = cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8), iterations=3) > 0
                    model = base_model.blend(ColourModel.fit(rgb, mask, ~ring_t, distractors), adapt)
            else:
                state.centre = state.centre + state.velocity
                state.velocity = 0.5 * state.velocity  # a hidden object's motion is unknown
                state.lost += 1
            masks[t] = mask
            done += 1
            if on_frame:
                on_frame(done)
            t += direction
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
