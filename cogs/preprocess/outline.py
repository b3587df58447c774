"""An object's outline followed through the frames by the image's edges alone.

Over a few frames a rigid object's silhouette is its outline in an earlier frame moved,
turned and scaled in the image. Where the object's colours do not set it apart from what
lies behind it (a transparent bottle shows the floor or the shirt behind it, and a colour
model of it calls both object), its outline still shows as an edge. ``follow`` fits a
prompt's outline to each frame's colour gradients in turn, each fit starting from the
last.

Alone, a followed outline drifts onto a neighbouring edge (the forearm beside a bottle,
a crease in the trousers) and nothing in a frame says when: the edge there is as strong
as the object's, often stronger. So between two prompts (``bridge``) a pass from each,
towards the other, must meet, the two outlines lying on each other in some frame
(``BRIDGE_AGREE``), and a hand must hold the result (``BRIDGE_HELD``): two passes that
drift apart never meet, and two that drift onto the same edge (a white shirt's hem over
black shorts) meet away from the hands. Then each frame takes the pass that reaches it
before that meeting. Beyond the first prompt and the last, and between two prompts whose
passes do not meet, a pass from one prompt alone (``lone_pass``) is checked by the hand
that holds the prompt, while it holds the outline, and by following each frame's outline
back: it must land on the prompt it came from (``returns``: a pass that drifted onto a
neighbouring edge stays on that edge on the way back); the tracker ends it earlier where a
find the colour cues trust lies elsewhere.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from cogs.preprocess.hands import forearm_regions, hand_points, hand_regions, holding_hand
from cogs.preprocess.segment import grown

# How far an outline may move between two frames, as a share of its longer side: 0.3 of
# the bottle's 26 px at 384 px is 8 px, which kept up with it being picked up, lifted
# and opened (docs/experiments/2026-12-05-d-an-outline-followed-by-its-edges.md).
SEARCH_REACH = 0.3
MIN_REACH_PX = 3
# Turns and scalings tried per frame on top of the last frame's.
TURNS_DEG = tuple(range(-12, 13, 3))
SCALINGS = (0.92, 1.0, 1.08)
# An outline no further scaled than this from its prompt's size (a pass that swells onto
# a larger neighbouring edge, or shrinks onto a fold, stops there).
MAX_SCALE = 1.6
# An outline of fewer contour pixels than this is too small to follow by its edges.
MIN_POINTS = 16
# At most this many contour points are scored (evenly spaced along the outline).
MAX_POINTS = 240
# Two passes meet where their outlines overlap this much (IoU).
BRIDGE_AGREE = 0.6
# A bridge holds only where a hand holds the object (``hands.holding_hand``) in this share of
# its frames at least: the passes between the tennis clip's two boxes both drifted onto the
# shirt's hem and met there (IoU 0.73), in a hand in 16 % and 23 % of the frames; the
# bottle's, on the bottle, in 98 % and 100 %.
BRIDGE_HELD = 0.75
# The confidence of a frame an outline gives: trusted (``ObjectConfig.min_confidence``)
# but not a clear view (``tracking.CLEAR_CONFIDENCE``).
OUTLINE_CONFIDENCE = 0.5
# ... and a frame a lone pass gives (``lone_pass``), which only the hand holding its prompt
# or its own way back checks: still trusted.
LONE_CONFIDENCE = 0.3
# A frame's outline followed back returns to its prompt where it lands with its centre
# within this share of the prompt's longer side of the prompt's centre. Measured at 384 and
# 640 px, each frame of a pass followed back by the edges alone: on the object the centres
# landed 0.00-0.19 apart (the tennis racket at frames 1-8, the bottle at 1-17), where the
# pass had left it 0.26-2.4 (the racket's outline on the forearm from frame 9, the
# bottle's from 18). The outlines' IoU told them apart less well: 0.46 on a bottle 26 px
# tall a pixel or two off, 0.32 off the racket
# (docs/experiments/2026-12-05-f-an-outline-that-returns.md).
RETURN_REACH = 0.2


@dataclass
class Outline:
    """A mask's outer contour: ``polygon`` [P, 2] (pixel centres, for drawing the mask),
    ``points`` [N, 2] the scored subset and its ``normals`` [N, 2] (unit), around ``centre``
    [2]; ``extent`` the longer side of its bounding box in pixels."""

    polygon: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    centre: np.ndarray
    extent: float

    @classmethod
    def of(cls, mask: np.ndarray) -> "Outline | None":
        """The outline of ``mask`` [H, W] bool's largest piece, or None where it is too
        small to follow."""
        import cv2

        contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        if not contours:
            return None
        c = max(contours, key=cv2.contourArea)[:, 0, :].astype(np.float64) + 0.5
        if len(c) < MIN_POINTS:
            return None
        # The tangent over two pixels either side, the normal across it (its sign does not
        # matter: the score takes the gradient's size along it).
        tangent = np.roll(c, -2, axis=0) - np.roll(c, 2, axis=0)
        normal = np.stack([tangent[:, 1], -tangent[:, 0]], axis=1)
        length = np.linalg.norm(normal, axis=1)
        ok = length > 0
        c_ok, n_ok = c[ok], normal[ok] / length[ok, None]
        keep = np.unique(np.linspace(0, len(c_ok) - 1, min(MAX_POINTS, len(c_ok))).round().astype(int))
        centre = c.mean(axis=0)
        extent = float(max(np.ptp(c[:, 0]), np.ptp(c[:, 1])))
        return cls(c - centre, c_ok[keep] - centre, n_ok[keep], centre, extent)

    def placed(self, pose: tuple[float, float, float, float], which: str = "points") -> np.ndarray:
        """The outline's ``points`` (or ``polygon``) in the image under ``pose`` = (dx, dy,
        turn in radians, scale) about its centre."""
        dx, dy, th, s = pose
        return (getattr(self, which) @ _turn(th).T) * s + self.centre + (dx, dy)

    def turned_normals(self, th: float) -> np.ndarray:
        return self.normals @ _turn(th).T

    def mask(self, pose: tuple[float, float, float, float], shape: tuple[int, int]) -> np.ndarray:
        """[H, W] bool: the outline filled under ``pose``."""
        import cv2

        m = np.zeros(shape, np.uint8)
        poly = np.round((self.placed(pose, "polygon") - 0.5) * 4).astype(np.int32)
        cv2.fillPoly(m, [poly], 1, lineType=cv2.LINE_8, shift=2)
        return m.astype(bool)


def _turn(th: float) -> np.ndarray:
    """[2, 2] rotation by ``th`` radians (image axes)."""
    c, sn = np.cos(th), np.sin(th)
    return np.array([[c, -sn], [sn, c]])


def gradients(rgb: np.ndarray, box: tuple[int, int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Each colour channel's horizontal and vertical Sobel gradients ([h, w, 3] float32
    each) inside ``box`` = (x0, y0, x1, y1) of ``rgb`` [H, W, 3] uint8."""
    import cv2

    x0, y0, x1, y1 = box
    crop = np.ascontiguousarray(rgb[y0:y1, x0:x1]).astype(np.float32)
    return cv2.Sobel(crop, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(crop, cv2.CV_32F, 0, 1, ksize=3)


def edge_scores(gx: np.ndarray, gy: np.ndarray, origin: np.ndarray, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """[M] mean over an outline's N points of the largest channel's gradient across the
    outline, for M placements ``points`` [M, N, 2] (image pixels; ``origin`` [2] is the
    gradient crop's corner) with ``normals`` [N, 2]; points off the crop count 0."""
    h, w = gx.shape[:2]
    xy = np.floor(points - origin).astype(np.int64)
    inside = (xy[..., 0] >= 0) & (xy[..., 0] < w) & (xy[..., 1] >= 0) & (xy[..., 1] < h)
    xi, yi = np.clip(xy[..., 0], 0, w - 1), np.clip(xy[..., 1], 0, h - 1)
    across = np.abs(gx[yi, xi] * normals[None, :, None, 0] + gy[yi, xi] * normals[None, :, None, 1]).max(axis=-1)
    return (across * inside).mean(axis=1)


def fit(outline: Outline, rgb: np.ndarray, pose: tuple[float, float, float, float],
        off: np.ndarray | None = None) -> tuple[tuple[float, float, float, float], float]:
    """The pose near ``pose`` whose outline lies best on ``rgb``'s edges, and its edge
    score: every turn in ``TURNS_DEG`` and scaling in ``SCALINGS`` of it, each moved
    within ``SEARCH_REACH`` of the outline's size (on a grid, then to the pixel). ``off``
    [H, W] bool: pixels whose edges count for nothing."""
    H, W = rgb.shape[:2]
    reach = max(MIN_REACH_PX, int(round(SEARCH_REACH * outline.extent * pose[3])))
    step = max(1, reach // 4)
    placed = outline.placed(pose, "polygon")
    pad = reach + int(np.ceil(0.1 * outline.extent * pose[3])) + 2
    box = (max(int(placed[:, 0].min()) - pad, 0), max(int(placed[:, 1].min()) - pad, 0),
           min(int(np.ceil(placed[:, 0].max())) + pad + 1, W), min(int(np.ceil(placed[:, 1].max())) + pad + 1, H))
    if box[2] - box[0] < 3 or box[3] - box[1] < 3:
        return pose, 0.0
    gx, gy = gradients(rgb, box)
    if off is not None:  # edges that say nothing of the object
        gx[off[box[1]:box[3], box[0]:box[2]]] = 0.0
        gy[off[box[1]:box[3], box[0]:box[2]]] = 0.0
    origin = np.array(box[:2], dtype=np.float64)

    def grid(half: int, by: int) -> np.ndarray:
        o = np.arange(-half, half + 1, by, dtype=np.float64)
        return np.stack(np.meshgrid(o, o), axis=-1).reshape(-1, 2)

    best_score, best = -1.0, pose
    coarse = grid(reach, step)
    for turn in np.radians(TURNS_DEG):
        th = pose[2] + turn
        normals = outline.turned_normals(th)
        for k in SCALINGS:
            s = float(np.clip(pose[3] * k, 1.0 / MAX_SCALE, MAX_SCALE))
            pts = outline.placed((pose[0], pose[1], th, s))
            sc = edge_scores(gx, gy, origin, pts[None] + coarse[:, None], normals)
            i = int(np.argmax(sc))
            if sc[i] > best_score:
                best_score, best = float(sc[i]), (pose[0] + coarse[i, 0], pose[1] + coarse[i, 1], th, s)
    if step > 1:
        fine = grid(step - 1, 1)
        pts = outline.placed(best)
        sc = edge_scores(gx, gy, origin, pts[None] + fine[:, None], outline.turned_normals(best[2]))
        i = int(np.argmax(sc))
        if sc[i] > best_score:
            best_score, best = float(sc[i]), (best[0] + fine[i, 0], best[1] + fine[i, 1], best[2], best[3])
    return best, best_score


def follow(images: np.ndarray, mask: np.ndarray, start: int, stop: int, kp2d: np.ndarray | None = None,
           on_frame=None, carry: bool = True) -> tuple[Outline, dict[int, tuple[float, float, float, float]]] | None:
    """Frame start's ``mask`` [H, W] bool followed by its outline's edges through the frames
    from start towards ``stop`` (inclusive; either direction) -> (its outline, {frame:
    pose}: ``Outline.mask`` draws each); None where the mask is too small to follow. With
    MediaPipe's keypoints ``kp2d`` [T, 33, 3], an outline a hand holds
    (``hands.holding_hand``) is looked for where that hand took it (the hand that held it
    in the frame before, while it still does), and the forearms' edges do not count
    (``hands.forearm_regions``); ``carry`` False: the hands' motion is not used, the edges
    alone move the outline. ``on_frame()`` is called after each frame."""
    outline = Outline.of(mask)
    if outline is None:
        return None
    return outline, {t: pose for t, pose, _ in _passing(images, outline, mask, start, stop, kp2d, on_frame, carry)}


def _passing(images: np.ndarray, outline: Outline, mask: np.ndarray, start: int, stop: int, kp2d: np.ndarray | None,
             on_frame=None, carry: bool = True):
    """``follow``'s frames one at a time: yields (frame, pose, the outline drawn under it
    [H, W] bool, or None where it is not drawn: without keypoints, or without ``carry``)."""
    H, W = images.shape[1:3]
    hands = hand_points(kp2d)
    direction = 1 if stop >= start else -1
    pose = (0.0, 0.0, 0.0, 1.0)
    last = mask
    h = None
    for t in range(start + direction, stop + direction, direction):
        # The hand that held it holds it still, or the one that does now: the other hand
        # taking the cap off a bottle covers as much of it for a while, then leaves.
        if carry and kp2d is not None and (h is None or holding_hand(kp2d, t - direction, last, which=(h,)) is None):
            h = holding_hand(kp2d, t - direction, last)
        if h is not None and hands[t - direction, h, 2] >= 0.5 and hands[t, h, 2] >= 0.5:
            shift = hands[t, h, :2] - hands[t - direction, h, :2]
            pose = (pose[0] + float(shift[0]), pose[1] + float(shift[1]), pose[2], pose[3])
        # A forearm's long straight edges beside a held object draw its outline onto the
        # arm: they count for nothing (the hand beyond the wrist still does).
        off = None if kp2d is None else forearm_regions(kp2d[t], (H, W)) & ~hand_regions(kp2d[t], (H, W))
        pose, _ = fit(outline, images[t], pose, off)
        if on_frame:
            on_frame()
        last = outline.mask(pose, (H, W)) if carry and kp2d is not None else None  # read only where it is drawn
        yield t, pose, last


def bridge(images: np.ndarray, mask_a: np.ndarray, a: int, mask_b: np.ndarray, b: int, kp2d: np.ndarray,
           agree: float = BRIDGE_AGREE, held: float = BRIDGE_HELD, on_frame=None) -> tuple[dict[int, np.ndarray], int, float] | None:
    """The frames strictly between prompts a < b given by their outlines, for an object a
    hand holds: a pass from each prompt towards the other (``follow``); the frames up to
    the one where the two overlap most take the pass from a, the rest the pass from b.
    -> ({frame: [H, W] bool}, that frame, its IoU), or None where the passes never overlap
    by ``agree`` (one drifted off the object, or both did), where a hand (``kp2d`` [T, 33,
    3], ``hands.holding_hand``) holds the result in under ``held`` of those frames, or
    where a prompt is too small to follow. ``on_frame()`` is called after each frame a pass
    fits."""
    if b - a < 2:
        return None
    fwd, bwd = follow(images, mask_a, a, b, kp2d, on_frame), follow(images, mask_b, b, a, kp2d, on_frame)
    if fwd is None or bwd is None:
        return None
    shape = images.shape[1:3]

    def drawn(passed, t: int, prompt: np.ndarray) -> np.ndarray:
        outline, poses = passed
        return outline.mask(poses[t], shape) if t in poses else prompt

    overlap = []
    for t in range(a, b + 1):
        f, g = drawn(fwd, t, mask_a), drawn(bwd, t, mask_b)
        union = np.count_nonzero(f | g)
        overlap.append(np.count_nonzero(f & g) / union if union else 0.0)
    meet = int(np.argmax(overlap))
    if overlap[meet] < agree:
        return None
    switch = a + meet
    shapes = {t: (drawn(fwd, t, mask_a) if t <= switch else drawn(bwd, t, mask_b)) for t in range(a + 1, b)}
    in_hand = np.mean([holding_hand(kp2d, t, m) is not None for t, m in shapes.items()])
    if in_hand < held:
        return None
    return shapes, switch, float(overlap[meet])


class Drawn(Mapping):
    """{frame: [H, W] bool} of a followed outline, each mask drawn from its pose when asked:
    a pass over a long clip at full size keeps its poses, not its masks."""

    def __init__(self, outline: Outline, poses: dict[int, tuple[float, float, float, float]], shape: tuple[int, int]):
        self.outline, self.poses, self.shape = outline, poses, shape

    def __getitem__(self, t: int) -> np.ndarray:
        return self.outline.mask(self.poses[t], self.shape)

    def __iter__(self):
        return iter(self.poses)

    def __len__(self) -> int:
        return len(self.poses)


def returns(images: np.ndarray, outline: Outline, pose: tuple[float, float, float, float], t: int, start: int,
            prompt: np.ndarray, kp2d: np.ndarray | None, reach: float = RETURN_REACH) -> bool:
    """Whether frame t's ``outline`` under ``pose``, followed back to frame ``start``
    (``follow``), lands on ``prompt`` [H, W] bool there: its centre within ``reach`` of the
    prompt's longer side of the prompt's centre. A pass that drifted onto a neighbouring
    edge stays on that edge on the way back (the forward-backward check of Kalal, Mikolajczyk
    and Matas, 2010)."""
    shape = images.shape[1:3]
    back = follow(images, outline.mask(pose, shape), t, start, kp2d, carry=False)
    if back is None:
        return False
    landed = back[0].mask(back[1][start], shape)
    if not landed.any():
        return False
    (ly, lx), (ys, xs) = (a.mean() for a in np.nonzero(landed)), np.nonzero(prompt)
    size = max(np.ptp(ys), np.ptp(xs)) + 1
    return float(np.hypot(ly - ys.mean(), lx - xs.mean())) <= reach * size


class Lone(Drawn):
    """A lone pass (``lone_pass``): {frame: [H, W] bool} as ``Drawn``, with the frames the
    hand that holds the prompt holds (``held``) and those that return to the prompt
    (``returning``), each a run from the prompt on."""

    def __init__(self, outline: Outline, poses: dict[int, tuple[float, float, float, float]], shape: tuple[int, int],
                 held: list[int], returning: list[int]):
        super().__init__(outline, poses, shape)
        self.held, self.returning = held, returning


def lone_pass(images: np.ndarray, mask: np.ndarray, start: int, stop: int, kp2d: np.ndarray | None,
              on_frame=None, check_back: bool = True) -> Lone | None:
    """The frames from prompt ``start`` towards ``stop`` (inclusive) given by the prompt's
    outline alone (``follow``), where no second prompt's pass meets it, and what checks
    each: the frames up to the first whose outline the hand that holds the prompt
    (``hands.holding_hand``, with MediaPipe's keypoints ``kp2d`` [T, 33, 3]) does not
    hold, and those up to the first whose outline does not return to the prompt
    (``returns``; none without ``check_back``). None where the prompt is too small to
    follow, or where no hand holds it and the way back is not checked. ``on_frame()`` is
    called after each frame the pass fits.

    A followed outline moves with its hand by construction, so that hand's hold says little
    while it lasts; it ends where the hand leaves the outline (on the bottle clip at 384 px,
    the pass after the second box: from 91 on the outline slid off towards the other hand,
    which had twisted the cap off). Following the outline back, by the edges alone, says
    where it left the object (on the tennis clip the racket's outline returns from frames
    1-8 at 384 px; from 9 on it lies on the forearm); but an outline that stalled on the
    background where the object was returns as well. The tracker takes each check where
    it holds (``tracking.lone_outline_frames``).

    The way back is checked at frames ever further out (each about 1.4x as far as the
    last), then by bisection between the last that returns and the first that does not: a
    pass that holds for n frames costs a few n fits, not n²/2. The pass is followed no
    further than both checks hold."""
    outline = Outline.of(mask)
    hand = None if kp2d is None else holding_hand(kp2d, start, mask)
    if outline is None or (hand is None and not check_back):
        return None
    shape = images.shape[1:3]

    def back(i: int) -> bool:
        return returns(images, outline, poses[order[i]], order[i], start, mask, kp2d)

    poses, order = {}, []
    n_held, holding = 0, hand is not None
    # Indices into order: the last that returns, the first that does not, the next checked.
    ok, fail, check = -1, (None if check_back else 0), 0
    for t, pose, drawn in _passing(images, outline, mask, start, stop, kp2d, on_frame):
        poses[t] = pose
        order.append(t)
        i = len(order) - 1
        if holding:  # drawn: a held prompt has keypoints
            holding = holding_hand(kp2d, t, drawn, which=(hand,)) is not None
            n_held += holding
        if fail is None and i == check:
            if back(i):
                ok, check = i, max(i + 1, int(1.4 * (i + 1)))
            else:
                fail = i
        if fail is not None and not holding:
            break
    if fail is None and ok < len(order) - 1:  # the pass reached ``stop`` between two checks
        if back(len(order) - 1):
            ok = len(order) - 1
        else:
            fail = len(order) - 1
    while fail is not None and fail - ok > 1:
        mid = (ok + fail) // 2
        ok, fail = (mid, fail) if back(mid) else (ok, mid)
    reached = order[: max(n_held, ok + 1)]
    return Lone(outline, {t: poses[t] for t in reached}, shape, order[:n_held], order[: ok + 1])


def within_reach(find: np.ndarray, shape: np.ndarray, share: float = 0.5) -> bool:
    """Whether at least ``share`` of ``find`` [H, W] bool lies on ``shape`` [H, W] bool grown
    by one frame's search reach (``SEARCH_REACH`` of its longer side): a find at the same
    object, though it takes in only a piece of it (a transparent bottle's base, the part
    that shows the colours of its prompt) or the outline lies a few pixels off."""
    n = int(find.sum())
    if not n or not shape.any():
        return False
    ys, xs = np.nonzero(shape)
    reach = max(MIN_REACH_PX, int(round(SEARCH_REACH * max(ys.max() - ys.min() + 1, xs.max() - xs.min() + 1))))
    return int((find & grown(shape, reach)).sum()) >= share * n
