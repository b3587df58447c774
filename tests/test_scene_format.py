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


# -- masks: 0/255 and 0/1 alike ---------------------------------------------------------


def _meta(root):
    return json.loads((root / "scene.json").read_text())


def _set_meta(root, **changes):
    meta = _meta(root)
    meta.update(changes)
    (root / "scene.json").write_text(json.dumps(meta))


def test_masks_stored_as_0_and_1_read_as_masks_in_check_and_load(tiny_scene):
    from PIL import Image

    want = load_scene(tiny_scene).human_masks
    for t, fid in enumerate(_meta(tiny_scene)["frames"]):
        Image.fromarray(want[t].astype(np.uint8)).save(tiny_scene / "masks" / "human" / f"{fid}.png")  # values 0/1
    assert check_scene(tiny_scene) == []
    np.testing.assert_array_equal(load_scene(tiny_scene).human_masks, want)


def test_a_clip_whose_human_masks_are_all_empty_is_a_problem(tiny_scene):
    for fid in _meta(tiny_scene)["frames"]:
        write_mask(tiny_scene / "masks" / "human" / f"{fid}.png", np.zeros((30, 40), bool))
    assert _messages(tiny_scene) == ["masks/human: every human mask is empty: no person in any of the 6 frames "
                                     "(the person is 255, or 1, in these masks)"]


def test_some_empty_human_masks_are_fine(tiny_scene):
    write_mask(tiny_scene / "masks" / "human" / "000002.png", np.zeros((30, 40), bool))  # the person stepped out
    assert check_scene(tiny_scene) == []


@pytest.mark.parametrize("fps", [0, -1, "fast", None, True])
def test_fps_must_be_a_positive_number(tiny_scene, fps):
    _set_meta(tiny_scene, fps=fps)
    assert _messages(tiny_scene) == [f"scene.json: `fps` must be a positive number (frames per second), got {fps!r}"]


# -- the check is total: whatever it reads ends in a problem naming the file --------------


def test_scene_json_or_cameras_json_that_is_a_folder_is_named(tiny_scene):
    for name in ("scene.json", "cameras.json"):
        (tiny_scene / name).unlink()
        (tiny_scene / name).mkdir()
    msgs = _messages(tiny_scene)
    assert "scene.json: is a folder, expected a file" in msgs, msgs
    assert "cameras.json: is a folder, expected a file" in msgs, msgs


def test_symbolic_link_loops_and_pipes_are_named_without_hanging(tiny_scene):
    import os

    img = tiny_scene / "images" / "000001.png"
    img.unlink()
    img.symlink_to(img)
    (tiny_scene / "object.json").unlink()
    os.mkfifo(tiny_scene / "object.json")  # opening it for reading would block forever
    msgs = _messages(tiny_scene)
    assert "images/000001.png (frame 000001): a symbolic link loop" in msgs, msgs
    assert "object.json: not a regular file (a pipe, socket or device?)" in msgs, msgs


@pytest.mark.skipif(hasattr(__import__("os"), "geteuid") and __import__("os").geteuid() == 0,
                    reason="root reads files whatever their mode")
def test_unreadable_files_are_named(tiny_scene):
    (tiny_scene / "body.npz").chmod(0)
    (tiny_scene / "masks" / "object").chmod(0)
    try:
        msgs = _messages(tiny_scene)
    finally:
        (tiny_scene / "body.npz").chmod(0o644)
        (tiny_scene / "masks" / "object").chmod(0o755)
    assert "body.npz: unreadable (Permission denied)" in msgs, msgs
    assert "masks/object: folder cannot be read (Permission denied)" in msgs, msgs


def test_truncated_png_and_16_bit_image_are_named_with_their_frame(tiny_scene):
    from PIL import Image

    png = tiny_scene / "images" / "000004.png"
    png.write_bytes(png.read_bytes()[:200])
    Image.fromarray(np.zeros((30, 40), np.uint16)).save(tiny_scene / "images" / "000005.png")
    msgs = _messages(tiny_scene)
    assert any(m.startswith("images/000004.png (frame 000004): corrupt or unreadable image") for m in msgs), msgs
    assert "images/000005.png (frame 000005): expected an 8-bit image, got PIL mode I;16 (16-bit or float?)" in msgs, msgs


def test_non_numeric_and_misshapen_body_arrays_are_named(tiny_scene):
    z = dict(np.load(tiny_scene / "body.npz"))
    z["pose"] = np.full(z["pose"].shape, "x")
    z["shape"] = z["shape"][:3]
    np.savez(tiny_scene / "body.npz", **z)
    msgs = _messages(tiny_scene)
    assert "body.npz: `pose` must hold numbers, got dtype <U1" in msgs, msgs
    assert "body.npz: `shape` must have 6 values for anny, got [3]" in msgs, msgs


def test_frame_ids_that_cannot_be_file_names_are_refused(tiny_scene):
    meta = _meta(tiny_scene)
    meta["frames"][1] = "../../etc/passwd"
    (tiny_scene / "scene.json").write_text(json.dumps(meta))
    assert any("frame id '../../etc/passwd' cannot be a file name" in m for m in _messages(tiny_scene))


@pytest.fixture
def gt_scene(tmp_path):
    from tests.fixtures import make_tiny_scene

    return make_tiny_scene(tmp_path / "scene", ground_truth=True)


def test_ground_truth_with_novel_views_is_checked_and_loads(gt_scene):
    assert check_scene(gt_scene) == []
    s = load_scene(gt_scene)
    assert s.gt.novel.images.shape == (2, 30, 40, 3) and len(s.gt.planes) == 1


def test_gt_planes_without_offset_is_named(gt_scene):
    planes = json.loads((gt_scene / "gt" / "planes.json").read_text())
    del planes["planes"][0]["offset"]
    (gt_scene / "gt" / "planes.json").write_text(json.dumps(planes))
    assert _messages(gt_scene) == ["gt/planes.json: plane 0: `offset` is missing (the plane is n . x + offset = 0)"]


def test_gt_novel_views_missing_or_malformed_are_named(gt_scene):
    cams = json.loads((gt_scene / "gt" / "novel" / "cameras.json").read_text())
    cams["frames"][1]["frame"] = 99
    (gt_scene / "gt" / "novel" / "cameras.json").write_text(json.dumps(cams))
    (gt_scene / "gt" / "novel" / "masks" / "object" / "v000.png").unlink()
    (gt_scene / "gt" / "novel" / "depth.npz").write_bytes(b"PK\x03\x04 not a zip")
    msgs = _messages(gt_scene)
    assert "gt/novel/cameras.json (frame v001): `frame` must be the index of the scene frame the view shows (0..5), got 99" in msgs, msgs
    assert "gt/novel/masks/object/v000.png (frame v000): missing" in msgs, msgs
    assert any(m.startswith("gt/novel/depth.npz: unreadable npz") for m in msgs), msgs


CORRUPTIONS = {
    "scene.json is a bare string": lambda r: (r / "scene.json").write_text('"hello"'),
    "scene.json nested 100000 deep": lambda r: (r / "scene.json").write_text("[" * 100000 + "]" * 100000),
    "cameras K of strings": lambda r: (r / "cameras.json").write_text(json.dumps({"frames": [{"K": "abc"}] * 6})),
    "cameras number too large for a float": lambda r: (r / "cameras.json").write_text(
        (r / "cameras.json").read_text().replace('"K": [', '"K": [' + "1" * 400 + ", ", 1)),
    "body.npz is a single .npy": lambda r: np.save(r / "body.npy", np.zeros(3)) or (r / "body.npy").rename(r / "body.npz"),
    "body.npz holds a pickled object": lambda r: np.savez(r / "body.npz", model=np.array([{}], dtype=object)),
    "points.ply is text": lambda r: (r / "points.ply").write_text("ply\nformat ascii 1.0\nend_header\n"),
    "object.json frames are numbers": lambda r: (r / "object.json").write_text('{"centre": [0,0,0], "frames": [1,2,3,4,5,6]}'),
    "split holds an extra entry that is not a list": lambda r: _set_meta(r, split={"train": [1, 2], "test": [0], "val": 5}),
    "gt is a file": lambda r: shutil.rmtree(r / "gt") or (r / "gt").write_text("x"),
    "masks/human is a file": lambda r: shutil.rmtree(r / "masks" / "human") or (r / "masks" / "human").write_text("x"),
    "gt/depth.npz of strings": lambda r: np.savez(r / "gt" / "depth.npz", depth=np.full((6, 30, 40), "a")),
    "gt/novel ids that are paths": lambda r: (r / "gt" / "novel" / "cameras.json").write_text(
        (r / "gt" / "novel" / "cameras.json").read_text().replace('"v000"', '"../../x"')),
}


@pytest.mark.parametrize("name", list(CORRUPTIONS))
def test_check_never_raises_and_a_clean_check_means_load_works(gt_scene, name):
    CORRUPTIONS[name](gt_scene)
    problems = check_scene(gt_scene)
    assert problems, f"{name}: no problem reported"
    with pytest.raises(SceneError):
        load_scene(gt_scene)


# -- files keep the user's permissions -------------------------------------------------------


def test_json_and_png_files_get_the_same_permissions_from_the_umask(tmp_path):
    import os

    from tests.fixtures import make_tiny_scene

    old = os.umask(0o022)
    try:
        root = make_tiny_scene(tmp_path / "scene")
    finally:
        os.umask(old)
    modes = {p.name: p.stat().st_mode & 0o777 for p in (root / "scene.json", root / "cameras.json",
                                                         root / "images" / "000000.png", root / "body.npz")}
    assert set(modes.values()) == {0o644}, modes
    assert not list(root.glob(".*.tmp")), "a temporary file was left behind"
