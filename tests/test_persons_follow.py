"""Following one person among several (`cogs preprocess --person-box`).

The clip: twelve frames of the synthetic benchmark with a second person pasted beside the
first — the same body, 70 px to the right and in other clothes (colour channels
reversed), so the two walk side by side, and touch when the first bends. MediaPipe runs
for real (the test skips without the `preprocess` extra).
"""

from __future__ import annotations

import numpy as np
import pytest

from cogs.errors import UserError

SHIFT = 70  # pixels between the two people


@pytest.fixture(scope="module")
def two_people(default_scene_dir):
    pytest.importorskip("mediapipe", reason="mediapipe is in the optional `preprocess` extra")
    from PIL import Image

    frames = range(0, 48, 4)
    images = np.stack([np.asarray(Image.open(default_scene_dir / "images" / f"{t:06d}.png").convert("RGB")) for t in frames])
    human = np.stack([np.asarray(Image.open(default_scene_dir / "masks" / "human" / f"{t:06d}.png")) > 127 for t in frames])
    T, H, W, _ = images.shape
    out, second = images.copy(), np.zeros_like(human)
    second[:, :, SHIFT:] = human[:, :, : W - SHIFT]
    recoloured = np.zeros_like(images)
    recoloured[:, :, SHIFT:] = images[:, :, : W - SHIFT, ::-1]
    out[second] = recoloured[second]
    first = human & ~second  # what stays visible of the first person
    return out, first, second


def _box(mask: np.ndarray) -> np.ndarray:
    ys, xs = np.nonzero(mask)
    return np.array([xs.min() - 3, ys.min() - 3, xs.max() + 4, ys.max() + 4], float)


def _share(mask: np.ndarray, of: np.ndarray) -> float:
    return float((mask & of).sum()) / max(1, int(mask.sum()))


@pytest.mark.parametrize("followed", ["first", "second"])
def test_the_person_in_the_box_is_followed_and_the_other_never_enters_the_mask(two_people, followed):
    from cogs.preprocess.persons import follow_person

    images, first, second = two_people
    own, other = (first, second) if followed == "first" else (second, first)
    track = follow_person(images, 0, _box(own[0]))
    found = np.flatnonzero(track.detected)
    # MediaPipe finds the recoloured person less often (its skin is blue); a frame where
    # the followed person is not found has no person rather than the other one.
    assert len(found) >= (10 if followed == "first" else 3)
    for t in found:
        assert _share(track.masks[t], other[t]) < 0.02, f"frame {t}: the mask took the other person"
        assert _share(track.masks[t], own[t]) > 0.6, f"frame {t}: the mask is not on the followed person"
        centre = track.kp2d[t, [11, 12, 23, 24], :2].mean(0)
        assert own[t][int(centre[1]), int(centre[0])] or _share(track.masks[t], own[t]) > 0.9
    assert np.isnan(track.kp2d[~track.detected]).all()


def test_the_first_person_found_must_be_in_the_box(two_people):
    """A box on an empty part of the frame follows nobody, not whoever is nearest."""
    from cogs.preprocess.persons import follow_person

    images, _, _ = two_people
    H, W = images.shape[1:3]
    track = follow_person(images[:3], 0, np.array([W - 30, 0, W, 30], float))
    assert not track.detected.any()


def _figure(dx: float = 0.0, face=(50.0, 20.0)) -> np.ndarray:
    """A standing figure's keypoints (shoulders at y 40, hips at y 80: a 40 px torso, knees
    110, ankles 140) moved ``dx`` to the right, its face's points around ``face``."""
    from cogs.preprocess.persons import N_LANDMARKS

    kp = np.full((N_LANDMARKS, 3), np.nan, np.float32)
    for i, (x, y) in {11: (40, 40), 12: (60, 40), 23: (44, 80), 24: (56, 80), 25: (44, 110),
                      26: (56, 110), 27: (44, 140), 28: (56, 140), 13: (36, 60), 15: (34, 80)}.items():
        kp[i] = (x + dx, y, 1.0)
    for i in range(11):
        kp[i] = (face[0] + dx + (i % 3 - 1) * 3, face[1] + (i % 2) * 2, 1.0)
    return kp


def test_body_region_covers_the_limbs_and_leaves_a_neighbour_out():
    from cogs.preprocess.persons import body_region

    region = body_region(_figure(), (160, 160), reach=6)
    assert region[60, 50] and region[125, 44] and region[70, 35] and region[20, 50]  # torso, shin, forearm, face
    assert not region[60, 100] and not region[20, 130]  # a neighbour's place


def test_a_face_that_moves_further_on_the_body_than_a_head_can_is_somebody_elses():
    """MediaPipe lays the followed body under the face of a person just behind its
    shoulder (the loading development clip, frame 91): the face moves on the body."""
    from cogs.preprocess.persons import FollowSettings, _Followed

    s = FollowSettings()
    person = _Followed(np.array([30, 10, 70, 150], float), (160, 160), s)
    assert person.face_moved(_figure()) is None  # nothing known yet
    person.found(_figure(), np.zeros((160, 160), bool), None)
    # The whole body walking 12 px, the head bending 0.3 torso lengths: the same person.
    assert person.face_moved(_figure(dx=12)) is None
    assert person.face_moved(_figure(face=(50, 32))) is None
    # The face 0.6 torso lengths off, over the right shoulder: somebody else's.
    moved = person.face_moved(_figure(face=(70, 30)))
    assert moved is not None and moved == pytest.approx(np.hypot(20, 10) / 40, abs=0.01)
    person.missed()  # without a find on the previous frame there is nothing to compare
    assert person.face_moved(_figure(face=(70, 30))) is None


def test_somebody_elses_face_is_followed_by_its_look_and_let_go_when_gone():
    import cv2

    from cogs.preprocess.persons import _OtherFaces

    rng = np.random.default_rng(0)
    room = cv2.GaussianBlur(rng.integers(0, 255, (120, 160, 3), dtype=np.uint8), (5, 5), 0)
    head = cv2.GaussianBlur(rng.integers(0, 255, (21, 21, 3), dtype=np.uint8), (3, 3), 0)

    def frame(x, y):  # the head's centre at (x, y)
        im = room.copy()
        im[y - 10:y + 11, x - 10:x + 11] = head
        return im

    others = _OtherFaces(min_match=0.5)
    disc = others.add(frame(60, 50), np.array([60.0, 50.0]), 8)
    assert disc[50, 60] and disc[50, 67] and not disc[50, 70]
    for k in range(1, 7):  # walking 3 px right and 1 px down a frame
        others.follow(frame(60 + 3 * k, 50 + k))
        assert len(others.faces) == 1
        centre = others.faces[0][0]
        assert np.allclose(centre, (60 + 3 * k, 50 + k), atol=1.0), (k, centre)
    assert others.region((120, 160))[56, 78] and not others.region((120, 160))[56, 60]
    # The followed person's own face found on it: let go (painting it out would hide them).
    kept = list(others.faces)
    others.drop_at(np.array([100.0, 20.0]))
    assert len(others.faces) == 1
    others.drop_at(np.array([80.0, 57.0]))
    assert others.faces == []
    # Gone from the room: let go.
    others.faces = kept
    others.follow(room)
    assert others.faces == []


@pytest.mark.parametrize("value, message", [
    ((10, 10, 5, 20), "X1 > X0"),
    ((1, 2, 3), "got 3 numbers"),
    ((-1, 0, 0, 10, 10), "whole number >= 0"),
])  # fmt: skip
def test_bad_person_boxes_raise_user_errors_naming_the_option(value, message):
    from cogs.preprocess.prompts import parse_person_box

    with pytest.raises(UserError, match=f"--person-box.*{message}"):
        parse_person_box(value)


def test_a_person_box_off_the_frames_is_refused_before_any_work():
    from cogs.preprocess.prompts import check_against_frames, parse_person_box

    assert parse_person_box(None) is None
    prompt = parse_person_box((3, 10, 10, 40, 60))
    assert (prompt.frame, prompt.box) == (3, (10.0, 10.0, 40.0, 60.0))
    assert parse_person_box((10, 10, 40, 60)).frame == 0
    with pytest.raises(UserError, match="--person-box 3 10 10 40 60: frame 3 is outside"):
        check_against_frames([prompt], (160, 120), 3)
    with pytest.raises(UserError, match="--person-box 500 10 600 60 lies outside the 160x120 frame"):
        check_against_frames([parse_person_box((500, 10, 600, 60))], (160, 120), 3)


@pytest.fixture(scope="module")
def two_alike(default_scene_dir):
    """The benchmark's person, and the same person 50 frames later pasted 80 px to the
    right: two people who look alike and both look like people to MediaPipe."""
    pytest.importorskip("mediapipe", reason="mediapipe is in the optional `preprocess` extra")
    from PIL import Image

    def load(t):
        return (np.asarray(Image.open(default_scene_dir / "images" / f"{t:06d}.png").convert("RGB")),
                np.asarray(Image.open(default_scene_dir / "masks" / "human" / f"{t:06d}.png")) > 127)

    frames = range(0, 48, 4)
    images, first, second = [], [], []
    for t in frames:
        im, m = load(t)
        later, m2 = load(t + 50)
        W = im.shape[1]
        pasted = np.zeros_like(m2)
        pasted[:, 80:] = m2[:, : W - 80]
        out = im.copy()
        out[pasted] = np.roll(later, 80, axis=1)[pasted]
        images.append(out)
        first.append(m & ~pasted)
        second.append(pasted)
    return np.stack(images), np.stack(first), np.stack(second)


def test_with_several_people_and_no_box_one_is_chosen_and_followed_alone(two_alike, default_scene_dir):
    from PIL import Image

    from cogs.preprocess.persons import choose_person, follow_person

    images, first, second = two_alike
    # One person in view: no choice to make (the whole-frame path runs unchanged).
    alone = np.stack([np.asarray(Image.open(default_scene_dir / "images" / f"{t:06d}.png").convert("RGB")) for t in range(0, 48, 4)])
    assert choose_person(alone) is None
    # Without an object box: the person nearest the frame's centre (the first, here).
    t, box = choose_person(images)
    cx = (box[0] + box[2]) / 2
    assert first[t][:, int(box[0]):int(box[2]) + 1].any() and not second[t][:, int(cx)].any()
    # With an object box held against the second person (at the middle of their mask), that person.
    y, x = np.argwhere(second[t]).mean(0)
    near = (t, np.array([x - 5, y - 5, x + 5, y + 5], float))
    t2, box2 = choose_person(images, near)
    assert second[t2][int((box2[1] + box2[3]) / 2), :][int(box2[0]):int(box2[2]) + 1].any()
    assert not first[t2][:, int((box2[0] + box2[2]) / 2)].any()
    track = follow_person(images, t, box)
    for k in np.flatnonzero(track.detected):
        assert _share(track.masks[k], second[k]) < 0.02, f"frame {k}: the mask took the other person"
    assert track.detected.sum() >= 10


@pytest.fixture(scope="module")
def headless(default_scene_dir):
    """Twelve frames of the synthetic benchmark with the top quarter of the person (the
    head and neck) painted grey, as in a clip framed from the shoulders down."""
    pytest.importorskip("mediapipe", reason="mediapipe is in the optional `preprocess` extra")
    from PIL import Image

    frames = range(0, 48, 4)
    images = np.stack([np.asarray(Image.open(default_scene_dir / "images" / f"{t:06d}.png").convert("RGB")) for t in frames])
    human = np.stack([np.asarray(Image.open(default_scene_dir / "masks" / "human" / f"{t:06d}.png")) > 127 for t in frames])
    for t in range(len(images)):
        ys, xs = np.nonzero(human[t])
        cut = ys.min() + int(0.25 * (ys.max() - ys.min()))
        images[t, :cut, max(0, xs.min() - 8) : xs.max() + 8] = 127
        human[t, :cut] = False
    return images, human


def test_a_body_is_followed_from_a_box_by_the_landmark_model_alone(headless):
    from cogs.preprocess.persons import follow_body

    images, human = headless
    track = follow_body(images, 0, _box(human[0]))
    assert track.detected.sum() >= 10
    ious = [(track.masks[t] & human[t]).sum() / (track.masks[t] | human[t]).sum() for t in np.flatnonzero(track.detected)]
    assert np.median(ious) > 0.65 and min(ious) > 0.4, ious  # 0.51-0.82 seen
    for t in np.flatnonzero(track.detected):
        hips = track.kp2d[t, [23, 24], :2].mean(0)
        assert human[t][int(hips[1]), int(hips[0])], f"frame {t}: the hips are off the body"
    assert (track.kp2d[track.detected, :11, 2] == 0).all()  # the face it cannot see is left out
    assert np.isnan(track.kp2d[~track.detected]).all()


def test_a_box_on_no_body_follows_nobody(headless):
    """(A random texture that the model's presence score passes on one frame is refused
    by the track's own check: test_preprocess's test_pipeline_refuses_frames_without_a_person.)"""
    from cogs.preprocess.persons import follow_body

    images, _ = headless
    H, W = images.shape[1:3]
    assert not follow_body(images[:4], 0, np.array([W - 60, H - 50, W, H], float)).detected.any()


def test_a_skeleton_that_explains_the_person_mask_scores_above_a_scrambled_one(default_scene_dir):
    """`skeleton_fit` decides where MediaPipe's video-mode landmarks give way to a fresh
    detection's: real landmarks of a synthetic frame explain its person mask; the same
    landmarks shrunk into the middle of the body (what video mode's tracking kept on the
    bottle clip: the face at the hands, the hips at the belt) or moved off it do not."""
    pytest.importorskip("mediapipe", reason="mediapipe is in the optional `preprocess` extra")
    from PIL import Image

    from cogs.preprocess.persons import _run_pose, _static_pose, import_mediapipe, skeleton_fit

    image = np.asarray(Image.open(default_scene_dir / "images" / "000030.png").convert("RGB"))
    human = np.asarray(Image.open(default_scene_dir / "masks" / "human" / "000030.png")) > 127
    pose = _static_pose(import_mediapipe())
    try:
        kp = _run_pose(pose, image, (0, 0, image.shape[1], image.shape[0]), np.ones(human.shape, bool))[0]
    finally:
        pose.close()
    good = skeleton_fit(kp, human)
    centre = kp[[11, 12, 23, 24], :2].mean(0)
    shrunk = kp.copy()
    shrunk[:, :2] = centre + 0.5 * (kp[:, :2] - centre)
    moved = kp.copy()
    moved[:, 0] += 0.6 * (np.ptp(np.nonzero(human.any(0))[0]) + 1)
    assert good > 0.3
    assert skeleton_fit(shrunk, human) < good - 0.1 and skeleton_fit(moved, human) < good - 0.1
    assert skeleton_fit(kp, np.zeros_like(human)) == 0.0


# -- bodies laid on a hand ----------------------------------------------------------------


def _standing(height: float = 180.0, x: float = 120.0, top: float = 10.0) -> np.ndarray:
    """MediaPipe-ordered keypoints [33, 3] of an upright body ``height`` pixels tall: the
    torso (shoulders to hips) a third of it."""
    kp = np.full((33, 3), np.nan, np.float32)
    u = height / 6.0
    pts = {0: (x, top + 0.3 * u), 11: (x + 0.6 * u, top + u), 12: (x - 0.6 * u, top + u), 13: (x + 0.8 * u, top + 2 * u),
           14: (x - 0.8 * u, top + 2 * u), 15: (x + 0.9 * u, top + 3 * u), 16: (x - 0.9 * u, top + 3 * u),
           23: (x + 0.4 * u, top + 3 * u), 24: (x - 0.4 * u, top + 3 * u), 25: (x + 0.4 * u, top + 4.5 * u),
           26: (x - 0.4 * u, top + 4.5 * u), 27: (x + 0.4 * u, top + 6 * u), 28: (x - 0.4 * u, top + 6 * u)}
    for j, (px, py) in pts.items():
        kp[j] = (px, py, 0.9)
    return kp


def _hand(wrist, palm: float) -> np.ndarray:
    """21 Hands landmarks [21, 2] of an open hand pointing up, palm (wrist to the middle
    finger's knuckle) ``palm`` pixels long."""
    wx, wy = wrist
    pts = np.zeros((21, 2))
    pts[0] = (wx, wy)
    for f, dx in enumerate((-0.5, -0.2, 0.0, 0.2, 0.4)):  # thumb, index, middle, ring, little
        for k in range(4):
            pts[1 + 4 * f + k] = (wx + dx * palm * (1 + 0.3 * k), wy - palm * (1 + 0.5 * k) * (0.6 if f == 0 else 1.0))
    pts[9] = (wx, wy - palm)  # the middle finger's knuckle
    return pts


def _mask_of(kp: np.ndarray, shape=(200, 240)) -> np.ndarray:
    from cogs.preprocess.persons import _torso_length, body_region

    return body_region(kp, shape, 0.15 * _torso_length(kp), 0.3 * _torso_length(kp))


def test_a_body_with_its_hands_is_a_person_and_one_inside_a_hand_is_not():
    """`body_on_a_hand`: a hand is about a third of a torso long, and holds little of the
    person's mask; a body the pose model laid on a close-up hand is smaller than the hand,
    or its mask is mostly the hand."""
    from cogs.preprocess.persons import HAND_BODY_SHARE, body_on_a_hand

    person = _standing()
    mask = _mask_of(person)
    hands = [_hand(person[15, :2], 20.0), _hand(person[16, :2], 20.0)]  # torso 60 px: three palms
    assert not body_on_a_hand(person, mask, hands)
    assert not body_on_a_hand(person, mask, [])  # no hand found: nothing to compare with
    # A hand twice as long, held out to the camera beside the body: still a person (1.5 palms).
    assert not body_on_a_hand(person, mask, [_hand((215.0, 195.0), 39.0)])
    # A close-up hand, palm 40 px, with a body whose torso is 45 px laid on it.
    small = _standing(height=135.0, x=120.0, top=40.0)
    big_hand = [_hand((120.0, 190.0), 40.0)]
    assert body_on_a_hand(small, _mask_of(small), big_hand)
    # A body whose torso is over three of that hand's palms is one, unless its mask lies on the hand.
    tall = _standing(height=400.0, x=120.0, top=-100.0)
    wide = np.zeros((200, 240), bool)
    wide[:, 20:220] = True  # a mask over the whole frame: the hand's box holds little of it
    assert not body_on_a_hand(tall, wide, big_hand)
    on_hand = np.zeros((200, 240), bool)
    lo, hi = big_hand[0].min(0).astype(int), big_hand[0].max(0).astype(int)
    on_hand[lo[1] : hi[1], lo[0] : hi[0]] = True
    on_hand[:, :2] = True  # and a sliver elsewhere
    assert on_hand[:, :2].sum() < (1 - HAND_BODY_SHARE) * on_hand.sum()
    assert body_on_a_hand(tall, on_hand, big_hand)


def test_bodies_on_hands_are_dropped_and_a_track_mostly_on_hands_is_dropped_whole():
    from cogs.preprocess.persons import PersonTrack, drop_bodies_on_hands

    def track(T=6):
        tr = PersonTrack.empty(T, 20, 30)
        tr.detected[:] = True
        tr.masks[:, 5:15, 10:20] = True
        tr.kp2d[:] = 1.0
        return tr

    few = np.zeros(6, bool)
    few[[1, 4]] = True
    tr = drop_bodies_on_hands(track(), few)
    assert tr.detected.tolist() == [True, False, True, True, False, True]
    assert not tr.masks[[1, 4]].any() and np.isnan(tr.kp2d[[1, 4]]).all() and tr.masks[0].any()
    half = np.zeros(6, bool)
    half[:3] = True  # half the finds are hands: the rest are the same hand, missed by Hands
    assert not drop_bodies_on_hands(track(), half).detected.any()
    assert drop_bodies_on_hands(track(), np.zeros(6, bool)).detected.all()


def test_frames_the_detector_missed_are_filled_from_the_frames_next_to_them(default_scene_dir):
    """MediaPipe's detector can miss a person it finds a few frames later (the backpack clip at
    480 pixels: the first 29 frames). Those frames are followed into by the landmark model
    from the frame next to them; a frame with nobody in it stays missing."""
    pytest.importorskip("mediapipe", reason="mediapipe is in the optional `preprocess` extra")
    from PIL import Image

    from cogs.preprocess.persons import PersonTrack, detect_persons, fill_missing

    frames = range(0, 40, 4)
    images = np.stack([np.asarray(Image.open(default_scene_dir / "images" / f"{t:06d}.png").convert("RGB")) for t in frames])
    human = np.stack([np.asarray(Image.open(default_scene_dir / "masks" / "human" / f"{t:06d}.png")) > 127 for t in frames])
    images[9] = 127  # nobody on the last frame
    track = detect_persons(images)
    assert track.detected[:9].all() and not track.detected[9]
    missed = PersonTrack.from_arrays({k: v.copy() for k, v in track.arrays().items()})
    for t in (0, 1, 2, 5):  # what the detector did not find on these frames
        missed.masks[t], missed.probs[t], missed.detected[t] = False, 0, False
        missed.kp2d[t], missed.kp3d[t] = np.nan, np.nan
    filled_track, filled = fill_missing(images, missed)
    assert filled == [0, 1, 2, 5]  # frame 9 has nobody to follow
    for t in filled:
        iou = (filled_track.masks[t] & human[t]).sum() / (filled_track.masks[t] | human[t]).sum()
        assert iou > 0.6, f"frame {t}: IoU {iou:.2f} with the true person"
        hips = filled_track.kp2d[t, [23, 24], :2].mean(0)
        assert human[t][int(hips[1]), int(hips[0])], f"frame {t}: the hips are off the body"
    assert not filled_track.detected[9] and np.isnan(filled_track.kp2d[9]).all()
