"""The native scene format: round trip, and `cogs check` naming every problem."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from cogs.cli import main
from cogs.data.io import write_image, write_mask
from cogs.data.scene import SceneError, load_scene, save_scene
from cogs.data.validate import check_scene


def test_saved_scene_loads_back_identical(tiny_scene, tmp_path):
    s = load_scene(tiny_scene)
    assert s.n_frames == 6 and (s.width, s.height) == (40, 30)
    copy = save_scene(s, tmp_path / "copy")
    t = load_scene(copy)
    np.testing.assert_array_equal(s.images, t.images)
    np.testing.assert_array_equal(s.human_masks, t.human_masks)
    np.testing.assert_array_equal(s.object_masks, t.object_masks)
    np.testing.assert_allclose(s.cameras.world_to_camera, t.cameras.world_to_camera)
    np.testing.assert_allclose(s.body.pose, t.body.pose)
    np.testing.assert_allclose(s.object.translations, t.object.translations)
    np.testing.assert_allclose(s.points_xyz, t.points_xyz)
    assert s.split == t.split


def test_valid_scene_has_no_problems(tiny_scene):
    assert check_scene(tiny_scene) == []


def _messages(root):
    return [str(p) for p in check_scene(root)]


def test_missing_image_is_named_with_its_frame(tiny_scene):
    (tiny_scene / "images" / "000003.png").unlink()
    msgs = _messages(tiny_scene)
    assert any("images/000003.png (frame 000003): missing" in m for m in msgs), msgs


def test_count_mismatch_between_images_and_cameras_is_reported(tiny_scene):
    cams = json.loads((tiny_scene / "cameras.json").read_text())
    cams["frames"] = cams["frames"][:4]
    (tiny_scene / "cameras.json").write_text(json.dumps(cams))
    msgs = _messages(tiny_scene)
    assert any("cameras.json: has 4 frames but the scene has 6 images" in m for m in msgs), msgs


def test_count_mismatch_in_body_poses_is_reported(tiny_scene):
    z = dict(np.load(tiny_scene / "body.npz"))
    z["pose"] = z["pose"][:5]
    np.savez(tiny_scene / "body.npz", **z)
    assert any("`pose` has 5 frames but the scene has 6 images" in m for m in _messages(tiny_scene))


def test_wrong_image_size_is_reported(tiny_scene):
    write_image(tiny_scene / "images" / "000002.png", np.zeros((31, 40, 3), np.uint8))
    assert any("(frame 000002): image is 40x31, expected 40x30" in m for m in _messages(tiny_scene))


def test_non_binary_mask_is_reported(tiny_scene):
    from PIL import Image

    grey = (np.arange(30 * 40).reshape(30, 40) % 256).astype(np.uint8)
    Image.fromarray(grey).save(tiny_scene / "masks" / "object" / "000001.png")
    msgs = _messages(tiny_scene)
    assert any("masks/object/000001.png (frame 000001): mask is not binary" in m for m in msgs), msgs


def test_non_finite_numbers_are_reported_per_frame(tiny_scene):
    z = dict(np.load(tiny_scene / "body.npz"))
    z["transl"][4, 1] = np.nan
    np.savez(tiny_scene / "body.npz", **z)
    cams = json.loads((tiny_scene / "cameras.json").read_text())
    cams["frames"][2]["K"][0][0] = float("inf")
    (tiny_scene / "cameras.json").write_text(json.dumps(cams).replace("Infinity", "1e999"))
    msgs = _messages(tiny_scene)
    assert any("body.npz (frame 000004): `transl` has non-finite numbers" in m for m in msgs), msgs
    assert any("cameras.json (frame 000002): `K` has non-finite numbers" in m for m in msgs), msgs


def test_unknown_body_model_is_reported(tiny_scene):
    meta = json.loads((tiny_scene / "scene.json").read_text())
    meta["body_model"] = "mystery"
    (tiny_scene / "scene.json").write_text(json.dumps(meta))
    assert any("unknown body model 'mystery'" in m for m in _messages(tiny_scene))


def test_corrupt_png_is_reported(tiny_scene):
    (tiny_scene / "masks" / "human" / "000005.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    msgs = _messages(tiny_scene)
    assert any("masks/human/000005.png (frame 000005): corrupt or unreadable image" in m for m in msgs), msgs


def test_every_problem_is_reported_at_once(tiny_scene):
    (tiny_scene / "images" / "000000.png").unlink()
    write_mask(tiny_scene / "masks" / "human" / "000001.png", np.zeros((10, 10), bool))
    (tiny_scene / "points.ply").unlink()
    msgs = _messages(tiny_scene)
    assert len(msgs) >= 3, msgs


def test_load_scene_refuses_an_invalid_scene(tiny_scene):
    shutil.rmtree(tiny_scene / "masks" / "object")
    with pytest.raises(SceneError) as e:
        load_scene(tiny_scene)
    assert "masks/object" in str(e.value)


def test_cli_check_exit_codes_and_no_traceback(tiny_scene, capsys):
    assert main(["check", "--scene", str(tiny_scene)]) == 0
    (tiny_scene / "object.json").write_text("{not json")
    assert main(["check", "--scene", str(tiny_scene)]) == 1
    err = capsys.readouterr().err
    assert "object.json: not valid JSON" in err
    assert "Traceback" not in err


def test_cli_check_on_missing_folder_fails_cleanly(tmp_path, capsys):
    assert main(["check", "--scene", str(tmp_path / "nope")]) == 1
    assert "does not exist" in capsys.readouterr().err
