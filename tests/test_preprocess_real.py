"""`cogs preprocess` end to end on real footage: 12 frames of the shared basketball clip.

The clip lives outside the repository (``<repo>/../shared/data/real/basketball_dribble.mp4``,
or the path in ``COGS_REAL_CLIP``); the test skips with a reason when it, MediaPipe or
pycolmap is missing. It runs in CI (marked ``slow``: about a minute on two cores).
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from pathlib import Path

import numpy as np
import pytest
import torch

CLIP = Path(os.environ.get("COGS_REAL_CLIP", Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real" / "basketball_dribble.mp4"))
# The ball on frame 5 of the clip, in pixels of the 1080x1920 source video.
BALL_BOX = (500.0, 1260.0, 660.0, 1430.0)


@pytest.fixture(scope="module")
def real_scene(tmp_path_factory):
    if not CLIP.exists():
        pytest.skip(f"real clip not found at {CLIP} (set COGS_REAL_CLIP)")
    pytest.importorskip("mediapipe", reason="mediapipe is in the optional `preprocess` extra")
    pytest.importorskip("pycolmap", reason="pycolmap is in the optional `preprocess` extra")
    from cogs.preprocess.command import Preprocess

    out = tmp_path_factory.mktemp("real") / "scene"
    cfg = Preprocess(input=CLIP, out=out, limit=12, max_side=480, object_box=BALL_BOX, object_box_frame=5,
                     body_iterations=150, progress=False)
    from cogs.preprocess.pipeline import run_preprocess

    t0 = time.perf_counter()
    report = run_preprocess(cfg)
    return cfg, report, time.perf_counter() - t0


@pytest.mark.slow
def test_real_clip_becomes_a_scene_that_cogs_check_accepts(real_scene):
    from cogs.data.scene import load_scene
    from cogs.data.validate import check_scene

    cfg, report, _ = real_scene
    assert check_scene(cfg.out) == []
    s = load_scene(cfg.out)
    assert s.n_frames == 12 and (s.width, s.height) == (270, 480)
    assert s.has_object and len(s.points_xyz) > 0
    assert s.human_masks.reshape(12, -1).any(1).all()  # a person in every frame
    # MediaPipe Hands finds the dribbling hand on some frames: none of them is taken for the body.
    assert json.loads((cfg.out / ".cache" / "persons.json").read_text())["stats"]["bodies_on_hands"] == []
    # The ball, prompted on frame 5, is found around it.
    assert s.object_masks[3:8].reshape(5, -1).any(1).all()
    assert not np.logical_and(s.human_masks, s.object_masks).any()  # one owner per pixel
    # The tracker's per-frame confidence is recorded in the scene, as the objects step gave it.
    with np.load(cfg.out / ".cache" / "objects.npz") as z:
        tracker_conf = z["confidence"]
    assert s.object.confidence is not None
    np.testing.assert_array_equal(s.object.confidence, tracker_conf)
    assert s.object.confidence[5] == 1.0  # the prompted frame
    # The step's summary counts the frames that supervise the object (confidence 0.2 and up).
    assert report.stats["objects"]["trusted_frames"] == int((tracker_conf >= 0.2).sum()) > 0
    # The initial trajectory's proxy and the frames turned with a fitted forearm are recorded.
    init = json.loads((cfg.out / "scene.json").read_text())["source"]["object_init"]
    assert init["shape"] in ("cuboid", "ellipsoid") and len(init["radii_m"]) == 3
    assert all(0 <= t < 12 for t in init["carried_frames"])
    assert report.stats["body"]["reprojection_error_mean"] < 0.05  # of the person's height
    assert report.preview.exists() and report.preview.stat().st_size > 10_000
    # The body is an adult of the default stature, which the scene records.
    body_fit = json.loads((cfg.out / "scene.json").read_text())["source"]["body_fit"]
    assert body_fit["stature_from"] == "adult prior" and body_fit["stature_m"] == pytest.approx(1.70)


@pytest.mark.slow
def test_a_given_person_height_scales_the_whole_scene(real_scene, tmp_path):
    # One view cannot tell a tall person far away from a short one near: the height the
    # user gives sets the body and, through it, the world's metric scale.
    import shutil

    from cogs.body import load_body_model
    from cogs.data.scene import load_scene
    from cogs.preprocess.bodyfit import stature
    from cogs.preprocess.pipeline import run_preprocess

    cfg, _, _ = real_scene
    out = tmp_path / "tall"
    shutil.copytree(cfg.out / ".cache", out / ".cache")  # frames, persons, objects, cameras are reused
    report = run_preprocess(dataclasses.replace(cfg, out=out, person_height=1.85))
    assert {"frames", "persons", "objects", "cameras"} <= set(report.cached) and "body" not in report.cached
    model = load_body_model("anny")
    short, tall = load_scene(cfg.out), load_scene(out)
    assert stature(model, short.body.shape) == pytest.approx(1.70, abs=0.005)
    assert stature(model, tall.body.shape) == pytest.approx(1.85, abs=0.005)

    def root_depth(s):  # the person's distance along the camera's axis, median over frames
        with torch.no_grad():
            _, joints = model.bone_transforms(torch.tensor(s.body.pose), torch.tensor(s.body.transl), torch.tensor(s.body.shape))
        root = joints[:, model.bone_index("root")].double().numpy()
        w2c = s.cameras.world_to_camera
        return float(np.median(np.einsum("tj,tj->t", w2c[:, 2, :3], root) + w2c[:, 2, 3]))

    assert root_depth(tall) / root_depth(short) == pytest.approx(1.85 / 1.70, rel=0.03)
    radii = [json.loads((d / "scene.json").read_text())["source"]["object_init"]["radii_m"] for d in (cfg.out, out)]
    np.testing.assert_allclose(np.array(radii[1]) / np.array(radii[0]), 1.85 / 1.70, rtol=0.05)  # the ball grows too


@pytest.mark.slow
def test_a_second_run_resumes_from_the_cache(real_scene):
    from cogs.preprocess.pipeline import STEPS, run_preprocess

    cfg, _, first_seconds = real_scene
    # The finished scene is replaced only when asked; its cached steps are then reused.
    report = run_preprocess(dataclasses.replace(cfg, overwrite=True))
    assert set(report.cached) == set(STEPS) - {"scene"}
    computed = sum(v for k, v in report.seconds.items() if k != "scene")
    assert computed == 0.0


@pytest.mark.slow
def test_track_side_tracks_the_ball_on_shrunk_frames_and_keeps_the_masks_at_full_size(real_scene, tmp_path):
    import shutil

    from cogs.data.scene import load_scene
    from cogs.preprocess.pipeline import run_preprocess

    cfg, _, _ = real_scene
    out = tmp_path / "scene"
    shutil.copytree(cfg.out, out)  # a copy of the full-size scene, replaced reusing its cache
    report = run_preprocess(dataclasses.replace(cfg, out=out, track_side=240, overwrite=True))
    assert {"frames", "persons"} <= set(report.cached) and "objects" not in report.cached
    s = load_scene(out)
    assert s.object_masks.shape == (12, 480, 270)
    assert s.object_masks[3:8].reshape(5, -1).any(1).all()
    # The same ball as at full size: the masks overlap where both found it.
    full = load_scene(cfg.out).object_masks
    both = [t for t in range(12) if full[t].any() and s.object_masks[t].any()]
    ious = [(full[t] & s.object_masks[t]).sum() / (full[t] | s.object_masks[t]).sum() for t in both]
    assert len(both) >= 5 and np.median(ious) > 0.6, ious
    assert not np.array_equal(full, s.object_masks)  # tracked on other pixels
