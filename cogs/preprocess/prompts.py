"""The prompts of `cogs preprocess`: boxes on the object, boxes that are not it, and the person's box.

On the command line (see `Preprocess.object_box`):

    --object-box X0 Y0 X1 Y1 [--object-box-frame K]      one box, on frame K (default 0)
    --object-box K X0 Y0 X1 Y1 --object-box M X0 Y0 X1 Y1 ...   a box on each of several frames
    --object-negative-box K X0 Y0 X1 Y1 ...               not the object, on frame K

Boxes are in pixels of the input video; frames are indices among the kept frames. The
tracker restarts from every positive box (``tracking.propagate_masks``); a negative box's
pixels are never object on its frame, and its colours count against the object in every
colour model of the clip.

The person to follow when several are in view is one box on one frame:

    --person-box [K] X0 Y0 X1 Y1                          the person inside the box on frame K (default 0)

(``persons.follow_person``). Everything that can be checked without the frames is checked by ``parse_prompts`` (called
by ``Preprocess.check_options`` before any work); the frame indices and the boxes against
the frame size by ``check_against_frames``, as soon as the clip's size is known.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from numbers import Real

import numpy as np

from cogs.errors import UserError

POSITIVE = "--object-box"
PERSON = "--person-box"
NEGATIVE = "--object-negative-box"
FRAME_OPTION = "--object-box-frame"


@dataclass(frozen=True)
class BoxPrompt:
    """One box on one frame."""

    frame: int  # index among the kept frames
    box: tuple[float, float, float, float]  # x0, y0, x1, y1 in pixels of the input video
    option: str  # the option that gave it (for messages)
    text: str  # its value as the user wrote it (for messages)
    own_frame: bool = True  # False: the single-box form, whose frame is --object-box-frame

    def frame_text(self) -> str:
        return f"{self.option} {self.text}: frame {self.frame}" if self.own_frame else f"{FRAME_OPTION} {self.frame}"

    def record(self) -> list[float]:
        """[frame, x0, y0, x1, y1], as scene.json and the cache key store it."""
        return [self.frame, *self.box]


def _fmt(values) -> str:
    return " ".join(f"{float(v):g}" for v in values)


def as_entries(value) -> list[tuple]:
    """The option's value as a list of number tuples: None or () -> []; one flat list of
    numbers (the Python API's and the batch manifest's single box) -> [it]; a list of
    lists (one per box, what the command line's repeated option gives) -> the lists."""
    if value is None:
        return []
    value = tuple(value)
    if not value:
        return []
    if all(isinstance(v, Real) and not isinstance(v, bool) for v in value):
        return [value]
    return [tuple(v) if isinstance(v, (list, tuple)) else (v,) for v in value]


def parse_prompts(object_box, object_box_frame: int | None, negative_box) -> tuple[list[BoxPrompt], list[BoxPrompt]]:
    """(positive prompts sorted by frame, negative prompts) from the option values, or a
    UserError naming the option and the value at fault."""
    entries = as_entries(object_box)
    positives: list[BoxPrompt] = []
    single = len(entries) == 1 and len(entries[0]) == 4
    if object_box_frame is not None and object_box_frame < 0:
        raise UserError(f"{FRAME_OPTION} must be >= 0, got {object_box_frame}")
    for e in entries:
        text = _fmt(e) if all(isinstance(v, Real) for v in e) else " ".join(map(str, e))
        if len(e) == 4:
            if not single:
                raise UserError(f"{POSITIVE} {text}: with several boxes, give each its frame: "
                                f"{POSITIVE} FRAME X0 Y0 X1 Y1")
            frame, box, own = object_box_frame or 0, e, False
        elif len(e) == 5:
            if object_box_frame is not None:
                raise UserError(f"{FRAME_OPTION} {object_box_frame} goes with the single-box form {POSITIVE} X0 Y0 X1 Y1; "
                                f"{POSITIVE} {text} names its own frame")
            frame, box, own = e[0], e[1:], True
        else:
            raise UserError(f"{POSITIVE} {text}: expected X0 Y0 X1 Y1 or FRAME X0 Y0 X1 Y1, got {len(e)} numbers")
        positives.append(_prompt(POSITIVE, text, frame, box, own))
    if object_box_frame is not None and not entries:
        raise UserError(f"{FRAME_OPTION} {object_box_frame} needs {POSITIVE} X0 Y0 X1 Y1")
    negatives = []
    for e in as_entries(negative_box):
        text = " ".join(f"{v:g}" if isinstance(v, Real) else str(v) for v in e)
        if len(e) != 5:
            raise UserError(f"{NEGATIVE} {text}: expected FRAME X0 Y0 X1 Y1, got {len(e)} numbers")
        negatives.append(_prompt(NEGATIVE, text, e[0], e[1:], True))
    if negatives and not positives:
        raise UserError(f"{NEGATIVE} {negatives[0].text} needs {POSITIVE}: a negative box only corrects the tracker "
                        "that the object boxes start")
    seen: dict[int, BoxPrompt] = {}
    for p in positives:
        if p.frame in seen:
            raise UserError(f"{POSITIVE} {p.text}: frame {p.frame} already has the box {seen[p.frame].text}; "
                            "give one box per frame")
        seen[p.frame] = p
    for n in negatives:
        p = seen.get(n.frame)
        if p is not None and covered_fraction(p.box, [m.box for m in negatives if m.frame == n.frame]) > 0.5:
            raise UserError(f"{NEGATIVE} {n.text} covers most of {POSITIVE} {p.text} on frame {n.frame}: "
                            "a negative box marks what is not the object")
    return sorted(positives, key=lambda p: p.frame), negatives


def parse_person_box(person_box) -> BoxPrompt | None:
    """The ``--person-box [FRAME] X0 Y0 X1 Y1`` prompt (frame 0 when not given), None
    without one, or a UserError naming the value at fault."""
    entries = as_entries(person_box)
    if not entries:
        return None
    e = entries[0] if len(entries) == 1 else tuple(v for entry in entries for v in entry)
    text = " ".join(f"{v:g}" if isinstance(v, Real) else str(v) for v in e)
    if len(e) == 4:
        return _prompt(PERSON, text, 0, e, True)
    if len(e) == 5:
        return _prompt(PERSON, text, e[0], e[1:], True)
    raise UserError(f"{PERSON} {text}: expected X0 Y0 X1 Y1 or FRAME X0 Y0 X1 Y1, got {len(e)} numbers")


def _prompt(option: str, text: str, frame, box, own: bool) -> BoxPrompt:
    if not all(isinstance(v, Real) and not isinstance(v, bool) and math.isfinite(v) for v in (frame, *box)):
        raise UserError(f"{option} {text}: every value must be a finite number")
    if float(frame) != int(frame) or frame < 0:
        raise UserError(f"{option} {text}: the frame {frame:g} must be a whole number >= 0 (an index among the kept frames)")
    x0, y0, x1, y1 = (float(v) for v in box)
    if not (x1 > x0 and y1 > y0):
        raise UserError(f"{option} {text}: the box must be X0 Y0 X1 Y1 with X1 > X0 and Y1 > Y0")
    return BoxPrompt(int(frame), (x0, y0, x1, y1), option, text, own)


def covered_fraction(box, others) -> float:
    """The share of ``box``'s area that the union of the boxes ``others`` covers."""
    x0, y0, x1, y1 = box
    w, h = x1 - x0, y1 - y0
    # On a grid fine enough for a check (1 % of the box), not exact geometry.
    n = 100
    xs = x0 + (np.arange(n) + 0.5) * w / n
    ys = y0 + (np.arange(n) + 0.5) * h / n
    gx, gy = np.meshgrid(xs, ys)
    inside = np.zeros_like(gx, bool)
    for a0, b0, a1, b1 in others:
        inside |= (gx >= a0) & (gx <= a1) & (gy >= b0) & (gy <= b1)
    return float(inside.mean())


def check_against_frames(prompts: list[BoxPrompt], source_size: tuple[int, int], n_frames: int) -> None:
    """UserError naming the option and value when a prompt's frame is not among the
    ``n_frames`` kept frames or its box misses the ``source_size`` (width, height) frame."""
    W, H = source_size
    for p in prompts:
        if not 0 <= p.frame < n_frames:
            raise UserError(f"{p.frame_text()} is outside the {n_frames} processed frames (0..{n_frames - 1})")
        x0, y0, x1, y1 = p.box
        if x1 <= 0 or y1 <= 0 or x0 >= W or y0 >= H:
            raise UserError(f"{p.option} {p.text} lies outside the {W}x{H} frame (the box is given in pixels of the input video)")
        if (min(x1, W) - max(x0, 0)) < 3 or (min(y1, H) - max(y0, 0)) < 3:
            raise UserError(f"{p.option} {p.text} covers less than 3x3 pixels of the frame")


# The fewest pixels an object prompt's mask should cover for the classical tracker. Set on
# the development clips at --max-side 384: a bottle of 171 pixels was lost once lifted
# (its prompt's colour model held as much floor as bottle); balls of 407 and 626 pixels
# were followed. A warning, not a refusal: only the size of the frames can fix it.
MIN_PROMPT_PIXELS = 300


def small_prompt_warning(prompt: BoxPrompt, pixels: int, size: tuple[int, int], max_side: int) -> str | None:
    """The warning for an object prompt whose mask covers only ``pixels`` pixels of its
    frame at the processed ``size`` (width, height), or None when it is large enough."""
    if pixels >= MIN_PROMPT_PIXELS:
        return None
    return (f"{prompt.option} {prompt.text}: the object covers only {pixels} pixels of frame {prompt.frame} at "
            f"{size[0]}x{size[1]}; the classical tracker needs about {MIN_PROMPT_PIXELS} to tell it from what is around "
            f"it and may lose it: a larger --max-side (now {max_side}) gives it more (docs/preprocess.md, "
            "'The development clips')")


# The share of an object prompt's surroundings that may look like it before the user is
# warned: 0.24 on the bottle clip (a transparent bottle on a grey floor, whose track stays
# on the floor); 0.003-0.15 on the other development clips' prompts (second prompts
# included), 0.001-0.002 on the synthetic video benchmark's box at two settings
# (docs/experiments/2026-11-27-tracker-feet-and-pieces.md).
MAX_LOOKALIKE_SURROUNDINGS = 0.2


def lookalike_prompt_warning(prompt: BoxPrompt, share: float) -> str | None:
    """The warning for an object prompt whose surroundings look like it (``share``: see
    ``tracking.propagate_masks``'s ``lookalike``), or None."""
    if share < MAX_LOOKALIKE_SURROUNDINGS:
        return None
    return (f"{prompt.option} {prompt.text}: {share:.0%} of what surrounds the object on frame {prompt.frame} has its colours "
            "(a transparent or small object on a like-coloured background); the classical tracker may follow that "
            "background once the object moves: draw the box where the object stands against other colours, add an "
            f"{POSITIVE} on a later frame, or give --sam2-checkpoint")


def person_lookalike_warning(prompt: BoxPrompt, share: float) -> str | None:
    """The warning for an object prompt whose colours are the person's clothes' (``share``
    of the person's pixels look like it: see ``tracking.propagate_masks``'s
    ``like_person``), or None below ``tracking.LIKE_PERSON_SHARE``."""
    from cogs.preprocess.tracking import LIKE_PERSON_SHARE

    if share < LIKE_PERSON_SHARE:
        return None
    return (f"{prompt.option} {prompt.text}: {share:.0%} of the person on frame {prompt.frame} has the object's colours "
            "(a white racket and a white shirt); the classical tracker cannot tell them apart, so up to the boxes either "
            "side of this one it looks for the object only off the person's body and limbs dressed in other colours, "
            "and marks it lost where it is in front of the rest: add an "
            f"{POSITIVE} where it stands clear of the person, or give --sam2-checkpoint")


def guessed_prompt_warning(prompt: BoxPrompt) -> str:
    """The warning for an object prompt in whose box GrabCut found nothing standing out
    (``segment.grabcut_box``'s ``guessed``): the box's inscribed ellipse is tracked
    instead, colours of the background included."""
    return (f"{prompt.option} {prompt.text}: nothing in the box on frame {prompt.frame} stands out from what is around "
            "it (GrabCut kept under 5 % of the box), so the box's inscribed ellipse is taken for the object, with the "
            "background's colours inside it; the classical tracker may follow that background: draw the box where the "
            "object stands against other colours, or give --sam2-checkpoint or --object-masks")


# The share of one side of an object prompt's box that its mask may run along before the user
# is warned. GrabCut learns the background from outside the box: where the box cuts the object,
# or lies on the frame's edge with scenery inside it, the mask runs along that side. 0.24 at
# most on the development clips' prompts (the loading clip's second) but the guitar's, whose box
# cuts the guitar's body on the left (0.51); 0.32 at most on the synthetic video benchmark's 21
# settings (variant 9, along the frame's edge); 0.84 on an unseen clip whose box reached the
# frame's right edge and whose mask took the bed there (a black guitar on a black dress), 0 on
# another
# (docs/experiments/2026-12-02-a-lock-a-keep-away-and-prompts-that-run-along-their-box.md).
MAX_EDGE_RUN = 0.4
_SIDES = ("top", "bottom", "left", "right")


def edge_run(mask: np.ndarray, box: np.ndarray) -> tuple[str, float, bool]:
    """The side of ``box`` (x0, y0, x1, y1, processed pixels) along which ``mask`` [H, W]
    bool runs furthest -> (side, the share of its pixels the mask covers, whether that side
    lies on the frame's edge)."""
    H, W = mask.shape
    x0, y0 = int(max(0, np.floor(box[0]))), int(max(0, np.floor(box[1])))
    x1, y1 = int(min(W, np.ceil(box[2]))), int(min(H, np.ceil(box[3])))
    if x1 <= x0 or y1 <= y0:
        return "top", 0.0, False
    runs = (mask[y0, x0:x1], mask[y1 - 1, x0:x1], mask[y0:y1, x0], mask[y0:y1, x1 - 1])
    on_edge = (y0 == 0, y1 == H, x0 == 0, x1 == W)
    i = int(np.argmax([r.mean() for r in runs]))
    return _SIDES[i], float(runs[i].mean()), bool(on_edge[i])


def edge_prompt_warning(prompt: BoxPrompt, side: str, share: float, on_frame_edge: bool) -> str | None:
    """The warning for an object prompt whose mask runs along ``share`` of its box's
    ``side`` (``edge_run``), or None when it stays inside the box."""
    if share < MAX_EDGE_RUN:
        return None
    if on_frame_edge:
        where, cut, fix = (f"the box's {side} side, the frame's edge", "the object leaves the frame there",
                           "prompt a frame where the object is whole in view")
    else:
        where, cut, fix = f"the box's {side} side", "the box cuts the object there", "draw the box a little larger than the object"
    return (f"{prompt.option} {prompt.text}: the object's mask on frame {prompt.frame} runs along {share:.0%} of {where}: "
            f"{cut}, or GrabCut took in what lies beside it (it learns the background from outside the box only), and "
            f"the classical tracker follows whatever the mask holds. {fix[0].upper() + fix[1:]}, give {NEGATIVE} over "
            "what is not the object, or give --sam2-checkpoint or --object-masks")


# A stretch of frames where the classical tracker lost the object, or does not trust its
# mask (confidence under the object branch's ``min_confidence``), is pointed out when it is at
# least this many frames and this share of the clip long: those frames do not supervise the
# object, and a box on one of them restarts the tracking there.
LOST_STRETCH_FRAMES = 5
LOST_STRETCH_SHARE = 0.1


def untrusted_stretches(confidence: np.ndarray, min_confidence: float) -> list[tuple[int, int]]:
    """(first, last) frame of each run of frames with ``confidence`` [T] under
    ``min_confidence`` that is long enough to point out (``LOST_STRETCH_FRAMES``,
    ``LOST_STRETCH_SHARE``), longest first."""
    low = np.asarray(confidence) < min_confidence
    least = max(LOST_STRETCH_FRAMES, int(math.ceil(LOST_STRETCH_SHARE * len(low))))
    return sorted((r for r in runs_of(low) if r[1] - r[0] + 1 >= least), key=lambda r: (r[0] - r[1], r[0]))


def runs_of(flags: np.ndarray) -> list[tuple[int, int]]:
    """(first, last) index of each run of True in ``flags`` [T] bool, in order."""
    runs, start = [], None
    for t, v in enumerate([*np.asarray(flags, bool), False]):
        if v and start is None:
            start = t
        elif not v and start is not None:
            runs.append((start, t - 1))
            start = None
    return runs


def lost_stretch_warning(stretches: list[tuple[int, int]], n_frames: int) -> str | None:
    """The warning for the stretches ``untrusted_stretches`` found in a clip of
    ``n_frames`` kept frames, or None without any."""
    if not stretches:
        return None
    shown = ", ".join(f"{a}-{b}" for a, b in stretches[:3]) + (" and more" if len(stretches) > 3 else "")
    total = sum(b - a + 1 for a, b in stretches)
    a, b = stretches[0]
    return (f"the classical tracker lost the object, or does not trust its mask, in frames {shown} ({total} of "
            f"{n_frames} kept frames): those frames do not supervise the object. Where it is in view there, an "
            f"{POSITIVE} on a frame inside (e.g. {POSITIVE} {(a + b) // 2} X0 Y0 X1 Y1, besides the first) restarts "
            "the tracking from it (docs/preprocess.md, 'Several prompts')")


def box_mask(box: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """[H, W] bool: the pixels whose centres lie in ``box`` (x0, y0, x1, y1, processed pixels)."""
    H, W = shape
    x0, y0, x1, y1 = box
    xs, ys = np.arange(W) + 0.5, np.arange(H) + 0.5
    return ((ys >= y0) & (ys <= y1))[:, None] & ((xs >= x0) & (xs <= x1))[None, :]
