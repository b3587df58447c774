"""`cogs preprocess`: each step on small inputs the tests make themselves.

MediaPipe and pycolmap are optional (the `preprocess` extra); tests that need them skip
with a reason when they are missing. Everything else runs on synthetic frames.
"""

from __future__ import annotations

import os
import re

import numpy as np
import pytest
import torch

from cogs.errors import UserError
from cogs.preprocess import frames as F
from cogs.preprocess import objects as O
from cogs.preprocess import sfm as S
from cogs.preprocess.pipeline import Cache, hosnerf_split


def _texture(h: int, w: int, seed: int = 0) -> np.ndarray:
    """A smooth random colour texture with corners SIFT can match."""
    import cv2

    rng = np.random.default_rng(seed)
    small = rng.integers(0, 255, (h // 8 + 1, w // 8 + 1, 3), dtype=np.uint8)
    big = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
    noise = rng.integers(0, 40, (h, w, 3))
    return np.clip(big.astype(int) + noise - 20, 0, 255).astype(np.uint8)


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.logical_and(a, b).sum() / max(np.logical_or(a, b).sum(), 1))


# -- frames ---------------------------------------------------------------------------


def test_video_frames_respect_stride_limit_and_max_side(tmp_path):
    video = np.stack([np.full((120, 80, 3), 10 * i, np.uint8) for i in range(10)])
    F.write_video(tmp_path / "v.mp4", video, fps=10)
    fr = F.read_frames(tmp_path / "v.mp4", stride=2, limit=3, max_side=60)
    assert fr.images.shape == (3, 60, 40, 3)
    assert fr.source_indices.tolist() == [0, 2, 4]
    assert fr.fps == pytest.approx(5.0)
    assert fr.source_size == (80, 120)
    # Frame 4 of the source was grey level 40 (H.264 is lossy: within a few levels).
    assert abs(float(fr.images[2].mean()) - 40) < 4


@pytest.mark.parametrize("rotation, corner", [(-90, (0, -1)), (90, (-1, 0)), (180, (-1, -1)), (0, (0, 0))])
def test_a_phone_clip_stored_on_its_side_is_read_upright(tmp_path, rotation, corner):
    """Phones store a portrait clip as landscape pixels with a quarter turn in the header's
    display matrix; players (and so the user drawing boxes) see it turned. A red mark in
    the stored top-left corner must be where a player shows it."""
    import av

    img = np.zeros((48, 64, 3), np.uint8)
    img[:10, :10] = (255, 0, 0)
    with av.open(str(tmp_path / "v.mp4"), "w") as c:
        st = c.add_stream("libx264", rate=10)
        st.width, st.height, st.pix_fmt = 64, 48, "yuv420p"
        if rotation:
            st.set_display_rotation(rotation)  # counter-clockwise, as players apply it
        for _ in range(3):
            for packet in st.encode(av.VideoFrame.from_ndarray(img, format="rgb24")):
                c.mux(packet)
        for packet in st.encode():
            c.mux(packet)
    fr = F.read_frames(tmp_path / "v.mp4", max_side=None)
    quarter = rotation % 180 != 0
    assert fr.images.shape == ((3, 64, 48, 3) if quarter else (3, 48, 64, 3))
    assert fr.source_size == ((48, 64) if quarter else (64, 48))
    assert F.probe(tmp_path / "v.mp4") == (3, fr.source_size)  # prompts are checked against the turned size
    red = fr.images[0, ..., 0].astype(float)
    H, W = red.shape
    y = slice(0, 10) if corner[0] == 0 else slice(H - 10, H)
    x = slice(0, 10) if corner[1] == 0 else slice(W - 10, W)
    assert red[y, x].mean() > 200 and red.mean() < 60


def test_photos_with_an_exif_orientation_are_read_upright(tmp_path):
    from PIL import Image

    img = np.zeros((48, 64, 3), np.uint8)
    img[:10, :10] = (255, 0, 0)
    exif = Image.Exif()
    exif[0x0112] = 6  # "turn 90 degrees clockwise to display", as phones write portrait photos
    for i in range(2):
        Image.fromarray(img).save(tmp_path / f"{i}.jpg", exif=exif, quality=95)
    fr = F.read_frames(tmp_path, max_side=None)
    assert fr.images.shape == (2, 64, 48, 3) and fr.source_size == (48, 64)
    assert F.probe(tmp_path) == (2, (48, 64))
    assert fr.images[0, :10, -10:, 0].mean() > 200 and fr.images[0, ..., 0].mean() < 60  # top-right, as shown


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity") or len(os.sched_getaffinity(0)) < 2, reason="needs two CPUs to vary")
def test_encoded_video_does_not_depend_on_how_many_cpus_the_encoder_sees(tmp_path):
    # libx264 picks its thread count from the CPUs it may use, and its output from that;
    # the accuracy benchmark's numbers must not change from machine to machine.
    big = _texture(240, 480, seed=1)
    video = np.stack([big[:, 8 * i : 8 * i + 320] for i in range(12)])
    cpus = os.sched_getaffinity(0)
    F.write_video(tmp_path / "all.mp4", video)
    os.sched_setaffinity(0, {min(cpus)})
    try:
        F.write_video(tmp_path / "one.mp4", video)
    finally:
        os.sched_setaffinity(0, cpus)
    assert np.array_equal(F.read_frames(tmp_path / "all.mp4").images, F.read_frames(tmp_path / "one.mp4").images)


def test_encoding_the_same_frames_twice_gives_the_same_video(tmp_path):
    # libx264's macroblock-tree lookahead read memory it never wrote: repeated encodes of
    # the synthetic scene's frames decoded differently.
    from cogs.data.synth.config import SynthConfig
    from cogs.data.synth.generate import generate_scene

    frames = generate_scene(SynthConfig(frames=8, width=280, height=210, seed=0), show_progress=False).images
    decoded = []
    for k in range(3):
        F.write_video(tmp_path / f"{k}.mp4", frames)
        decoded.append(F.read_frames(tmp_path / f"{k}.mp4").images)
    assert np.array_equal(decoded[0], decoded[1]) and np.array_equal(decoded[0], decoded[2])


def test_image_folder_is_read_in_name_order(tmp_path):
    from cogs.data.io import write_image

    for i in (2, 0, 1):
        write_image(tmp_path / f"f{i}.png", np.full((10, 12, 3), 50 * i, np.uint8))
    fr = F.read_frames(tmp_path, max_side=None)
    assert [int(im.mean()) for im in fr.images] == [0, 50, 100]


def _missing(p):
    return p / "missing.mp4"


def _garbage(p):
    (p / "bad.mp4").write_bytes(b"not a video at all")
    return p / "bad.mp4"


def _empty_dir(p):
    (p / "empty").mkdir()
    return p / "empty"


@pytest.mark.parametrize("make, message", [
    (_missing, "does not exist"),
    (_garbage, "bad.mp4"),
    (_empty_dir, "holds no images"),
])  # fmt: skip
def test_unusable_inputs_raise_user_errors_naming_the_file(tmp_path, make, message):
    with pytest.raises(UserError, match=message):
        F.read_frames(make(tmp_path))


def test_frames_of_different_sizes_in_a_folder_are_refused(tmp_path):
    from cogs.data.io import write_image

    write_image(tmp_path / "a.png", np.zeros((10, 10, 3), np.uint8))
    write_image(tmp_path / "b.png", np.zeros((12, 10, 3), np.uint8))
    with pytest.raises(UserError, match="b.png"):
        F.read_frames(tmp_path)


# -- split and cache ------------------------------------------------------------------


def test_hosnerf_split_holds_out_16_uniform_frames_for_long_clips():
    s = hosnerf_split(40)
    assert s["test"] == [2 * i for i in range(16)]
    assert sorted(s["train"] + s["test"]) == list(range(40))


def test_short_clips_hold_out_every_fourth_frame_and_keep_tiny_clips_for_training():
    assert hosnerf_split(12) == {"train": [0, 1, 3, 4, 5, 7, 8, 9, 11], "test": [2, 6, 10]}
    assert hosnerf_split(2) == {"train": [0, 1], "test": []}


def test_cache_returns_a_step_only_while_its_key_matches(tmp_path):
    c = Cache(tmp_path)
    k1 = c.key("frames", {"stride": 1}, [])
    c.save("frames", k1, {"x": np.arange(3)}, {"summary": "s"}, compress=True)
    arrays, meta = c.load("frames", k1)
    assert arrays["x"].tolist() == [0, 1, 2] and meta["summary"] == "s"
    assert c.load("frames", c.key("frames", {"stride": 2}, [])) is None
    c.keys["frames"] = k1
    k_dep = c.key("persons", {}, ["frames"])
    c.keys["frames"] = k1 + "changed"
    assert c.key("persons", {}, ["frames"]) != k_dep  # an upstream change invalidates
    assert Cache(tmp_path, force=True).load("frames", k1) is None


def test_a_recomputed_step_invalidates_the_steps_that_read_it(tmp_path):
    from types import SimpleNamespace

    from cogs.preprocess.pipeline import _Progress, _Runner

    runner = _Runner(SimpleNamespace(out=tmp_path, force=False))
    ui = _Progress(enabled=False)
    calls = []

    def compute(name):
        return lambda label: (calls.append(name) or {"x": np.zeros(1)}, {})

    for _ in range(2):
        runner.cache.keys.clear()
        runner._step(ui, 1, "a", {}, [], compute("a"))
        runner._step(ui, 2, "b", {}, ["a"], compute("b"))
    assert calls == ["a", "b"]  # the second pass is all cached
    (runner.cache.root / "a.json").unlink()  # step a lost: recomputed with the same options
    runner.cache.keys.clear()
    runner._step(ui, 1, "a", {}, [], compute("a"))
    runner._step(ui, 2, "b", {}, ["a"], compute("b"))
    assert calls == ["a", "b", "a", "b"]


# -- objects --------------------------------------------------------------------------


def _object_clip(T=8, H=120, W=160):
    """A textured background, a 'person' bar and an orange disc that moves and passes it."""
    bg = _texture(H, W, seed=1) // 2 + 60
    yy, xx = np.mgrid[:H, :W]
    images, obj, person = [], [], []
    for t in range(T):
        im = bg.copy()
        pm = (np.abs(xx - 80) < 12) & (yy > 20)
        im[pm] = (90, 60, 140)
        cx, cy = 30 + 12 * t, 60 + 10 * np.sin(t)
        om = (xx + 0.5 - cx) ** 2 + (yy + 0.5 - cy) ** 2 < 11**2
        im[om] = (235, 120, 30)
        images.append(im)
        obj.append(om)
        person.append(pm & ~om)
    return np.stack(images), np.stack(obj), np.stack(person)


def test_object_masks_follow_a_moving_object_from_one_box():
    images, gt, person = _object_clip()
    k = 3
    ys, xs = np.nonzero(gt[k])
    box = np.array([xs.min() - 3, ys.min() - 3, xs.max() + 4, ys.max() + 4], float)
    prompt, _ = O.grabcut_box(images[k], box)
    assert _iou(prompt, gt[k]) > 0.85
    masks, conf = O.propagate_masks(images, prompt, k, human_probs=(person * 255).astype(np.uint8))
    ious = [_iou(masks[t], gt[t]) for t in range(len(images))]
    assert min(ious) > 0.8, ious
    assert (conf > 0).all()


def test_frames_larger_than_the_track_side_are_tracked_shrunk_and_their_masks_come_back_at_full_size():
    import cv2

    small, gt_small, person_small = _object_clip()
    T, h, w, _ = small.shape
    images = np.stack([cv2.resize(f, (2 * w, 2 * h), interpolation=cv2.INTER_LINEAR) for f in small])
    gt = np.stack([cv2.resize(m.astype(np.uint8), (2 * w, 2 * h), interpolation=cv2.INTER_NEAREST) > 0 for m in gt_small])
    probs = np.stack([cv2.resize(m.astype(np.uint8) * 255, (2 * w, 2 * h), interpolation=cv2.INTER_NEAREST) for m in person_small])
    k = 3
    ys, xs = np.nonzero(gt[k])
    prompt, _ = O.grabcut_box(images[k], np.array([xs.min() - 6, ys.min() - 6, xs.max() + 8, ys.max() + 8], float))
    still: dict = {}
    masks, conf = O.track(images, {k: prompt}, side=w, human_probs=probs, still=still)
    assert masks.shape == gt.shape and (conf > 0).all()
    ious = [_iou(masks[t], gt[t]) for t in range(T)]
    assert min(ious) > 0.8, ious
    assert set(still) == {k}
    # Frames no larger than the side are tracked as they are.
    same, same_conf = O.track(images, {k: prompt}, side=2 * w, human_probs=probs)
    ref, ref_conf = O.propagate_masks(images, prompt, k, human_probs=probs)
    assert (same == ref).all() and np.array_equal(same_conf, ref_conf)


def test_a_doubtful_run_is_tracked_again_from_the_clear_view_after_it():
    # A forward track left the disc for a look-alike patch of background on frames 5-6
    # (found with little confidence) and found the disc again, clearly, on frame 7. The
    # pass back from frame 7 follows the disc: its clear masks replace the wrong ones. A
    # doubtful run on the disc itself (2-3) agrees with that pass and is left alone, and
    # so is a doubtful run with no clear view after it (the clip's last frame).
    from cogs.preprocess.tracking import _Tracker, cross_check

    images, gt, person = _object_clip(T=10)
    T = len(images)
    wrong = np.zeros_like(gt[0])
    wrong[10:30, 120:140] = True
    masks, conf = gt.copy(), np.ones(T)
    found = ["prompt"] + ["flow"] * (T - 1)
    masks[5:7] = wrong
    conf[[2, 3, 5, 6, 9]] = 0.5
    masks[9] = wrong
    tracker = _Tracker(images, None, None, (person * 255).astype(np.uint8), None, 0.5, 0.1, 0.5, 4, prompts={0: gt[0]})
    changed = cross_check(tracker, masks, conf, found, [0] * T, np.ones(T, int))
    assert changed == [5, 6]
    assert all(_iou(masks[t], gt[t]) > 0.8 and conf[t] >= 0.8 for t in (5, 6)), [_iou(masks[t], gt[t]) for t in (5, 6)]
    assert (masks[[2, 3]] == gt[[2, 3]]).all() and (conf[[2, 3]] == 0.5).all()
    assert (masks[9] == wrong).all() and conf[9] == 0.5


def test_object_is_reported_lost_while_hidden():
    images, gt, person = _object_clip()
    images[5][gt[5]] = images[4][~gt[4]].mean(0).astype(np.uint8)  # frame 5: disc painted over
    ys, xs = np.nonzero(gt[0])
    prompt, _ = O.grabcut_box(images[0], np.array([xs.min() - 3, ys.min() - 3, xs.max() + 4, ys.max() + 4], float))
    masks, conf = O.propagate_masks(images, prompt, 0)
    assert not masks[5].any() and conf[5] == 0
    assert _iou(masks[6], gt[6]) > 0.8  # and found again after


def test_resemblance_to_the_prompt_caps_confidence_on_pixels_that_are_not_its_colours():
    """The tracker's confidence in a frame is capped by how much the found pixels look
    like the prompt's object under the prompt's own colour model (never adapted): the
    object itself scores about 1, a patch of the scene a drifting track could end on
    scores near 0, half of each lies between."""
    from cogs.preprocess.tracking import _Tracker

    images, gt, person = _object_clip()
    tracker = _Tracker(images, None, None, (person * 255).astype(np.uint8), None, 0.5, 0.1, 0.5, 4, prompts={0: gt[0]})
    on_object = tracker.resemblance(5, gt[5])
    scene = np.roll(gt[5], 40, axis=0) & ~gt[5] & ~person[5]
    on_scene = tracker.resemblance(5, scene)
    half = tracker.resemblance(5, gt[5] | np.roll(gt[5], 22, axis=1))
    assert on_object > 0.9 and on_scene < 0.2 and on_scene < half < on_object, (on_object, half, on_scene)
    assert tracker.resemblance(5, np.zeros_like(gt[5])) == 0.0


def _square(H, W, cx, cy, half, angle_deg=0.0):
    yy, xx = np.mgrid[:H, :W]
    a = np.radians(angle_deg)
    u = (xx + 0.5 - cx) * np.cos(a) + (yy + 0.5 - cy) * np.sin(a)
    v = -(xx + 0.5 - cx) * np.sin(a) + (yy + 0.5 - cy) * np.cos(a)
    return (np.abs(u) <= half) & (np.abs(v) <= half)


def _hand_keypoints(T, wrist, direction=(1.0, 0.0), palm=10.0):
    """[T, 33, 3] MediaPipe-like keypoints with only the right arm's hand visible: wrist at
    ``wrist[t]``, knuckles one palm length along ``direction``."""
    kp = np.full((T, 33, 3), np.nan)
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    n = np.array([-d[1], d[0]])
    for t in range(T):
        w = np.asarray(wrist[t], float)
        kp[t, 14] = [*(w - 3 * palm * d), 1.0]  # elbow
        kp[t, 16] = [*w, 1.0]  # wrist
        kp[t, 18] = [*(w + palm * d - 0.4 * palm * n), 1.0]  # pinky
        kp[t, 20] = [*(w + palm * d + 0.4 * palm * n), 1.0]  # index
        kp[t, 22] = [*(w + 0.5 * palm * d + 0.7 * palm * n), 1.0]  # thumb
    return kp


def test_align_mask_fits_a_shifted_and_turned_object_and_says_so():
    from cogs.preprocess.tracking import align_mask

    H, W = 120, 160
    before = _square(H, W, 70, 60, 15)
    after = _square(H, W, 78, 55, 15, angle_deg=12)
    moved, cc = align_mask(before, after.astype(np.float32))
    assert _iou(moved, after) > 0.85 and cc > 0.9
    flat, cc_flat = align_mask(before, np.full((H, W), 0.5, np.float32))
    assert flat is None and cc_flat == 0.0  # nothing object-like: no fit to trust


def test_features_find_a_textured_object_after_a_jump_flow_cannot_follow():
    from cogs.preprocess.tracking import FeatureBank, warp_mask_by_flow

    H, W = 160, 240
    bg = (_texture(H, W, seed=4) // 4 + 90).astype(np.uint8)
    tex = _texture(H, W, seed=5)
    m0 = _square(H, W, 60, 80, 22)
    m1 = _square(H, W, 170, 70, 22)  # 110 px further in one frame
    f0, f1 = bg.copy(), bg.copy()
    f0[m0] = tex[m0]
    f1[m1] = np.roll(np.roll(tex, 110, axis=1), -10, axis=0)[m1]
    images = np.stack([f0, f1])
    bank = FeatureBank(images)
    bank.add(0, m0)
    warped, inliers = bank.match(1)
    assert _iou(warped, m1) > 0.85 and inliers >= 5
    assert _iou(warp_mask_by_flow(f0, f1, m0)[0], m1) < 0.5


def test_hand_regions_cover_the_fingers_but_not_the_forearm_far_away():
    from cogs.preprocess.tracking import hand_regions

    kp = _hand_keypoints(1, [(50, 60)], palm=10)[0]
    hr = hand_regions(kp, (120, 160))
    assert hr[60, 50] and hr[60, 65] and hr[60, 69]  # wrist, knuckles, finger tips
    assert not hr[60, 25] and not hr[60, 85]  # forearm, beyond the tips
    kp[16, 2] = 0.1  # a hidden hand covers nothing
    assert not hand_regions(kp, (120, 160)).any()


def test_a_convex_objects_mask_keeps_the_pieces_inside_its_outline_and_drops_the_others():
    from cogs.preprocess.tracking import drop_stray_pieces

    H, W = 120, 160
    yy, xx = np.mgrid[:H, :W]
    ball = (xx - 60) ** 2 + (yy - 50) ** 2 <= 15**2
    split = ball & ~(np.abs(xx - 62) <= 2)  # an arm in front: two halves
    kept = drop_stray_pieces(split, ball.sum())
    assert (kept == split).all()
    shoe = (np.abs(xx - 70) <= 12) & (np.abs(yy - 95) <= 5)  # carried along from a touch
    kept = drop_stray_pieces(ball | shoe, ball.sum())
    assert (kept == ball).all()
    assert (drop_stray_pieces(ball, ball.sum()) == ball).all()


def test_a_prompt_whose_surroundings_share_its_colours_is_warned_about():
    from cogs.preprocess.prompts import MAX_LOOKALIKE_SURROUNDINGS, parse_prompts, lookalike_prompt_warning

    images, gt, person = _object_clip()
    share = {}
    O.propagate_masks(images, gt[0], 0, human_probs=(person * 255).astype(np.uint8), lookalike=share)
    assert share[0] < 0.05  # an orange disc on a grey texture
    # A pale object on a floor of its own greys: most of what surrounds it looks like it.
    floor = np.random.default_rng(1).integers(120, 200, size=images.shape[1:3])[..., None].repeat(3, -1)
    pale = images.copy()
    pale[:] = floor
    pale[gt] = np.random.default_rng(2).integers(150, 215, size=(int(gt.sum()), 1)).repeat(3, -1)
    share = {}
    O.propagate_masks(pale[:2], gt[0], 0, lookalike=share)
    assert share[0] > 2 * MAX_LOOKALIKE_SURROUNDINGS
    prompt = parse_prompts((0, 10, 20, 30, 40), None, None)[0][0]
    assert lookalike_prompt_warning(prompt, 0.05) is None
    text = lookalike_prompt_warning(prompt, share[0])
    assert "--object-box 0 10 20 30 40" in text and "frame 0" in text and "--sam2-checkpoint" in text


def test_a_box_where_nothing_stands_out_is_tracked_as_its_ellipse_and_warned_about():
    from cogs.preprocess.prompts import guessed_prompt_warning, parse_prompts

    images, gt, _ = _object_clip()
    ys, xs = np.nonzero(gt[0])
    box = np.array([xs.min() - 3, ys.min() - 3, xs.max() + 4, ys.max() + 4], float)
    mask, guessed = O.grabcut_box(images[0], box)
    assert not guessed and _iou(mask, gt[0]) > 0.85
    # The disc painted over with the background's texture: nothing in the box stands out.
    bare = images[0].copy()
    bare[gt[0]] = np.roll(images[0], 40, axis=1)[gt[0]]
    mask, guessed = O.grabcut_box(bare, box)
    area = (box[2] - box[0]) * (box[3] - box[1])
    assert guessed and abs(mask.sum() - np.pi / 4 * area) < 0.1 * area
    prompt = parse_prompts((0, 10, 20, 30, 40), None, None)[0][0]
    text = guessed_prompt_warning(prompt)
    assert "--object-box 0 10 20 30 40" in text and "frame 0" in text and "--sam2-checkpoint" in text


def test_a_prompt_whose_mask_runs_along_its_box_is_warned_about_naming_the_side():
    from cogs.preprocess.prompts import MAX_EDGE_RUN, edge_prompt_warning, edge_run, parse_prompts

    images, gt, _ = _object_clip()
    ys, xs = np.nonzero(gt[0])
    prompt = parse_prompts((0, 10, 20, 30, 40), None, None)[0][0]
    roomy = np.array([xs.min() - 3, ys.min() - 3, xs.max() + 4, ys.max() + 4], float)
    side, share, _ = edge_run(O.grabcut_box(images[0], roomy)[0], roomy)
    assert share < 0.1 and edge_prompt_warning(prompt, side, share, False) is None
    cut = roomy.copy()
    cut[2] = xs.mean() + 4  # through the disc: its mask runs along the box's right side
    side, share, on_edge = edge_run(O.grabcut_box(images[0], cut)[0], cut)
    assert side == "right" and share > MAX_EDGE_RUN and not on_edge
    text = edge_prompt_warning(prompt, side, share, on_edge)
    assert text.startswith(f"--object-box 0 10 20 30 40: the object's mask on frame 0 runs along {share:.0%} of the box's right side: "
                           "the box cuts the object there")
    assert "Draw the box a little larger than the object" in text and "--object-negative-box" in text
    # The disc half out of the frame, the box on the frame's edge.
    shifted = np.roll(images[0], images.shape[2] - int(xs.mean()), axis=1)
    W = images.shape[2]
    edge_box = np.array([W - (xs.max() - xs.min()) // 2 - 6, ys.min() - 3, W, ys.max() + 4], float)
    side, share, on_edge = edge_run(O.grabcut_box(shifted, edge_box)[0], edge_box)
    assert side == "right" and share > MAX_EDGE_RUN and on_edge
    text = edge_prompt_warning(prompt, side, share, on_edge)
    assert "of the box's right side, the frame's edge: the object leaves the frame there" in text
    assert "Prompt a frame where the object is whole in view" in text


def test_a_body_laid_on_the_object_itself_is_warned_about_naming_the_frames_and_the_remedy():
    from cogs.preprocess.persons import body_on_object, body_on_object_warning

    T, H, W = 10, 120, 160
    yy, xx = np.mgrid[:H, :W]
    masks = np.stack([(xx - 80) ** 2 + (yy - 60) ** 2 < 30**2] * T)  # a round object in the middle
    rng = np.random.default_rng(0)
    beside = np.zeros((T, 33, 3))
    beside[..., 0], beside[..., 1], beside[..., 2] = rng.uniform(120, 155, (T, 33)), rng.uniform(5, 115, (T, 33)), 0.9
    beside[:, :8, :2] = [80, 60]  # the hands and wrists on the object, the rest off it: a person holding it
    assert body_on_object(beside, masks) == ([], T) and body_on_object_warning(beside, masks) is None
    on = beside.copy()
    on[2:, :, 0], on[2:, :, 1] = rng.uniform(65, 95, (T - 2, 33)), rng.uniform(45, 75, (T - 2, 33))  # a doll
    on[5, :, 2] = 0.1  # a frame without a body is not judged
    frames, judged = body_on_object(on, masks)
    assert frames == [2, 3, 4, 6, 7, 8, 9] and judged == T - 1
    text = body_on_object_warning(on, masks)
    assert text.startswith("the body MediaPipe found lies on the object in 7 of the 9 frames with both (frames 2, 3, 4, 6, 7, 8, 9)")
    assert "--person-box FRAME X0 Y0 X1 Y1" in text


def _kicked_ball_clip(T=10, H=160, W=160):
    """Grass, a leg (person) ending in a white shoe, and a white ball with dark spots that
    drops onto the shoe (frames 3-4) and flies back up; MediaPipe-like keypoints on the
    right foot (ankle, heel, toe)."""
    ys = (60, 85, 108, 124, 127, 100, 72, 50, 40, 36)
    bg = (_texture(H, W, seed=4) // 3 + np.array([40, 90, 30])).clip(0, 255).astype(np.uint8)
    yy, xx = np.mgrid[:H, :W]
    leg = (np.abs(xx - 80) < 9) & (yy > 30) & (yy < 132)
    shoe = ((xx + 0.5 - 82) / 14) ** 2 + ((yy + 0.5 - 138) / 7) ** 2 <= 1
    images, gt, person = [], [], []
    kp = np.full((T, 33, 3), np.nan)
    for t in range(T):
        im = bg.copy()
        im[leg], im[shoe] = (30, 35, 70), (240, 240, 240)
        ball = (xx + 0.5 - 80) ** 2 + (yy + 0.5 - ys[t]) ** 2 <= 10**2
        im[ball] = (245, 245, 245)
        im[ball & (((xx - 80) // 4 + (yy - ys[t]) // 4) % 3 == 0)] = (60, 60, 60)
        images.append(im)
        gt.append(ball)
        person.append((leg | shoe) & ~ball)
        kp[t, [28, 30, 32]] = [[80, 131, 1.0], [69, 139, 1.0], [96, 140, 1.0]]
    return np.stack(images), np.stack(gt), (np.stack(person) * 255).astype(np.uint8), kp


def test_a_ball_kicked_off_a_shoe_of_its_colour_is_followed_not_the_shoe(monkeypatch):
    from cogs.preprocess.tracking import _Tracker

    images, gt, person, kp = _kicked_ball_clip()
    masks, conf = O.propagate_masks(images, gt[0], 0, human_probs=person, kp2d=kp)
    assert min(_iou(masks[t], gt[t]) for t in (5, 6, 7)) > 0.8
    # Without the feet the track stays on the shoe as the ball flies off.
    monkeypatch.setattr(_Tracker, "_feet_mask", lambda self, t: np.zeros(self.images.shape[1:3], bool))
    masks, _ = O.propagate_masks(images, gt[0], 0, human_probs=person, kp2d=kp)
    assert _iou(masks[5], gt[5]) < 0.2


def test_grabcut_spreading_from_a_ball_onto_the_shoe_it_touches_is_cut_back():
    """What GrabCut adds to a fitted ball on a foot, beyond a few pixels of the ball, is not
    the ball (a white ball touching a white shoe); what it adds elsewhere stays, and without
    keypoints nothing is cut."""
    from cogs.preprocess.tracking import FOOT_MARGIN, _Tracker, foot_regions

    images, gt, person, kp = _kicked_ball_clip()
    t = 3
    H, W = gt.shape[1:]
    yy, xx = np.mgrid[:H, :W]
    shoe = ((xx + 0.5 - 82) / 14) ** 2 + ((yy + 0.5 - 138) / 7) ** 2 <= 1
    ball = (xx + 0.5 - 80) ** 2 + (yy + 0.5 - 120) ** 2 <= 10**2  # touching the shoe's top
    bulge = (np.abs(xx - 66) <= 3) & (np.abs(yy - 118) <= 3)  # off the feet, beside the ball
    feet = foot_regions(kp[t], (H, W))
    assert (shoe & ~ball).sum() > 200 and (shoe & ~feet).sum() == 0 and not (bulge & feet).any()
    seg = ball | shoe | bulge
    tracker = _Tracker(images, gt[0], 0, person, kp, 0.5, 0.1, 0.5, 4)
    out = tracker._off_the_feet(t, seg, ball)
    assert (out & ball).sum() == ball.sum() and (out & bulge).sum() == bulge.sum()
    margin = int(np.ceil(FOOT_MARGIN * 20)) + 1  # the ball's size is 20 px
    dist = np.sqrt((xx + 0.5 - 80) ** 2 + (yy + 0.5 - 120) ** 2) - 10
    assert not (out & shoe & (dist > margin)).any()
    assert (shoe & ~ball & (dist > margin)).sum() > 150  # there was a shoe to cut
    blind = _Tracker(images, gt[0], 0, person, None, 0.5, 0.1, 0.5, 4)
    assert (blind._off_the_feet(t, seg, ball) == seg).all()


def test_a_foot_seen_end_on_covers_its_shoe_sized_from_the_shin():
    """A foot pointing at the camera shows heel and toe 3 px apart: its region still takes
    in the shoe (sized from the knee-to-ankle length), unless the knee is not visible; a
    foot seen side-on, longer than that, is sized by heel and toe as before."""
    from cogs.preprocess.tracking import FOOT_SHIN_SHARE, foot_regions

    H, W = 120, 120
    yy, xx = np.mgrid[:H, :W]
    kp = np.full((33, 3), np.nan)
    kp[25] = (60, 40, 1.0)  # left knee, 40 px above the ankle
    kp[[27, 29, 31]] = [(60, 80, 1.0), (60, 84, 1.0), (61, 87, 1.0)]  # ankle, heel, toe
    shoe = ((xx + 0.5 - 60) / 6) ** 2 + ((yy + 0.5 - 87) / 4) ** 2 <= 1  # the shoe's width and sole
    region = foot_regions(kp, (H, W))
    assert (shoe & ~region).sum() == 0
    assert region.sum() < 4 * (FOOT_SHIN_SHARE * 40) ** 2  # a foot's size, not the leg's
    unseen_knee = kp.copy()
    unseen_knee[25, 2] = 0.2
    assert (shoe & ~foot_regions(unseen_knee, (H, W))).sum() > 0.5 * shoe.sum()
    side_on = kp.copy()
    side_on[31] = (85, 86, 1.0)  # toe 25 px from the heel: longer than the shin's share
    no_knee = side_on.copy()
    no_knee[25] = np.nan
    assert (foot_regions(side_on, (H, W)) == foot_regions(no_knee, (H, W))).all()


def _held_object_clip(T=8, H=180, W=200, new_face_from=None, hidden=(), speed=9, decoy=None, pan=0, decoy_colour=(40, 170, 60),
                      decoy_from=0):
    """A textured background with a blue strip at the bottom, an arm (person) reaching in
    from the left, its hand holding an orange square by the left side and carrying it to
    the right (``speed`` pixels a frame); from frame ``new_face_from`` on the square shows
    another face, blue (the strip's colour) with yellow stripes; in ``hidden`` frames it
    is out of view. MediaPipe-like, the person mask holds the arm but misses the
    fingers. ``decoy`` (x, y): a square of the object's size painted on the background
    there, green unless ``decoy_colour`` says otherwise, in view from frame ``decoy_from`` on. ``pan``: the camera turns so the background slides ``pan`` pixels
    a frame to the left (the person and the object move in the image as before)."""
    Wb = W + pan * T
    big = (_texture(H, Wb, seed=6) // 3 + 100).astype(np.uint8)
    big[150:] = (40, 60, 200)
    plain = big.copy()
    if decoy is not None:
        big[_square(H, Wb, *decoy, 14)] = decoy_colour
    yy, xx = np.mgrid[:H, :W]
    images, obj, hands_gt, person = [], [], [], []
    wrists = []
    for t in range(T):
        wx, wy = 40 + speed * t, 70
        wrists.append((wx, wy))
        im = (big if t >= decoy_from else plain)[:, pan * t : pan * t + W].copy()
        om = _square(H, W, wx + 24, wy, 14) if t not in hidden else np.zeros((H, W), bool)
        if new_face_from is not None and t >= new_face_from:
            im[om] = (40, 60, 200)
            im[om & ((xx // 6) % 2 == 0)] = (230, 210, 40)
        else:
            im[om] = (235, 120, 30)
        arm = (np.abs(yy - wy) <= 5) & (xx <= wx)
        fingers = (np.abs(yy - wy) <= 4) & (xx > wx) & (xx <= wx + 17)  # over the object's left part
        im[arm] = (60, 70, 150)
        im[fingers] = (200, 160, 130)
        images.append(im)
        obj.append(om & ~fingers)
        hands_gt.append(fingers)
        person.append(arm)
    kp = _hand_keypoints(T, wrists, palm=9)
    return np.stack(images), np.stack(obj), np.stack(hands_gt), (np.stack(person) * 255).astype(np.uint8), kp


def test_fingers_closing_over_an_object_are_left_out_of_its_mask():
    # The hand arrives over a resting object; the person mask (like MediaPipe's, low
    # resolution) holds the arm but misses the fingers.
    T, H, W = 7, 140, 200
    bg = (_texture(H, W, seed=6) // 3 + 100).astype(np.uint8)
    yy, xx = np.mgrid[:H, :W]
    obj = _square(H, W, 110, 70, 18)
    images, gt, fingers, person, wrists = [], [], [], [], []
    for t in range(T):
        wx = min(30 + 14 * t, 84)
        wrists.append((wx, 70))
        im = bg.copy()
        im[obj] = (235, 120, 30)
        arm = (np.abs(yy - 70) <= 5) & (xx <= wx)
        fing = (np.abs(yy - 70) <= 4) & (xx > wx) & (xx <= wx + 17)
        im[arm] = (60, 70, 150)
        im[fing] = (200, 160, 130)
        images.append(im)
        gt.append(obj & ~fing)
        fingers.append(fing & obj)
        person.append(arm)
    images, gt, fingers = np.stack(images), np.stack(gt), np.stack(fingers)
    kp = _hand_keypoints(T, wrists, palm=9)
    masks, _ = O.propagate_masks(images, gt[0], 0, human_probs=(np.stack(person) * 255).astype(np.uint8), kp2d=kp)
    assert fingers[-1].sum() >= 80  # the fingers do cover the object at the end
    for t in range(1, T):
        assert _iou(masks[t], gt[t]) > 0.85, t
        assert (masks[t] & fingers[t]).sum() <= 0.2 * fingers[t].sum(), t


@pytest.mark.parametrize("person_known, cue", [(True, "moving"), (False, "hand")])
def test_a_carried_object_that_turns_a_new_face_is_found_again_at_its_hand(person_known, cue):
    # Hidden for two frames, it comes back further along in colours the colour model
    # counts as background: only the hand that carried it says where it is. With the
    # person's mask, what moves there and is not the person is the object; without it
    # (no static scene to compare with), GrabCut next to the hand finds it.
    images, gt, _, person, kp = _held_object_clip(T=9, new_face_from=5, hidden=(3, 4), speed=14)
    cues = []
    masks, _ = O.propagate_masks(images, gt[0], 0, human_probs=person if person_known else None, kp2d=kp, cues=cues)
    assert not masks[3].any() and not masks[4].any()
    assert cues[5] == cue, cues
    for t in range(5, 9):
        assert _iou(masks[t], gt[t]) > 0.7, (t, cues)


def test_a_carried_object_turned_to_other_colours_is_followed_where_it_moves(monkeypatch):
    # The hand's points lie 10 px above the object all along (the pose model's hand on a box
    # held by its far side), so it is never seen carried; from frame 8 on it shows a face in
    # the background's colours. The motion fit there no longer looks like the object, and
    # neither the colour search nor the hand finds it: what moves there and is not the
    # person is kept, at a confidence that says so. Without that, it is lost.
    from cogs.preprocess import tracking

    images, gt, _, person, kp = _held_object_clip(T=12, new_face_from=8, speed=9)
    kp[:, :, 1] -= 24
    hands = tracking.hand_points(kp)
    assert all(tracking.carrying_hand(hands, t, t + 1, gt[t], gt[t + 1]) is None for t in range(11))
    masks, conf = O.propagate_masks(images, gt[0], 0, human_probs=person, kp2d=kp)
    for t in range(8, 12):
        assert _iou(masks[t], gt[t]) > 0.7 and 0 < conf[t] <= 0.5, t
    monkeypatch.setattr(tracking, "MOVING_FIT_SHARE", 2.0)  # never: lost from the turn on
    masks, _ = O.propagate_masks(images, gt[0], 0, human_probs=person, kp2d=kp)
    assert _iou(masks[7], gt[7]) > 0.9 and not masks[8:].any()


def test_a_carried_object_turning_to_the_scenes_colours_keeps_the_trust_its_hand_carried_it_with(monkeypatch):
    # Carried by its hand, the square turns: at frame 7 its right half shows a face striped
    # in the background's blue and grey, from 8 on all of it. The motion fit follows it
    # frame after frame, but its colours no longer resemble the prompt's (0.01 of its
    # evidence). Carried without a break from a trusted frame, it keeps that frame's trust
    # (never more than the fit's own), so it supervises the object; without the rule it
    # is below the trusted threshold from 8 on.
    from cogs.branches.object import ObjectConfig
    from cogs.preprocess import tracking

    T = 12
    images, gt, _, person, kp = _held_object_clip(T=T, speed=9)
    xx = np.mgrid[: images.shape[1], : images.shape[2]][1]
    for t in range(7, T):
        face = gt[t] & (xx >= np.nonzero(gt[t])[1].mean()) if t == 7 else gt[t]
        images[t][face] = (40, 60, 200)
        images[t][face & ((xx // 4) % 2 == 0)] = (140, 140, 140)
    trusted = ObjectConfig().min_confidence
    cues = []
    masks, conf = O.propagate_masks(images, gt[0], 0, human_probs=person, kp2d=kp, cues=cues)
    for t in range(8, T):
        assert _iou(masks[t], gt[t]) > 0.5 and cues[t] in tracking.CARRIED_TRUST_CUES, (t, cues[t])
        assert trusted <= conf[t] <= conf[t - 1], (t, conf[t - 1], conf[t])
    monkeypatch.setattr(tracking, "CARRIED_TRUST_CUES", ())
    masks, conf = O.propagate_masks(images, gt[0], 0, human_probs=person, kp2d=kp)
    assert all(_iou(masks[t], gt[t]) > 0.5 and 0 < conf[t] < trusted for t in range(8, T)), conf


def test_a_carried_object_back_in_view_is_judged_against_the_frames_it_was_lost_in(monkeypatch):
    # Carried, out of view for three frames, during which the camera's exposure jumps by 40
    # grey levels, then back with a face in the background's colours. Against the frames
    # that found it (4 and 8 back) every pixel differs: the residual noise is far above a
    # working warp's, everything would be called static scene, the object too, and nothing
    # finds it. The frames it was lost in show the scene as it now looks.
    from cogs.preprocess import tracking

    images, gt, _, person, kp = _held_object_clip(T=14, new_face_from=11, hidden=(8, 9, 10), speed=3)
    images = np.clip(images.astype(np.int16) + 40 * (np.arange(14) >= 8)[:, None, None, None], 0, 255).astype(np.uint8)
    masks, conf = O.propagate_masks(images, gt[0], 0, human_probs=person, kp2d=kp)
    assert not masks[8:11].any()
    assert _iou(masks[11], gt[11]) > 0.9
    for t in (12, 13):
        assert _iou(masks[t], gt[t]) > 0.7 and conf[t] > 0, t
    monkeypatch.setattr(tracking, "LOST_REFS", 100)  # only the frames that found it: lost for good
    masks, _ = O.propagate_masks(images, gt[0], 0, human_probs=person, kp2d=kp)
    assert not masks[11:].any()


def _carried_out_of_view_while_a_look_alike_appears():
    """``_held_object_clip``'s square carried for three frames, then out of view for six
    while a square of its very colours comes into view on the far wall, then back in the
    hand -> (images, object masks, keypoints, the look-alike's mask)."""
    images, gt, _, _, kp = _held_object_clip(T=12, hidden=tuple(range(3, 9)), speed=4, decoy=(170, 25),
                                             decoy_colour=(235, 120, 30), decoy_from=5)
    return images, gt, kp, _square(*images.shape[1:3], 170, 25, 14)


def test_an_object_lost_while_carried_is_not_refound_where_no_hand_has_been(monkeypatch):
    # Carried, then out of view for longer than the hand cue waits (the body turned with
    # it), while a square of its very colours comes into view on the far wall (the camera
    # turned): that is not it. Without a person mask there is no static scene to rule the
    # wall out, so only the hands' path does.
    from cogs.preprocess import tracking

    images, gt, kp, decoy = _carried_out_of_view_while_a_look_alike_appears()
    masks, conf = O.propagate_masks(images, gt[0], 0, kp2d=kp)
    assert not (masks[3:9] & decoy).any()
    for t in range(9, 12):  # back in the hand: found again
        assert _iou(masks[t], gt[t]) > 0.7 and conf[t] > 0, t
    monkeypatch.setattr(tracking, "HAND_PATH_REACH", 1e6)  # anywhere: the wall's square is taken
    masks, _ = O.propagate_masks(images, gt[0], 0, kp2d=kp)
    assert (masks[3:9] & decoy).any()


def test_a_faint_look_alike_at_the_hand_is_not_taken_for_an_object_lost_for_longer_than_a_carry():
    # Carried, then out of view to the end of the clip. Five frames after the loss a square
    # of its colour shows up just below the hand, striped with the background over three
    # quarters of it (0.41 of the prompt's evidence): near a hand the colour search would
    # take 0.7x the evidence it asks elsewhere, but the object has been gone longer than a
    # carry is kept, so it asks the full evidence and finds nothing.
    from cogs.preprocess import tracking

    T, (x, y) = 12, (70, 92)
    images, gt, _, _, kp = _held_object_clip(T=T, hidden=tuple(range(3, T)), speed=4, decoy=(x, y),
                                             decoy_colour=(235, 120, 30), decoy_from=8)
    decoy = _square(*images.shape[1:3], x, y, 14)
    xx = np.mgrid[: images.shape[1], : images.shape[2]][1]
    stripes = decoy & (xx % 8 >= 2)
    images[8:, stripes] = images[0, stripes]
    hands = tracking.hand_points(kp)
    assert np.hypot(*(hands[8, 1, :2] - (x, y))) < 25  # next to the hand
    masks, conf = O.propagate_masks(images, gt[0], 0, kp2d=kp)
    assert _iou(masks[2], gt[2]) > 0.85 and conf[2] > 0
    assert not masks[3:].any() and not conf[3:].any()


def test_a_hand_point_off_a_clearly_seen_carried_object_does_not_end_the_carry(monkeypatch):
    # As above, but on the last frame before the loss the hand's landmarks sit 10 px off
    # the object (a body turning away, whose hands the pose model places loosely): the
    # object is clearly seen there, next to the hand, and is still carried.
    from cogs.preprocess import tracking

    images, gt, kp, decoy = _carried_out_of_view_while_a_look_alike_appears()
    kp[2, :, 1] -= 24  # the hand point 10 px above the object's top edge
    hands = tracking.hand_points(kp)
    assert tracking.carrying_hand(hands, 1, 2, gt[1], gt[2]) is None  # the carry test alone lets go here
    masks, conf = O.propagate_masks(images, gt[0], 0, kp2d=kp)
    assert _iou(masks[2], gt[2]) > 0.85 and conf[2] >= 0.8
    assert not (masks[3:9] & decoy).any()
    for t in range(9, 12):
        assert _iou(masks[t], gt[t]) > 0.7 and conf[t] > 0, t
    monkeypatch.setattr(tracking, "HAND_NEAR", 0.0)  # any clear view away from the carry ends it: the square is taken
    masks, _ = O.propagate_masks(images, gt[0], 0, kp2d=kp)
    assert (masks[3:9] & decoy).any()


def test_a_carried_object_taken_over_by_the_other_hand_is_still_carried():
    # As above, but the left hand comes to the object's right side and carries it from
    # the last frame before the loss on (a handover, or the pose model swapping left and
    # right on a body turning away): still carried, so the wall's square is not it.
    from cogs.preprocess import tracking

    images, gt, kp, decoy = _carried_out_of_view_while_a_look_alike_appears()
    T = len(images)
    for t in range(1, T):
        x = 40 + 4 * t + (43 if t == 1 else 38)  # 5 px off the object's right edge at 1, on it from 2 on
        kp[t, 13] = (x + 30, 70, 1.0)  # elbow
        kp[t, 15] = (x + 2.7, 70, 1.0)  # wrist: the hand point lands at x
        kp[t, 17], kp[t, 19], kp[t, 21] = (x - 1.3, 68, 1.0), (x - 1.3, 72, 1.0), (x, 73, 1.0)  # pinky, index, thumb
    kp[2, [14, 16, 18, 20, 22], 1] -= 24  # the right hand point 10 px off the object: that hand lets go
    hands = tracking.hand_points(kp)
    assert tracking.carrying_hand(hands, 0, 1, gt[0], gt[1]) == 1
    assert tracking.carrying_hand(hands, 1, 2, gt[1], gt[2]) == 0  # the carry passes to the left hand
    masks, conf = O.propagate_masks(images, gt[0], 0, kp2d=kp)
    assert not (masks[3:9] & decoy).any()
    for t in range(9, 12):
        assert _iou(masks[t], gt[t]) > 0.7 and conf[t] > 0, t


def test_a_look_alike_in_the_static_scene_is_not_taken_for_an_object_lost_for_long():
    # Out of view for 14 frames; a square of its colours hangs on the wall throughout.
    # Long after the loss no frame the pass found it in lies at the static-scene offsets,
    # yet the last one still shows the square as scene (no hands known here: only the
    # static scene can rule it out). Found again where it comes back.
    T = 20
    images, gt, _, person, _ = _held_object_clip(T=T, hidden=tuple(range(3, 17)), speed=3, decoy=(170, 25),
                                                 decoy_colour=(235, 120, 30))
    decoy = _square(*images.shape[1:3], 170, 25, 14)
    masks, conf = O.propagate_masks(images, gt[0], 0, human_probs=person)
    assert not (masks & decoy).any()
    assert _iou(masks[17], gt[17]) > 0.7 and conf[17] > 0


def test_an_object_prompted_in_a_hand_is_followed_with_that_hand_when_it_turns_at_once():
    # The fingers close over the prompt, and from the next frame on it shows a face in the
    # background's colours: nothing but the hand says where it went (a transparent bottle
    # shows whatever is behind it). Without the prompt's hand it is lost for good.
    from cogs.preprocess.tracking import holding_hand

    images, gt, fingers, person, kp = _held_object_clip(T=6, new_face_from=1, speed=14)
    assert holding_hand(kp, 0, gt[0]) == 1  # the right hand's fingers are over it
    masks, conf = O.propagate_masks(images, gt[0], 0, human_probs=person, kp2d=kp)
    for t in range(1, 6):
        assert _iou(masks[t], gt[t]) > 0.7 and conf[t] > 0, t


def _prompted_in_a_loose_hand(lifted: int):
    """``_held_object_clip`` played backwards: carried to the left, out of view in frames 5
    and 6, and before that (0-4) showing a face in the background's colours. The prompt is
    frame 7; there and on the ``lifted`` - 1 frames after it the hand's points sit 10 px
    above the object (the pose model's hand on a box held by its far side), so the prompt
    does not show the hand holding it."""
    images, gt, _, person, kp = _held_object_clip(T=11, new_face_from=6, hidden=(4, 5), speed=10)
    images, gt, person, kp = images[::-1].copy(), gt[::-1].copy(), person[::-1].copy(), kp[::-1].copy()
    kp[7 : 7 + lifted, :, 1] -= 24
    return images, gt, person, kp


def test_an_object_a_pass_sees_carried_from_its_prompt_is_carried_in_the_pass_the_other_way():
    # The pass forwards sees the hand carry the object from the frame after the prompt on; the
    # pass backwards starts from the same prompt carried by that hand, so once the object
    # is out of view and back with another face, the hand finds it.
    from cogs.preprocess import tracking

    images, gt, person, kp = _prompted_in_a_loose_hand(lifted=1)
    hands = tracking.hand_points(kp)
    assert tracking.holding_hand(kp, 7, gt[7]) is None and tracking.carrying_hand(hands, 7, 8, gt[7], gt[8]) is None
    assert tracking.carrying_hand(hands, 8, 9, gt[8], gt[9]) == 1
    masks, conf = O.propagate_masks(images, gt[7], 7, human_probs=person, kp2d=kp)
    for t in range(8, 11):
        assert _iou(masks[t], gt[t]) > 0.7, t
    assert not masks[5].any() and not masks[6].any()
    assert _iou(masks[4], gt[4]) > 0.4  # back in view: what moves at the hand
    for t in range(0, 4):
        assert _iou(masks[t], gt[t]) > 0.9 and conf[t] > 0, t
    # The hand off the object in every frame after the prompt: no pass sees it carried,
    # and the face in the background's colours is not found.
    images, gt, person, kp = _prompted_in_a_loose_hand(lifted=4)
    masks, _ = O.propagate_masks(images, gt[7], 7, human_probs=person, kp2d=kp)
    assert _iou(masks[8], gt[8]) > 0.7
    assert not masks[:5].any()


def test_a_hand_beside_an_object_does_not_hold_it():
    from cogs.preprocess.tracking import holding_hand

    H, W = 120, 160
    kp = _hand_keypoints(1, [(40, 60)], palm=10)
    near = _square(H, W, 85, 60, 12)  # starts a few pixels past the finger tips
    assert holding_hand(kp, 0, near) is None
    assert holding_hand(kp, 0, _square(H, W, 62, 60, 12)) == 1  # under the fingers
    kp[0, 16, 2] = 0.1  # a hand MediaPipe does not see holds nothing
    assert holding_hand(kp, 0, _square(H, W, 62, 60, 12)) is None
    assert holding_hand(None, 0, near) is None


def test_a_mask_that_cannot_be_told_from_its_surroundings_is_not_trusted():
    # The disc moves onto a wide patch of its own colour (a transparent bottle over the
    # floor it stood on): whatever the tracker keeps there, it is no evidence, and its
    # confidence drops below what supervises the object branch. Before, nothing changes.
    from cogs.branches.object import ObjectConfig
    from cogs.preprocess.tracking import UNCLEAR_CONFIDENCE, _Tracker

    T, H, W = 10, 120, 200
    bg = _texture(H, W, seed=1) // 2 + 60
    bg[:, 130:] = (235, 120, 30)
    yy, xx = np.mgrid[:H, :W]
    images, gt = [], []
    for t in range(T):
        im = bg.copy()
        om = (xx + 0.5 - (30 + 12 * t)) ** 2 + (yy + 0.5 - 60) ** 2 < 11**2
        im[om] = (235, 120, 30)
        images.append(im)
        gt.append(om)
    images, gt = np.stack(images), np.stack(gt)
    masks, conf = O.propagate_masks(images, gt[0], 0)
    assert (conf[1:6] >= 0.5).all() and all(_iou(masks[t], gt[t]) > 0.8 for t in range(1, 6)), conf
    assert (conf[9] <= UNCLEAR_CONFIDENCE) and UNCLEAR_CONFIDENCE < ObjectConfig().min_confidence, conf
    tracker = _Tracker(images, None, None, None, None, 0.5, 0.1, 0.5, 4, prompts={0: gt[0]})
    assert not tracker.unclear(3, gt[3])  # the whole disc on the texture stands out
    assert tracker.unclear(3, gt[3] & (np.abs(xx - 66) < 5) & (np.abs(yy - 60) < 5))  # a piece of its middle: the rest is all round it
    assert tracker.unclear(9, gt[9]) and not tracker.unclear(9, np.zeros_like(gt[9]))


def _transparent_bottle_clip(T=12, H=160, W=220, hand_at_it=True, let_go=None, tint=0.8):
    """A clear bottle carried up and to the right across a textured background, turning
    2 degrees a frame: inside its outline the background shows through (a little darker and
    shifted, as refraction does), and only its 2 px rim, darker still, outlines it. A
    right hand holds it by its left side, or (``hand_at_it`` False) moves along 60 px
    below it; from frame ``let_go`` on it leaves the bottle, 12 px further down a frame.
    -> (images, the bottle's masks, MediaPipe-like keypoints)."""
    bg = _texture(H, W, seed=4)
    seen_through = (tint * np.roll(bg, 3, axis=1)).astype(np.uint8)
    yy, xx = np.mgrid[:H, :W]
    images, gt, wrists = [], [], []
    for t in range(T):
        cx, cy, a = 50 + 10 * t, 100 - 3 * t, np.radians(2 * t)
        u = (xx + 0.5 - cx) * np.cos(a) + (yy + 0.5 - cy) * np.sin(a)
        v = -(xx + 0.5 - cx) * np.sin(a) + (yy + 0.5 - cy) * np.cos(a)
        inside = (np.abs(u) <= 9) & (np.abs(v) <= 22)
        rim = inside & ~((np.abs(u) <= 7) & (np.abs(v) <= 20))
        im = bg.copy()
        im[inside] = seen_through[inside]
        im[rim] = (0.35 * bg[rim]).astype(np.uint8)
        images.append(im)
        gt.append(inside)
        away = 0 if let_go is None or t < let_go else min(60, 12 * (t - let_go + 1))
        wrists.append((cx - 14, cy + away if hand_at_it else cy + 60))
    return np.stack(images), np.stack(gt), _hand_keypoints(T, wrists, palm=9)


def _bottle_beside_its_forearm(T=12):
    """``_transparent_bottle_clip`` with the forearm that holds the bottle drawn from the
    elbow to the wrist, as dark as the bottle's rim: the bottle's colour model (the rim,
    and the background it shows) finds the arm. -> (images, the bottle's masks,
    keypoints)."""
    images, gt, kp = _transparent_bottle_clip(T)
    H, W = gt.shape[1:]
    yy, xx = np.mgrid[:H, :W]
    for t in range(T):
        (ex, ey), (wx, wy) = kp[t, 14, :2], kp[t, 16, :2]
        arm = (xx >= ex) & (xx <= wx) & (np.abs(yy - wy) <= 4)
        images[t][arm] = (0.35 * images[t][arm]).astype(np.uint8)
    return images, gt, kp


def test_a_transparent_object_held_between_two_prompts_is_followed_by_its_outline():
    # Its colours are the background's, so the colour cues take patches of background for
    # it (trusted, too). Its outline still shows as an edge: between the two boxes the
    # prompts' outlines, followed by the edges, meet on it in the hand that holds it.
    from cogs.preprocess.outline import OUTLINE_CONFIDENCE

    images, gt, kp = _transparent_bottle_clip()
    T = len(images)
    cues = []
    masks, conf = O.propagate_masks(images, [gt[0], gt[-1]], [0, T - 1], kp2d=kp, cues=cues)
    for t in range(1, T - 1):
        assert cues[t] == "outline" and conf[t] == OUTLINE_CONFIDENCE and _iou(masks[t], gt[t]) > 0.75, (t, cues[t], _iou(masks[t], gt[t]))
    # The pose model unsure of the hand on one frame (its points' visibility under 0.5, as
    # when they jitter off the fingers): held on the frames either side, that frame takes
    # the outline too; on two frames running, neither does.
    for jitter in ((5,), (5, 6)):
        off = kp.copy()
        off[list(jitter), :, 2] = 0.2
        masks, conf = O.propagate_masks(images, [gt[0], gt[-1]], [0, T - 1], kp2d=off, cues=cues)
        took = [t for t in jitter if cues[t] == "outline" and _iou(masks[t], gt[t]) > 0.75]
        assert took == (list(jitter) if len(jitter) == 1 else []), (jitter, cues)
    # The progress bar, which counts the frames between two boxes twice (a pass from each)
    # and the outlines' fits, never goes back and ends on the last frame.
    bar = []
    O.propagate_masks(images, [gt[0], gt[3]], [0, 3], kp2d=kp, on_frame=bar.append)
    assert bar[-1] == T and all(b >= a for a, b in zip(bar, bar[1:])), bar
    # The same bottle with no hand at it: no outline is taken, and colour alone misses it.
    images, gt, kp = _transparent_bottle_clip(hand_at_it=False)
    masks, conf = O.propagate_masks(images, [gt[0], gt[-1]], [0, T - 1], kp2d=kp, cues=cues)
    assert "outline" not in cues
    assert min(_iou(masks[t], gt[t]) for t in range(1, T - 1)) < 0.5


def test_outlines_from_two_prompts_bridge_them_only_where_they_meet_in_a_hand():
    from cogs.preprocess.outline import bridge

    images, gt, kp = _transparent_bottle_clip()
    T = len(images)
    shapes, switch, agree = bridge(images, gt[0], 0, gt[-1], T - 1, kp)
    assert sorted(shapes) == list(range(1, T - 1)) and 0 <= switch < T and agree >= 0.6
    # A second prompt where the bottle is not (the box drawn on the wrong frame): the pass
    # from it never meets the other.
    elsewhere = np.roll(gt[-1], (40, -120), axis=(0, 1))
    assert bridge(images, gt[0], 0, elsewhere, T - 1, kp) is None
    # Passes that meet, on an object no hand holds.
    _, _, away = _transparent_bottle_clip(hand_at_it=False)
    assert bridge(images, gt[0], 0, gt[-1], T - 1, away) is None
    # Neighbouring prompts leave nothing between them.
    assert bridge(images, gt[0], 0, gt[1], 1, kp) is None


def test_a_lone_outline_pass_says_which_frames_its_hand_holds_and_which_return_to_the_prompt():
    # One prompt: no second one checks a pass. Two things do: the hand that holds the
    # prompt, while it holds the outline; and the outline followed back by the edges alone,
    # landing on the prompt.
    from cogs.preprocess.outline import follow, lone_pass, returns

    images, gt, kp = _transparent_bottle_clip()
    T = len(images)
    shapes = lone_pass(images, gt[-1], T - 1, 0, kp)
    assert sorted(shapes) == sorted(shapes.held) == sorted(shapes.returning) == list(range(T - 1))
    assert all(_iou(shapes[t], gt[t]) > 0.75 for t in shapes)
    # The hand leaves it from frame 7 on, 12 px a frame: the hold ends within two frames,
    # where the hand no longer covers the outline, still on the bottle.
    images, gt, kp = _transparent_bottle_clip(let_go=7)
    shapes = lone_pass(images, gt[0], 0, T - 1, kp)
    assert shapes.held == list(range(1, max(shapes.held) + 1)) and 6 <= max(shapes.held) <= 8, shapes.held
    assert all(_iou(shapes[t], gt[t]) > 0.75 for t in shapes.held)
    # No hand holds the prompt: nothing held, and the pass returns all the way.
    images, gt, kp = _transparent_bottle_clip(hand_at_it=False)
    shapes = lone_pass(images, gt[0], 0, T - 1, kp)
    assert shapes.held == [] and shapes.returning == list(range(1, T)), shapes.returning
    assert all(_iou(shapes[t], gt[t]) > 0.75 for t in shapes)
    # The bottle passes over a still bar of its shape with a darker rim (a forearm beside a
    # racket, a shirt's hem) at frame 4, and the outline stays on the bar from there on.
    # Followed back from there it stays on the bar too, landing 40 px from the prompt. The
    # pass returns as far as frame 2; from frame 3, 10 px from the bar, the way back is
    # drawn onto the bar as well: the check ends a pass early rather than late.
    H, W = gt.shape[1:]
    yy, xx = np.mgrid[:H, :W]
    bar = (np.abs(xx + 0.5 - 90) <= 9) & (np.abs(yy + 0.5 - 88) <= 22)
    rim = bar & ~((np.abs(xx + 0.5 - 90) <= 7) & (np.abs(yy + 0.5 - 88) <= 20))
    images = images.copy()
    images[:, rim] //= 5
    shapes = lone_pass(images, gt[0], 0, T - 1, kp)
    assert shapes.returning == sorted(shapes) == [1, 2] and all(_iou(shapes[t], gt[t]) > 0.75 for t in shapes), shapes.returning
    outline, poses = follow(images, gt[0], 0, T - 1, kp)
    assert _iou(outline.mask(poses[8], (H, W)), bar) > 0.75 and not outline.mask(poses[8], (H, W))[gt[8]].any()
    assert not returns(images, outline, poses[8], 8, 0, gt[0], kp)
    assert returns(images, outline, poses[8], 8, 4, bar, kp)  # it does return to the bar


def test_a_lone_outline_gives_the_frames_whose_colour_find_is_doubted_and_none_the_colour_cues_trust():
    # A clear bottle whose dark rim has the colours of the forearm holding it: the colour
    # cues slide onto the arm from the first frame on, and doubt every find there (on the
    # arm: 0.1; IoU 0 with the bottle, checked). The outline, followed by the rim, gives
    # those frames. Where the colour cues trust what they found (the bottle alone, pieces
    # of the background it shows), a lone outline overrides nothing.
    from cogs.preprocess.outline import LONE_CONFIDENCE
    from cogs.preprocess.tracking import UNCLEAR_CONFIDENCE

    images, gt, kp = _transparent_bottle_clip()
    T = len(images)
    cues = []
    masks, conf = O.propagate_masks(images, gt[-1], T - 1, kp2d=kp, cues=cues)
    assert "outline" not in cues and (conf[:-1] >= 0.2).all(), conf
    images, gt, kp = _bottle_beside_its_forearm()
    masks, conf = O.propagate_masks(images, gt[0], 0, kp2d=kp, cues=cues)
    took = [t for t in range(T) if cues[t] == "outline"]
    assert len(took) >= T // 2, cues
    assert all(conf[t] == LONE_CONFIDENCE and _iou(masks[t], gt[t]) > 0.75 for t in took)
    assert all(conf[t] <= UNCLEAR_CONFIDENCE or _iou(masks[t], gt[t]) > 0.5 for t in range(1, T))


def test_a_lone_outline_holds_until_a_trusted_find_lies_beyond_its_reach():
    from cogs.preprocess.outline import within_reach
    from cogs.preprocess.tracking import lone_outline_frames

    T, H, W = 8, 100, 100
    yy, xx = np.mgrid[:H, :W]
    bottle = (np.abs(xx - 50) <= 6) & (np.abs(yy - 50) <= 15)  # the outline, 31 px tall: reach 9 px
    base = (np.abs(xx - 50) <= 5) & (np.abs(yy - 70) <= 3)  # just below it (a bottle's base)
    far = (np.abs(xx - 85) <= 5) & (np.abs(yy - 50) <= 5)
    assert within_reach(base, bottle) and not within_reach(far, bottle) and not within_reach(base, np.zeros_like(bottle))
    shapes = {t: bottle for t in range(1, T)}  # a pass after the prompt on frame 0
    every = list(range(1, T))
    masks = np.stack([bottle, base, base, bottle, far, far, base, base])
    conf = np.array([1.0, 0.1, 0.4, 0.9, 0.1, 0.5, 0.1, 0.1])
    # 1: doubted and within reach; 2 trusted and within reach, 3 clear: they keep their
    # masks; 4 far but doubted; 5 far and trusted: the pass ends there.
    assert lone_outline_frames(0, shapes, masks, conf, held=every) == [1, 4]
    # A doubted frame takes the outline only where its hand holds it.
    assert lone_outline_frames(0, shapes, masks, conf, held=[1], returning=every) == [1]
    # A frame the colour cues lost ends the pass (hidden, or an outline that stalled where
    # the object was) ...
    conf[2] = 0.0
    masks[2] = False
    assert lone_outline_frames(0, shapes, masks, conf, held=every, returning=every) == [1]
    # ... unless they could not see it there (an object coloured like the person, on the
    # person), where the outline returns to the prompt.
    unseen = lambda t: t == 2  # noqa: E731
    assert lone_outline_frames(0, shapes, masks, conf, held=every, returning=every, unseen=unseen) == [1, 2, 4]
    assert lone_outline_frames(0, shapes, masks, conf, held=every, returning=[1], unseen=unseen) == [1]
    # The same pass before a prompt on the last frame runs the other way.
    back = {t: bottle for t in range(T - 1)}
    assert lone_outline_frames(T - 1, back, masks, conf, held=range(T - 1)) == [6]


def test_an_outline_is_fitted_to_the_edges_that_count_and_not_to_a_stronger_one_beside_it():
    # A faint outlined bar and, 9 px to its left, a strong bar of the same shape (a forearm
    # beside a held bottle): from between them the fit goes to the strong one unless its
    # pixels are marked as saying nothing of the object.
    from cogs.preprocess.outline import Outline, fit

    H, W = 80, 80
    yy, xx = np.mgrid[:H, :W]
    rgb = np.full((H, W, 3), 120, np.uint8)
    faint = (np.abs(xx - 45) <= 4) & (np.abs(yy - 40) <= 15)
    strong = (np.abs(xx - 27) <= 4) & (np.abs(yy - 40) <= 15)
    rgb[faint] = 150
    rgb[strong] = 250
    outline = Outline.of(faint)
    start = (-9.0, 0.0, 0.0, 1.0)  # halfway between the two
    pose, _ = fit(outline, rgb, start)
    assert abs(pose[0] - -18) <= 1 and abs(pose[1]) <= 1  # onto the strong bar
    pose, _ = fit(outline, rgb, start, off=(np.abs(xx - 27) <= 8) & (np.abs(yy - 40) <= 19))
    assert abs(pose[0]) <= 1 and abs(pose[1]) <= 1 and abs(pose[3] - 1.0) < 0.1  # back on the faint one
    assert _iou(outline.mask(pose, (H, W)), faint) > 0.85
    assert Outline.of(np.zeros((H, W), bool)) is None and Outline.of((xx == 5) & (yy == 5)) is None


def test_a_mask_along_a_forearm_frame_after_frame_is_the_arm_and_not_the_object():
    from cogs.preprocess.tracking import forearm_regions, on_forearm

    T, H, W = 6, 120, 160
    kp = _hand_keypoints(T, [(50, 60)] * T, palm=10)  # the right forearm from (20, 60) to the wrist
    fa = forearm_regions(kp[0], (H, W))
    assert fa[60, 22] and fa[60, 48] and fa[63, 35] and not fa[70, 35] and not fa[60, 70]
    yy, xx = np.mgrid[:H, :W]
    arm = (np.abs(xx - 35) <= 12) & (np.abs(yy - 60) <= 3)
    held = (xx - 70) ** 2 + (yy - 60) ** 2 <= 9**2  # beyond the finger tips
    masks = np.stack([arm, arm, arm, held, arm, held])
    # On the arm for three frames running: the arm. Once, between two frames elsewhere: an
    # object passing in front of it. Beyond the hand: the object.
    assert on_forearm(masks, kp).tolist() == [True, True, True, False, False, False]
    kp[:, 14, 2] = 0.1  # an elbow MediaPipe does not see: no forearm to be on
    assert not on_forearm(masks, kp).any()


def test_a_track_that_slid_onto_the_arm_stays_on_it_until_something_finds_the_object_anew():
    from cogs.preprocess.tracking import carried_on

    H, W = 120, 160
    yy, xx = np.mgrid[:H, :W]
    arm = (np.abs(xx - 35) <= 12) & (np.abs(yy - 60) <= 3)
    wrist = (np.abs(xx - 40) <= 11) & (np.abs(yy - 60) <= 4)  # moved on towards the hand
    elsewhere = (xx - 120) ** 2 + (yy - 30) ** 2 <= 8**2
    masks = np.stack([elsewhere, arm, arm, wrist, wrist, wrist, elsewhere])
    cues = ["prompt", "stay", "flow", "flow", "stay", "colour", "flow"]
    on = np.array([False, True, True, False, False, False, False])
    # Frames 3-4 followed the arm by motion; 5 is a colour find (fresh evidence), 6 moved far.
    assert carried_on(on, masks, cues).tolist() == [False, True, True, True, True, False, False]
    # A track on the forearm and the hand that shrinks to the hand: under half the IoU, but
    # all of it lies on the arm frame's mask. Half of a mask off it is not on the arm.
    forearm_and_hand = (np.abs(xx - 40) <= 20) & (np.abs(yy - 60) <= 4)
    hand = (np.abs(xx - 54) <= 6) & (np.abs(yy - 60) <= 4)
    half_off = (np.abs(xx - 62) <= 6) & (np.abs(yy - 60) <= 4)
    assert _iou(hand, forearm_and_hand) < 0.5 and (half_off & forearm_and_hand).sum() < 0.5 * half_off.sum()
    masks = np.stack([elsewhere, forearm_and_hand, hand, hand, half_off])
    cues = ["prompt", "flow", "carried", "stay", "flow"]
    on = np.array([False, True, False, False, False])
    assert carried_on(on, masks, cues).tolist() == [False, True, True, True, False]


def test_a_track_along_the_arm_does_not_supervise_the_object():
    # The prompt was drawn on the arm (as a track that slid onto it would be): every cue
    # follows it with full confidence, and the forearm caps that below what supervises the
    # object branch. The same frames with the arm elsewhere keep their confidence.
    from cogs.branches.object import ObjectConfig
    from cogs.preprocess.tracking import UNCLEAR_CONFIDENCE

    T, H, W = 5, 120, 160
    bg = (_texture(H, W, seed=2) // 3 + 40).astype(np.uint8)
    yy, xx = np.mgrid[:H, :W]
    arm = (np.abs(xx - 35) <= 12) & (np.abs(yy - 60) <= 4)
    bg[arm] = (230, 140, 60)
    images = np.stack([bg] * T)
    kp = _hand_keypoints(T, [(50, 60)] * T, palm=10)
    masks, conf = O.propagate_masks(images, arm, 0, kp2d=kp)
    assert all(_iou(masks[t], arm) > 0.9 for t in range(T))
    assert conf[0] == 1.0 and (conf[1:] <= UNCLEAR_CONFIDENCE).all() and UNCLEAR_CONFIDENCE < ObjectConfig().min_confidence, conf
    elsewhere = _hand_keypoints(T, [(130, 20)] * T, palm=10)
    _, conf = O.propagate_masks(images, arm, 0, kp2d=elsewhere)
    assert (conf[1:] >= 0.5).all(), conf
    # The patch slides along the arm into the hand: at the end it is mostly on the hand,
    # no longer mostly on the forearm, and the track that followed it there by motion is
    # still the arm.
    from cogs.preprocess.tracking import on_forearm

    images, slid = [], []
    for t in range(T):
        im = (_texture(H, W, seed=2) // 3 + 40).astype(np.uint8)
        m = (np.abs(xx - (35 + 4 * t)) <= 12) & (np.abs(yy - 60) <= 4)
        im[m] = (230, 140, 60)
        images.append(im)
        slid.append(m)
    masks, conf = O.propagate_masks(np.stack(images), slid[0], 0, kp2d=kp)
    assert all(_iou(masks[t], slid[t]) > 0.8 for t in range(T))
    assert not on_forearm(masks, kp)[-1] and (conf[1:] <= UNCLEAR_CONFIDENCE).all(), conf


def test_a_mask_over_three_times_its_prompts_area_is_a_track_that_spread():
    # Two prompts of different sizes: each frame is judged against the prompt its mask was
    # tracked from, and a prompt itself never is.
    from cogs.preprocess.tracking import MAX_AREA_GROWTH, too_large

    H, W = 60, 80
    yy, xx = np.mgrid[:H, :W]

    def square(side):
        return (xx < side) & (yy < side)

    masks = np.stack([square(10), square(17), square(18), square(30), square(30), square(52)])
    found = ["prompt", "flow", "stay", "prompt", "colour", "features"]
    origin = [0, 0, 0, 3, 3, 3]
    # 289 and 324 px against a 100 px prompt; 900 and 2704 against 900.
    assert too_large(masks, found, origin, {0: 100, 3: 900}, growth=3.0).tolist() == [2, 5]
    assert too_large(masks, found, origin, {0: 100, 3: 900}, growth=2.5).tolist() == [1, 2, 5]
    assert too_large(masks, found, origin, {0: 100, 3: 900}).tolist() == too_large(masks, found, origin, {0: 100, 3: 900}, MAX_AREA_GROWTH).tolist()
    assert too_large(masks, found, [0] * 6, {0: 100}, growth=3.0).tolist() == [2, 4, 5]


def _disc_past_a_person(shirt):
    """_object_clip's disc passing the person, the person's mask taking the disc in where it
    is in front (as MediaPipe's takes a held racket in), the upper body in ``shirt``."""
    images, gt, person = _object_clip(T=8)
    H, W = gt.shape[1:]
    yy, xx = np.mgrid[:H, :W]
    upper = (np.abs(xx - 80) < 30) & (yy > 20) & (yy <= 34)  # shoulders and arms
    bar = (np.abs(xx - 80) < 12) & (yy > 20) | upper
    for t in range(len(images)):
        images[t][upper & ~gt[t]] = shirt
    probs = np.stack([(bar | (gt[t] & ((bar & gt[t]).sum() >= 0.5 * gt[t].sum()))) for t in range(len(images))])
    return images, gt, (probs * 255).astype(np.uint8)


def test_an_object_coloured_like_the_persons_clothes_is_looked_for_off_the_person_only():
    # A white racket in front of a white shirt: where the object's colours are the person's,
    # nothing tells the two apart on the person, so the tracker looks for the object off the
    # person only. The disc is marked lost while in front of the person (instead of a mask
    # that might be the shirt) and found again beyond it. The same disc past a person
    # dressed in other colours is followed across the person.
    from cogs.preprocess.tracking import LIKE_PERSON_SHARE

    on, off = (4, 5), (1, 2, 6, 7)  # the disc in front of the person on frames 4-5, a third of it on 3
    like, unlike = {}, {}
    images, gt, probs = _disc_past_a_person(shirt=(235, 120, 30))
    masks, conf = O.propagate_masks(images, gt[0], 0, human_probs=probs, like_person=like)
    assert like[0] >= LIKE_PERSON_SHARE, like
    assert all(not masks[t].any() and conf[t] == 0 for t in on), conf
    assert all(_iou(masks[t], gt[t]) > 0.8 and conf[t] > 0 for t in off), ([_iou(masks[t], gt[t]) for t in off], conf)
    assert (masks[3] & gt[3]).sum() >= 0.9 * masks[3].sum() > 0  # the part off the person
    images, gt, probs = _disc_past_a_person(shirt=(40, 160, 200))
    masks, conf = O.propagate_masks(images, gt[0], 0, human_probs=probs, like_person=unlike)
    assert unlike[0] < LIKE_PERSON_SHARE, unlike
    assert all(_iou(masks[t], gt[t]) > 0.8 and conf[t] >= 0.5 for t in range(8)), conf
    from cogs.preprocess.prompts import parse_prompts, person_lookalike_warning

    prompt = parse_prompts((0, 10, 20, 30, 40), None, None)[0][0]
    assert person_lookalike_warning(prompt, unlike[0]) is None
    text = person_lookalike_warning(prompt, like[0])
    assert "--object-box 0 10 20 30 40" in text and "frame 0" in text and "--sam2-checkpoint" in text


def test_whether_the_object_looks_like_the_person_is_asked_of_the_prompts_either_side_of_a_pass():
    # A prompt shows the object as it looks on its frame (a face-on racket's strings show the
    # court, a transparent bottle the shirt behind it): the rule that keeps an object in the
    # person's colours off the person holds for the frames between two prompts if either
    # shows it so, and beyond the last prompt only if that one does. Here the second prompt
    # (frame 3) sees no look-alike clothes (its frame's person mask leaves the shirt out):
    # past it the disc is followed across the person, where with the first prompt alone,
    # and with both under a rule asked of every prompt, it is marked lost.
    from cogs.preprocess import tracking

    images, gt, probs = _disc_past_a_person(shirt=(235, 120, 30))
    shirt = (probs[3] > 127) & ~gt[3] & (np.abs(images[3].astype(int) - (235, 120, 30)).sum(-1) < 30)
    probs[3][shirt] = 0
    two = tracking._Tracker(images, None, None, probs, None, 0.5, 0.1, 0.5, 4, prompts={0: gt[0], 3: gt[3]})
    assert two.like_person[3] < tracking.LIKE_PERSON_SHARE <= two.like_person[0], two.like_person
    assert two.coloured_like_person(0, +1) and two.coloured_like_person(3, -1) and two.coloured_like_person(1, +1)
    assert not two.coloured_like_person(3, +1) and not two.coloured_like_person(5, -1)
    one = tracking._Tracker(images, None, None, probs, None, 0.5, 0.1, 0.5, 4, prompts={3: gt[3]})
    assert not one.coloured_like_person(3, -1)  # a lone prompt decides for the whole clip
    masks, conf = O.propagate_masks(images, [gt[0], gt[3]], [0, 3], human_probs=probs)
    ious = [_iou(masks[t], gt[t]) for t in range(len(images))]
    assert all(ious[t] > 0.8 and conf[t] > 0 for t in range(len(images))), (ious, conf)
    masks, conf = O.propagate_masks(images, gt[0], 0, human_probs=probs)
    assert all(not masks[t].any() and conf[t] == 0 for t in (4, 5)), conf


def test_an_object_coloured_like_the_clothes_is_found_where_the_persons_mask_takes_it_in_beyond_the_body():
    # A racket held out beside the legs: the person's segmentation takes it in, though the
    # body's joints do not reach there. An object coloured like the clothes is looked for
    # off the body (the landmarks' limbs, torso, head, hands and feet), not off the whole
    # mask: beside the body it is found; in front of the body it is still marked lost, but
    # where the body's clothes there are not the object's colours.
    from cogs.preprocess import tracking
    from cogs.preprocess.tracking import body_regions

    images, gt, probs = _disc_past_a_person(shirt=(235, 120, 30))
    T, H, W = gt.shape
    for t in (1, 2):  # the disc beside the body (6 and 2 px from it), taken into the person's mask
        probs[t][gt[t]] = 255
    kp = np.zeros((T, 33, 3))
    joints = {11: (70, 27), 12: (90, 27), 13: (50, 27), 14: (110, 27), 23: (72, 80), 24: (88, 80),
              25: (74, 100), 26: (86, 100), 27: (74, 118), 28: (86, 118)}
    for i, (x, y) in joints.items():
        kp[:, i] = (x, y, 1.0)
    body = body_regions(kp[0], (H, W))
    person = probs[0] > 127
    assert (body & person).sum() >= 0.9 * person.sum()  # the joints cover the body
    assert not (body & gt[1]).any() and (body & gt[2]).sum() < 0.1 * gt[2].sum()  # and not the disc beside it
    like = {}
    masks, conf = O.propagate_masks(images, gt[0], 0, human_probs=probs, kp2d=kp, like_person=like)
    assert like[0] >= 0.2, like
    ious = [_iou(masks[t], gt[t]) for t in range(T)]
    assert all(ious[t] > 0.8 and conf[t] >= 0.2 for t in (1, 2, 3, 6, 7)), (ious, conf)
    assert not masks[4].any() and conf[4] == 0, conf  # in front of the body: lost, as before
    assert (masks[5] & gt[5]).sum() >= 0.9 * masks[5].sum() > 0  # half in front: the half beyond the body
    # Without the landmarks the whole person's mask is ruled out: the disc beside the body is
    # lost too. So it is where they cover too little of the mask to say where the body is
    # (the arms and legs unseen: a seated, half-hidden person).
    masks, conf = O.propagate_masks(images, gt[0], 0, human_probs=probs)
    assert all(not masks[t].any() and conf[t] == 0 for t in (1, 2)), conf
    hidden_limbs = kp.copy()
    hidden_limbs[:, [13, 14, 25, 26, 27, 28], 2] = 0.0
    assert (body_regions(hidden_limbs[0], (H, W)) & person).sum() < tracking.BODY_COVER * person.sum()
    masks, conf = O.propagate_masks(images, gt[0], 0, human_probs=probs, kp2d=hidden_limbs)
    assert all(not masks[t].any() and conf[t] == 0 for t in (1, 2)), conf
    # The legs are dressed in other colours than the disc's: with the hips higher, the disc
    # passes in front of the thighs at 4-5, which tell it apart, and is found there.
    kp[:, 23, 1] = kp[:, 24, 1] = 45
    kp[:, 25, 1] = kp[:, 26, 1] = 80
    tracker = tracking._Tracker(images, None, None, probs, kp, 0.5, 0.1, 0.5, 4, prompts={0: gt[0]})
    assert tracker.colours_of_person and "thigh" in tracker.limbs_apart and "upper arm" not in tracker.limbs_apart
    # The limbs told apart are the object's, whichever prompt shows them: a second prompt on
    # a frame whose person mask leaves the shirt out sees no look-alike clothes, and changes
    # neither the clip's verdict nor the limbs.
    shirt = (probs[6] > 127) & ~gt[6] & (np.abs(images[6].astype(int) - (235, 120, 30)).sum(-1) < 30)
    missed = probs.copy()
    missed[6][shirt] = 0
    two = tracking._Tracker(images, None, None, missed, kp, 0.5, 0.1, 0.5, 4, prompts={0: gt[0], 6: gt[6]})
    assert two.like_person[6] < tracking.LIKE_PERSON_SHARE <= two.like_person[0], two.like_person
    assert two.colours_of_person and two.limbs_apart == tracker.limbs_apart
    masks, conf = O.propagate_masks(images, gt[0], 0, human_probs=probs, kp2d=kp)
    ious = [_iou(masks[t], gt[t]) for t in range(T)]
    assert all(ious[t] > 0.8 and conf[t] >= 0.2 for t in (1, 2, 3, 6, 7)), (ious, conf)
    # in front of the thighs, all but the rim over the hips (the torso's, which stays hidden)
    assert all(ious[t] > 0.7 and conf[t] >= 0.2 and (masks[t] & gt[t]).sum() >= 0.95 * masks[t].sum() for t in (4, 5)), (ious, conf)


def _arm_swung_across_a_disc(T=7, across=(3, 4, 5)):
    """A racket's head (a disc, its rim in the colour of the stripes of a person's shirt,
    grey strings) held nearly still beside the body, and the person's forearm swung across
    its edge on frames ``across`` (MediaPipe's mask then takes the disc in, and the arm's
    region covers it) -> images, disc masks, person probabilities, keypoints."""
    import cv2

    H, W = 120, 160
    bg = _texture(H, W, seed=1) // 8 + 50  # a dark wall
    yy, xx = np.mgrid[:H, :W]
    shirt, stripes, shorts, skin, strings = (235, 120, 30), (60, 120, 200), (30, 30, 60), (120, 170, 210), (170, 170, 170)
    torso = (np.abs(xx - 80) < 12) & (yy > 20) & (yy < 80)
    legs = (np.abs(np.abs(xx - 80) - 7) < 6) & (yy >= 80) & (yy < 118)
    kp = np.zeros((T, 33, 3))
    for i, (x, y) in {11: (70, 27), 12: (90, 27), 14: (110, 27), 16: (120, 50), 23: (72, 78), 24: (88, 78)}.items():
        kp[:, i] = (x, y, 1.0)
    images, gt, probs = [], [], []
    for t in range(T):
        im = bg.copy()
        r2 = (xx + 0.5 - (22 + t)) ** 2 + (yy + 0.5 - 62) ** 2
        disc = r2 < 14**2
        elbow, wrist = ((37 + t, 28), (37 + t, 94)) if t in across else ((64, 45), (66, 74))
        kp[t, 13], kp[t, 15] = (*elbow, 1.0), (*wrist, 1.0)
        arm = np.zeros((H, W), np.uint8)
        cv2.line(arm, elbow, wrist, 1, 4)
        arm = arm > 0
        im[torso], im[torso & (yy % 6 < 3)], im[legs] = stripes, shirt, shorts
        im[disc], im[r2 < 10**2], im[arm] = shirt, strings, skin
        images.append(im)
        gt.append(disc & ~arm)
        person = torso | legs | arm | (disc if t in across else False)
        probs.append((person * 255).astype(np.uint8))
    return np.stack(images), np.stack(gt), np.stack(probs), kp


def test_a_clear_fit_from_beside_the_body_holds_an_object_the_arm_swings_across(monkeypatch):
    # The tennis clip's racket beside the hip, the forearm swung across its head (frames
    # 101-102): MediaPipe's mask takes the head in and the arm's region covers it, so an
    # object in the shirt's colours counted as lying on the body and was lost. The rigid fit
    # from the frame before, where it lay beside the body, explains it clearly and is kept.
    # (In front of the shirt itself it is still lost: the test above.)
    from cogs.preprocess import tracking

    images, gt, probs, kp = _arm_swung_across_a_disc()
    like, cues = {}, []
    tracker = tracking._Tracker(images, None, None, probs, kp, 0.5, 0.1, 0.5, 4, prompts={0: gt[0]})
    assert tracker.colours_of_person
    assert all(tracker.on_person(t, gt[t]) for t in (3, 4, 5)) and not any(tracker.on_person(t, gt[t]) for t in (0, 1, 2, 6))
    masks, conf = O.propagate_masks(images, gt[0], 0, human_probs=probs, kp2d=kp, like_person=like, cues=cues)
    assert like[0] >= tracking.LIKE_PERSON_SHARE
    ious = [_iou(masks[t], gt[t]) for t in range(len(images))]
    assert all(ious[t] > 0.8 and conf[t] >= 0.5 for t in range(1, 7)), (ious, conf, cues)
    assert all(cues[t] in tracking.MOTION_CUES for t in (3, 4, 5)), cues
    # Without the rule the colour cues lose it while the arm lies across it: they do not
    # look for it on the person. Its outline, followed alone and returning to the prompt
    # when followed back, gives those frames; without that too they are lost.
    from cogs.preprocess.outline import LONE_CONFIDENCE

    monkeypatch.setattr(tracking, "FIT_ON_PERSON", 1.01)
    masks, conf = O.propagate_masks(images, gt[0], 0, human_probs=probs, kp2d=kp, cues=cues)
    assert all(cues[t] == "outline" and conf[t] == LONE_CONFIDENCE and _iou(masks[t], gt[t]) > 0.8 for t in (3, 4, 5)), (cues, conf)
    monkeypatch.setattr(tracking, "lone_pass", lambda *args, **kwargs: None)
    masks, conf = O.propagate_masks(images, gt[0], 0, human_probs=probs, kp2d=kp)
    assert not masks[3].any() and conf[3] == 0, conf


def test_an_object_coloured_like_the_person_is_found_where_it_moves_at_a_hand_though_never_seen_carried():
    # Held by its far side (the hand's points 24 px off it, as a racket's head lies a
    # handle's length from the palm), the object is never seen carried. Out of view for two
    # frames, it comes back further along with a face the colour model calls background.
    # Coloured like the person's clothes (the arm here), it is looked for off the person
    # only, so what moves at the hand and is not the person is what finds it again.
    from cogs.preprocess import tracking

    images, gt, _, person, kp = _held_object_clip(T=9, new_face_from=5, hidden=(3, 4), speed=14)
    kp[:, :, 1] -= 24
    hands = tracking.hand_points(kp)
    assert all(tracking.carrying_hand(hands, t, t + 1, gt[t], gt[t + 1]) is None for t in (0, 1, 5, 6, 7))
    images[person > 127] = (235, 120, 30)  # the arm in the object's colours
    like, cues = {}, []
    masks, conf = O.propagate_masks(images, gt[0], 0, human_probs=person, kp2d=kp, like_person=like, cues=cues)
    assert like[0] >= tracking.LIKE_PERSON_SHARE, like
    assert not masks[3].any() and not masks[4].any()
    assert cues[5] == "moving", cues
    for t in range(5, 9):
        assert _iou(masks[t], gt[t]) > 0.7 and 0 < conf[t] <= 0.5, (t, cues, conf)
    # Such a find shows what the colour model calls background (the scene through a
    # racket's strings, a swing's blur): the model learns nothing from it, where a find that
    # looks like the object still adapts it.
    tracker = tracking._Tracker(images, None, None, person, kp, 0.5, 0.1, 0.5, 4, prompts={0: gt[0]})
    model = tracker._adapted(0, gt[0])

    def update(t):
        c, size = tracking.mask_stats(gt[t - 1])
        st = tracking._State(c, np.zeros(2), size, gt[t - 1], gt[t - 1], t - 1, 1.0, float(gt[0].sum()))
        colour = float(model.prob(images[t])[gt[t]].mean())
        return colour, tracker._update(st, t, 1, tracking._Found(gt[t], gt[t], 0.5, "moving", colour), model)

    colour, after = update(6)
    assert colour < tracker.min_score * tracker.ref_score and after is model
    colour, after = update(2)
    assert colour >= tracker.min_score * tracker.ref_score and after is not model
    # The other way round, an object unlike the person needs the carry seen first: what moves
    # near a hand that never held it may be anything else the hand passes.
    images, gt, _, person, kp = _held_object_clip(T=9, new_face_from=5, hidden=(3, 4), speed=14)
    kp[:, :, 1] -= 24
    masks, conf = O.propagate_masks(images, gt[0], 0, human_probs=person, kp2d=kp)
    assert not masks[5:].any() and not conf[5:].any()


def test_a_piece_grabcut_cuts_out_of_a_refound_object_yields_to_the_whole_window(monkeypatch):
    # On the basketball clip GrabCut re-found a dribbled ball as one panel between its
    # seams, the rest of the ball all round it. That GrabCut failure is forced here (only
    # the middle of its find is kept); the piece is unclear (its surroundings look like
    # it), so the colour search keeps the probable pixels of the located window instead.
    from cogs.preprocess import tracking

    images, gt, person = _object_clip(T=8)
    images[3][gt[3]] = images[2][~gt[2]].mean(0).astype(np.uint8)  # hidden on frame 3: frame 4 is found by colour
    real = tracking.grabcut_at

    def piece(rgb, prob, centre, size, hp, static=None):
        seg = real(rgb, prob, centre, size, hp, static=static)
        yy, xx = np.mgrid[: seg.shape[0], : seg.shape[1]]
        return seg & ((xx + 0.5 - centre[0]) ** 2 + (yy + 0.5 - centre[1]) ** 2 < 6**2)

    monkeypatch.setattr(tracking, "grabcut_at", piece)
    cues = []
    masks, conf = O.propagate_masks(images, gt[0], 0, human_probs=(person * 255).astype(np.uint8), cues=cues)
    assert cues[4] == "colour" and _iou(masks[4], gt[4]) > 0.8, (cues, _iou(masks[4], gt[4]))
    assert conf[4] > 0.5


def test_the_moving_piece_at_a_hand_gets_back_the_bites_of_look_alike_scene_if_convex():
    from cogs.preprocess.tracking import moving_at_hand

    H, W = 120, 160
    yy, xx = np.mgrid[:H, :W]
    box = _square(H, W, 80, 60, 20)
    bite = box & (np.abs(xx + 0.5 - 80) <= 6) & (yy < 60)  # its colour matched the wall behind
    moving = box & ~bite
    moving[10:14, 5:30] = True  # a sliver of something else, away from the hand
    hand = np.array([58.0, 60.0])
    assert _iou(moving_at_hand(moving, hand, 40, convex=True), box) > 0.97
    assert _iou(moving_at_hand(moving, hand, 40, convex=False), box & ~bite) > 0.97
    assert not moving_at_hand(moving, np.array([150.0, 110.0]), 20).any()  # nothing within reach of that hand
    thin = (np.abs(yy - 60) <= 2) & (xx > 60) & (xx < 120) | (np.abs(xx - 118) <= 2) & (yy > 20) & (yy < 100)
    assert not moving_at_hand(thin, hand, 40, convex=True).any()  # an arm's outline, not an object


def test_grabcut_gives_the_same_mask_whatever_opencvs_random_state():
    import cv2

    images, gt, _ = _object_clip()
    ys, xs = np.nonzero(gt[2])
    box = np.array([xs.min() - 6, ys.min() - 6, xs.max() + 7, ys.max() + 7], float)
    cv2.setRNGSeed(1)
    a, _ = O.grabcut_box(images[2], box)
    cv2.setRNGSeed(12345)
    b, _ = O.grabcut_box(images[2], box)
    assert np.array_equal(a, b)


def test_the_hand_cue_invents_nothing_once_the_object_is_gone():
    # The hand passes a static square of the object's size: it is next to the hand, but
    # it stays with the background while the hand moves on.
    images, gt, _, person, kp = _held_object_clip(T=9, hidden=tuple(range(3, 9)), speed=14, decoy=(125, 70))
    masks, conf = O.propagate_masks(images, gt[0], 0, human_probs=person, kp2d=kp)
    assert not masks[3:].any() and (conf[3:] == 0).all()


def test_a_patch_of_background_beside_the_hand_is_told_from_a_carried_object():
    # The hand cue's guard: with the camera panning, a background patch (the decoy) is
    # what the previous frame showed there once the background's motion is undone; the
    # carried object, which moved with the hand, is not.
    from cogs.preprocess.tracking import _Tracker

    pan, t = 5, 4
    images, gt, _, person, kp = _held_object_clip(T=6, speed=14, decoy=(150, 120), pan=pan)
    tracker = _Tracker(images, gt[0], 0, person, kp, 0.5, 0.1, 0.5, 4)
    H, W = gt.shape[1:]
    decoy_now = _square(H, W, 150 - pan * t, 120, 14)
    assert (images[t][decoy_now] == (40, 170, 60)).all()
    assert tracker._unchanged(t, t - 1, decoy_now)
    assert not tracker._unchanged(t, t - 1, gt[t])


def _room(T, H, W, wall, floor, seed=3):
    """A camera sliding sideways past a wall (the top half, ``wall`` pixels a frame) and a
    floor (the bottom half, receding: from ``wall`` pixels a frame at the crease to
    ``floor`` at the bottom): parallax that no one homography undoes."""
    import cv2

    big = _texture(H, W + 2 * floor * T, seed=seed)
    yy, xx = np.mgrid[:H, :W].astype(np.float32)
    speed = np.where(yy < H // 2, wall, wall + (floor - wall) * (yy - H // 2) / (H // 2)).astype(np.float32)
    return np.stack([cv2.remap(big, xx + speed * t, yy, cv2.INTER_LINEAR) for t in range(T)])


def test_static_scene_is_recognised_on_a_wall_and_a_floor_that_slide_differently():
    from cogs.preprocess.background import StaticScene
    from cogs.preprocess.tracking import FeatureBank

    T, H, W = 4, 160, 240
    images = _room(T, H, W, wall=2, floor=8)
    square = _square(H, W, 120, 50, 12)
    images[3][square] = (220, 30, 30)  # something that moved in
    scene = StaticScene(images, np.zeros((T, H, W), np.uint8), FeatureBank(images).static_matches)
    r = scene.residual(3, [(0, None)])
    wall, floor = r[8 : H // 2 - 8, 20:-20], r[H // 2 + 8 : -8, 20:-20]
    assert (wall <= 8).mean() > 0.9 and (floor <= 8).mean() > 0.9  # a homography alone: 0.72 on the floor
    assert np.median(r[square]) > 50


def test_a_resting_object_whose_mask_is_known_is_not_taken_for_static_scene():
    from cogs.preprocess.background import StaticScene
    from cogs.preprocess.tracking import FeatureBank

    T, H, W = 3, 160, 240
    images = _room(T, H, W, wall=2, floor=2)
    box = np.stack([_square(H, W, 100 - 2 * t, 60, 12) for t in range(T)])  # resting: slides with the wall
    images[box] = (220, 30, 30)
    scene = StaticScene(images, np.zeros((T, H, W), np.uint8), FeatureBank(images).static_matches)
    assert np.nanmax(scene.residual(2, [(0, None)])[box[2]]) <= 8  # unknown: it looks like scene
    assert np.isnan(scene.residual(2, [(0, box[0])])[box[2]]).all()  # known: no verdict on it


def test_a_track_left_where_the_object_was_shows_the_room_and_is_not_trusted():
    # A box rests on the wall (frames 0-2), then is carried off to the right (3-7), while
    # the camera pans. A track that stayed behind at frame 6 holds the room the box left:
    # the frames that found the box elsewhere show the same pixels there. The box itself,
    # resting (1) or carried (4), does not; nor does a mask lying on the person, whom those
    # frames leave out.
    from cogs.preprocess.tracking import UNCLEAR_CONFIDENCE, _Tracker

    T, H, W = 8, 160, 240
    images = _room(T, H, W, wall=2, floor=2)
    box = np.stack([_square(H, W, 100 - 2 * t, 50, 12) if t < 3 else _square(H, W, 190, 50, 12) for t in range(T)])
    images[box] = (220, 30, 30)
    masks, conf = box.copy(), np.full(T, 0.8)
    masks[6] = _square(H, W, 100 - 2 * 6, 50, 12)  # where it rested, now the wall behind it
    person = np.zeros((T, H, W), np.uint8)
    tracker = _Tracker(images, None, None, person, None, 0.5, 0.1, 0.5, 4, prompts={0: box[0]})
    assert tracker.shows_the_scene(6, masks, conf)
    assert not tracker.shows_the_scene(1, masks, conf) and not tracker.shows_the_scene(4, masks, conf)
    # Only frames that found the object elsewhere with some confidence say what is room.
    doubted = conf.copy()
    doubted[3:] = UNCLEAR_CONFIDENCE
    assert not tracker.shows_the_scene(6, masks, doubted)
    person[6, 20:80, 60:120] = 255  # someone stands there: behind the mask is the person
    on_person = _Tracker(images, None, None, person, None, 0.5, 0.1, 0.5, 4, prompts={0: box[0]})
    assert not on_person.shows_the_scene(6, masks, conf)


def test_masks_grow_and_shrink_by_round_discs_of_any_size():
    import cv2

    from cogs.preprocess.segment import LARGE_DISC, grown, shrunk

    H, W = 300, 400
    yy, xx = np.mgrid[:H, :W]
    point = np.zeros((H, W), bool)
    point[150, 200] = True
    square = np.zeros((H, W), bool)
    square[20:280, 60:340] = True
    for r in (3, 40, LARGE_DISC, LARGE_DISC + 1, 125):
        euclid = (yy - 150) ** 2 + (xx - 200) ** 2 <= r * r
        if r <= LARGE_DISC:  # OpenCV's digital ellipse, as measured
            ellipse = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1,) * 2)
            assert (grown(point, r) == (cv2.dilate(point.astype(np.uint8), ellipse) > 0)).all()
            assert (shrunk(square, r) == (cv2.erode(square.astype(np.uint8), ellipse) > 0)).all()
        else:  # the exact disc, at a cost that does not grow with it
            assert (grown(point, r) == euclid).all()
            inner = shrunk(square, r)
            assert inner.sum() == (260 - 2 * r) * (280 - 2 * r) and inner[20 + r : 280 - r, 60 + r : 340 - r].all()
        assert abs(int(grown(point, r).sum()) - int(euclid.sum())) <= 4 * r  # round either way: along the outline
        assert shrunk(np.ones((H, W), bool), r).all()  # the frame's border is not outside
        assert not grown(np.zeros((H, W), bool), r).any()


def test_the_static_scene_keeps_a_known_objects_size_away_from_it():
    """Static pixels stay off a known object by its size (a missed face of it must not turn
    into scenery), for an object filling much of the frame as for a small one, and no
    farther."""
    import cv2

    from cogs.preprocess.background import StaticScene

    H, W = 270, 480
    images = np.zeros((2, H, W, 3), np.uint8)
    scene = StaticScene(images, np.zeros((2, H, W), np.uint8), None)
    for x0, y0, w, h in ((200, 120, 16, 10), (40, 60, 240, 130)):
        obj = np.zeros((H, W), bool)
        obj[y0 : y0 + h, x0 : x0 + w] = True
        free = scene.static_pixels(0, obj)
        far = cv2.distanceTransform((~obj).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        size = max(w, h) - 1  # the mask's extent in pixels
        assert not free[far <= size].any()
        assert free[far > size + 1].all()
        assert free.sum() < (far > 0.5 * size).sum()  # farther than half its size


def _prompt_with_a_still_patch(object_speed):
    """13 frames of a camera panning past a textured room (2 px a frame), a bluish textured
    square moving ``object_speed`` (x, y) pixels a frame and, touching it in frame 0, a
    reddish textured patch of the room: (images, the square's mask, the patch's) in frame 0."""
    T, H, W = 13, 160, 240
    images = _room(T, H, W, wall=2, floor=2)
    def blocks(seed, tint):  # random 5-pixel blocks: corners for SIFT everywhere
        cells = np.random.default_rng(seed).integers(0, 90, (10, 10, 3))
        return (np.kron(cells, np.ones((5, 5, 1), int)) + np.array(tint)).astype(np.uint8)

    obj_tex, patch_tex = blocks(11, (20, 40, 120)), blocks(12, (120, 30, 40))
    for t in range(T):
        px = 120 - 2 * t  # the patch slides with the room
        images[t, 50:100, px:px + 50] = patch_tex
        ox, oy = 70 + round(object_speed[0] * t), 50 + round(object_speed[1] * t)
        images[t, oy:oy + 50, ox:ox + 50] = obj_tex
    square = np.zeros((H, W), bool)
    square[50:100, 70:120] = True
    patch = np.zeros((H, W), bool)
    patch[50:100, 120:170] = True
    return images, square, patch


def test_the_parts_of_a_prompt_that_hold_still_with_the_room_are_left_out():
    # A box drawn around a moving object also holds a piece of the room behind it (the bed
    # behind a guitar) that GrabCut cannot tell from the object by colour against the
    # surroundings: its keypoints follow the camera's motion, the object's do not.
    from cogs.preprocess.background import StaticScene
    from cogs.preprocess.tracking import FeatureBank, without_still_parts

    images, square, patch = _prompt_with_a_still_patch((3, 1))
    T, H, W = images.shape[:3]
    scene = StaticScene(images, np.zeros((T, H, W), np.uint8), FeatureBank(images).static_matches)
    out = without_still_parts(images[0], square | patch, scene, 0)
    assert _iou(out, square) > 0.9 and (out & patch).sum() < 0.1 * patch.sum()
    # Tracked from such a prompt, the square is followed without the patch.
    still = {}
    masks, _ = O.propagate_masks(images, square | patch, 0, human_probs=np.zeros((T, H, W), np.uint8), still=still)
    assert still[0] > 0.9 * patch.sum()
    assert min(_iou(masks[t], np.roll(square, (round(t), 3 * t), (0, 1))) for t in range(T)) > 0.85
    # An object at rest holds still as a whole: the prompt stays as drawn.
    images, square, patch = _prompt_with_a_still_patch((-2, 0))
    scene = StaticScene(images, np.zeros((T, H, W), np.uint8), FeatureBank(images).static_matches)
    assert np.array_equal(without_still_parts(images[0], square | patch, scene, 0), square | patch)


def test_a_look_alike_patch_of_static_scene_beside_the_object_stays_out_of_its_mask():
    # A patch in the object's colour lies along its path; colour and GrabCut alone merge
    # the two once they touch (IoU 0.15-0.36), the static scene model keeps them apart.
    T, H, W = 8, 140, 220
    bg = (_texture(H, W, seed=6) // 3 + 100).astype(np.uint8)
    bg[38:55, 70:170] = (235, 120, 30)
    yy, _ = np.mgrid[:H, :W]
    images, gt = [], []
    for t in range(T):
        om = _square(H, W, 40 + 18 * t, 70, 14)
        im = bg.copy()
        im[om] = (235, 120, 30)
        im[om & (yy < 62)] = (250, 240, 220)
        images.append(im)
        gt.append(om)
    images, gt = np.stack(images), np.stack(gt)
    masks, _ = O.propagate_masks(images, gt[0], 0, human_probs=np.zeros((T, H, W), np.uint8))
    assert min(_iou(masks[t], gt[t]) for t in range(5, T)) > 0.85


@pytest.mark.parametrize("box, frame, message", [
    ((10, 10, 5, 20), 0, "x1 > x0"),
    ((500, 10, 600, 20), 0, "outside"),
    ((10, 10, 20, 20), 9, "--object-box-frame 9"),
])  # fmt: skip
def test_bad_object_prompts_raise_user_errors_naming_the_option(box, frame, message):
    from cogs.preprocess.prompts import check_against_frames, parse_prompts

    with pytest.raises(UserError, match=f"(?i){re.escape(message)}"):
        check_against_frames(parse_prompts(box, frame, None)[0], (160, 120), 8)


def _turning_object_clip(T=14, H=120, W=220, turn=6, hidden=()):
    """An orange disc moving right 12 px a frame that turns a blue and yellow face into view
    from frame ``turn`` (hidden in ``hidden`` frames), and a resting orange disc of the
    same size above its path: a look-alike of the prompt's face. -> (images, object masks,
    look-alike mask)."""
    bg = (_texture(H, W, seed=6) // 3 + 100).astype(np.uint8)
    yy, xx = np.mgrid[:H, :W]
    decoy = (xx + 0.5 - 150) ** 2 + (yy + 0.5 - 25) ** 2 < 12**2
    bg[decoy] = (235, 120, 30)
    images, gt = [], []
    for t in range(T):
        im = bg.copy()
        om = ((xx + 0.5 - (25 + 12 * t)) ** 2 + (yy + 0.5 - 80) ** 2 < 12**2) & (t not in hidden)
        if t >= turn:
            im[om] = (40, 60, 200)
            im[om & ((xx // 5) % 2 == 0)] = (230, 210, 40)
        else:
            im[om] = (235, 120, 30)
        images.append(im)
        gt.append(om)
    return np.stack(images), np.stack(gt), decoy


def test_a_second_prompt_restores_a_track_that_drifted_to_a_look_alike():
    # From one prompt the track leaves the object when it turns a face no colour model
    # knows and settles on the look-alike for the rest of the clip. A second prompt on
    # the new face restores it, and the frames between the prompts take the second
    # prompt's pass from where the first one left the object (not from the middle).
    images, gt, decoy = _turning_object_clip()
    T = len(images)
    one, _ = O.propagate_masks(images, gt[0], 0)
    sources = []
    two, conf = O.propagate_masks(images, [gt[0], gt[9]], [0, 9], sources=sources)
    ious_one = [_iou(one[t], gt[t]) for t in range(T)]
    ious_two = [_iou(two[t], gt[t]) for t in range(T)]
    assert max(ious_one[6:]) < 0.2 and (one[7] & decoy).sum() > 0.8 * decoy.sum()  # the failure being fixed
    assert min(ious_two) > 0.85, ious_two
    assert np.mean(ious_two[9:]) > np.mean(ious_one[9:]) + 0.5
    assert sources == [0] * 6 + [9] * (T - 6)
    assert (conf > 0).all()


def test_a_racket_face_on_is_the_thick_piece_at_the_hand_once_its_strings_are_filled():
    # What moves of a racket over a look-alike banner: a 1-px frame round strings that
    # show the banner and a 1-px handle from the palm. The opening takes it all; told the
    # person, the piece at the hand is the filled head and its handle, while a sliver
    # (a seam of the banner that the warp misses) stays out.
    import cv2

    from cogs.preprocess.tracking import moving_at_hand

    H, W = 120, 160
    yy, xx = np.mgrid[:H, :W]
    person = (xx < 60) & (yy > 30)
    hand = np.array([62.0, 60.0])
    ring = np.zeros((H, W), np.uint8)
    cv2.ellipse(ring, (100, 40), (12, 18), 30, 0, 360, 1, 1)
    head = np.zeros((H, W), np.uint8)
    cv2.ellipse(head, (100, 40), (12, 18), 30, 0, 360, 1, -1)
    handle = np.zeros((H, W), np.uint8)
    cv2.line(handle, (64, 60), (92, 52), 1, 1)
    moving = (ring | handle).astype(bool) & ~person
    size = 20.0
    assert not moving_at_hand(moving, hand, size).any()
    found = moving_at_hand(moving, hand, size, person=person)
    assert _iou(found, (head | handle).astype(bool)) > 0.9
    sliver = (np.abs(xx + 0.5 - 80) <= 0.5) & (yy > 55) & (yy < 110)
    assert not moving_at_hand(sliver, hand, size, person=person).any()
    outline = (xx >= 60) & (xx <= 61) & (yy > 30)  # what MediaPipe's mask leaves along the arm
    assert not moving_at_hand(outline, hand, size, person=person).any()


def test_between_two_prompts_the_switch_is_where_each_pass_still_holds_the_object():
    from cogs.preprocess.tracking import combine_passes

    n, H, W = 11, 20, 20
    obj = np.zeros((n, H, W), bool)
    obj[:, 5:10, 5:10] = True
    wrong = np.zeros((H, W), bool)
    wrong[12:18, 12:18] = True
    fwd, bwd = obj.copy(), obj.copy()
    fwd[3:] = wrong  # the first prompt's pass drifts at frame 3 ...
    bwd[:2] = False  # ... the second's loses the object before frame 2
    assert combine_passes(fwd, bwd) == 2  # agree on 2 only
    bwd[:2] = obj[:2]
    assert combine_passes(fwd, bwd) in (1, 2)  # agree on 0..2: switch before the drift
    fwd, bwd = obj.copy(), obj.copy()
    fwd[8:] = wrong
    bwd[:7] = False  # they never agree (7..8 on different things): each keeps its reach
    bwd[7:9] = np.roll(obj[7:9], 6, axis=2)
    assert combine_passes(fwd, bwd) == 7 and combine_passes(obj, obj) == 5  # all agree: the middle


def test_a_pass_that_holds_the_object_on_from_the_switch_keeps_the_frames_the_other_lost():
    from cogs.preprocess.tracking import beyond_the_switch, combine_passes

    n, H, W = 12, 20, 20
    obj = np.zeros((n, H, W), bool)
    obj[:, 5:10, 5:10] = True
    fwd, bwd = obj.copy(), obj.copy()
    fwd[1:3] = False  # the first prompt's pass loses the object at once, finds it again at 3 ...
    fwd[9:] = False  # ... and holds it to 8
    bwd[4:9] = False  # the second's holds it from 11 down to 9, loses it, finds it again at 3
    bwd[3] = np.roll(obj[3], 1, axis=1)
    switch = combine_passes(fwd, bwd)
    assert switch == 3  # where both are on the object (neither pass reaches the other's prompt)
    second = beyond_the_switch(fwd, bwd, switch)
    # 4-8 from the first pass, which held on from the switch, not from the second, which
    # lost them; 1-2 from the second, which holds them from the switch, where the first lost them
    assert second.tolist() == [False] + [True] * 3 + [False] * 5 + [True] * 3
    assert np.array_equal(beyond_the_switch(fwd, np.roll(bwd, 6, axis=2), switch), np.arange(n) >= switch)  # no agreement there
    both = obj.copy()
    both[8:] = np.roll(obj[8:], 6, axis=2)  # the first pass drifts at 8; the second holds throughout
    switch = combine_passes(both, obj)
    assert np.array_equal(beyond_the_switch(both, obj, switch), np.arange(n) >= switch)  # within both reaches: as before


def test_a_negative_box_keeps_the_track_off_what_it_marks():
    # The object hides in frames 5-6 and the track jumps to the orange look-alike; a
    # negative box on it in frame 5 keeps it out there, and its colours then count
    # against the object in the colour models. (The look-alike has exactly the prompt's
    # colour, so from frame 6 on the lowered belief is not enough: the track takes it
    # again. A second prompt after the object is back is the remedy there.)
    from cogs.preprocess.prompts import box_mask
    from cogs.preprocess.tracking import _Tracker

    images, gt, decoy = _turning_object_clip(T=9, turn=99, hidden=(5, 6))
    negative = {5: box_mask(np.array([134, 9, 166, 41]), decoy.shape)}
    assert (negative[5] & decoy).sum() == decoy.sum()
    plain, _ = O.propagate_masks(images, gt[0], 0)
    masks, conf = O.propagate_masks(images, gt[0], 0, negatives=negative)
    assert (plain[5] & decoy).sum() > 0.8 * decoy.sum()  # without it: on the look-alike
    assert not (masks[5] & negative[5]).any() and conf[5] == 0
    assert min(_iou(masks[t], gt[t]) for t in range(5)) > 0.85

    def look_alike(negatives):
        tr = _Tracker(images, gt[0], 0, None, None, 0.5, 0.1, 0.5, 4, negatives=negatives)
        return float(tr.base_model.prob(images[5])[decoy].mean())

    assert look_alike(negative) < look_alike(None) - 0.1  # 0.98 -> 0.81: capped, the prompt is all that orange


def test_every_prompt_is_checked_before_the_frames_are_read():
    from cogs.preprocess.prompts import check_against_frames, parse_prompts

    pos, neg = parse_prompts((10, 10, 40, 40), None, ())
    assert [(p.frame, p.box) for p in pos] == [(0, (10.0, 10.0, 40.0, 40.0))] and neg == []
    pos, _ = parse_prompts((10, 10, 40, 40), 5, None)
    assert pos[0].frame == 5
    pos, neg = parse_prompts(((9, 1, 1, 9, 9), (2, 10, 10, 40, 40)), None, ((2, 50, 50, 60, 60),))
    assert [p.frame for p in pos] == [2, 9] and neg[0].frame == 2
    bad = [
        (((1, 2, 3),), None, (), "--object-box 1 2 3: expected X0 Y0 X1 Y1 or FRAME X0 Y0 X1 Y1"),
        (((0, 0, 9, 9), (3, 0, 0, 9, 9)), None, (), "--object-box 0 0 9 9: with several boxes, give each its frame"),
        (((3, 0, 0, 9, 9), (3, 5, 5, 20, 20)), None, (), "--object-box 3 5 5 20 20: frame 3 already has the box 3 0 0 9 9"),
        (((3, 0, 0, 9, 9),), 4, (), "--object-box-frame 4 goes with the single-box form"),
        (((2.5, 0, 0, 9, 9),), None, (), "--object-box 2.5 0 0 9 9: the frame 2.5 must be a whole number"),
        (((3, 9, 0, 0, 9),), None, (), "--object-box 3 9 0 0 9: the box must be X0 Y0 X1 Y1 with X1 > X0"),
        (((3, 0, 0, float("nan"), 9),), None, (), "--object-box 3 0 0 nan 9: every value must be a finite number"),
        ((), None, ((3, 0, 0, 9, 9),), "--object-negative-box 3 0 0 9 9 needs --object-box"),
        (((3, 10, 10, 20, 20),), None, ((3, 0, 0, 18, 30),), "--object-negative-box 3 0 0 18 30 covers most of --object-box 3 10 10 20 20"),
        (((3, 10, 10, 20, 20),), None, ((3, 0, 0, 9),), "--object-negative-box 3 0 0 9: expected FRAME X0 Y0 X1 Y1"),
    ]
    for box, frame, negative, message in bad:
        with pytest.raises(UserError) as e:
            parse_prompts(box, frame, negative)
        assert str(e.value).startswith(message), str(e.value)
    parse_prompts(((3, 10, 10, 20, 20),), None, ((3, 0, 0, 14, 30),))  # a negative over part of the box is fine
    pos, neg = parse_prompts(((7, 10, 10, 20, 20), (2, 10, 10, 20, 20)), None, ((4, 500, 10, 600, 20),))
    with pytest.raises(UserError, match=r"^--object-box 7 10 10 20 20: frame 7 is outside the 6 processed frames \(0..5\)"):
        check_against_frames(pos, (160, 120), 6)
    with pytest.raises(UserError, match=r"^--object-negative-box 4 500 10 600 20 lies outside the 160x120 frame"):
        check_against_frames(pos + neg, (160, 120), 8)
    pos, _ = parse_prompts((10, 10, 20, 20), 9, ())
    with pytest.raises(UserError, match=r"^--object-box-frame 9 is outside the 8 processed frames"):
        check_against_frames(pos, (160, 120), 8)


def test_sam2_gets_a_box_per_prompt_and_negative_clicks_inside_each_negative_box():
    calls = O.sam2_prompts([(7, np.array([1, 2, 30, 40])), (2, np.array([5, 5, 9, 9]))], [(7, np.array([40, 40, 80, 60])), (4, np.array([0, 0, 8, 8]))])
    assert [c["frame_idx"] for c in calls] == [2, 4, 7] and all(c["obj_id"] == 1 for c in calls)
    assert "points" not in calls[0] and calls[0]["box"].tolist() == [5, 5, 9, 9]
    assert "box" not in calls[1] and (calls[1]["labels"] == 0).all()
    pts = calls[2]["points"]
    assert len(pts) == 5 and (calls[2]["labels"] == 0).all() and calls[2]["box"].tolist() == [1, 2, 30, 40]
    assert ((pts[:, 0] > 40) & (pts[:, 0] < 80) & (pts[:, 1] > 40) & (pts[:, 1] < 60)).all()


def test_box_is_scaled_from_source_to_processed_pixels():
    assert O.scale_box((100, 50, 200, 150), (1000, 500), (500, 250)).tolist() == [50, 25, 100, 75]


def test_mask_folder_with_one_mask_per_source_frame_is_subsampled(tmp_path):
    from cogs.data.io import write_mask

    for i in range(6):
        m = np.zeros((20, 30), bool)
        m[i, :] = True
        write_mask(tmp_path / f"{i:03d}.png", m)
    masks = O.read_mask_folder(tmp_path, 3, (30, 20), np.array([0, 2, 4]))
    assert [int(np.flatnonzero(m.any(1))[0]) for m in masks] == [0, 2, 4]
    with pytest.raises(UserError, match="holds 6 masks"):
        O.read_mask_folder(tmp_path, 4, (30, 20), None)


# -- cameras --------------------------------------------------------------------------


def _rot(axis: int, deg: float) -> np.ndarray:
    from cogs.preprocess.objectfit import _axis_rotation

    return _axis_rotation(axis, np.radians(deg))


def test_colmap_gives_the_same_cameras_for_the_same_frames(tmp_path):
    """Incremental SfM on twelve synthetic frames, twice: the same frames registered and
    bit-identical poses and points (COLMAP's two-view RANSAC draws from a fresh seed unless
    told: two unseeded runs triangulated 609 and 612 points here, with poses 0.08 apart;
    feature extraction and bundle adjustment on several threads change them too)."""
    pytest.importorskip("pycolmap", reason="pycolmap is in the optional `preprocess` extra")
    from cogs.data.synth import SynthConfig, generate_scene
    from cogs.preprocess.sfm import feature_mask, run_colmap

    sc = generate_scene(SynthConfig(frames=12, width=320, height=240, points=300), show_progress=False)
    moving = sc.gt.human_masks | sc.gt.object_masks
    static = np.stack([feature_mask(m, None, 4) for m in moving])
    runs = [run_colmap(sc.images, static, sc.gt.cameras.K[0], tmp_path / f"run{k}") for k in range(2)]
    (p0, x0, _, s0), (p1, x1, _, s1) = runs
    assert len(p0) == 12 and sorted(p0) == sorted(p1)
    assert s0["n_points"] == s1["n_points"] > 100 and np.array_equal(x0, x1)
    assert all(np.array_equal(p0[t], p1[t]) for t in p0)


def test_a_mapper_run_posing_too_few_frames_is_mapped_again_with_the_next_seeds(tmp_path):
    """Asked for more frames than the clip has, the mapper runs with MAPPER_ATTEMPTS seeds
    from the same matches and keeps the model posing the most frames, the first of equals:
    here every seed poses all twelve, so the cameras are the first seed's, bit for bit as a
    run that asks for nothing more."""
    pytest.importorskip("pycolmap", reason="pycolmap is in the optional `preprocess` extra")
    from cogs.data.synth import SynthConfig, generate_scene
    from cogs.preprocess.sfm import MAPPER_ATTEMPTS, feature_mask, run_colmap

    sc = generate_scene(SynthConfig(frames=12, width=320, height=240, points=300), show_progress=False)
    static = np.stack([feature_mask(m, None, 4) for m in sc.gt.human_masks | sc.gt.object_masks])
    K = sc.gt.cameras.K[0]
    p1, x1, _, s1 = run_colmap(sc.images, static, K, tmp_path / "once")
    pn, xn, _, sn = run_colmap(sc.images, static, K, tmp_path / "again", enough=13)
    assert s1["mapper_seeds"] == [0] and s1["mapper_posed"] == [12]
    assert sn["mapper_seeds"] == list(range(MAPPER_ATTEMPTS)) and len(sn["mapper_posed"]) == MAPPER_ATTEMPTS
    assert sn["n_registered"] == max(sn["mapper_posed"]) == sn["mapper_posed"][sn["mapper_seeds"].index(sn["mapper_seed"])]
    assert sn["mapper_seed"] == 0 and sorted(pn) == sorted(p1) and np.array_equal(xn, x1)
    assert all(np.array_equal(pn[t], p1[t]) for t in p1)


def _sift_like(n, rng):
    """``n`` SIFT-like uint8 descriptors: non-negative unit vectors scaled by 512, clipped."""
    d = np.abs(rng.normal(size=(n, 128)))
    return np.clip(np.round(512 * d / np.linalg.norm(d, axis=1, keepdims=True)), 0, 255).astype(np.uint8)


def test_descriptors_match_as_colmaps_brute_force_rules_say_exactly():
    """Nearest neighbour by angle under 0.7 rad, under 0.8x the second nearest's, both ways:
    checked against a float64 loop on descriptors where half of one image's are noisy
    copies of the other's; the result does not depend on the order the images come in."""
    from cogs.preprocess.sfm import match_descriptors

    rng = np.random.default_rng(3)
    d1 = _sift_like(300, rng)
    # Ten near-twins in image 1 of descriptors that image 2 has: each twin's nearest is the
    # same descriptor there, which cannot tell the two apart (only the cross check drops them).
    d1[290:] = np.clip(d1[:10].astype(int) + rng.integers(-2, 3, (10, 128)), 0, 255)
    d2 = np.concatenate([np.clip(d1[:150].astype(int) + rng.integers(-12, 13, (150, 128)), 0, 255).astype(np.uint8),
                         _sift_like(200, rng)])[rng.permutation(350)]
    got = match_descriptors(d1, d2)

    ang = np.arccos(np.clip(d1.astype(np.float64) @ d2.astype(np.float64).T / 512.0**2, -1, 1))

    def one_way(a):
        out = {}
        for i, row in enumerate(a):
            j, k = np.argsort(row, kind="stable")[:2]
            if row[j] <= 0.7 and row[j] < 0.8 * row[k]:
                out[i] = j
        return out

    fwd, back = one_way(ang), one_way(ang.T)
    want = {(i, j) for i, j in fwd.items() if back.get(j) == i}
    assert 100 <= len(want) <= 150  # the noisy copies but the twins' originals
    twins = lambda pairs: sum(i < 10 or i >= 290 for i in pairs)  # noqa: E731
    assert twins(fwd) - twins(i for i, _ in want) >= 10  # one way they match; both ways, not
    assert set(map(tuple, got.tolist())) == want and got.dtype == np.uint32
    assert set(map(tuple, match_descriptors(d2, d1)[:, ::-1].tolist())) == want
    assert match_descriptors(d1, d2[:0]).shape == (0, 2)


def test_the_two_best_each_way_are_numpys_with_ties_to_the_first_index():
    """``_fold_two_best`` (one compiled pass, fed a product a block of rows at a time) against
    numpy on small integer products, where ties are common: the first index of the largest,
    a tie making the second equal to it, and -inf for the second of a single entry; the
    same whether the rows come at once or in blocks."""
    from cogs.preprocess.sfm import _fold_two_best

    rng = np.random.default_rng(5)
    for shape in [(40, 33), (1, 7), (6, 1), (200, 180)]:
        dots = rng.integers(0, 6, shape).astype(np.float32)
        for rows in (shape[0], 7):
            N, M = shape
            got = (np.zeros(N, np.int64), np.empty(N, np.float32), np.empty(N, np.float32),
                   np.zeros(M, np.int64), np.full(M, -np.inf, np.float32), np.full(M, -np.inf, np.float32))
            for i0 in range(0, N, rows):
                _fold_two_best(dots[i0 : i0 + rows], i0, *got)
            for axis, (best, top, second) in ((1, got[:3]), (0, got[3:])):
                want = dots.argmax(axis)
                assert np.array_equal(best, want) and np.array_equal(top, dots.max(axis))
                rest = dots.copy()
                if axis == 1:
                    rest[np.arange(len(want)), want] = -np.inf
                else:
                    rest[want, np.arange(len(want))] = -np.inf
                assert np.array_equal(second, rest.max(axis))
            assert (got[2] == got[1]).any() and (got[5] == got[4]).any() or 1 in shape  # ties were there


def test_sequential_pairs_are_the_overlap_and_its_powers_of_two():
    from cogs.preprocess.sfm import image_pairs

    assert image_pairs(4) == [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    pairs = image_pairs(40, "sequential", overlap=3)
    assert len(set(pairs)) == len(pairs) and all(a < b < 40 for a, b in pairs)
    assert {b - a for a, b in pairs if a == 0} == {1, 2, 3, 4}  # 1..3, and 2^0, 2^1, 2^2
    assert {b - a for a, b in pairs if a == 38} == {1}


def test_rotation_only_fallback_recovers_a_panning_camera():
    import cv2

    H, W = 240, 320
    K = S.intrinsics(W, H, 300.0)
    pano = _texture(3 * H, 3 * W, seed=2)
    R_true = [_rot(1, 2.0 * t) @ _rot(0, 0.7 * t) for t in range(5)]
    images = []
    for R in R_true:
        # Image of a distant texture (plane at infinity, a homography): K R K_pano^-1.
        Kp = S.intrinsics(3 * W, 3 * H, 300.0)
        Hm = K @ R @ np.linalg.inv(Kp)
        images.append(cv2.warpPerspective(pano, Hm, (W, H)))
    images = np.stack(images)
    w2c, ok, stats = S.rotation_only(images, np.ones(images.shape[:3], bool), K)
    assert ok.all(), stats
    from cogs.geometry.rotations import rotmat_geodesic_angle

    for t in range(5):
        rel_est = w2c[t, :3, :3] @ w2c[0, :3, :3].T
        rel_true = R_true[t] @ R_true[0].T
        err = np.degrees(float(rotmat_geodesic_angle(torch.tensor(rel_est), torch.tensor(rel_true))))
        assert err < 0.3, (t, err)


def test_a_camera_that_only_turns_is_not_mapped(tmp_path):
    # The mapper needs an initial pair with parallax; a camera that only turns has none,
    # and COLMAP would try every pair before giving up (6 minutes on a 100-frame clip).
    import cv2

    H, W = 240, 320
    K = S.intrinsics(W, H, 300.0)
    turn = _rot(1, 3.0) @ _rot(0, 1.0)
    H_turn = K @ turn @ np.linalg.inv(K)
    # The same turn seen with the camera also moving 5 % of the way to a wall.
    n, t = np.array([0.0, 0.0, 1.0]), np.array([0.05, 0.0, 0.0])
    H_wall = K @ (turn + np.outer(t, n)) @ np.linalg.inv(K)
    assert S.rotations_only([("PLANAR_OR_PANORAMIC", 400, H_turn), ("PANORAMIC", 300, 2.0 * H_turn)], K)
    assert not S.rotations_only([("PLANAR_OR_PANORAMIC", 400, H_turn), ("PLANAR_OR_PANORAMIC", 400, H_wall)], K)
    assert not S.rotations_only([("PLANAR_OR_PANORAMIC", 400, H_turn), ("CALIBRATED", 400, np.eye(3))], K)
    # Pairs too weak to start the mapper do not count.
    assert S.rotations_only([("PLANAR_OR_PANORAMIC", 400, H_turn), ("CALIBRATED", 20, np.eye(3))], K)
    # End to end: a camera panning over a distant texture.
    pano = _texture(3 * H, 3 * W, seed=2)
    Kp = S.intrinsics(3 * W, 3 * H, 300.0)
    images = np.stack([cv2.warpPerspective(pano, K @ _rot(1, 2.0 * k) @ _rot(0, 0.7 * k) @ np.linalg.inv(Kp), (W, H)) for k in range(5)])
    poses, xyz, _, stats = S.run_colmap(images, np.ones(images.shape[:3], bool), K, tmp_path / "colmap")
    assert poses == {} and len(xyz) == 0 and stats["mapping"].startswith("skipped"), stats


def test_a_fixed_camera_is_told_from_a_probe_of_the_pairs(tmp_path):
    # Pairs among 12 frames spread over the clip: a tripod is known from them, the other
    # pairs are not matched. Too few strong pairs leave the clip to full matching.
    import cv2

    H, W = 240, 320
    K = S.intrinsics(W, H, 300.0)
    pairs = S.image_pairs(100)
    probe = S.probe_pairs(100, pairs)
    assert len(probe) == 66 and {a for a, _ in probe} | {b for _, b in probe} == {0, 9, 18, 27, 36, 45, 54, 63, 72, 81, 90, 99}
    assert S.probe_pairs(12, S.image_pairs(12)) == []  # the probe would be every pair
    H_turn = K @ _rot(1, 3.0) @ np.linalg.inv(K)
    assert S.fixed_camera([("PANORAMIC", 400, H_turn)] * 40, 66, K)
    assert not S.fixed_camera([("PANORAMIC", 400, H_turn)] * 20 + [("PANORAMIC", 30, H_turn)] * 20, 66, K)
    assert not S.fixed_camera([("PANORAMIC", 400, H_turn)] * 40 + [("CALIBRATED", 400, np.eye(3))], 66, K)
    # End to end: 14 frames of a camera panning over a distant texture.
    pano = _texture(3 * H, 3 * W, seed=2)
    Kp = S.intrinsics(3 * W, 3 * H, 300.0)
    images = np.stack([cv2.warpPerspective(pano, K @ _rot(1, 0.6 * k) @ _rot(0, 0.2 * k) @ np.linalg.inv(Kp), (W, H)) for k in range(14)])
    phases = []
    poses, xyz, _, stats = S.run_colmap(images, np.ones(images.shape[:3], bool), K, tmp_path / "colmap",
                                        progress=lambda phase, done, total: phases.append(phase))
    assert poses == {} and stats["mapping"] == "skipped: no pair with parallax among 66 probe pairs", stats
    assert phases[-1] == "mapping"


def test_background_residual_prefers_the_rotations_without_a_jump():
    # A camera panning over a distant texture; the same track with a 0.75 degree jump
    # halfway (what COLMAP gave the basketball clip without parallax) explains the
    # background worse, and the homography chain as well as the truth.
    import cv2

    H, W, T = 120, 160, 12
    K = S.intrinsics(W, H, 150.0)
    Kp = S.intrinsics(3 * W, 3 * H, 150.0)
    pano = _texture(3 * H, 3 * W, seed=3)
    R_true = [_rot(1, 1.5 * t) @ _rot(0, 0.5 * t) for t in range(T)]
    images = np.stack([cv2.warpPerspective(pano, K @ R @ np.linalg.inv(Kp), (W, H)) for R in R_true])
    static = np.ones(images.shape[:3], bool)
    static[:, 40:90, 60:100] = False  # where a person would stand
    w2c = np.tile(np.eye(4), (T, 1, 1))
    w2c[:, :3, :3] = R_true
    jump = w2c.copy()
    jump[T // 2 :, :3, :3] = np.einsum("ij,tjk->tik", _rot(1, 0.75), w2c[T // 2 :, :3, :3])
    chain, ok, _ = S.rotation_only(images, static, K)
    truth, jumped, found = S.background_residuals(images, static, K, [w2c, jump, chain])
    assert ok.all() and truth < 0.7 * jumped, (truth, jumped)
    assert found < 1.1 * truth + 0.5, (found, truth)


def test_a_camera_path_that_teleports_is_told_from_a_walk():
    # A camera walking at 1.5 m/s past points about 4 m away (30 fps) moves 0.375 scene
    # depths per second, at any frame rate it is sampled at and across frames that are not
    # registered; the same path with a 1.2 m jump between two frames and back, as COLMAP gave
    # the tennis clip's panning camera, moves 9 depths per second there and is refused.
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-3, 3, 400), rng.uniform(-2, 2, 400), rng.uniform(3.5, 4.5, 400)])
    T = 60
    w2c = np.tile(np.eye(4), (T, 1, 1))
    w2c[:, 0, 3] = -1.5 * np.arange(T) / 30.0  # centre at x = 1.5 t
    every = np.ones(T, bool)
    speed, a, b = S.fastest_move(w2c, every, points, 30.0)
    depth = float(np.median(points[:, 2]))  # the cameras look along +z
    assert speed == pytest.approx(1.5 / depth, rel=0.05) and speed < S.MAX_CAMERA_SPEED
    assert S.fastest_move(w2c[::3], every[::3], points, 10.0)[0] == pytest.approx(speed, rel=1e-9)
    gaps = every.copy()
    gaps[10:40] = False
    assert S.fastest_move(w2c, gaps, points, 30.0)[0] == pytest.approx(speed, rel=1e-9)
    jumped = w2c.copy()
    jumped[20:30, 0, 3] -= 1.2
    speed, a, b = S.fastest_move(jumped, every, points, 30.0)
    assert speed > S.MAX_CAMERA_SPEED and (a, b) in [(19, 20), (29, 30)], (speed, a, b)
    assert S.fastest_move(w2c, np.zeros(T, bool), points, 30.0) == (0.0, -1, -1)


def test_unregistered_frames_get_interpolated_poses():
    a, b = np.eye(4), np.eye(4)
    b[:3, :3] = _rot(2, 40.0)
    b[:3, 3] = -b[:3, :3] @ np.array([2.0, 0.0, 0.0])  # centre at x = 2
    w2c, reg = S.fill_unregistered({1: a, 3: b}, 5)
    assert reg.tolist() == [False, True, False, True, False]
    np.testing.assert_allclose(w2c[0], a)
    np.testing.assert_allclose(w2c[4], b)
    np.testing.assert_allclose(w2c[2, :3, :3], _rot(2, 20.0), atol=1e-9)
    np.testing.assert_allclose(-w2c[2, :3, :3].T @ w2c[2, :3, 3], [1.0, 0.0, 0.0], atol=1e-9)


def test_world_alignment_keeps_every_projection():
    from cogs.geometry.camera import project_points
    from cogs.preprocess.world import Alignment, _rotation_to_z

    rng = np.random.default_rng(0)
    w2c = np.tile(np.eye(4), (3, 1, 1))
    for t in range(3):
        w2c[t, :3, :3] = _rot(0, 10 * t) @ _rot(1, 5 * t)
        w2c[t, :3, 3] = [0.1 * t, 0.0, 2.0]
    pts = rng.normal(size=(20, 3))
    al = Alignment(scale=3.5, rotation=_rotation_to_z(np.array([0.2, -0.9, 0.1]), np.array([0.0, 0.0, 1.0])),
                   origin=np.array([0.3, 0.2, -0.1]), ground_source="points")
    K = S.intrinsics(64, 48, 50.0)
    for t in range(3):
        uv0, z0 = project_points(pts, w2c[t], K)
        uv1, z1 = project_points(al.points(pts), al.cameras(w2c)[t], K)
        np.testing.assert_allclose(uv1, uv0, atol=1e-9)
        np.testing.assert_allclose(z1, 3.5 * z0, atol=1e-9)  # depth in metres


def test_rotation_to_z_maps_the_normal_up_and_forward_to_y():
    from cogs.preprocess.world import _rotation_to_z

    n = np.array([0.0, -1.0, 0.2])
    n /= np.linalg.norm(n)
    R = _rotation_to_z(n, np.array([1.0, 0.0, 0.0]))
    np.testing.assert_allclose(R @ n, [0, 0, 1], atol=1e-12)
    f = R @ np.array([1.0, 0.0, 0.0])
    assert f[1] > 0.99 and abs(f[0]) < 1e-12
    assert np.linalg.det(R) == pytest.approx(1.0)


# -- body fit -------------------------------------------------------------------------


def _synthetic_keypoints(model, pose, transl, w2c, K):
    """MediaPipe-like keypoints of a posed body: mapped landmarks visible, the rest hidden."""
    from cogs.preprocess.bodyfit import MP_TO_ANNY

    T = len(pose)
    _, joints = model.bone_transforms(pose, transl)
    joints = joints.double().numpy()
    kp2d = np.zeros((T, 33, 3))
    kp3d = np.zeros((T, 33, 3))
    for t in range(T):
        cam = joints[t] @ w2c[t, :3, :3].T + w2c[t, :3, 3]
        hips = 0.5 * (cam[model.bone_index("upperleg01.L")] + cam[model.bone_index("upperleg01.R")])
        for m, b in MP_TO_ANNY:
            p = cam[model.bone_index(b)]
            kp2d[t, m] = [K[0, 0] * p[0] / p[2] + K[0, 2], K[1, 1] * p[1] / p[2] + K[1, 2], 1.0]
            kp3d[t, m] = p - hips
        # Heels and the unmapped landmarks: near the ankles / hips, invisible.
        for m in range(33):
            if kp2d[t, m, 2] == 0:
                kp2d[t, m, :2] = kp2d[t, 27, :2]
                kp3d[t, m] = kp3d[t, 27]
    return kp2d, kp3d, joints


def test_body_fit_reprojects_synthetic_keypoints(body_model):
    from cogs.geometry.camera import look_at
    from cogs.preprocess import bodyfit as B

    m = body_model
    T = 3
    pose = torch.zeros(T, m.n_bones, 3)
    for t in range(T):
        pose[t, m.bone_index("upperarm01.L"), 1] = 0.6 + 0.2 * t
        pose[t, m.bone_index("lowerleg01.R"), 0] = 0.5
        pose[t, m.bone_index("root"), 2] = 0.3
    transl = torch.tensor([[0.0, 0.0, 0.95]] * T)
    H, W = 240, 160
    K = S.intrinsics(W, H, 220.0)
    w2c = np.stack([look_at([0.4 * t, -4.0, 1.2], [0, 0, 0.9]) for t in range(T)])
    kp2d, kp3d, joints = _synthetic_keypoints(m, pose, transl, w2c, K)
    shape = m.default_shape.numpy().astype(np.float64)
    R_cam, t_cam = B.init_camera_space(kp2d, kp3d, K, 1.0)
    # The perspective solve puts the pelvis at the right depth from the metric skeleton.
    true_root_cam = np.einsum("tij,tj->ti", w2c[:, :3, :3], joints[:, m.bone_index("root")]) + w2c[:, :3, 3]
    np.testing.assert_allclose(t_cam[:, 2], true_root_cam[:, 2], rtol=0.05)
    R_w, root_w = B.camera_to_world_init(R_cam, t_cam, w2c)
    fit = B.fit_body(m, kp2d, kp3d, K, w2c, shape, R_w, root_w, ground=(np.array([0.0, 0.0, 1.0]), 0.0), iterations=150)
    assert np.nanmax(fit.reprojection_error) < 0.02, fit.reprojection_error
    assert fit.track.pose.shape == (T, m.n_bones, 3) and np.isfinite(fit.track.pose).all()
    # Metric placement: the fitted pelvis is within 15 cm of the truth.
    err = np.linalg.norm(fit.joints_world[:, m.bone_index("root")] - joints[:, m.bone_index("root")], axis=1)
    assert err.max() < 0.15, err


def test_body_fit_keeps_to_the_ground_only_where_a_foot_is_seen(body_model):
    # A clip cut at the knees: MediaPipe guesses the feet (visibility 0.1) and the ground
    # placed through guessed feet can lie anywhere, here at knee height. The legs must
    # still follow the knees and the 3D landmarks, not fold up to keep the feet above it.
    from cogs.geometry.camera import look_at
    from cogs.preprocess import bodyfit as B

    m = body_model
    T = 3
    pose = torch.zeros(T, m.n_bones, 3)
    transl = torch.tensor([[0.0, 0.0, 0.95]] * T)
    K = S.intrinsics(160, 240, 220.0)
    w2c = np.stack([look_at([0.3 * t, -4.0, 1.2], [0, 0, 0.9]) for t in range(T)])
    kp2d, kp3d, joints = _synthetic_keypoints(m, pose, transl, w2c, K)
    kp2d[:, [27, 28, 29, 30, 31, 32], 2] = 0.1
    shape = m.default_shape.numpy().astype(np.float64)
    R_w, root_w = B.camera_to_world_init(*B.init_camera_space(kp2d, kp3d, K, 1.0), w2c)
    knee_high = (np.array([0.0, 0.0, 1.0]), -0.45)
    ankles = [m.bone_index("foot.L"), m.bone_index("foot.R")]
    fit = B.fit_body(m, kp2d, kp3d, K, w2c, shape, R_w, root_w, ground=knee_high, iterations=150)
    err = np.linalg.norm(fit.joints_world[:, ankles] - joints[:, ankles], axis=-1)
    assert err.max() < 0.1, err
    # Where the feet are seen, the same ground holds them: no sole below it.
    kp2d[:, [27, 28, 31, 32], 2] = 1.0
    fit = B.fit_body(m, kp2d, kp3d, K, w2c, shape, R_w, root_w, ground=knee_high, iterations=150)
    feet = [m.bone_index(b) for b in B.FOOT_BONES]
    sole = B.foot_sole_offsets(m, shape)
    assert (fit.joints_world[:, feet, 2] - sole).min() > 0.45 - 0.05


def test_body_shape_is_an_adult_of_the_given_stature_and_the_landmarks_scale_to_it(body_model):
    # MediaPipe's metric landmarks cannot tell a person's size: the body is an adult as tall
    # as asked, and the landmarks' own scale (here 0.7 of the body's) is measured against it.
    from cogs.preprocess import bodyfit as B

    m = body_model
    names = list(m.shape_names)
    for height in (1.31, 1.62, 1.85, 2.37):
        s = B.choose_shape(m, height_m=height)
        assert abs(B.stature(m, s) - height) < 0.005
        assert s[names.index("age")] == B.ADULT_AGE
    assert B.stature(m, B.choose_shape(m)) == pytest.approx(B.ADULT_STATURE_M, abs=0.005)
    np.testing.assert_allclose(B.stature_range(m), B.STATURE_RANGE_M, atol=0.01)
    s = B.choose_shape(m, height_m=1.80)
    pose = torch.zeros(2, m.n_bones, 3)
    pose[1, m.bone_index("upperarm01.L"), 1] = 0.6
    with torch.no_grad():
        _, joints = m.bone_transforms(pose.double(), torch.zeros(2, 3, dtype=torch.float64), torch.tensor(s, dtype=torch.float64))
    kp3d = np.zeros((2, 33, 3))  # the unmapped landmarks are not used
    for mp, b in B.MP_TO_ANNY:
        kp3d[:, mp] = 0.7 * joints.numpy()[:, m.bone_index(b)]
    assert B.limb_scale(m, s, kp3d) == pytest.approx(1 / 0.7, rel=1e-3)


def test_preprocess_refuses_a_person_height_out_of_reach(tmp_path, capsys):
    from cogs.cli import main
    from cogs.data.io import write_image

    for i in range(3):
        write_image(tmp_path / "in" / f"{i}.png", _texture(96, 128, seed=i))
    for bad in ("170", "0.9", "nan"):
        assert main(["preprocess", str(tmp_path / "in"), "--out", str(tmp_path / "s"), "--person-height", bad]) == 2
        err = capsys.readouterr().err
        assert "--person-height" in err and "metres" in err and "Traceback" not in err
    assert not (tmp_path / "s").exists()


def test_missing_keypoint_frames_are_filled_by_interpolation():
    from cogs.preprocess.bodyfit import fill_missing

    a = np.array([[0.0], [np.nan], [2.0], [np.nan]])
    assert fill_missing(a).ravel().tolist() == [0.0, 1.0, 2.0, 2.0]


# -- masks from the fitted body --------------------------------------------------------


def test_body_parts_are_named_for_anny_and_smpl_bones():
    from cogs.preprocess.bodymasks import bone_parts

    names = ["root", "spine01", "upperarm01.L", "lowerarm01.L", "lowerarm02.R", "wrist.R", "finger3-1.L", "metacarpal2.R",
             "left_shoulder", "left_elbow", "right_wrist", "left_hand", "head"]
    assert bone_parts(names).tolist() == [0, 0, 0, 1, 1, 2, 2, 2, 0, 1, 2, 2, 0]


def _body_masks_frame():
    """A person (shirt and skin) whose mask misses the forearm and bleeds over the scene,
    holding a green box whose mask takes in two fingers."""
    H, W = 160, 200
    rng = np.random.default_rng(0)
    img = np.clip(np.full((H, W, 3), (150, 120, 90)) + rng.integers(-10, 10, (H, W, 3)), 0, 255).astype(np.uint8)
    parts = np.zeros((H, W), np.uint8)
    torso = np.zeros((H, W), bool)
    torso[20:150, 60:100] = True
    img[torso] = (40, 50, 150)
    parts[torso] = 1
    img[22:40, 70:90] = (230, 180, 160)  # the face's skin
    forearm = np.zeros((H, W), bool)
    forearm[90:100, 100:140] = True
    img[forearm] = (230, 180, 160)
    parts[forearm] = 2
    box = np.zeros((H, W), bool)
    box[80:125, 140:185] = True
    img[box] = (40, 170, 60)
    fingers = np.zeros((H, W), bool)
    fingers[88:92, 140:160] = fingers[96:100, 140:158] = True
    img[fingers] = (230, 180, 160)
    box &= ~fingers
    parts[85:103, 138:162] = 3  # the fitted hand, a little larger than the fingers
    person = torso.copy()
    person[90:100, 100:110] = True  # MediaPipe has only the elbow's end of the forearm
    bleed = np.zeros((H, W), bool)
    bleed[30:140, 55:60] = True  # a band of scene along the shirt
    person |= bleed
    obj = box | fingers
    return img, person, obj, parts, torso, forearm, box, fingers, bleed


def test_the_fitted_body_adds_a_missed_forearm_and_takes_fingers_and_bleed_out():
    from cogs.preprocess.bodymasks import refine_frame

    img, person, obj, parts, torso, forearm, box, fingers, bleed = _body_masks_frame()
    human, obj2, info = refine_frame(img, person, obj, parts)
    assert not (human & obj2).any()
    assert (human & forearm).sum() >= 0.95 * forearm.sum()  # the forearm joins the person
    assert not (obj2 & fingers).any() and (obj2 & box).sum() == box.sum()  # the box keeps its pixels, not the fingers
    assert not (human & bleed).any() and (human & torso).sum() == torso.sum()  # the bleed goes, the shirt stays
    assert info["forearm_px"] > 0 and info["finger_px"] == fingers.sum() and info["bleed_px"] == bleed.sum()


def test_without_a_fitted_body_or_with_given_masks_the_masks_only_become_disjoint():
    from cogs.preprocess.bodymasks import refine_masks
    from cogs.preprocess.segment import align_to_edges

    img, person, obj, parts, *_ = _body_masks_frame()
    # No body: disjoint, the outlines onto the frame's edges (the object's is on them already here).
    edged = align_to_edges(img, person & ~obj, keep_thin=False) & ~obj
    human, obj2, stats = refine_masks(img[None], person[None], obj[None], np.zeros_like(parts)[None], np.array([True]))
    assert (obj2[0] == obj).all() and (human[0] == edged).all()
    human, obj2, _ = refine_masks(img[None], person[None], obj[None], parts[None], np.array([False]))  # no detection: untouched
    assert (obj2[0] == obj).all() and (human[0] == (person & ~obj)).all()
    human, obj2, _ = refine_masks(img[None], person[None], None, parts[None], np.array([True]))
    assert obj2 is None and human[0].sum() > 0
    # Masks from the user or SAM2 are kept: no fingers taken out, no person outline moved.
    human, obj2, _ = refine_masks(img[None], person[None], obj[None], parts[None], np.array([True]), fingers=False, person_edges=False)
    assert (obj2[0] == obj).all() and (human[0] == (person & ~obj)).all()
    # A body fit far off its keypoints in a frame is no evidence there.
    human, obj2, stats = refine_masks(img[None], person[None], obj[None], parts[None], np.array([True]), fit_error=np.array([0.3]))
    assert (obj2[0] == obj).all() and (human[0] == edged).all() and stats["frames_body_unfit"] == 1
    human, obj2, stats = refine_masks(img[None], person[None], obj[None], parts[None], np.array([True]), fit_error=np.array([0.02]))
    assert (human[0] != edged).any() and stats["frames_body_unfit"] == 0


def test_an_object_held_in_front_of_the_body_grows_by_the_pixels_that_move_with_it():
    import cv2

    from cogs.preprocess.bodymasks import motion_grow

    rng = np.random.default_rng(0)
    H, W = 160, 200
    shirt_tex = cv2.GaussianBlur(rng.integers(0, 255, (H + 40, W + 40, 3)).astype(np.uint8), (5, 5), 0)
    box_tex = cv2.GaussianBlur(rng.integers(0, 255, (44, 44, 3)).astype(np.uint8), (5, 5), 0)
    images, boxes = [], []
    T = 5
    for t in range(T):
        img = shirt_tex[3 * t:3 * t + H, 10:10 + W].copy()  # the shirt moves up 3 px a frame
        x0 = 60 + 5 * t  # the box moves right 5 px a frame, in front of the shirt
        img[60:104, x0:x0 + 44] = box_tex
        box = np.zeros((H, W), bool)
        box[60:104, x0:x0 + 44] = True
        images.append(img)
        boxes.append(box)
    images, boxes = np.stack(images), np.stack(boxes)
    person = np.zeros((T, H, W), bool)
    person[:, 10:150, 20:180] = True  # MediaPipe's mask takes the box in
    obj = boxes.copy()
    # Seen whole in the first three frames, then a face is missed: half the box (a convex
    # mask, but half the size the tracker saw around it).
    obj[3:, :, :] &= np.arange(W)[None, None, :] < (60 + 5 * np.arange(T))[3:, None, None] + 22
    parts = np.zeros((T, H, W), np.uint8)
    grown, added = motion_grow(images, person, obj, parts, np.ones(T, bool))
    assert added > 0
    for t in (3, 4):
        missed = boxes[t] & ~obj[t]
        assert (grown[t] & missed).sum() >= 0.6 * missed.sum()  # the missed face moves with the box: it joins
        assert (grown[t] & ~boxes[t]).sum() <= 0.05 * boxes[t].sum()  # the shirt moves otherwise: it stays out
    # Off the person (not held in front of the body) the test does not apply.
    grown, added = motion_grow(images, np.zeros_like(person), obj, parts, np.ones(T, bool))
    assert added == 0 and (grown == obj).all()
    # Half the box from frame 1 on: as convex and as large as its neighbours, so taken for
    # the whole box, unless the tracker saw it clearly (and twice as large) elsewhere.
    half = boxes.copy()
    half[1:] &= np.arange(W)[None, None, :] < (60 + 5 * np.arange(T))[1:, None, None] + 22
    grown, added = motion_grow(images, person, half, parts, np.ones(T, bool))
    assert added == 0
    grown, added = motion_grow(images, person, half, parts, np.ones(T, bool), np.full(T, 0.5))
    assert added == 0  # no frame seen clearly
    grown, added = motion_grow(images, person, half, parts, np.ones(T, bool), np.r_[1.0, np.full(T - 1, 0.5)])
    for t in range(2, T):
        missed = boxes[t] & ~half[t]
        assert (grown[t] & missed).sum() >= 0.6 * missed.sum()
        assert (grown[t] & ~boxes[t]).sum() <= 0.05 * boxes[t].sum()


def test_a_whole_ball_in_front_of_a_moving_leg_does_not_take_the_leg_in():
    """A juggled ball: the tracker's mask is the whole ball in every frame (convex, steady
    size) while the kicking leg behind it moves with it; the rest of the person moves
    otherwise. The leg stays out of the object's mask."""
    import cv2

    from cogs.preprocess.bodymasks import motion_grow

    rng = np.random.default_rng(2)
    H, W, T = 160, 200, 7
    body_tex = cv2.GaussianBlur(rng.integers(0, 255, (H + 40, W + 40, 3)).astype(np.uint8), (5, 5), 0)
    leg_tex = cv2.GaussianBlur(rng.integers(0, 255, (90, 30, 3)).astype(np.uint8), (5, 5), 0)
    ball_tex = cv2.GaussianBlur(rng.integers(0, 255, (40, 40, 3)).astype(np.uint8), (5, 5), 0)
    disk = np.hypot(*np.mgrid[-19.5:20, -19.5:20]) <= 19
    images, balls, legs = [], [], []
    for t in range(T):
        img = body_tex[20 - 3 * t:20 - 3 * t + H, 10:10 + W].copy()  # the body moves down 3 px a frame
        y0 = 60 - 4 * t  # the leg and the ball in front of it rise 4 px a frame together
        img[y0:y0 + 90, 90:120] = leg_tex
        ball = np.zeros((H, W), bool)
        ball[y0:y0 + 40, 85:125] = disk
        img[ball] = ball_tex[disk]
        leg = np.zeros((H, W), bool)
        leg[y0:y0 + 90, 90:120] = True
        images.append(img)
        balls.append(ball)
        legs.append(leg & ~ball)
    images, balls, legs = np.stack(images), np.stack(balls), np.stack(legs)
    person = np.zeros((T, H, W), bool)
    person[:, 5:155, 40:170] = True
    parts = np.zeros((T, H, W), np.uint8)
    grown, added = motion_grow(images, person, balls, parts, np.ones(T, bool))
    assert added == 0 and (grown == balls).all()
    # A speck of 3 px half a ball below it (the tracker leaves such specks) does not make the
    # ball look less than whole.
    specked = balls.copy()
    for t in range(T):
        specked[t, 60 - 4 * t + 60:60 - 4 * t + 63, 104] = True
    grown, added = motion_grow(images, person, specked, parts, np.ones(T, bool))
    assert added == 0 and (grown == specked).all()
    # The same scene with the tracker missing the ball's lower half from frame 4 on: that
    # half grows back (the motion test itself still works here).
    half = balls & (np.arange(H)[None, :, None] < (60 - 4 * np.arange(T))[:, None, None] + 20)
    half[:4] = balls[:4]
    grown, added = motion_grow(images, person, half, parts, np.ones(T, bool))
    for t in (4, 5, 6):
        missed = balls[t] & ~half[t]
        assert (grown[t] & missed).sum() >= 0.6 * missed.sum()


def test_the_motions_that_tell_a_held_object_from_the_shirt_must_differ_more_on_larger_frames():
    # A box held in front of the body, a face of it turning into view beside it and moving
    # with it by 3 px, the shirt still. At 384 px (where the 2 px bound was chosen) the face
    # joins the box; on a 960 px frame 3 px is what 1.2 px is at 384, under the bound, and
    # nothing grows; 7.5 px there (3 px at 384) grows it again.
    from cogs.preprocess.bodymasks import motion_grow_frame

    def held_box(side, shift):
        yy, xx = np.mgrid[:side, :side]
        box = (np.abs(xx - 150) <= 20) & (np.abs(yy - 150) <= 20)
        face = (xx > 170) & (xx <= 180) & (np.abs(yy - 150) <= 20)
        person = (np.abs(xx - 150) <= 90) & (np.abs(yy - 150) <= 90)
        flow = np.zeros((side, side, 2), np.float32)
        flow[box | face] = (shift, 0.0)
        return motion_grow_frame(box, person, np.zeros_like(box), flow), face

    add, face = held_box(384, 3.0)
    assert (add & face).sum() >= 0.9 * face.sum() and not (add & ~face).any()
    add, face = held_box(960, 3.0)
    assert not add.any()
    add, face = held_box(960, 7.5)
    assert (add & face).sum() >= 0.9 * face.sum() and not (add & ~face).any()


def test_a_ball_beside_the_body_is_not_taken_for_one_held_in_front_of_it_on_a_larger_frame():
    # A ball beside the body, MediaPipe's person mask spreading a pixel of a 384 px frame
    # past it, and the flow's halo: two such pixels round the ball moving with it. Growth
    # runs only for an object whose outline lies mostly inside the person mask; that outline
    # is a ring of 3 px at 384, which reaches past the spread: nothing grows. At 960 px the
    # spread is 3 px and the halo 4: a ring of 3 px lay inside the spread, the ball counted as
    # held in front of the body, and the halo grew into it. As much of the frame, it does not.
    from cogs.preprocess.bodymasks import motion_grow_frame
    from cogs.preprocess.segment import grown

    def beside_the_body(side):
        k = side / 384
        yy, xx = np.mgrid[:side, :side]
        c, r = 200 * k, 30 * k
        ball = (xx - c) ** 2 + (yy - c) ** 2 <= r**2
        torso = (xx < c - r) & (xx > c - 160 * k) & (np.abs(yy - c) <= 120 * k)
        person = torso | grown(ball, round(1.2 * k))
        flow = np.zeros((side, side, 2), np.float32)
        flow[grown(ball, round(1.6 * k))] = (4.0 * k, 0.0)
        return motion_grow_frame(ball, person, np.zeros_like(ball), flow)

    assert not beside_the_body(384).any()
    assert not beside_the_body(960).any()


def test_a_held_object_that_suddenly_shrinks_is_filled_back_in_from_the_previous_frame():
    import cv2

    from cogs.preprocess.bodymasks import motion_grow

    rng = np.random.default_rng(1)
    H, W = 160, 200
    tex = cv2.GaussianBlur(rng.integers(0, 255, (H, W + 20, 3)).astype(np.uint8), (5, 5), 0)
    # Box and shirt move together (2 px right a frame): the flow cannot tell them apart.
    images = np.stack([tex[:, 20 - 2 * t:20 - 2 * t + W] for t in range(2)])
    boxes = np.zeros((2, H, W), bool)
    for t in range(2):
        boxes[t, 60:104, 60 + 2 * t:104 + 2 * t] = True
    person = np.zeros((2, H, W), bool)
    person[:, 10:150, 20:180] = True
    obj = boxes.copy()
    obj[1, :, 84:] = False  # the tracker keeps half the box in frame 1
    parts = np.zeros((2, H, W), np.uint8)
    grown, _ = motion_grow(images, person, obj, parts, np.ones(2, bool))
    assert (grown[1] & boxes[1]).sum() >= 0.95 * boxes[1].sum()
    assert (grown[1] & ~boxes[1]).sum() <= 0.02 * boxes[1].sum()
    # Not held in front of the body (off the person mask): left as it is.
    grown, _ = motion_grow(images, np.zeros_like(person), obj, parts, np.ones(2, bool))
    assert (grown == obj).all()


# -- object pose ----------------------------------------------------------------------


def test_object_fit_recovers_a_ball_carried_by_a_hand():
    from cogs.geometry.camera import look_at
    from cogs.preprocess.objectfit import ellipsoid_points, fit_object, silhouette

    T, H, W = 6, 240, 320
    K = S.intrinsics(W, H, 300.0)
    w2c = np.stack([look_at([0.1 * t, -3.0, 1.0], [0, 0, 0.8]) for t in range(T)])
    centres = np.array([[0.3, 0.0, 0.8 + 0.05 * t] for t in range(T)])
    r = 0.12
    pts = ellipsoid_points(np.array([r, r, r]), 400)
    masks = np.stack([silhouette(pts @ w2c[t, :3, :3].T + (w2c[t, :3, :3] @ centres[t] + w2c[t, :3, 3]), K, (H, W)) for t in range(T)])
    hand = centres[:, None, :] + np.array([0.0, 0.0, 0.13])  # the hand on top of the ball
    root = np.tile([0.0, 0.0, 0.9], (T, 1))
    fit = fit_object(masks, np.ones(T), K, w2c, np.repeat(hand, 4, axis=1), root, ground=(np.array([0.0, 0.0, 1.0]), 0.0))
    assert fit.radii_m == pytest.approx([r, r, r], rel=0.15)
    err = np.linalg.norm(fit.track.translations - centres, axis=1)
    assert err.max() < 0.07, err  # about 2 % of the 3 m to the camera
    assert np.nanmin(fit.iou) > 0.85
    # A floor 2 m above the ball (a shelf taken for the floor): the masks are trusted, the
    # ball is not lifted off screen onto it.
    fit = fit_object(masks, np.ones(T), K, w2c, np.repeat(hand, 4, axis=1), root, ground=(np.array([0.0, 0.0, 1.0]), -2.0))
    assert np.linalg.norm(fit.track.translations - centres, axis=1).max() < 0.07
    assert np.nanmin(fit.iou) > 0.85



def test_viterbi_keeps_the_smooth_path_through_a_frame_that_prefers_a_far_state():
    from cogs.preprocess.objectfit import viterbi

    # States on a line; frame 2's evidence is slightly better at a far state than at the one
    # its neighbours agree on: turning there and back costs more than it gains.
    pos = np.arange(5.0)
    pairwise = 0.5 * np.abs(pos[:, None] - pos[None])
    unary = np.ones((5, 5))
    unary[:, 1] = 0.0
    unary[2, 1], unary[2, 4] = 0.3, 0.0
    assert viterbi(unary, pairwise).tolist() == [1, 1, 1, 1, 1]
    # Strong, lasting evidence does move it.
    unary[2:, 4] = -1.0
    assert viterbi(unary, pairwise).tolist() == [1, 1, 4, 4, 4]


def test_object_fit_keeps_a_box_at_rest_still_while_the_camera_circles_it():
    # One silhouette of a box fits the box and its mirror image through the image plane
    # alike; fitted frame by frame the rotation flips between the two as the view changes.
    # Over the clip only the true rotation stays still in the world.
    from cogs.geometry.camera import look_at
    from cogs.preprocess.objectfit import cuboid_points, fit_object, silhouette

    T, H, W = 10, 240, 320
    K = S.intrinsics(W, H, 400.0)
    w2c = np.stack([look_at([2.5 * np.sin(np.radians(6 * t - 30)), -2.5 * np.cos(np.radians(6 * t - 30)), 1.3], [0.2, 0, 0.9])
                    for t in range(T)])
    axis = np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])
    R_box = _rot_about(axis, 40.0) @ _rot(0, 30.0)
    centre = np.array([0.2, 0.0, 0.9])
    corners = cuboid_points(np.array([0.15, 0.10, 0.06])) @ R_box.T + centre
    masks = np.stack([silhouette(corners @ w2c[t, :3, :3].T + w2c[t, :3, 3], K, (H, W)) for t in range(T)])
    hand = np.tile(centre + [0.0, 0.0, 0.05], (T, 4, 1))  # the hand on the box
    fit = fit_object(masks, np.ones(T), K, w2c, hand, np.tile([0.0, 0.0, 0.9], (T, 1)), ground=(np.array([0.0, 0.0, 1.0]), 0.0))
    R = fit.track.rotation_matrices()
    turn = np.degrees(np.arccos(np.clip((np.einsum("tij,ij->t", R, R[0]) - 1) / 2, -1, 1)))  # since the first frame
    assert turn.max() < 20.0 and turn.mean() < 12.0, turn
    assert np.linalg.norm(fit.track.translations - centre, axis=1).max() < 0.15  # 6 % of the 2.5 m to the camera
    assert np.nanmin(fit.iou) > 0.8


def _box_clip(w2c: np.ndarray, centres: np.ndarray, K: np.ndarray, shape=(240, 320)):
    from cogs.preprocess.objectfit import cuboid_points, silhouette

    R_box = _rot_about(np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8]), 40.0) @ _rot(0, 30.0)
    corners = cuboid_points(np.array([0.15, 0.10, 0.06])) @ R_box.T
    return np.stack([silhouette((corners + c) @ w[:3, :3].T + w[:3, 3], K, shape) for w, c in zip(w2c, centres)])


def _circling(T: int, step_deg: float = 6.0) -> np.ndarray:
    from cogs.geometry.camera import look_at

    return np.stack([look_at([2.5 * np.sin(np.radians(step_deg * t - 30)), -2.5 * np.cos(np.radians(step_deg * t - 30)), 1.3], [0.2, 0, 0.9])
                     for t in range(T)])


def test_rest_positions_triangulate_a_resting_object_and_refuse_a_moving_one_or_a_still_camera():
    from cogs.preprocess.objectfit import _CoarseMask, rest_positions

    T = 10
    K = S.intrinsics(320, 240, 400.0)
    centre = np.array([0.2, 0.0, 0.9])
    w2c = _circling(T)
    frames = [_CoarseMask(m, K) for m in _box_clip(w2c, np.tile(centre, (T, 1)), K)]
    X = rest_positions(frames, w2c, K, np.ones(T, bool))
    assert np.isfinite(X).all()
    # The mask centroid is not quite the centre's image: a few cm at 2.5 m.
    assert np.linalg.norm(X - centre, axis=1).max() < 0.05
    # Frames left out are not given a position.
    X = rest_positions(frames, w2c, K, np.arange(T) != 4)
    assert np.isnan(X[4]).all() and np.isfinite(X[np.arange(T) != 4]).all()
    # Rising 4 cm a frame (a ball in the air) while the camera moves sideways: no fixed point.
    moving = centre + np.outer(np.arange(T), [0.0, 0.0, 0.04])
    frames = [_CoarseMask(m, K) for m in _box_clip(w2c, moving, K)]
    assert np.isnan(rest_positions(frames, w2c, K, np.ones(T, bool))).all()
    # A window found is extended over frames left out (a hand at the still box) while their
    # centroids stay on its point, and not once the box rises.
    frames = [_CoarseMask(m, K) for m in _box_clip(w2c, np.tile(centre, (T, 1)), K)]
    X = rest_positions(frames, w2c, K, np.arange(T) < 6, extend=np.ones(T, bool))
    assert np.isfinite(X).all() and np.allclose(X, X[0])
    lifted = np.tile(centre, (T, 1)) + np.outer(np.maximum(np.arange(T) - 6, 0), [0.0, 0.0, 0.05])
    frames = [_CoarseMask(m, K) for m in _box_clip(w2c, lifted, K)]
    X = rest_positions(frames, w2c, K, np.arange(T) < 6, extend=np.ones(T, bool))
    assert np.isfinite(X[:7]).all() and np.isnan(X[7:]).all(), X
    # A nearly still camera (2.7 degrees round the box in all) sees too little parallax.
    still = _circling(T, step_deg=0.3)
    frames = [_CoarseMask(m, K) for m in _box_clip(still, np.tile(centre, (T, 1)), K)]
    assert np.isnan(rest_positions(frames, still, K, np.ones(T, bool))).all()


def test_object_fit_takes_a_resting_objects_depth_from_the_moving_camera():
    # No hand at the box and the person a metre behind it: without its rest the box would
    # be placed as far as the person, 40 % too far.
    from cogs.preprocess.objectfit import fit_object

    T = 10
    K = S.intrinsics(320, 240, 400.0)
    centre = np.array([0.2, 0.0, 0.9])
    w2c = _circling(T)
    masks = _box_clip(w2c, np.tile(centre, (T, 1)), K)
    cam_centres = -np.einsum("tji,tj->ti", w2c[:, :3, :3], w2c[:, :3, 3])
    away = centre - cam_centres
    root = centre + away / np.linalg.norm(away, axis=1, keepdims=True)
    hand = np.tile([-0.8, 0.0, 1.6], (T, 4, 1))  # a raised hand, far from the box in every view
    fit = fit_object(masks, np.ones(T), K, w2c, hand, root, ground=(np.array([0.0, 0.0, 1.0]), 0.0))
    assert fit.depth_source == ["rest"] * T
    depth_err = np.linalg.norm(fit.track.translations - centre, axis=1) / np.linalg.norm(away, axis=1)
    assert depth_err.max() < 0.02, depth_err


def test_a_held_objects_depth_from_its_size_stays_within_reach_of_the_hand_holding_it():
    # A box held still in the right hand 2.5 m from a still camera. From frame 6 on its
    # silhouette is half as wide (as a flat object's is when the rotation chosen shows it
    # more face-on than it is): its size alone would put it 5 m away, 2.5 m behind the hand.
    from cogs.geometry.camera import look_at
    from cogs.preprocess.objectfit import HAND_LENGTH_M, cuboid_points, fit_object, silhouette

    T, H, W = 10, 240, 320
    K = S.intrinsics(W, H, 400.0)
    w2c = np.tile(look_at([0.0, -2.5, 0.9], [0.0, 0.0, 0.9]), (T, 1, 1))
    centre = np.array([0.0, 0.0, 0.9])
    half = np.array([0.15, 0.10, 0.06])
    R_box = _rot_about(np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8]), 40.0)
    masks = np.stack([silhouette((cuboid_points(half * (1.0 if t < 6 else 0.5)) @ R_box.T + centre) @ w2c[t, :3, :3].T + w2c[t, :3, 3],
                                 K, (H, W)) for t in range(T)])
    hand = np.tile([[-0.6, 0.0, 1.0], [0.12, 0.0, 0.9]] * 2, (T, 1, 1))  # left hand away, right hand at the box
    root = np.tile([0.0, 0.3, 0.9], (T, 1))
    fit = fit_object(masks, np.ones(T), K, w2c, hand, root, ground=(np.array([0.0, 0.0, 1.0]), 0.0), n_hypotheses=300)
    depth = np.einsum("ij,tj->ti", w2c[0, :3, :3], fit.track.translations)[:, 2] + w2c[0, 2, 3]
    reach = 2.0 * fit.radii_m.max() + HAND_LENGTH_M
    # The first frames fix the size; later ones that outrun the hand are brought back to it.
    assert np.abs(depth[:6] - 2.5).max() < 0.15, depth
    assert set(fit.depth_source[6:]) == {"reach"}, fit.depth_source
    assert (np.abs(depth - 2.5) <= reach + 0.05).all(), (depth, reach)
    # Away from the hands the size alone decides: nothing holds the object.
    far = np.tile([-0.6, 0.0, 1.6], (T, 4, 1))
    fit = fit_object(masks, np.ones(T), K, w2c, far, root, ground=(np.array([0.0, 0.0, 1.0]), 0.0), n_hypotheses=300)
    assert "reach" not in fit.depth_source
    depth = np.einsum("ij,tj->ti", w2c[0, :3, :3], fit.track.translations)[:, 2] + w2c[0, 2, 3]
    assert depth[7:].min() > 2.5 + reach, depth


def test_object_fit_keeps_one_rotation_while_the_object_rests():
    # A box whose proportions lie between the proxy's candidates, resting with no hand at it:
    # fitted frame by frame, each view's best proxy pose turned its own way (the wrong shape
    # fits each outline differently); at rest the frames share one rotation in the world.
    from cogs.preprocess.objectfit import cuboid_points, fit_object, rest_windows, silhouette

    T, H, W = 12, 240, 320
    K = S.intrinsics(W, H, 400.0)
    centre = np.array([0.2, 0.0, 0.9])
    w2c = _circling(T)
    R_box = _rot_about(np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8]), 40.0) @ _rot(0, 30.0)
    corners = cuboid_points(np.array([0.15, 0.12, 0.05])) @ R_box.T + centre
    masks = np.stack([silhouette(corners @ w[:3, :3].T + w[:3, 3], K, (H, W)) for w in w2c])
    cam_centres = -np.einsum("tji,tj->ti", w2c[:, :3, :3], w2c[:, :3, 3])
    away = centre - cam_centres
    root = centre + away / np.linalg.norm(away, axis=1, keepdims=True)
    hand = np.tile([-0.8, 0.0, 1.6], (T, 4, 1))
    fit = fit_object(masks, np.ones(T), K, w2c, hand, root, ground=(np.array([0.0, 0.0, 1.0]), 0.0))
    assert fit.depth_source == ["rest"] * T
    R = fit.track.rotation_matrices()
    turn = np.degrees(np.arccos(np.clip((np.einsum("tij,ij->t", R, R[0]) - 1) / 2, -1, 1)))
    assert turn.max() < 0.5, turn
    assert np.nanmin(fit.iou) > 0.8, fit.iou
    # Windows are runs of frames at one point.
    X = np.full((7, 3), np.nan)
    X[1:3], X[3:5] = [0.0, 0.0, 1.0], [0.0, 0.1, 1.0]
    assert rest_windows(X).tolist() == [-1, 0, 0, 1, 1, -1, -1]


def test_object_proxy_holds_when_a_frame_leaves_the_clear_views():
    # A box between the proxy's candidate shapes (1 : 0.8 : 0.35), circled by the camera,
    # its masks a pixel too wide or too narrow here and there: the candidates nearly tie.
    # Chosen on a few sampled views, the shape flipped when one mask's confidence fell
    # under the clear views' 0.8 (the tennis racket, one frame: its whole trajectory moved).
    import cv2

    from cogs.geometry.camera import look_at
    from cogs.preprocess.objectfit import cuboid_points, fit_object, silhouette

    T, H, W = 40, 120, 160
    K = S.intrinsics(W, H, 200.0)
    w2c = np.stack([look_at([2.5 * np.sin(np.radians(9.0 * t)), -2.5 * np.cos(np.radians(9.0 * t)), 1.3 + 0.4 * np.sin(np.radians(18.0 * t))],
                            [0.2, 0, 0.9]) for t in range(T)])
    R_box = _rot_about(np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8]), 40.0)
    corners = cuboid_points(np.array([0.2, 0.16, 0.07])) @ R_box.T + np.array([0.2, 0.0, 0.9])
    rng = np.random.default_rng(1)
    masks = []
    for w in w2c:
        m = silhouette(corners @ w[:3, :3].T + w[:3, 3], K, (H, W)).astype(np.uint8)
        grow = int(rng.integers(-1, 2))
        m = cv2.dilate(m, np.ones((3, 3), np.uint8)) if grow > 0 else cv2.erode(m, np.ones((3, 3), np.uint8)) if grow < 0 else m
        masks.append(m.astype(bool))
    masks = np.stack(masks)
    hand, root = np.tile([-0.8, 0.0, 1.6], (T, 4, 1)), np.tile([-0.8, 0.5, 0.9], (T, 1))

    def proxy(confidence):
        fit = fit_object(masks, confidence, K, w2c, hand, root, ground=(np.array([0.0, 0.0, 1.0]), 0.0), n_hypotheses=300)
        return fit.kind, np.round(np.sort(fit.radii_m)[::-1] / fit.radii_m.max(), 2).tolist()

    kind, ratios = proxy(np.ones(T))
    assert kind == "cuboid" and ratios[2] < 0.5, ratios  # a flat box
    doubted = np.ones(T)
    doubted[[10, 30]] = 0.5  # two views no longer clear (they still count for the pose)
    assert proxy(doubted) == (kind, ratios)


def test_a_flat_object_seen_face_on_where_it_is_clear_gets_a_flat_proxy():
    # A racket's head: a flat disc (1 : 1 : 0.25), face-on to the camera wherever the
    # tracker is sure of it, and edge-on only in views the person partly hides (confidence
    # 0.6). Face-on, every thickness casts the same outline: the partial views tell it.
    from cogs.geometry.camera import look_at
    from cogs.preprocess.objectfit import ellipsoid_points, fit_object, silhouette

    T, H, W = 40, 120, 160
    K = S.intrinsics(W, H, 200.0)
    w2c = np.tile(look_at([0.0, -2.5, 1.0], [0.0, 0.0, 1.0]), (T, 1, 1))
    pts = ellipsoid_points(np.array([0.16, 0.16, 0.04]), 400)
    face_on = _rot(0, 90.0)  # the disc's normal along the view
    turn = [face_on if t < 20 else _rot(2, 4.5 * (t - 19)) @ face_on for t in range(T)]  # then turning edge-on
    centre = np.array([0.0, 0.0, 1.0])
    masks = np.stack([silhouette((pts @ R.T + centre) @ w2c[0, :3, :3].T + w2c[0, :3, 3], K, (H, W)) for R in turn])
    confidence = np.where(np.arange(T) < 20, 1.0, 0.6)
    hand, root = np.tile(centre + [0.0, 0.0, -0.2], (T, 4, 1)), np.tile([0.3, 0.3, 0.9], (T, 1))
    fit = fit_object(masks, confidence, K, w2c, hand, root, ground=(np.array([0.0, 0.0, 1.0]), 0.0), n_hypotheses=300)
    ratios = np.sort(fit.radii_m)[::-1] / fit.radii_m.max()
    assert ratios[1] > 0.6 and ratios[2] < 0.35, (fit.kind, ratios)


def test_fill_rotations_turns_a_hidden_held_object_with_its_carrier():
    from cogs.preprocess.objectfit import fill_rotations

    T = 9
    carrier = np.stack([_rot(2, 35.0 * t) for t in range(T)])  # the person turning round, 35 degrees a frame
    R0 = _rot_about(np.array([0.6, 0.0, 0.8]), 50.0)
    truth = np.einsum("tij,jk->tik", carrier, R0)  # held still in the hand
    has = np.array([1, 1, 0, 0, 0, 0, 0, 1, 1], bool)
    R = np.where(has[:, None, None], truth, np.eye(3))
    angle = lambda A, B: np.degrees(np.arccos(np.clip((np.einsum("tij,tij->t", A, B) - 1) / 2, -1, 1)))
    filled = fill_rotations(R, has, np.ones(T, bool), carrier)
    assert angle(filled, truth).max() < 1e-4
    # Not held at both ends, or no carrier: the shorter arc, which takes the 210 degrees the
    # hidden frames turned the other way round (150 degrees), in even steps between the ends
    # instead of the identity the hidden frames held.
    for held, c in ((np.arange(T) < 5, carrier), (np.ones(T, bool), None)):
        arc = fill_rotations(R, has, held, c)
        assert angle(arc[2:8], arc[1:7]).max() < 26.0  # frames 1 -> 7
        assert angle(arc, truth)[~has].max() > 1.0
    # Before the first and after the last mask: the nearest one's.
    edge = np.array([0, 1, 1, 1, 1, 1, 1, 1, 0], bool)
    out = fill_rotations(np.where(edge[:, None, None], truth, np.eye(3)), edge, np.ones(T, bool), carrier)
    assert np.allclose(out[0], truth[1]) and np.allclose(out[-1], truth[-2])


def _carried_box(T=16, H=240, W=320):
    """A box at rest for six frames while the camera circles
    it, then carried and turned by a forearm: (masks, K, w2c, hand, root, forearms, true
    rotations, true centres, resting frames)."""
    from cogs.preprocess.objectfit import cuboid_points, silhouette

    K = S.intrinsics(W, H, 400.0)
    w2c = _circling(T)
    R_box = _rot_about(np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8]), 40.0) @ _rot(0, 30.0)
    rest = np.arange(T) < 6
    forearm = np.stack([_rot_about(np.array([0.2, 0.0, 1.0]) / np.hypot(0.2, 1.0), 30.0 * max(t - 5, 0)) for t in range(T)])
    R_true = np.einsum("tij,jk->tik", forearm, R_box)
    centres = np.array([[0.2, 0.0, 0.9 + 0.05 * max(t - 5, 0)] for t in range(T)])
    half = np.array([0.15, 0.10, 0.06])
    masks = np.stack([silhouette((cuboid_points(half) @ R_true[t].T + centres[t]) @ w2c[t, :3, :3].T + w2c[t, :3, 3], K, (H, W))
                      for t in range(T)])
    hand = np.where(rest[:, None, None], np.array([-0.8, 0.0, 1.6]), centres[:, None, :] + [0.0, 0.0, 0.05])
    return masks, K, w2c, np.repeat(hand, 4, axis=1), np.tile([-0.5, 0.3, 0.9], (T, 1)), np.stack([forearm, forearm], 1), R_true, centres, rest


def test_object_fit_turns_a_carried_box_with_the_forearm_that_holds_it():
    # A box rests (the camera circling it), then a hand takes it and the forearm turns it
    # 30 degrees a frame while lifting it, partly hidden by the hand (low confidence) and
    # out of sight for three frames: the silhouettes cannot follow that, the forearm can.
    # Its rotation at rest is the anchor: the box then keeps its grasp on the forearm.
    from cogs.preprocess.objectfit import carry_in_hand, fit_object

    masks, K, w2c, hand, root, forearms, R_true, _, rest = _carried_box()
    T = len(masks)
    masks[9:12] = False
    confidence = np.where(rest, 1.0, 0.3)
    fit = fit_object(masks, confidence, K, w2c, hand, root, ground=(np.array([0.0, 0.0, 1.0]), 0.0), forearm_world=forearms)
    R = fit.track.rotation_matrices()
    # The box's symmetric twins (half-turns about its axes) have the same silhouettes: the
    # rotation is compared as it is, not up to them.
    angle = lambda A, B: np.degrees(np.arccos(np.clip((np.einsum("tij,tij->t", A, B) - 1) / 2, -1, 1)))
    rel = lambda Rs: np.einsum("tij,kj->tik", Rs, Rs[0])  # since the first frame (the world's own rotation is free)
    err = angle(rel(R), rel(R_true))
    assert err.max() < 12.0, err.round(1)
    assert fit.carried.tolist() == (~rest).tolist()  # from the grasp on, the hidden frames too
    # carry_in_hand itself: a stretch without an anchor either side is left as it is.
    held = ~rest
    out, carried_by = carry_in_hand(R_true, np.ones(T, bool), held, np.zeros(T, int), forearms, np.zeros(T, bool))
    assert (carried_by < 0).all() and np.allclose(out, R_true)


def test_a_box_at_rest_tracked_with_middling_confidence_still_anchors_its_carry():
    # Found again with faces the prompt never showed, a box on the table keeps a middling
    # confidence (0.37 on the synthetic video benchmark's variant 1, at 0.97 IoU): trusted,
    # so its rest is measured and its rotation there anchors the carry that follows.
    from cogs.preprocess.objectfit import fit_object

    masks, K, w2c, hand, root, forearms, R_true, _, rest = _carried_box()
    confidence = np.where(rest, 0.37, 0.3)
    ground = (np.array([0.0, 0.0, 1.0]), 0.0)
    fit = fit_object(masks, confidence, K, w2c, hand, root, ground=ground, forearm_world=forearms)
    assert fit.depth_source[:6] == ["rest"] * 6
    assert fit.carried.tolist() == (~rest).tolist()
    angle = lambda A, B: np.degrees(np.arccos(np.clip((np.einsum("tij,tij->t", A, B) - 1) / 2, -1, 1)))
    rel = lambda Rs: np.einsum("tij,kj->tik", Rs, Rs[0])
    err = angle(rel(fit.track.rotation_matrices()), rel(R_true))
    # (the rest's last frame, weighted by its confidence, is pulled towards the turn by the
    # smoother: 13 degrees)
    assert err[~rest].max() < 12.0 and err.max() < 15.0, err.round(1)
    # Below the bar that supervises the object branch, a mask says too little for a rest.
    fit = fit_object(masks, np.where(rest, 0.15, 0.3), K, w2c, hand, root, ground=ground, forearm_world=forearms)
    assert "rest" not in fit.depth_source and not fit.carried.any()


def test_a_doubted_mask_away_from_the_hands_does_not_pull_the_object_there():
    # While the box is carried the track slides onto a look-alike lying on the floor across
    # the room, and the tracker doubts it (confidence 0.07): the carried box stays with the
    # forearm and hand that hold it instead of being placed on the floor.
    from cogs.preprocess.objectfit import cuboid_points, fit_object, silhouette

    masks, K, w2c, hand, root, forearms, _, centres, rest = _carried_box()
    T, H, W = masks.shape
    decoy = np.array([-0.6, 0.5, 0.1])
    corners = cuboid_points(np.array([0.15, 0.10, 0.06])) + decoy
    masks[12:] = np.stack([silhouette(corners @ w2c[t, :3, :3].T + w2c[t, :3, 3], K, (H, W)) for t in range(12, T)])
    confidence = np.where(rest, 1.0, np.where(np.arange(T) < 12, 0.3, 0.07))
    ground = (np.array([0.0, 0.0, 1.0]), 0.0)
    fit = fit_object(masks, confidence, K, w2c, hand, root, ground=ground, forearm_world=forearms)
    off = np.linalg.norm(fit.track.translations - centres, axis=1)
    assert off[12:].max() < 0.25, off.round(2)
    assert fit.carried[12:].all()
    # Trusted as they are (the bar at 0), the masks would put it on the floor.
    fit = fit_object(masks, confidence, K, w2c, hand, root, ground=ground, forearm_world=forearms, trusted=0.0)
    assert np.linalg.norm(fit.track.translations - centres, axis=1)[12:].mean() > 0.75


def test_a_hidden_carried_object_moves_with_the_hand_that_holds_it():
    # Out of sight for six frames while the hand swings it towards the camera on an arc and
    # the forearm turns: between its last and next sighting it goes where the hand takes it,
    # not along the straight line between the two sightings.
    from cogs.preprocess.objectfit import carry_positions

    T = 12
    u = np.arange(T) / (T - 1)
    palm = np.stack([0.3 * np.sin(np.pi * u), -0.6 * u, 1.0 + 0.4 * np.sin(np.pi * u)], 1)
    forearm = np.stack([_rot_about(np.array([0.0, 0.0, 1.0]), 90.0 * x) for x in u])
    grasp = np.array([0.0, 0.12, 0.0])
    truth = palm + forearm @ grasp
    has = np.ones(T, bool)
    has[3:9] = False
    guess = truth.copy()
    for k in range(3):  # the straight line through the gap
        guess[~has, k] = np.interp(np.flatnonzero(~has), np.flatnonzero(has), truth[has, k])
    far = np.array([0.9, 0.9, 0.0])
    palms = np.stack([palm + far, palm], 1)  # the left hand elsewhere: the right one carries it
    forearms = np.stack([np.repeat(np.eye(3)[None], T, 0), forearm], 1)
    side = np.where(np.arange(T) >= 1, 1, -1)  # carried from frame 1 on
    out = carry_positions(guess, has, side, palms, forearms)
    np.testing.assert_allclose(out, truth, atol=1e-9)
    assert np.linalg.norm(guess - truth, axis=1).max() > 0.2  # the straight line is far off
    np.testing.assert_array_equal(carry_positions(guess, has, np.full(T, -1), palms, forearms), guess)  # not carried


def test_an_object_lost_for_good_while_carried_stays_in_the_hand():
    # Seen resting (frame 0), then carried while the forearm turns it 20 degrees a frame, and
    # out of view from frame 6 to the clip's end (a person turning away with it): there it
    # goes on turning and moving with the hand, instead of freezing at its last sighting.
    # Played backwards, the same clip is an object first seen carried: it was in that hand
    # before, too.
    from cogs.preprocess.objectfit import carry_in_hand, carry_positions

    T = 12
    u = np.arange(T) / (T - 1)
    forearm = np.stack([_rot_about(np.array([0.3, 0.0, 1.0]) / np.hypot(0.3, 1.0), 20.0 * t) for t in range(T)])
    palm = np.stack([0.4 * np.sin(np.pi * u), -0.5 * u, 1.0 + 0.3 * u], 1)
    grasp_R, grasp_t = _rot(0, 30.0), np.array([0.0, 0.1, 0.05])
    R_true = forearm @ grasp_R
    t_true = palm + forearm @ grasp_t
    forearms = np.stack([np.repeat(np.eye(3)[None], T, 0), forearm], 1)  # the right hand carries it
    palms = np.stack([palm + [1.0, 1.0, 0.0], palm], 1)
    has = np.arange(T) < 6
    held = has & (np.arange(T) >= 1)
    anchor = has & ~held
    for order in (np.arange(T), np.arange(T)[::-1]):
        h, hd, an, Ft, Pt = has[order], held[order], anchor[order], forearms[order], palms[order]
        Rt, tt = R_true[order], t_true[order]
        R_in = np.where(h[:, None, None], Rt, np.eye(3))
        t_in = np.where(h[:, None], tt, tt[np.flatnonzero(h)[-1 if order[0] == 0 else 0]])  # frozen at the last sighting
        R, by = carry_in_hand(R_in, h, hd, np.where(hd, 1, -1), Ft, an)
        assert by[~an].tolist() == [1] * (T - 1) and by[an].tolist() == [-1]
        np.testing.assert_allclose(R, Rt, atol=1e-9)
        np.testing.assert_allclose(carry_positions(t_in, h, by, Pt, Ft), tt, atol=1e-9)
        assert np.linalg.norm(t_in - tt, axis=1).max() > 0.2  # frozen, it would be far off


def test_the_carrying_hand_is_the_one_the_object_stays_fixed_to():
    # The right hand carries the object on an arc, turning it; the free left hand comes
    # close to it and is the nearer one in most frames, yet moves on its own: the object
    # keeps its grasp on the right forearm only.
    from cogs.preprocess.objectfit import carrying_side

    T = 10
    u = np.arange(T) / (T - 1)
    palm_r = np.stack([0.4 * np.sin(np.pi * u), -0.5 * u, 1.0 + 0.3 * u], 1)
    fore_r = np.stack([_rot_about(np.array([0.0, 0.0, 1.0]), 120.0 * x) for x in u])
    obj = palm_r + fore_r @ np.array([0.0, 0.15, 0.0])
    palm_l = obj + np.stack([0.05 * np.cos(5 * u), 0.08 * np.sin(7 * u), -0.05 + 0.1 * u], 1)  # near, but not holding
    fore_l = np.stack([_rot_about(np.array([1.0, 0.0, 0.0]), 40.0 * np.sin(4 * x)) for x in u])
    palms, forearms = np.stack([palm_l, palm_r], 1), np.stack([fore_l, fore_r], 1)
    nearest = np.array([0, 0, 1, 0, 0, 0, 1, 0, 0, 0])  # the image's nearest hand: mostly the free one
    frames = np.arange(T)
    assert carrying_side(frames, nearest, obj, palms, forearms) == 1
    assert carrying_side(frames, nearest, obj, np.stack([palm_r, palm_l], 1), np.stack([fore_r, fore_l], 1)) == 0  # sides swapped
    # Without positions, or over fewer than three frames, the nearest hand in most frames.
    assert carrying_side(frames, nearest) == 0
    assert carrying_side(frames[:2], np.array([1, 1] + [0] * 8), obj, palms, forearms) == 1


def _rot_about(axis: np.ndarray, deg: float) -> np.ndarray:
    from cogs.geometry.rotations import axis_angle_to_rotmat

    return axis_angle_to_rotmat(torch.tensor(axis * np.radians(deg))).numpy()


# -- MediaPipe (optional) -------------------------------------------------------------


def test_pipeline_refuses_frames_without_a_person(tmp_path):
    pytest.importorskip("mediapipe", reason="mediapipe is in the optional `preprocess` extra")
    from cogs.data.io import write_image
    from cogs.preprocess.command import Preprocess

    for i in range(3):
        write_image(tmp_path / "in" / f"{i}.png", _texture(96, 128, seed=i))
    with pytest.raises(UserError, match="no person detected in any of the 3 frames"):
        Preprocess(input=tmp_path / "in", out=tmp_path / "out", progress=False).run()


def test_preprocess_refuses_a_body_model_it_cannot_fit(tmp_path, capsys):
    # The body fit maps the landmarks onto Anny's bones: SMPL used to pass the options and
    # fail inside the body step with a KeyError.
    from cogs.cli import main
    from cogs.data.io import write_image

    for i in range(3):
        write_image(tmp_path / "in" / f"{i}.png", _texture(96, 128, seed=i))
    assert main(["preprocess", str(tmp_path / "in"), "--out", str(tmp_path / "s"), "--body-model", "smpl"]) == 2
    err = capsys.readouterr().err
    assert "--body-model smpl" in err and "Anny only" in err and "Traceback" not in err
    assert not (tmp_path / "s").exists()


def test_cli_reports_a_missing_video_with_exit_code_2(tmp_path, capsys):
    from cogs.cli import main

    code = main(["preprocess", str(tmp_path / "nope.mp4"), "--out", str(tmp_path / "s")])
    assert code == 2
    assert "nope.mp4" in capsys.readouterr().err


def test_a_mask_predicted_on_a_coarse_grid_is_moved_onto_the_frames_edges():
    """MediaPipe predicts its person mask on a 256-cell grid and upsamples it: the outline
    is off by up to a cell either way, and `align_to_edges` moves it onto the edges."""
    import cv2

    from cogs.preprocess.segment import align_to_edges, guided_filter

    H, W = 240, 320
    rng = np.random.default_rng(5)
    img = cv2.GaussianBlur(rng.integers(90, 200, (H, W, 3), dtype=np.uint8), (0, 0), 3)  # a textured room
    person = np.zeros((H, W), np.uint8)
    cv2.ellipse(person, (150, 120), (40, 95), 10, 0, 360, 1, -1)
    cv2.circle(person, (200, 70), 18, 1, -1)  # a raised hand
    cv2.line(person, (160, 60), (200, 70), 1, 6)  # its arm
    person = person > 0
    img[person] = np.clip(np.array([50, 60, 130]) + rng.integers(-15, 15, (int(person.sum()), 3)), 0, 255)
    # Predicted a pixel to the right on a grid of 4 px cells, upsampled bilinearly.
    small = cv2.resize(np.roll(person, 1, axis=1).astype(np.float32), (W // 4, H // 4), interpolation=cv2.INTER_AREA)
    coarse = cv2.resize(small, (W, H), interpolation=cv2.INTER_LINEAR) > 0.5
    before, after = _iou(coarse, person), _iou(align_to_edges(img, coarse, keep_thin=False), person)
    assert after > before + 0.02 and after > 0.99, (before, after)  # 0.970 -> 0.995 when written
    # A thin part (a racket's handle, 3 px wide, coloured like the room) stays whole when
    # asked to, and goes otherwise.
    handle = np.zeros((H, W), bool)
    handle[150:220, 240:243] = True
    thin = coarse | handle
    assert (align_to_edges(img, thin) & handle).sum() == handle.sum()
    assert (align_to_edges(img, thin, keep_thin=False) & handle).sum() < 0.5 * handle.sum()
    # A constant p stays constant; where the frame has no edges the outline cannot move far.
    assert np.allclose(guided_filter(img, np.full((H, W), 0.3, np.float32), 3, 1e-3), 0.3, atol=1e-3)
    flat = np.full((H, W, 3), 128, np.uint8)
    assert _iou(align_to_edges(flat, coarse, keep_thin=False), coarse) > 0.97
    assert not align_to_edges(img, np.zeros((H, W), bool)).any()


def test_boundary_refinement_tightens_a_mask_that_bleeds_into_the_background():
    import cv2

    from cogs.preprocess.persons import refine_mask_boundary

    H, W = 160, 120
    img = _texture(H, W, seed=3) // 3 + 150  # light background
    person = np.zeros((H, W), bool)
    person[20:150, 40:80] = True
    img[person] = (40, 50, 120)
    # A low-resolution soft mask, upsampled: it bleeds ~4 px past the true edge.
    soft = cv2.resize(cv2.resize(person.astype(np.float32), (15, 20), interpolation=cv2.INTER_AREA), (W, H))
    soft = cv2.dilate(soft, np.ones((9, 9), np.uint8))
    prob = (np.clip(soft, 0, 1) * 255).astype(np.uint8)
    before = _iou(prob > 127, person)
    after = _iou(refine_mask_boundary(img, prob), person)
    assert after > before + 0.05 and after > 0.9, (before, after)


def test_object_probability_is_damped_on_the_head_unless_the_object_was_there():
    from cogs.preprocess.tracking import suppress_head as _suppress_head

    kp = np.zeros((33, 3))
    kp[:11, :2] = [[50 + 5 * np.cos(a), 40 + 5 * np.sin(a)] for a in np.linspace(0, 6, 11)]
    kp[:11, 2] = 1.0
    prob = np.ones((100, 100))
    _suppress_head(prob, kp, np.array([90.0, 90.0]))
    assert prob[40, 50] == pytest.approx(0.2) and prob[90, 90] == 1.0
    prob = np.ones((100, 100))
    _suppress_head(prob, kp, np.array([50.0, 41.0]))  # last seen on the head: untouched
    assert prob.min() == 1.0


def test_a_long_stretch_without_a_trusted_object_mask_is_pointed_out_with_where_to_add_a_box():
    from cogs.preprocess.prompts import lost_stretch_warning, untrusted_stretches

    conf = np.full(40, 0.8)
    conf[3:5] = 0.0  # two frames: a blink, not worth a warning
    conf[10:16] = 0.1  # six frames under 0.2: pointed out
    conf[30:40] = 0.0  # ten frames to the end: pointed out first
    assert untrusted_stretches(conf, 0.2) == [(30, 39), (10, 15)]
    assert untrusted_stretches(conf, 0.05) == [(30, 39)]
    text = lost_stretch_warning(untrusted_stretches(conf, 0.2), 40)
    assert "frames 30-39, 10-15 (16 of 40 kept frames)" in text and "--object-box 34 X0 Y0 X1 Y1" in text
    # On a long clip, a stretch must be a tenth of it.
    assert untrusted_stretches(np.r_[np.zeros(8), np.ones(92)], 0.2) == []
    assert lost_stretch_warning([], 40) is None


def test_the_preview_caption_says_which_frames_do_not_supervise_the_object():
    from cogs.preprocess.preview import ORANGE, WHITE, caption

    assert caption("000007", "  cam: colmap", None, 0.2) == ("frame 000007  cam: colmap", WHITE)  # no object
    assert caption("000007", "", 0.84, 0.2) == ("frame 000007  obj 0.84", WHITE)
    assert caption("000008", "", 0.1, 0.2) == ("frame 000008  obj 0.10 not trusted", ORANGE)


def test_a_prompt_too_small_for_the_tracker_is_warned_about_naming_the_option_and_the_remedy():
    from cogs.preprocess.prompts import MIN_PROMPT_PIXELS, parse_prompts, small_prompt_warning

    prompt = parse_prompts((0, 370, 925, 410, 1020), None, None)[0][0]
    assert small_prompt_warning(prompt, MIN_PROMPT_PIXELS, (216, 384), 384) is None
    text = small_prompt_warning(prompt, 171, (216, 384), 384)
    assert text.startswith("--object-box 0 370 925 410 1020: the object covers only 171 pixels of frame 0 at 216x384")
    assert "--max-side (now 384)" in text


def test_a_clip_too_long_for_the_memory_is_refused_naming_a_stride_a_limit_and_a_size_that_fit(monkeypatch):
    from cogs.memory import GiB
    from cogs.preprocess.frames import output_size
    from cogs.preprocess.memory import check_fits, peak_bytes

    monkeypatch.setenv("COGS_MEMORY_GB", "6")
    check_fits("short.mp4", 100, (1920, 1080), 960, 1, None)  # a phone clip of 100 frames fits
    with pytest.raises(UserError) as e:  # ten minutes of it do not
        check_fits("long.mp4", 18000, (1920, 1080), 960, 1, None)
    msg = str(e.value)
    assert msg.startswith("long.mp4: preprocessing 18000 frames of 960x540 needs about") and "6.0 GiB available" in msg
    stride = int(msg.split("--stride ")[1].split()[0])
    limit = int(msg.split("--limit ")[1].split()[0].rstrip("."))
    assert peak_bytes(-(-18000 // stride), 960, 540) <= 6 * GiB and peak_bytes(limit, 960, 540) <= 6 * GiB
    assert peak_bytes(limit + 1, 960, 540) > 6 * GiB and peak_bytes(-(-18000 // (stride - 1)), 960, 540) > 6 * GiB
    assert "--max-side" not in msg  # even 64 px frames of 18000 do not fit: no size is named
    with pytest.raises(UserError) as e:
        check_fits("clip.mp4", 1000, (3840, 2160), 3840, 1, None)  # 4K kept at full size: a smaller size fits
    side = int(str(e.value).split("--max-side ")[1].split()[0].rstrip("."))
    assert 64 <= side < 3840 and peak_bytes(1000, *output_size(3840, 2160, side)) <= 6 * GiB


def _walked_past_cameras(k: float, T: int = 6):
    """Inputs of `world.align_sfm` for a camera moving sideways past a person standing 3 m
    ahead with the feet 1.5 m below it, in an SfM reconstruction whose units are `k` per
    metre (camera y down, z forward; SfM world axes = the first camera's)."""
    from cogs.preprocess import world as Wd

    K = np.array([[200.0, 0, 128], [0, 200.0, 96], [0, 0, 1]])
    w2c = np.tile(np.eye(4), (T, 1, 1))
    w2c[:, 0, 3] = -0.1 * k * np.arange(T)  # centres at (0.1 t k, 0, 0)
    feet_cam = np.tile(np.array([[0.0, 1.5, 3.0]]) + np.array([[0.05, 0, 0]]) * np.arange(4)[:, None], (T, 1, 1))
    kp2d = np.zeros((T, 33, 3))
    for i, j in enumerate(Wd.FOOT_LANDMARKS):
        uvw = feet_cam[:, i] @ K.T
        kp2d[:, j, :2], kp2d[:, j, 2] = uvw[:, :2] / uvw[:, 2:], 1.0
    up_cam = np.tile([0.0, -1.0, 0.0], (T, 1))
    root_cam = np.tile([0.0, 0.5, 3.0], (T, 1))
    rng = np.random.default_rng(0)
    ground = np.c_[rng.uniform(-2, 2, 300), np.full(300, 1.5), rng.uniform(1, 6, 300)] * k
    return w2c, np.ones(T, bool), ground, K, kp2d, up_cam, feet_cam, root_cam


def test_a_tilted_plane_that_gives_a_wandering_scale_is_not_taken_for_the_floor(monkeypatch):
    """A ramp (or a shelf top) within 30 degrees of up that the feet rays hit: the scale it
    gives changes from frame to frame as the camera moves along it, so it is refused and
    the ground goes through the feet."""
    from cogs.preprocess import world as Wd

    k, T = 4.0, 12
    w2c, reg, _, K, kp2d, up_cam, feet_cam, root_cam = _walked_past_cameras(k=k, T=T)
    w2c[:, 0, 3] = -0.3 * k * np.arange(T)  # a longer walk along the ramp
    rng = np.random.default_rng(0)
    x, z = rng.uniform(-2, 6, 400), rng.uniform(1, 8, 400)
    ramp = np.c_[x, 1.5 + np.tan(np.radians(25)) * x, z] * k  # rising 25 degrees along the walk
    al = Wd.align_sfm(w2c, reg, ramp, K, kp2d, up_cam, feet_cam, root_cam)
    assert al.ground_source == "feet" and al.notes["planes_refused"][0]["scale_spread"] > Wd.MAX_SCALE_SPREAD
    monkeypatch.setattr(Wd, "MAX_SCALE_SPREAD", np.inf)
    assert Wd.align_sfm(w2c, reg, ramp, K, kp2d, up_cam, feet_cam, root_cam).ground_source == "points"


def test_the_world_scale_comes_from_the_ground_and_its_absence_is_warned(caplog):
    """With the floor among the reconstructed points the metric scale is recovered from the
    feet on it; without any point the SfM units are kept, and the user is told so."""
    import logging

    from cogs.preprocess import world as Wd

    w2c, reg, ground, K, kp2d, up_cam, feet_cam, root_cam = _walked_past_cameras(k=4.0)
    with caplog.at_level(logging.WARNING, logger="cogs.preprocess.world"):
        al = Wd.align_sfm(w2c, reg, ground, K, kp2d, up_cam, feet_cam, root_cam)
    assert al.scale == pytest.approx(0.25, rel=0.02) and "scale" not in al.notes
    assert not [r for r in caplog.records if "scale is unknown" in r.getMessage()]
    with caplog.at_level(logging.WARNING, logger="cogs.preprocess.world"):
        al = Wd.align_sfm(w2c, reg, np.zeros((0, 3)), K, kp2d, up_cam, feet_cam, root_cam)
    assert al.scale == 1.0 and al.notes["scale"].startswith("unknown")
    assert [r for r in caplog.records if "scale is unknown" in r.getMessage() and "floor" in r.getMessage()]


def test_a_body_fitted_far_off_its_keypoints_is_reported_with_the_worlds_scale():
    from cogs.preprocess import bodyfit as B

    assert B.poor_fit_warning(0.015, None) is None and B.poor_fit_warning(0.06, "from the person's motion") is None
    assert B.poor_fit_warning(float("nan"), None) is None
    text = B.poor_fit_warning(0.128, "unknown: ... SfM units kept")
    assert "0.13 of the person's height" in text and "SfM units kept" in text and "floor" in text


def test_without_a_floor_a_hand_held_camera_gets_its_scale_from_the_persons_smooth_path():
    """The floor out of view and no point near the feet: a hand-held camera's jitter, in SfM
    units, would shake a person standing still by the wrong factor; the scale at which the
    person's world path is smoothest is the true one (the guitar clip's case)."""
    from cogs.preprocess import world as Wd

    k, T = 30.0, 40  # SfM units per metre
    rng = np.random.default_rng(3)
    w2c, reg, _, K, kp2d, up_cam, feet_cam, _ = _walked_past_cameras(k=k, T=T)
    centres_m = np.cumsum(rng.normal(0, 0.01, (T, 3)), axis=0)  # a hand-held path, metres
    w2c[:, :3, 3] = -k * centres_m  # identity rotations: t = -R c, in SfM units
    person_m = np.array([0.0, 0.5, 3.0]) + np.c_[np.linspace(0, 0.3, T), np.zeros(T), np.zeros(T)]  # a slow step aside
    root_cam = person_m - centres_m + rng.normal(0, 0.002, (T, 3))  # what the body's size gives, with noise
    al = Wd.align_sfm(w2c, reg, np.zeros((0, 3)), K, kp2d, up_cam, feet_cam, root_cam)
    assert al.scale == pytest.approx(1 / k, rel=0.1) and al.notes["scale"].startswith("from the person's motion")
    s, explained = Wd.scale_from_body_motion(w2c, reg, root_cam)
    assert explained > 0.9
    # A noisier body (2 cm a frame) leaves the camera's jitter 5-20 % of the person's
    # apparent acceleration (14 % on one of COLMAP's solutions for the guitar clip): the
    # scale is up to half off, the reconstruction's units (kept below 5 %) 30x.
    noisy = person_m - centres_m + rng.normal(0, 0.02, (T, 3))
    s, explained = Wd.scale_from_body_motion(w2c, reg, noisy)
    assert 0.05 < explained < 0.2
    al = Wd.align_sfm(w2c, reg, np.zeros((0, 3)), K, kp2d, up_cam, feet_cam, noisy)
    assert al.scale == pytest.approx(1 / k, rel=0.5) and al.notes["scale"].startswith("from the person's motion")
    # A camera that moves smoothly gives the person's path nothing to tell: no scale.
    w2c[:, :3, 3] = -k * np.c_[np.linspace(0, 0.5, T), np.zeros(T), np.zeros(T)]
    assert Wd.scale_from_body_motion(w2c, reg, root_cam)[0] is None
