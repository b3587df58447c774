"""Per-frame object confidence: recorded in the scene (object.json), read back, and used by
training to leave the frames where the object was lost out of the object's supervision."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from cogs.cli import main
from cogs.data.io import write_mask
from cogs.data.scene import load_scene, save_scene
from cogs.data.validate import check_scene
from cogs.train import checkpoint as ckpt
from tests.fixtures import TINY, make_tiny_scene


def _set_confidence(scene_dir: Path, conf) -> None:
    path = scene_dir / "object.json"
    obj = json.loads(path.read_text())
    for f, c in zip(obj["frames"], conf):
        f["confidence"] = float(c)
    path.write_text(json.dumps(obj))


def _branches(run: Path) -> dict:
    return ckpt.load(run / "checkpoints" / "last.pt")["branches"]


def _assert_identical(a: dict, b: dict, names) -> None:
    for name in names:
        assert a[name].keys() == b[name].keys(), name
        for k in a[name]:
            torch.testing.assert_close(a[name][k], b[name][k], rtol=0, atol=0, msg=f"{name}.{k}")


def test_object_confidence_round_trips_and_absent_means_every_frame_trusted(tmp_path):
    root = make_tiny_scene(tmp_path / "tiny")
    s = load_scene(root)
    assert s.object.confidence is None
    np.testing.assert_array_equal(s.object_confidence, np.ones(s.n_frames))
    s.images  # noqa: B018  (pixels loaded, so the scene can be written again)
    s.human_masks, s.object_masks  # noqa: B018
    conf = np.array([1.0, 0.0, 0.35, 0.9, 0.0, 1.0])
    s.object.confidence = conf
    save_scene(s, tmp_path / "again")
    assert check_scene(tmp_path / "again") == []
    back = load_scene(tmp_path / "again")
    np.testing.assert_array_equal(back.object.confidence, conf)
    np.testing.assert_array_equal(back.object_trusted(0.2), [True, False, True, True, False, True])


def test_an_all_ones_confidence_trains_bit_for_bit_as_no_confidence(small_synthetic, tmp_path):
    """A scene that records no confidence (every synthetic scene, the demo) and the same
    scene with every frame at 1 run every stage to the same tensors."""
    ones = tmp_path / "ones"
    shutil.copytree(small_synthetic, ones)
    _set_confidence(ones, np.ones(len(json.loads((ones / "scene.json").read_text())["frames"])))
    assert load_scene(ones).object.confidence is not None
    for scene, run in ((small_synthetic, tmp_path / "plain"), (ones, tmp_path / "with_ones")):
        assert main(["train", "--scene", str(scene), "--out", str(run), "--set", *TINY]) == 0
    _assert_identical(_branches(tmp_path / "plain"), _branches(tmp_path / "with_ones"), ("human", "object", "scene"))
    plain = json.loads((tmp_path / "plain" / "train_log.json").read_text())["history"]
    ones_log = json.loads((tmp_path / "with_ones" / "train_log.json").read_text())["history"]
    assert [h["frame"] for h in plain] == [h["frame"] for h in ones_log]


# Stages III and IV alone (the human built, untrained): the object's supervision in isolation.
OBJECT_STAGES = [*TINY, "schedule.I=0", "schedule.II=0", "schedule.V=0", "schedule.VI=0", "refit.steps=0"]


def _lost_frames_variant(src: Path, dst: Path, lost: list[int], where: str) -> None:
    """`src` with the object masks of `lost` frames replaced by wrong ones, those frames at
    confidence 0: a block of static scene (`where` = "left" or "right", off the person),
    as a tracker that slid off the object would leave."""
    shutil.copytree(src, dst)
    s = load_scene(dst)
    H, W = s.height, s.width
    for t in lost:
        m = np.zeros((H, W), bool)
        x0 = 2 if where == "left" else W - 14
        m[2:14, x0:x0 + 12] = True
        m &= ~s.human_masks[t]
        assert m.any()
        write_mask(dst / "masks" / "object" / f"{s.frame_ids[t]}.png", m)
    conf = np.ones(s.n_frames)
    conf[lost] = 0.0
    _set_confidence(dst, conf)
    assert check_scene(dst) == []


@pytest.mark.parametrize("exclude", [True, False])
def test_lost_frames_give_the_object_no_supervision(small_synthetic, tmp_path, exclude):
    """Two scenes that differ only in the (wrong) object masks of frames marked lost train
    the same object when lost frames are left out, and different objects when the
    exclusion is switched off (min_confidence 0: every frame supervises), which shows the
    comparison can fail."""
    train = load_scene(small_synthetic).split["train"]
    lost = train[1::3]
    a, b = tmp_path / "a", tmp_path / "b"
    _lost_frames_variant(small_synthetic, a, lost, "left")
    _lost_frames_variant(small_synthetic, b, lost, "right")
    extra = [] if exclude else ["branches.object.min_confidence=0.0"]
    for scene in (a, b):
        assert main(["train", "--scene", str(scene), "--out", str(tmp_path / f"run_{scene.name}"),
                     "--set", *OBJECT_STAGES, *extra]) == 0
    oa, ob = _branches(tmp_path / "run_a")["object"], _branches(tmp_path / "run_b")["object"]
    if exclude:
        _assert_identical({"object": oa}, {"object": ob}, ["object"])
        frames = {h["frame"] for h in json.loads((tmp_path / "run_a" / "train_log.json").read_text())["history"]}
        assert not frames & set(lost)  # the object stages never drew a lost frame
    else:
        assert oa.keys() == ob.keys()
        assert any(oa[k].shape != ob[k].shape or not torch.equal(oa[k], ob[k]) for k in oa)


def test_a_scene_whose_object_is_lost_on_every_training_frame_is_refused(tmp_path, capsys):
    root = make_tiny_scene(tmp_path / "tiny")
    _set_confidence(root, np.zeros(6))
    assert main(["train", "--scene", str(root), "--out", str(tmp_path / "run"), "--set", *TINY]) != 0
    err = " ".join(capsys.readouterr().err.split())
    assert "no training frame has an object confidence of at least 0.2 (object.json)" in err
    assert not (tmp_path / "run").exists()  # refused before anything was written


@pytest.mark.parametrize("single_stage", [False, True])
def test_lost_frames_drop_the_object_mask_terms_but_keep_the_full_frame_rgb(small_synthetic, tmp_path, single_stage):
    """Compositional stages (and the joint ablation) still draw lost frames: there the
    object's mask and crop terms are absent, the full-frame RGB is not."""
    train = load_scene(small_synthetic).split["train"]
    lost = set(train[1::3])
    scene = tmp_path / "a"
    _lost_frames_variant(small_synthetic, scene, sorted(lost), "left")
    extra = ["log_every=1", *(["schedule.single_stage=true"] if single_stage else [])]
    assert main(["train", "--scene", str(scene), "--out", str(tmp_path / "run"), "--set", *TINY, *extra]) == 0
    history = json.loads((tmp_path / "run" / "train_log.json").read_text())["history"]
    rows = [h for h in history if h["stage"] in ("V", "VI", "joint")]
    assert {h["frame"] in lost for h in rows} == {True, False}  # both kinds were drawn
    for h in rows:
        assert "compose.rgb" in h
        assert ("compose.decomp_object" in h) == (h["frame"] not in lost), h
        if single_stage:
            assert ("object.silhouette" in h) == (h["frame"] not in lost), h


def test_the_object_branch_records_the_training_split_and_each_frames_confidence(small_synthetic, tmp_path):
    """What a held-out frame's object pose is decided from (`ObjectConfig.held_out_input_weight`)
    is taken from the scene when the branch is built: the frames of the training split and
    each frame's object confidence."""
    from cogs.branches.build import build_object
    from cogs.config import TrainConfig

    scene_dir = tmp_path / "conf"
    shutil.copytree(small_synthetic, scene_dir)
    n = len(json.loads((scene_dir / "scene.json").read_text())["frames"])
    conf = np.linspace(0.0, 1.0, n)
    _set_confidence(scene_dir, conf)
    scene = load_scene(scene_dir)
    obj = build_object(scene, TrainConfig().branches, "cpu")
    in_split = np.zeros(n, bool)
    in_split[list(scene.split["train"])] = True
    assert 0 < in_split.sum() < n
    np.testing.assert_array_equal(obj.trained.numpy(), in_split)
    np.testing.assert_allclose(obj.input_confidence.numpy(), conf, atol=1e-6)
