"""Step 2: the person in every frame: a mask, 33 2D keypoints and 33 metric 3D keypoints.

MediaPipe Pose (BlazePose GHUM, ``model_complexity=1``, the only variant whose model ships in
the 0.10.14 wheel, so nothing is downloaded) runs in video mode (landmarks tracked from frame
to frame) with segmentation on. Its outputs, per frame:

- ``kp2d [33, 3]``: pixel x, y and a visibility score in [0, 1];
- ``kp3d [33, 3]``: "world" landmarks in metres, origin between the hips, axes roughly
  aligned with the camera's (x right, y down, z away from the camera);
- a soft person mask, thresholded at 0.5 and cleaned to the components that touch the
  detected pose.

Landmark order is MediaPipe's (``LANDMARK_NAMES``). Frames where no person is found get an
empty mask and NaN keypoints; later steps interpolate over them.

When the optional ``sam2`` package is installed and a checkpoint is given, SAM2 re-segments
the person from a box prompt around MediaPipe's mask (sharper boundaries); it is imported
only then.
"""

from __future__ import annotations

import contextlib
import logging
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cogs.errors import UserError
from cogs.preprocess.segment import disk

log = logging.getLogger(__name__)

LANDMARK_NAMES = [
    "nose", "left_eye_inner", "left_eye", "left_eye_outer", "right_eye_inner", "right_eye",
    "right_eye_outer", "left_ear", "right_ear", "mouth_left", "mouth_right", "left_shoulder",
    "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_pinky",
    "right_pinky", "left_index", "right_index", "left_thumb", "right_thumb", "left_hip",
    "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle", "left_heel",
    "right_heel", "left_foot_index", "right_foot_index",
]  # fmt: skip
N_LANDMARKS = 33
# Skeleton edges for drawing (indices into LANDMARK_NAMES).
EDGES = [
    (11, 12), (11, 13), (13, 15), (12, 14), (14, 16), (11, 23), (12, 24), (23, 24), (23, 25),
    (25, 27), (27, 29), (29, 31), (27, 31), (24, 26), (26, 28), (28, 30), (30, 32), (28, 32),
    (0, 2), (0, 5), (2, 7), (5, 8),
]  # fmt: skip


@dataclass
class PersonTrack:
    masks: np.ndarray  # [T, H, W] bool
    probs: np.ndarray  # [T, H, W] uint8, soft mask * 255
    kp2d: np.ndarray  # [T, 33, 3] pixels x, y and visibility; NaN where undetected
    kp3d: np.ndarray  # [T, 33, 3] metres, hip-centred, camera-aligned axes; NaN where undetected
    detected: np.ndarray  # [T] bool

    @classmethod
    def empty(cls, T: int, H: int, W: int) -> "PersonTrack":
        """T frames of H x W with nobody found yet."""
        nan = np.full((T, N_LANDMARKS, 3), np.nan, dtype=np.float32)
        return cls(np.zeros((T, H, W), bool), np.zeros((T, H, W), np.uint8), nan, nan.copy(), np.zeros(T, bool))

    def arrays(self) -> dict[str, np.ndarray]:
        return {"masks": self.masks, "probs": self.probs, "kp2d": self.kp2d, "kp3d": self.kp3d, "detected": self.detected}

    @classmethod
    def from_arrays(cls, a: dict) -> "PersonTrack":
        return cls(a["masks"].astype(bool), a["probs"], a["kp2d"], a["kp3d"], a["detected"].astype(bool))


@contextlib.contextmanager
def _quiet_native_logs():
    """MediaPipe's C++ side (absl, TFLite) writes INFO/WARNING lines straight to fd 2."""
    os.environ.setdefault("GLOG_minloglevel", "2")
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")
    try:
        fd = 2
        saved = os.dup(fd)
    except OSError:
        yield
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, fd)
    try:
        yield
    finally:
        os.dup2(saved, fd)
        os.close(saved)
        os.close(devnull)


def import_mediapipe():
    """The mediapipe module, or a UserError saying how to install it."""
    import cv2  # noqa: F401  (FACTS: cv2 before mediapipe/pycolmap keeps native libs sane)

    try:
        with _quiet_native_logs():
            import mediapipe as mp
    except ImportError as e:
        raise UserError(
            f"mediapipe is not installed ({e}); install the preprocessing extra: "
            'pip install -e ".[preprocess]" (see docs/preprocess.md)'
        ) from None
    return mp


def clean_person_mask(mask: np.ndarray, kp2d: np.ndarray | None) -> np.ndarray:
    """Keep the connected components that hold a confident keypoint (or the largest)."""
    import cv2

    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 2:
        return mask
    keep = set()
    if kp2d is not None and np.isfinite(kp2d).all():
        H, W = mask.shape
        for x, y, v in kp2d:
            xi, yi = int(round(x)), int(round(y))
            if v > 0.5 and 0 <= xi < W and 0 <= yi < H and labels[yi, xi] > 0:
                keep.add(int(labels[yi, xi]))
    if not keep:
        keep = {int(np.argmax(stats[1:, cv2.CC_STAT_AREA])) + 1}
    # Components larger than a fifth of the kept area stay too (an arm split off by a held object).
    kept_area = sum(stats[k, cv2.CC_STAT_AREA] for k in keep)
    for k in range(1, n):
        if stats[k, cv2.CC_STAT_AREA] > 0.2 * kept_area:
            keep.add(k)
    return np.isin(labels, sorted(keep))


RELOCK_MARGIN = 0.1
"""How much better (`skeleton_fit`) the landmarks of MediaPipe's static mode must explain
the frame's person mask than video mode's for the frame to take them. On the bottle clip
(the face pixelated in the source) video mode's tracking stayed on a mid-body region after
the person bent over, and its landmarks stayed scrambled (face points at the hands): 84 of
100 frames are replaced. The synthetic benchmark's default clip has 2 such frames of 40;
the guitar, juggle and basketball clips none."""


def skeleton_fit(kp: np.ndarray, mask: np.ndarray) -> float:
    """How well landmarks explain a person mask: the share of the mask the skeleton's region
    covers (`body_region`, bones 3 % and the face 10 % of the mask's height wide, so that a
    skeleton shrunk into the body covers less, not more), discounted where under half of
    that region lies on the mask (a skeleton spread beyond the person)."""
    rows = np.flatnonzero(mask.any(axis=1))
    if not len(rows) or not np.isfinite(kp[:, :2]).all(axis=1).any():
        return 0.0
    height = float(rows[-1] - rows[0] + 1)
    region = body_region(kp, mask.shape, 0.03 * height, 0.1 * height)
    on = float((region & mask).sum())
    recall, precision = on / float(mask.sum()), on / max(float(region.sum()), 1.0)
    return recall * min(1.0, precision / 0.5)


def detect_persons(images: np.ndarray, on_frame=None, mask_threshold: float = 0.5) -> PersonTrack:
    """Run MediaPipe Pose over frames [T, H, W, 3] uint8 RGB (video mode). Each frame is
    also asked in static mode, whose landmarks replace video mode's where they explain the
    person mask clearly better (`RELOCK_MARGIN`): video mode's tracking can stay locked on
    a wrong region."""
    mp = import_mediapipe()
    T, H, W, _ = images.shape
    track = PersonTrack.empty(T, H, W)
    masks, probs, kp2d, kp3d, detected = track.masks, track.probs, track.kp2d, track.kp3d, track.detected
    with _quiet_native_logs():
        pose = mp.solutions.pose.Pose(
            static_image_mode=False,
            model_complexity=1,  # 0 and 2 download their models at first use
            smooth_landmarks=True,
            enable_segmentation=True,
            smooth_segmentation=True,
            min_detection_confidence=0.5,
            min_tracking_confidence=0.5,
        )
    static = _static_pose(mp)
    everything = np.ones((H, W), bool)
    relocked = 0
    try:
        for t in range(T):
            with _quiet_native_logs(), warnings.catch_warnings():
                # protobuf 4.25 warns about an API mediapipe 0.10.14 still uses.
                warnings.filterwarnings("ignore", message=".*GetPrototype.*", category=UserWarning)
                res = pose.process(np.ascontiguousarray(images[t]))
            if res.pose_landmarks is not None:
                detected[t] = True
                lm = res.pose_landmarks.landmark
                kp2d[t] = [(p.x * W, p.y * H, p.visibility) for p in lm]
                if res.pose_world_landmarks is not None:
                    kp3d[t] = [(p.x, p.y, p.z) for p in res.pose_world_landmarks.landmark]
                if res.segmentation_mask is not None:
                    soft = np.clip(res.segmentation_mask, 0.0, 1.0)
                    probs[t] = (soft * 255 + 0.5).astype(np.uint8)
                    masks[t] = clean_person_mask(soft > mask_threshold, kp2d[t])
                found = _run_pose(static, images[t], (0, 0, W, H), everything)
                if found is not None and skeleton_fit(found[0], masks[t]) > skeleton_fit(kp2d[t], masks[t]) + RELOCK_MARGIN:
                    kp2d[t] = found[0]
                    if found[1] is not None:
                        kp3d[t] = found[1]
                    relocked += 1
            if on_frame:
                on_frame(t + 1)
    finally:
        pose.close()
        static.close()
    if relocked:
        log.info("MediaPipe's video tracking lost the body in %d of %d frames; its landmarks there are a fresh "
                 "detection's", relocked, T)
    return track


# Hand edges (wrist to pinky, index and thumb) drawn besides EDGES when bounding a body.
_HAND_EDGES = ((15, 17), (15, 19), (15, 21), (16, 18), (16, 20), (16, 22))


_FACE = slice(0, 11)  # nose to mouth in LANDMARK_NAMES


def _torso_length(kp: np.ndarray) -> float:
    """Pixels from the shoulders' midpoint to the hips' (NaN when a point is missing)."""
    return float(np.linalg.norm(kp[[11, 12], :2].mean(0) - kp[[23, 24], :2].mean(0)))


def body_region(kp: np.ndarray, shape: tuple[int, int], reach: float, head: float | None = None) -> np.ndarray:
    """[H, W] bool: the pixels a body with 2D keypoints ``kp`` [33, 3] can cover: every bone
    drawn ``reach`` pixels to each side, the torso's quadrilateral filled, a disc of radius
    ``head`` (default ``reach``) around the face's points. A neighbour whose mask touches
    the person's lies mostly outside it."""
    import cv2

    region = np.zeros(shape, np.uint8)
    pts = kp[:, :2]
    ok = np.isfinite(pts).all(1)
    r = max(1, int(round(reach)))
    xy = np.round(np.where(ok[:, None], pts, 0)).astype(np.int64).clip(-(2**20), 2**20)
    for a, b in (*EDGES, *_HAND_EDGES):
        if ok[a] and ok[b]:
            cv2.line(region, (int(xy[a, 0]), int(xy[a, 1])), (int(xy[b, 0]), int(xy[b, 1])), 1, thickness=2 * r + 1)
    torso = [i for i in (11, 12, 24, 23) if ok[i]]
    if len(torso) >= 3:
        cv2.fillPoly(region, [xy[torso].astype(np.int32)], 1)
    face = [i for i in range(11) if ok[i]]
    if face:
        c = xy[face].mean(0)
        cv2.circle(region, (int(c[0]), int(c[1])), max(1, int(round(head or reach))), 1, thickness=-1)
    return region > 0


def _grow(box: np.ndarray, by: float, shape: tuple[int, int]) -> np.ndarray:
    """A box (x0, y0, x1, y1) grown by ``by`` times its longer side on every side, clipped."""
    H, W = shape
    x0, y0, x1, y1 = box
    m = by * max(x1 - x0, y1 - y0)
    return np.array([max(0.0, x0 - m), max(0.0, y0 - m), min(float(W), x1 + m), min(float(H), y1 + m)])


def _extent(mask: np.ndarray, kp: np.ndarray) -> np.ndarray:
    """The box around a person's mask and confidently seen keypoints."""
    H, W = mask.shape
    xs, ys = [], []
    if mask.any():
        yy, xx = np.nonzero(mask)
        xs += [xx.min(), xx.max() + 1]
        ys += [yy.min(), yy.max() + 1]
    finite = np.isfinite(kp).all(1)
    seen = kp[(kp[:, 2] > 0.5) & finite, :2]
    if not len(seen) and not xs:
        seen = kp[finite, :2]  # nothing sure: where the model guessed the body is
    xs += list(seen[:, 0])
    ys += list(seen[:, 1])
    return np.array([max(0.0, min(xs)), max(0.0, min(ys)), min(float(W), max(xs)), min(float(H), max(ys))])


def torso_colours(image: np.ndarray, kp: np.ndarray, mask: np.ndarray) -> np.ndarray | None:
    """A person's clothes as a normalised 8x8x8 RGB histogram of the pixels inside the torso's
    quadrilateral (shoulders, hips) and the person's mask; None when fewer than 30 pixels."""
    import cv2

    poly = kp[[11, 12, 24, 23], :2]
    if not np.isfinite(poly).all():
        return None
    H, W = mask.shape
    x0, y0 = np.clip(np.floor(poly.min(0)).astype(int), 0, [W, H])
    x1, y1 = np.clip(np.ceil(poly.max(0)).astype(int) + 1, 0, [W, H])
    if x1 - x0 < 2 or y1 - y0 < 2:
        return None
    region = np.zeros((y1 - y0, x1 - x0), np.uint8)
    cv2.fillPoly(region, [(poly - [x0, y0]).round().astype(np.int32)], 1)
    region &= mask[y0:y1, x0:x1].astype(np.uint8)
    if region.sum() < 30:
        return None
    hist = cv2.calcHist([np.ascontiguousarray(image[y0:y1, x0:x1])], [0, 1, 2], region, [8, 8, 8], [0, 256] * 3)
    return (hist / hist.sum()).astype(np.float32)


def colour_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Bhattacharyya distance of two normalised histograms: 0 alike .. 1 disjoint."""
    import cv2

    return float(cv2.compareHist(a, b, cv2.HISTCMP_BHATTACHARYYA))


@dataclass
class FollowSettings:
    """How ``follow_person`` keeps to one person. Set from the human build, not swept:
    ``context`` is how much of the frame beyond the person's last box the pose model sees
    (the person's motion between frames); ``reach`` how far beyond the last mask the
    person may be now and how thick a limb may be, as a fraction of the torso length
    (shoulders to hips, about a third of a standing person's height); ``limb`` and
    ``head`` how far from the skeleton the person's mask may reach; ``max_jump`` and
    ``max_scale`` what a torso can do from one frame to the next; ``max_colour`` the
    Bhattacharyya distance of torso colours (``torso_colours``) beyond which a find is
    somebody else. ``max_face_move`` is how far the face may move on the body between
    two frames (the face's centre from the shoulders' midpoint, torso lengths): at most
    0.27 on the six development clips and 0.34 on the synthetic video benchmark at seven
    settings (a bend), 0.5 and 0.63 where the loading clip's pose model laid the followed
    body under the face of the man behind its shoulder."""

    context: float = 0.3  # of the last box's longer side, on every side
    reach: float = 0.6  # of the torso length
    limb: float = 0.3  # torso lengths a mask pixel may lie from a bone (clothes, keypoint error)
    head: float = 0.5  # torso lengths a mask pixel may lie from the face's centre
    max_jump: float = 1.0  # torso lengths the torso's centre may move from one frame to the next
    miss_jump: float = 0.25  # how much more, times max_jump, for each frame missed since the last find
    max_scale: float = 2.5  # the most the torso length may grow or shrink between found frames (a bend)
    near: float = 0.3  # torso lengths: a find closer to the last one needs no colour check
    max_colour: float = 0.6
    attempts: int = 3  # finds tried per frame, each after painting out the ones rejected
    max_face_move: float = 0.45  # torso lengths the face may move on the body from one frame to the next
    face_size: float = 0.25  # torso lengths: the radius of the head painted out where a face is somebody else's
    face_match: float = 0.5  # normalised cross-correlation below which somebody else's face is lost


class _Followed:
    """What is known of the followed person along one pass."""

    def __init__(self, box: np.ndarray, shape: tuple[int, int], s: FollowSettings):
        self.s = s
        self.shape = shape
        self.last = np.clip(box, 0, [shape[1], shape[0]] * 2)  # the box where they were last found
        self.allowed = np.zeros(shape, bool)  # where they can be now
        x0, y0, x1, y1 = _grow(self.last, 0.05, shape).round().astype(int)
        self.allowed[y0:y1, x0:x1] = True
        self.torso = None  # (centre, length) at the last find
        self.face = None  # the face's centre from the shoulders' midpoint, in torso lengths, at the last find
        self.colours = None  # torso_colours, a running mean over the finds
        self.misses = 0

    def rejects(self, kp: np.ndarray, colours: np.ndarray | None) -> str | None:
        """Why a find ``kp`` is not the followed person, or None when it may be."""
        length = _torso_length(kp)
        if not (np.isfinite(length) and length > 1):
            return "no torso"
        jump = 0.0
        if self.torso is None:  # the first find: the person in the user's box
            x0, y0, x1, y1 = self.last
            cx, cy = kp[[11, 12, 23, 24], :2].mean(0)
            if not (x0 <= cx <= x1 and y0 <= cy <= y1):
                return "torso outside the box"
        else:
            centre, last = self.torso
            jump = float(np.linalg.norm(kp[[11, 12, 23, 24], :2].mean(0) - centre)) / last
            if jump > self.s.max_jump * (1 + self.s.miss_jump * self.misses):
                return f"moved {jump:.2f} torso lengths"
            if not 1 / self.s.max_scale <= length / last <= self.s.max_scale:
                return f"torso {length / last:.2f}x the last"
        # Where the person was, a turn or a shadow may change the clothes' colours; a find
        # that moved further must also look like them.
        if jump > self.s.near and self.colours is not None and colours is not None:
            d = colour_distance(colours, self.colours)
            if d > self.s.max_colour:
                return f"moved {jump:.2f} torso lengths and colours {d:.2f} apart"
        return None

    def face_moved(self, kp: np.ndarray) -> float | None:
        """How far (torso lengths) the face of a find moved on its body since the previous
        frame's find, when that is more than a head can turn or bend in a frame: the pose
        model then laid the followed body under somebody else's face (a person standing
        just behind their shoulder). None otherwise, or without a find on the previous frame."""
        if self.face is None or self.misses:
            return None
        moved = float(np.linalg.norm(_face_on_body(kp) - self.face))
        return moved if moved > self.s.max_face_move else None

    def found(self, kp: np.ndarray, mask: np.ndarray, colours: np.ndarray | None) -> None:
        import cv2

        length = _torso_length(kp)
        self.torso = (kp[[11, 12, 23, 24], :2].mean(0), length)
        self.face = _face_on_body(kp)
        if colours is not None:
            self.colours = colours if self.colours is None else 0.8 * self.colours + 0.2 * colours
        self.last = _extent(mask, kp)
        grown = (mask | body_region(kp, self.shape, 0.5 * self.s.reach * length)).astype(np.uint8)
        self.allowed = cv2.dilate(grown, _disc(self.s.reach * length)) > 0
        self.misses = 0

    def missed(self) -> None:
        import cv2

        self.misses += 1
        if self.torso is not None:  # they may have moved on: widen where they may be
            self.allowed = cv2.dilate(self.allowed.astype(np.uint8), _disc(self.s.reach * self.torso[1])) > 0


def _face_on_body(kp: np.ndarray) -> np.ndarray:
    """The face's centre from the shoulders' midpoint, in torso lengths."""
    return (kp[_FACE, :2].mean(0) - kp[[11, 12], :2].mean(0)) / _torso_length(kp)


def _run_pose(pose, image: np.ndarray, window, visible: np.ndarray):
    """MediaPipe Pose (a ``solutions.pose.Pose``) on ``image[window]`` (x0, y0, x1, y1) with
    the pixels outside ``visible`` [H, W] painted grey -> (kp2d [33, 3] in the frame's
    pixels, kp3d [33, 3] or None, soft mask [h, w] of the window or None), or None when
    nobody is found."""
    x0, y0, x1, y1 = window
    crop = image[y0:y1, x0:x1].copy()
    crop[~visible[y0:y1, x0:x1]] = 127
    with _quiet_native_logs(), warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*GetPrototype.*", category=UserWarning)
        res = pose.process(np.ascontiguousarray(crop))
    if res.pose_landmarks is None:
        return None
    h, w = crop.shape[:2]
    kp = np.array([(p.x * w + x0, p.y * h + y0, p.visibility) for p in res.pose_landmarks.landmark], np.float32)
    kp3 = None if res.pose_world_landmarks is None else np.array([(p.x, p.y, p.z) for p in res.pose_world_landmarks.landmark], np.float32)
    soft = None if res.segmentation_mask is None else np.clip(res.segmentation_mask, 0.0, 1.0)
    return kp, kp3, soft


def _static_pose(mp):
    with _quiet_native_logs():
        # Static mode: each image stands alone (video mode's own tracking assumes the
        # whole frame, which moves here with a window).
        return mp.solutions.pose.Pose(static_image_mode=True, model_complexity=1, enable_segmentation=True,
                                      min_detection_confidence=0.5)


def find_people(images: np.ndarray, frames, most: int = 3) -> dict[int, list[np.ndarray]]:
    """The 2D keypoints [33, 3] of each person MediaPipe finds on each of ``frames``: the
    whole frame is asked, then asked again with every person found so far painted grey
    (within 0.6 torso lengths of their skeleton), up to ``most`` people. A find on a
    painted person's place or with a torso under a third of the first one's is no one."""
    mp = import_mediapipe()
    pose = _static_pose(mp)
    H, W = images.shape[1:3]
    out: dict[int, list[np.ndarray]] = {}
    try:
        for t in frames:
            visible = np.ones((H, W), bool)
            people: list[np.ndarray] = []
            for _ in range(most):
                found = _run_pose(pose, images[t], (0, 0, W, H), visible)
                if found is None:
                    break
                kp = found[0]
                length = _torso_length(kp)
                if not (np.isfinite(length) and length > 1) or (people and length < _torso_length(people[0]) / 3):
                    break
                cx, cy = np.clip(kp[[11, 12, 23, 24], :2].mean(0), 0, [W - 1, H - 1]).astype(int)
                if not visible[cy, cx]:
                    break  # a painted person found again
                people.append(kp)
                visible &= ~body_region(kp, (H, W), 0.6 * length)
            out[int(t)] = people
    finally:
        pose.close()
    return out


def choose_person(images: np.ndarray, near: tuple[int, np.ndarray] | None = None, samples: int = 5) -> tuple[int, np.ndarray] | None:
    """(frame, box x0 y0 x1 y1) of the person to follow when several are in view, or None
    when at most one person is seen. ``samples`` frames spread over the clip are searched
    (``find_people``); people are in view when two or more are found on most of them
    (MediaPipe sometimes sees a person in a chair or a screen: on the guitar development
    clip, in 2 of 5 frames). With ``near`` = (frame, object box), the person followed is
    the one whose hands are nearest the box's centre on that frame: the person handling
    the object is usually the clip's subject (not always: on the loading clip the man
    standing by touches the box on the prompt's frame). Without it, the one whose torso is
    nearest the frame's centre on the first frame with several people. Either way one
    person is followed through the clip; the others are scene."""
    T, H, W, _ = images.shape
    frames = sorted({int(round(x)) for x in np.linspace(0, T - 1, min(T, samples))})
    seen = find_people(images, sorted(set(frames) | ({near[0]} if near else set())))
    several = [t for t in frames if len(seen[t]) >= 2]
    if 2 * len(several) <= len(frames):
        return None
    if near is not None and seen[near[0]]:
        t, box = near
        target = np.array([(box[0] + box[2]) / 2, (box[1] + box[3]) / 2])

        def distance(kp):  # hands hidden by the object are still placed where they must be
            return float(np.linalg.norm(kp[15:23, :2] - target, axis=1).min())
    else:
        t, target = several[0], np.array([W / 2, H / 2])

        def distance(kp):
            return float(np.linalg.norm(kp[[11, 12, 23, 24], :2].mean(0) - target))
    kp = min(seen[t], key=distance)
    return t, _grow(_extent(np.zeros((H, W), bool), kp), 0.05, (H, W))


def _disc(radius: float) -> np.ndarray:
    return disk(int(round(radius)))


class _OtherFaces:
    """Faces found to be somebody else's (``_Followed.face_moved``) along one pass of
    ``follow_person``, followed from frame to frame by their look and painted out before
    the pose model is asked: once it has laid the followed body under a face just behind
    the person's shoulder, it moves the whole upper body over to that person within a few
    frames, too gradually for the face check to see (the loading development clip, frames
    91-98). Each face is its disc's patch, found again in the next frame where it
    correlates best (normalised cross-correlation, within the disc's radius of where it
    was); a face whose best match is under ``min_match``, or on which the followed
    person's own face is found, is let go."""

    def __init__(self, min_match: float):
        self.min_match = min_match
        self.faces: list[tuple[np.ndarray, float, np.ndarray]] = []  # (centre x y, radius, patch)

    @staticmethod
    def _patch(image: np.ndarray, centre: np.ndarray, r: int) -> np.ndarray:
        H, W = image.shape[:2]
        x, y = np.round(centre).astype(int)
        return image[max(0, y - r):min(H, y + r + 1), max(0, x - r):min(W, x + r + 1)]

    def add(self, image: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
        """Remember the face at ``centre`` of ``image``; returns its disc [H, W] bool."""
        r = max(1, int(round(radius)))
        patch = self._patch(image, centre, r)
        if min(patch.shape[:2]) > 2:
            self.faces.append((np.asarray(centre, np.float64), float(r), patch.copy()))
        return self._disc(image.shape[:2], centre, r)

    def follow(self, image: np.ndarray) -> None:
        import cv2

        kept = []
        for centre, r, patch in self.faces:
            h, w = patch.shape[:2]
            ri = int(round(r))
            area = self._patch(image, centre, 2 * ri)
            if area.shape[0] < h or area.shape[1] < w:
                continue  # gone out of the frame
            score = cv2.matchTemplate(np.ascontiguousarray(area), np.ascontiguousarray(patch), cv2.TM_CCOEFF_NORMED)
            best = float(np.nanmax(score)) if np.isfinite(score).any() else -1.0
            if best < self.min_match:
                continue
            dy, dx = np.unravel_index(int(np.nanargmax(score)), score.shape)
            x0 = max(0, int(round(centre[0])) - 2 * ri)
            y0 = max(0, int(round(centre[1])) - 2 * ri)
            moved = np.array([x0 + dx + w / 2 - 0.5, y0 + dy + h / 2 - 0.5])
            kept.append((moved, r, self._patch(image, moved, ri).copy()))
        self.faces = [f for f in kept if min(f[2].shape[:2]) > 2]

    def drop_at(self, face: np.ndarray) -> None:
        """Let go of the faces whose disc holds the followed person's face."""
        self.faces = [f for f in self.faces if np.linalg.norm(f[0] - face) > f[1]]

    def region(self, shape: tuple[int, int]) -> np.ndarray:
        out = np.zeros(shape, bool)
        for centre, r, _ in self.faces:
            out |= self._disc(shape, centre, int(round(r)))
        return out

    @staticmethod
    def _disc(shape: tuple[int, int], centre: np.ndarray, r: int) -> np.ndarray:
        import cv2

        out = np.zeros(shape, np.uint8)
        cv2.circle(out, (int(round(centre[0])), int(round(centre[1]))), r, 1, thickness=-1)
        return out > 0


def follow_person(images: np.ndarray, frame: int, box, on_frame=None, mask_threshold: float = 0.5,
                  settings: FollowSettings | None = None) -> PersonTrack:
    """The one person inside ``box`` (x0, y0, x1, y1, pixels of ``images``) on ``frame``,
    followed through frames [T, H, W, 3] -> a PersonTrack of that person only.

    With several people in view MediaPipe Pose finds one person per image, and on the
    whole frame not always the same one. Here each frame, walking forwards from ``frame``
    and then backwards from it, shows the pose model only a window around where the
    followed person was last found, with every pixel farther than ``reach`` from the
    person's last mask painted grey: whoever else stands there is mostly not in the image
    it sees. A find whose torso jumps, changes size, or whose clothes' colours differ
    (``FollowSettings``) is somebody else: that find's body is painted grey too and the
    model is asked again, up to ``attempts`` times; a frame without an accepted find has
    no person (the body is interpolated there), and the window widens until the person
    is found again. A find whose face moved on its body further than a head can in a
    frame (``max_face_move``) has the followed body under somebody else's face: that face
    alone is painted grey and the model asked again, and the face is followed by its look
    (``_OtherFaces``) and painted out of the following frames too, until it is lost. The
    person's mask keeps only the pixels within ``limb`` of the frame's bones and ``head``
    of its face (``body_region``) and none that were painted out, so a neighbour touching
    the person stays scene.
    """
    mp = import_mediapipe()
    s = settings or FollowSettings()
    T, H, W, _ = images.shape
    track = PersonTrack.empty(T, H, W)
    masks, probs, kp2d, kp3d, detected = track.masks, track.probs, track.kp2d, track.kp3d, track.detected
    pose = _static_pose(mp)
    done = 0
    try:
        for order in (range(frame, T), range(frame - 1, -1, -1)):
            person = _Followed(np.asarray(box, np.float64), (H, W), s)
            others = _OtherFaces(s.face_match)
            for t in order:
                others.follow(images[t])
                set_aside = others.region((H, W))  # the faces and bodies of finds taken for somebody else
                visible = person.allowed & ~set_aside
                # Nobody found: the window is widened, then the frame beyond where the person
                # could be is shown too (a bend or a subsampled clip moves a body further).
                wide, shown = 1, False
                for _ in range(s.attempts + 2):
                    x0, y0, x1, y1 = _grow(person.last, s.context * wide * (1 + person.misses), (H, W)).round().astype(int)
                    res = _run_pose(pose, images[t], (x0, y0, x1, y1), visible)
                    if res is None:
                        if wide == 1:
                            wide = 3
                            continue
                        if not shown:
                            shown, visible = True, ~set_aside
                            continue
                        break
                    kp, kp3, window_soft = res
                    length = _torso_length(kp)
                    soft = np.zeros((H, W), np.float32)
                    if window_soft is not None and np.isfinite(length):
                        soft[y0:y1, x0:x1] = window_soft
                        body = body_region(kp, (H, W), s.limb * length, s.head * length)
                        soft[~(body if shown else person.allowed & body)] = 0.0
                    mask = clean_person_mask(soft > mask_threshold, kp)
                    colours = torso_colours(images[t], kp, mask)
                    why = person.rejects(kp, colours)
                    aside = None
                    if why is None and (moved := person.face_moved(kp)) is not None:
                        # The body may be right: only the face is painted out and the model asked again.
                        why = f"its face moved {moved:.2f} torso lengths on the body: somebody else's"
                        aside = others.add(images[t], kp[_FACE, :2].mean(0), s.face_size * length)
                    if why is None:
                        soft[set_aside] = 0.0
                        mask &= ~set_aside
                        detected[t] = True
                        kp2d[t] = kp
                        if kp3 is not None:
                            kp3d[t] = kp3
                        probs[t] = (soft * 255 + 0.5).astype(np.uint8)
                        masks[t] = mask
                        person.found(kp, mask, colours)
                        others.drop_at(kp[_FACE, :2].mean(0))
                        break
                    log.debug("frame %d: a person set aside (%s)", t, why)
                    if not np.isfinite(length):
                        break
                    set_aside |= body_region(kp, (H, W), s.reach * length) if aside is None else aside
                    visible &= ~set_aside
                if not detected[t]:
                    person.missed()
                done += 1
                if on_frame:
                    on_frame(done)
    finally:
        pose.close()
    return track


# MediaPipe's graph for one image and a region of interest: the pose landmark model on
# the rotated square the ROI names (no person detector, which finds people by the face).
_BY_ROI_GRAPH = """
input_stream: "image"
input_stream: "roi"
output_stream: "landmarks"
output_stream: "auxiliary"
output_stream: "world"
output_stream: "segmentation"
node {
  calculator: "PoseLandmarkByRoiCpu"
  input_side_packet: "MODEL_COMPLEXITY:model_complexity"
  input_side_packet: "ENABLE_SEGMENTATION:enable_segmentation"
  input_stream: "IMAGE:image"
  input_stream: "ROI:roi"
  output_stream: "LANDMARKS:landmarks"
  output_stream: "AUXILIARY_LANDMARKS:auxiliary"
  output_stream: "WORLD_LANDMARKS:world"
  output_stream: "SEGMENTATION_MASK:segmentation"
}
"""


class _PoseInRegion:
    """MediaPipe's pose landmark model run on a region of interest of each image, as its
    own tracking does between frames, without the detector: a body whose face is out of
    view is never detected, but the landmark model finds it in a region around it.

    A region is (centre x, centre y, side, rotation) in pixels and radians: a square,
    turned so that the body's up points up in it. Each find gives the region for the next
    frame from its two auxiliary landmarks (the hips' centre and a point that sets the
    body's extent and direction), as MediaPipe does: centred on the first, side 2.5x their
    distance, turned so that the second lies straight above the first.
    """

    def __init__(self):
        import_mediapipe()  # the install check and its message
        from mediapipe.python.solution_base import PacketDataType, SolutionBase

        with _quiet_native_logs():
            self.graph = SolutionBase(graph_config=_BY_ROI_GRAPH, side_inputs={"model_complexity": 1, "enable_segmentation": True},
                                      stream_type_hints={"roi": PacketDataType.PROTO})

    def close(self) -> None:
        self.graph.close()

    def __call__(self, image: np.ndarray, region):
        """(kp2d [33, 3] pixels, kp3d [33, 3] metres, soft mask [H, W] or None, next
        region), or None when the model sees no body in ``region``."""
        from mediapipe.framework.formats import rect_pb2

        H, W = image.shape[:2]
        cx, cy, side, rotation = region
        roi = rect_pb2.NormalizedRect(x_center=cx / W, y_center=cy / H, width=side / W, height=side / H, rotation=rotation)
        with _quiet_native_logs(), warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*GetPrototype.*", category=UserWarning)
            res = self.graph.process({"image": np.ascontiguousarray(image), "roi": roi})
        if res.landmarks is None or res.auxiliary is None:
            return None
        kp = np.array([(p.x * W, p.y * H, p.visibility) for p in res.landmarks.landmark], np.float32)
        kp3 = None if res.world is None else np.array([(p.x, p.y, p.z) for p in res.world.landmark], np.float32)
        soft = None if res.segmentation is None else np.clip(res.segmentation, 0.0, 1.0)
        centre, top = (np.array([p.x * W, p.y * H]) for p in res.auxiliary.landmark[:2])
        d = top - centre
        nxt = (float(centre[0]), float(centre[1]), 2.5 * float(np.linalg.norm(d)), float(np.pi / 2 + np.arctan2(d[1], d[0])))
        return kp, kp3, soft, nxt


def follow_body(images: np.ndarray, frame: int, box, on_frame=None, mask_threshold: float = 0.5, settle: int = 3,
                min_found: float = 0.5, min_visibility: float = 0.7) -> PersonTrack:
    """The body inside ``box`` (x0, y0, x1, y1, pixels of ``images``) on ``frame``, followed
    through frames [T, H, W, 3] by MediaPipe's landmark model alone (``_PoseInRegion``),
    for a person its detector cannot find: the face out of view (a clip framed from the
    shoulders down) or turned away.

    The first region is the square around the box, refined ``settle`` times on its own
    frame from the model's finds; then each frame, forwards from ``frame`` and back from
    it, is searched in the region the previous find gives. A frame where the model sees
    no body keeps the last region for the next. The face's landmarks are the model's
    guess of a face it cannot see: their visibility is set to 0, so that the body fit
    ignores them. Masks as in ``detect_persons``.

    Without the detector nothing says a person is there but the model's own presence
    score, which a texture can pass on a frame (body keypoints' mean visibility 0.54 on
    one of three random textures). So the track is kept only when a body is found in at
    least ``min_found`` of the frames with a median (over those frames) mean visibility
    of its body keypoints of at least ``min_visibility`` (the backpack development clip,
    framed from the shoulders down: all 87 frames, median 0.90, lowest 0.73); otherwise
    nobody is found in any frame.
    """
    T, H, W, _ = images.shape
    track = PersonTrack.empty(T, H, W)
    x0, y0, x1, y1 = np.asarray(box, np.float64)
    seed = (0.5 * (x0 + x1), 0.5 * (y0 + y1), 1.25 * max(x1 - x0, y1 - y0), 0.0)
    model = _PoseInRegion()
    done = 0
    try:
        for _ in range(settle):
            res = model(images[frame], seed)
            if res is None:
                break
            seed = res[3]
        for order in (range(frame, T), range(frame - 1, -1, -1)):
            region = seed
            for t in order:
                res = model(images[t], region)
                if res is not None:
                    kp, kp3, soft, region = res
                    kp[_FACE, 2] = 0.0
                    track.detected[t] = True
                    track.kp2d[t] = kp
                    if kp3 is not None:
                        track.kp3d[t] = kp3
                    if soft is not None:
                        track.probs[t] = (soft * 255 + 0.5).astype(np.uint8)
                        track.masks[t] = clean_person_mask(soft > mask_threshold, kp)
                done += 1
                if on_frame:
                    on_frame(done)
    finally:
        model.close()
    found = track.detected
    visibility = float(np.median(track.kp2d[found, 11:, 2].mean(1))) if found.any() else 0.0
    if found.mean() < min_found or visibility < min_visibility:
        log.debug("no body: found in %d of %d frames, median body visibility %.2f", int(found.sum()), T, visibility)
        return PersonTrack.empty(T, H, W)
    return track


def fill_missing(images: np.ndarray, track: PersonTrack, on_frame=None, mask_threshold: float = 0.5) -> tuple[PersonTrack, list[int]]:
    """The frames where MediaPipe's detector missed a person it found elsewhere in the clip,
    filled (in place) by its landmark model alone (``follow_body``): each run of missed frames is
    followed into from the frame next to it that has the person (the one before, else the
    one after), starting from the box round that frame's person mask -> (track, frames
    filled). ``follow_body``'s own check decides whether a body is there; a frame where it
    finds none stays missing. The detector finds people by the face: on the backpack
    development clip at its full 480 pixels it missed the person, framed from the shoulders
    down, in the first 29 frames while the body was in view (at 384 it found nobody at all,
    and the whole clip was followed this way)."""
    from cogs.preprocess.prompts import runs_of

    filled: list[int] = []
    if track.detected.all() or not track.detected.any():
        return track, filled
    dst = track.arrays()  # the track's own arrays, written in place
    done = 0
    for a, b in runs_of(~track.detected):  # frames a..b missed
        k = a - 1 if a > 0 else b + 1
        lo, hi = min(a, k), max(b, k) + 1
        ys, xs = np.nonzero(track.masks[k])
        if len(ys):
            box = np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], np.float64)
            src = follow_body(images[lo:hi], k - lo, box, mask_threshold=mask_threshold).arrays()
            for u in range(a, b + 1):
                if src["detected"][u - lo]:
                    for name in dst:
                        dst[name][u] = src[name][u - lo]
                    filled.append(u)
        done += b - a + 1
        if on_frame:
            on_frame(done)
    return track, filled


# A "person" MediaPipe Pose finds is a hand when the hands MediaPipe Hands finds on the
# frame hold ``HAND_BODY_SHARE`` or more of its mask, or one of them is as long as the
# body's torso over ``HAND_BODY_TORSO`` or more (``body_on_a_hand``). The torso (shoulders
# to hips) is about three palms (wrist to the middle finger's knuckle) long; 1.5 is a hand
# twice as near the camera as the torso. Measured (docs/experiments/2026-11-28-bodies-on-hands.md)
# on every frame with a person of the six development clips, the synthetic video benchmark
# at three settings and a real clip of a person seen from the shoulders down moving cups:
# the hands hold at most 0.14 of a real person's mask (0.53 where the person's mask took the
# cups in), and the torso is at least 2.0 palms (2.7 on the development clips). On a clip of
# hands alone moving toy blocks and one of a torso cut at the shoulders, pouring from a
# kettle, the pose model laid a body on a hand: 0.43-1.0 of its mask on the hands, its torso
# 0.2-3.4 palms.
HAND_BODY_SHARE = 0.6
HAND_BODY_TORSO = 1.5
# Hands landmarks: the wrist and the middle finger's knuckle (a palm's length apart).
_WRIST, _MIDDLE_KNUCKLE = 0, 9


def body_on_a_hand(kp: np.ndarray, mask: np.ndarray, hands: list[np.ndarray]) -> bool:
    """Whether a body MediaPipe Pose found (keypoints ``kp`` [33, 3], person ``mask`` [H, W]
    bool) is a hand seen as a body: ``hands`` are the 21 landmarks (pixels [21, 2]) of each
    hand MediaPipe Hands found on the frame. The pose model lays a whole skeleton on a
    close-up hand (a clip of hands alone, or of a torso whose shoulders are out of view);
    its mask is then the hand and what the hand holds. See ``HAND_BODY_SHARE`` and
    ``HAND_BODY_TORSO``."""
    if not hands:
        return False
    H, W = mask.shape
    on_hands = np.zeros((H, W), bool)
    for pts in hands:
        lo, hi = pts.min(0), pts.max(0)
        grow = 0.25 * (hi - lo)  # the fingers' flesh beyond their joints
        x0, y0 = np.floor(np.maximum(lo - grow, 0)).astype(int)
        x1, y1 = np.ceil(np.minimum(hi + grow, (W, H))).astype(int)
        on_hands[y0:y1, x0:x1] = True
    if mask.any() and (mask & on_hands).sum() >= HAND_BODY_SHARE * mask.sum():
        return True
    palm = max(float(np.linalg.norm(pts[_MIDDLE_KNUCKLE] - pts[_WRIST])) for pts in hands)
    torso = _torso_length(kp)
    return bool(np.isfinite(torso) and torso < HAND_BODY_TORSO * palm)


def bodies_on_hands(images: np.ndarray, track: PersonTrack, on_frame=None) -> np.ndarray:
    """[T] bool: the frames of ``track`` whose body is a hand (``body_on_a_hand``), from
    MediaPipe Hands (palm detector and landmark model, both in the pip package) on each
    frame with a body. ``images`` [T, H, W, 3] uint8 RGB."""
    out = np.zeros(len(images), bool)
    if not track.detected.any():
        return out
    mp = import_mediapipe()
    H, W = images.shape[1:3]
    with _quiet_native_logs():
        model = mp.solutions.hands.Hands(static_image_mode=True, max_num_hands=2, model_complexity=1, min_detection_confidence=0.5)
    try:
        for i, t in enumerate(np.flatnonzero(track.detected)):
            with _quiet_native_logs(), warnings.catch_warnings():
                warnings.filterwarnings("ignore", message=".*GetPrototype.*", category=UserWarning)
                res = model.process(np.ascontiguousarray(images[t]))
            hands = [np.array([(p.x * W, p.y * H) for p in lm.landmark]) for lm in res.multi_hand_landmarks or []]
            out[t] = body_on_a_hand(track.kp2d[t], track.masks[t], hands)
            if on_frame:
                on_frame(i + 1)
    finally:
        model.close()
    return out


def without_bodies_on_hands(images: np.ndarray, track: PersonTrack, on_frame=None) -> tuple[PersonTrack, list[int], bool]:
    """``track`` without the bodies that are hands (``bodies_on_hands``) -> (the track, the
    frames dropped, whether the whole track was dropped). When half or more of the frames
    with a body are hands, the pose model was following a hand: its finds on the other
    frames (a hand Hands missed, the object in it) are no person either, and every frame is
    dropped. Otherwise only the frames on a hand are (the body is interpolated there)."""
    on_hand = bodies_on_hands(images, track, on_frame)
    whole = bool(on_hand.any()) and following_a_hand(track, on_hand)
    return drop_bodies_on_hands(track, on_hand), [int(t) for t in np.flatnonzero(on_hand)], whole


def following_a_hand(track: PersonTrack, on_hand: np.ndarray) -> bool:
    """Whether half or more of the frames with a body have it on a hand (``on_hand`` [T] bool)."""
    return 2 * int((on_hand & track.detected).sum()) >= max(1, int(track.detected.sum()))


def drop_bodies_on_hands(track: PersonTrack, on_hand: np.ndarray) -> PersonTrack:
    """``track`` (changed in place) with nobody on the frames ``on_hand`` [T] bool, or on
    every frame when it was following a hand (``following_a_hand``)."""
    if not on_hand.any():
        return track
    drop = track.detected.copy() if following_a_hand(track, on_hand) else on_hand
    empty = PersonTrack.empty(*track.masks.shape)
    for name in ("masks", "probs", "kp2d", "kp3d", "detected"):
        getattr(track, name)[drop] = getattr(empty, name)[drop]
    return track


# A body MediaPipe Pose lays on the object itself: at least BODY_ON_OBJECT_SHARE of its visible
# landmarks on the object's mask, on BODY_ON_OBJECT_FRAMES or more of the frames with a body
# (``body_on_object``). An unseen clip of a teddy bear held in the lap, the person seen from
# the chest down: 60 of the 62 frames with a body had it on the bear (median share 0.83). On
# the seven development clips, the synthetic video benchmark at eight settings and two other
# unseen clips no frame reaches 0.5: the most is 0.44 (the guitar held across the hips), the
# others 0.18 or less (docs/experiments/2026-12-02-a-lock-a-keep-away-and-prompts-that-run-along-their-box.md).
BODY_ON_OBJECT_SHARE = 0.5
BODY_ON_OBJECT_FRAMES = 0.1


def body_on_object(kp2d: np.ndarray, object_masks: np.ndarray, min_visibility: float = 0.5) -> tuple[list[int], int]:
    """The frames whose body (``kp2d`` [T, 33, 3] pixels and visibility) has at least
    ``BODY_ON_OBJECT_SHARE`` of its visible landmarks on the object's mask
    (``object_masks`` [T, H, W] bool), and how many frames have both a body (five or more
    visible landmarks) and an object mask."""
    T, H, W = object_masks.shape
    on, judged = [], 0
    for t in range(T):
        seen = kp2d[t, :, 2] >= min_visibility
        if seen.sum() < 5 or not object_masks[t].any():
            continue
        judged += 1
        x = np.clip(np.round(kp2d[t, seen, 0]).astype(int), 0, W - 1)
        y = np.clip(np.round(kp2d[t, seen, 1]).astype(int), 0, H - 1)
        if object_masks[t][y, x].mean() >= BODY_ON_OBJECT_SHARE:
            on.append(t)
    return on, judged


def body_on_object_warning(kp2d: np.ndarray, object_masks: np.ndarray) -> str | None:
    """The warning for a person MediaPipe found on the object itself (``body_on_object``),
    or None."""
    on, judged = body_on_object(kp2d, object_masks)
    if not on or len(on) < BODY_ON_OBJECT_FRAMES * judged:
        return None
    shown = ", ".join(str(t) for t in on[:10]) + (", ..." if len(on) > 10 else "")
    return (f"the body MediaPipe found lies on the object in {len(on)} of the {judged} frames with both (frames {shown}): "
            "the person it follows is the object itself (a doll or a toy looks like a person to it where the person's "
            "face and limbs are out of view), and the human branch would learn the object. Give --person-box FRAME X0 Y0 "
            "X1 Y1 around the person on a frame where the face is in view, or use a clip that shows the person whole")


def refine_masks_sam2(images: np.ndarray, track: PersonTrack, checkpoint: Path, config: str, on_frame=None) -> np.ndarray:
    """Re-segment the person with SAM2 (box prompt from each frame's MediaPipe mask) -> [T, H, W] bool.

    Needs the optional ``sam2`` package and a checkpoint file; frames without a detection keep
    their (empty) mask.
    """
    if not Path(checkpoint).exists():
        raise UserError(f"--sam2-checkpoint {checkpoint} does not exist")
    try:
        import torch
        from sam2.build_sam import build_sam2
        from sam2.sam2_image_predictor import SAM2ImagePredictor
    except ImportError as e:
        raise UserError(f"--sam2-checkpoint needs the `sam2` package ({e}); install it or drop the option") from None
    predictor = SAM2ImagePredictor(build_sam2(config, str(checkpoint), device="cpu"))
    out = track.masks.copy()
    with torch.inference_mode():
        for t in range(len(images)):
            m = track.masks[t]
            if m.any():
                ys, xs = np.nonzero(m)
                box = np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], dtype=np.float32)
                predictor.set_image(images[t])
                pred, _, _ = predictor.predict(box=box, multimask_output=False)
                out[t] = pred[0] > 0.5
            if on_frame:
                on_frame(t + 1)
    return out


def refine_mask_boundary(rgb: np.ndarray, prob: np.ndarray, threshold: float = 0.5, band_frac: float = 0.03, iterations: int = 3) -> np.ndarray:
    """Sharpen a soft person mask's boundary with GrabCut inside a narrow band -> [H, W] bool.

    MediaPipe's mask is predicted at low resolution and upsampled, so it bleeds a few
    pixels over the background. Pixels deeper than the band inside the mask are kept as
    person, pixels beyond the band outside it as background; only the band (``band_frac``
    of the person's height on each side) is relabelled, by GrabCut colour models learnt
    from this frame, so a wrong colour model can move the boundary by at most the band.
    """
    import cv2

    mask = prob >= threshold * 255 if prob.dtype == np.uint8 else prob >= threshold
    if mask.sum() < 50:
        return mask
    ys, xs = np.nonzero(mask)
    band = max(2, int(round(band_frac * (ys.max() - ys.min() + 1))))
    H, W = mask.shape
    y0, y1 = max(0, ys.min() - 2 * band), min(H, ys.max() + 2 * band + 1)
    x0, x1 = max(0, xs.min() - 2 * band), min(W, xs.max() + 2 * band + 1)
    m = mask[y0:y1, x0:x1].astype(np.uint8)
    k = disk(band)
    inner = cv2.erode(m, k) > 0
    outer = cv2.dilate(m, k) > 0
    gc = np.full(m.shape, cv2.GC_BGD, np.uint8)
    gc[outer] = cv2.GC_PR_BGD
    gc[m > 0] = cv2.GC_PR_FGD
    gc[inner] = cv2.GC_FGD
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    crop = np.ascontiguousarray(rgb[y0:y1, x0:x1, ::-1])
    try:
        cv2.grabCut(crop, gc, None, bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK)
    except cv2.error:
        return mask
    out = np.zeros_like(mask)
    out[y0:y1, x0:x1] = (gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD)
    return out
