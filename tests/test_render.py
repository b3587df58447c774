"""`cogs render` on a tiny trained run: every camera, motion and object option, the clean
plate, the Anny walk cycle, SMPL-family retargeting, and bad options as one-line errors."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from cogs.cli import main
from cogs.data.io import read_image
from cogs.model import Model
from tests.fixtures import TINY

SIZE = ["--size", "48x36"]


@pytest.fixture(scope="module")
def run(small_synthetic, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("render") / "run"
    assert main(["train", "--scene", str(small_synthetic), "--out", str(out), "--set", *TINY]) == 0
    return out


def _render(run: Path, out: Path, *args: str) -> dict:
    assert main(["render", "--run", str(run), "--out", str(out), *SIZE, *args]) == 0
    meta = out.with_suffix(".json") if out.suffix == ".mp4" else out / "render.json"
    return json.loads(meta.read_text())


def _frames(out: Path) -> list[np.ndarray]:
    return [read_image(p) for p in sorted((out / "rgb").glob("*.png"))]


# -- SMPL-family sequences, made here ----------------------------------------------------


def amass_like(T: int = 24, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """An AMASS-style sequence (SMPL axis-angle `poses` [T, 72], `trans` [T, 3], z-up world):
    a walk-like swing of hips, knees and arms, turning, with noise on every body joint."""
    from cogs.body.retarget import SMPL_JOINT_NAMES
    from cogs.geometry.rotations import axis_angle_to_rotmat, rotmat_to_axis_angle

    idx = {n: i for i, n in enumerate(SMPL_JOINT_NAMES)}
    t = torch.linspace(0, 2 * math.pi, T, dtype=torch.float64)
    P = torch.zeros(T, 24, 3, dtype=torch.float64)
    up = axis_angle_to_rotmat(torch.tensor([math.pi / 2, 0.0, 0.0], dtype=torch.float64))  # SMPL y-up -> z-up
    P[:, 0] = rotmat_to_axis_angle(axis_angle_to_rotmat(torch.stack([0 * t, 0 * t, 0.5 * t], -1)) @ up)
    P[:, idx["left_hip"], 0], P[:, idx["right_hip"], 0] = 0.4 * torch.sin(t), -0.4 * torch.sin(t)
    P[:, idx["left_knee"], 0], P[:, idx["right_knee"], 0] = 0.5 * (1 + torch.sin(t)), 0.5 * (1 - torch.sin(t))
    P[:, idx["left_shoulder"], 2], P[:, idx["right_shoulder"], 2] = -1.2, 1.2  # arms down from the T-pose
    P[:, idx["left_elbow"], 1], P[:, idx["right_elbow"], 1] = -0.6, 0.6
    g = torch.Generator().manual_seed(seed)
    P[:, 1:22] += 0.15 * torch.randn(T, 21, 3, generator=g, dtype=torch.float64)
    trans = torch.stack([0.3 * t, 0 * t, 0.9 + 0 * t], -1)
    return P.reshape(T, 72).float().numpy(), trans.float().numpy()


def limb_angle_errors(poses: np.ndarray, body, pose: torch.Tensor | None = None) -> dict[str, float]:
    """Max angle (degrees) over frames between each SMPL limb's direction (the idealised
    T-pose rest direction turned by the joint's world rotation) and the same limb of the
    Anny body in `pose` (default: the retargeted one), measured on its posed bone heads."""
    from cogs.body.retarget import (
        SMPL_JOINT_NAMES, SMPL_LIMB_REST, SMPL_TO_ANNY, retarget_smpl_rotations, smpl_global_rotations,
    )

    P = torch.from_numpy(poses)
    if pose is None:
        pose, _ = retarget_smpl_rotations(P, torch.zeros(len(P), 3), body)
    transl = torch.zeros(len(P), 3)
    G = smpl_global_rotations(P)
    _, J = body.bone_transforms(pose, transl)
    J = J.double()
    idx = {n: i for i, n in enumerate(SMPL_JOINT_NAMES)}
    out = {}
    for n, (child, d) in SMPL_LIMB_REST.items():
        ds = G[:, idx[n]] @ torch.tensor(d, dtype=torch.float64)
        da = J[:, body.bone_index(SMPL_TO_ANNY[child])] - J[:, body.bone_index(SMPL_TO_ANNY[n])]
        cos = (ds * da).sum(-1) / (ds.norm(dim=-1) * da.norm(dim=-1))
        out[n] = float(torch.rad2deg(torch.arccos(cos.clamp(-1, 1))).max())
    return out


def test_retargeting_an_smpl_sequence_keeps_limb_directions(body_model):
    errors = limb_angle_errors(amass_like()[0], body_model)
    print("limb direction error (deg, max over frames):", {k: round(v, 5) for k, v in errors.items()})
    assert max(errors.values()) < 0.05
    # The measure can fail: SMPL's rotations copied bone for bone (axes turned, no rest-pose
    # correction) leave Anny's A-pose limbs tens of degrees off.
    from cogs.body.retarget import SMPL_BODY_JOINTS, SMPL_JOINT_NAMES, SMPL_TO_ANNY, SMPL_TO_ANNY_AXES

    poses = amass_like()[0]
    C = torch.tensor(SMPL_TO_ANNY_AXES, dtype=torch.float32)
    naive = torch.zeros(len(poses), body_model.n_bones, 3)
    for j, n in enumerate(SMPL_JOINT_NAMES[:SMPL_BODY_JOINTS]):
        naive[:, body_model.bone_index(SMPL_TO_ANNY[n])] = torch.from_numpy(poses[:, 3 * j : 3 * j + 3]) @ C.T
    assert max(limb_angle_errors(poses, body_model, naive).values()) > 20


# -- the Anny walk cycle ----------------------------------------------------------------


def test_walk_cycle_evaluates_blender_bezier_keys_exactly():
    from cogs.use.walk import load_cycle, mpfb2_data

    curves, _, _ = load_cycle()
    raw = json.loads((mpfb2_data() / "walkcycles" / "crappy_experimental_female.json").read_text())["animation_data"]["root"]
    for frame, ch in raw.items():
        np.testing.assert_allclose(curves.value("root", "location", np.array([float(frame)]))[0],
                                   ch["location"]["values"], atol=1e-9)
    between = curves.value("root", "location", np.linspace(0, 40, 81))[:, 1]
    assert np.all(np.diff(between) > -1e-3)  # the root walks on along its track


def test_walk_cycle_walks_forward_with_alternating_feet(body_model):
    from cogs.use.walk import walk_cycle

    shape = body_model.default_shape
    pose, transl = walk_cycle(body_model, shape, fps=24.0, cycles=2)
    _, J = body_model.bone_transforms(torch.from_numpy(pose), torch.from_numpy(transl), shape)
    J = J.numpy()
    root = J[:, 0]
    assert root[-1, 1] - root[0, 1] < -1.0  # Anny faces -y: more than a metre forward in two cycles
    assert np.abs(root[:, 0]).max() < 0.1  # and straight
    lead = J[:, body_model.bone_index("foot.L"), 1] - J[:, body_model.bone_index("foot.R"), 1]
    assert lead.max() > 0.2 and lead.min() < -0.2  # each foot in front in turn
    lowest = J[:, :, 2].min(1)
    assert lowest.max() - lowest.min() < 0.08  # the lowest point stays near the floor


# -- rendering options --------------------------------------------------------------------


def test_each_camera_renders(run, small_synthetic, tmp_path):
    m = _render(run, tmp_path / "train", "--camera", "train", "--frames", "0:3", "--depth", "--alpha")
    assert m["frames"] == 3 and len(_frames(tmp_path / "train")) == 3
    depth = np.load(tmp_path / "train" / "depth.npz")["depth"]
    assert depth.shape == (3, 36, 48) and depth.max() > 0.5
    for b in ("human", "object", "scene"):
        assert len(list((tmp_path / "train" / "alpha" / b).glob("*.png"))) == 3
    orbit = _render(run, tmp_path / "orbit.mp4", "--camera", "orbit", "--frames", "0:4")
    assert orbit["frames"] == 4 and (tmp_path / "orbit.mp4").stat().st_size > 0
    spiral = _frames(tmp_path / "spiral") if _render(run, tmp_path / "spiral", "--camera", "spiral", "--frames", "0:3") else None
    assert len(spiral) == 3 and not np.array_equal(spiral[0], spiral[2])  # the camera moves
    novel = _render(run, tmp_path / "novel", "--camera", "novel", "--frames", "0:2")
    assert novel["frames"] == 2
    # A camera path: two keys, interpolated over six frames, passing through the middle.
    cams = json.loads((small_synthetic / "cameras.json").read_text())["frames"]
    path = tmp_path / "path.json"
    path.write_text(json.dumps({"frames": [{"K": cams[0]["K"], "world_to_camera": cams[0]["world_to_camera"], "frame": 0},
                                           {"K": cams[-1]["K"], "world_to_camera": cams[-1]["world_to_camera"], "frame": 5}]}))
    m = _render(run, tmp_path / "path", "--camera", str(path), "--motion", "run", "--frames", "0:6")
    frames = _frames(tmp_path / "path")
    assert len(frames) == 6 and not np.array_equal(frames[0], frames[5])


def test_each_motion_renders(run, small_synthetic, tmp_path):
    walk = _render(run, tmp_path / "walk", "--motion", "anny:walk", "--camera", "orbit", "--frames", "0:3")
    assert walk["fps"] == 24.0 and walk["start_frame"] == 0
    _render(run, tmp_path / "walk1", "--motion", "anny:walk:0.5", "--camera", "orbit", "--fps", "6")
    assert len(_frames(tmp_path / "walk1")) == int(0.5 * 40 / 24 * 6) + 1
    _render(run, tmp_path / "synth", "--motion", "synth:turn", "--camera", "orbit", "--frames", "0:2")
    _render(run, tmp_path / "native", "--motion", str(small_synthetic / "body.npz"), "--frames", "0:2")
    poses, trans = amass_like()
    np.savez(tmp_path / "seq.npz", poses=poses, trans=trans, mocap_framerate=30.0)
    m = _render(run, tmp_path / "amass", "--motion", str(tmp_path / "seq.npz"), "--camera", "orbit", "--frames", "0:2")
    assert m["fps"] == 30.0


def test_a_new_motion_starts_where_the_person_stands(run):
    """Placement: the first frame's root is the person's root at --start-frame, on the floor."""
    from cogs.use.motion import load_motion, place
    from cogs.use.posing import world_up

    model = Model.load(run)
    h = model.human
    with torch.no_grad():
        m = place(load_motion("anny:walk", model, 10.0), h, 3, world_up(h))
        _, J_new = h.body.bone_transforms(m.pose[:1], m.transl[:1], h.shape)
        _, J_run = h.body.bone_transforms(*h.frame_pose(3), h.shape)
    assert float((J_new[0, 0, :2] - J_run[0, 0, :2]).norm()) < 1e-4  # same place (z up)
    assert abs(float(J_new[0, 0, 2] - J_run[0, 0, 2])) < 0.15  # standing at about the same height


def test_each_object_option(run, tmp_path):
    from cogs.use.motion import load_motion, place
    from cogs.use.objects import HAND_BONES, object_path
    from cogs.use.posing import world_up

    model = Model.load(run)
    h, o = model.human, model.object
    with torch.no_grad():
        motion = place(load_motion("anny:walk", model, 10.0), h, 0, world_up(h))
        held = object_path("hand-right", model, motion, 4, None)
        # Attached: the object's pose relative to the hand bone stays what it was at frame 4.
        bone = h.body.bone_index(HAND_BONES["anny"][1])
        rel = []
        for k in (0, len(motion) // 2, len(motion) - 1):
            A, _ = h.body.bone_transforms(motion.pose[k : k + 1], motion.transl[k : k + 1], h.shape)
            rel.append(torch.linalg.solve(A[0, bone].double(), torch.cat([held.translation[k].double(), torch.ones(1, dtype=torch.float64)])))
        assert max(float((r - rel[0]).norm()) for r in rel) < 1e-4
        assert float((held.translation[-1] - held.translation[0]).norm()) > 0.5  # it went along
        static = object_path("static", model, motion, 2, None)
        assert torch.equal(static.translation[0], static.translation[-1])
        torch.testing.assert_close(static.translation[0], o.frame_pose(2)[0])
    traj = tmp_path / "traj.json"
    traj.write_text(json.dumps({"frames": [{"translation": [0.0, 0.0, 1.0], "quat_wxyz": [1, 0, 0, 0]},
                                           {"translation": [0.5, 0.0, 1.0], "quat_wxyz": [0, 0, 0, 1]}]}))
    for spec in ("run", "hand-left", "static", str(traj)):
        _render(run, tmp_path / Path(spec).stem, "--object", spec, "--frames", "0:2")
    m = _render(run, tmp_path / "none", "--object", "none", "--frames", "0:2", "--alpha")
    assert m["branches"] == ["human", "scene"] and not (tmp_path / "none" / "alpha" / "object").exists()


def test_the_clean_plate_shows_no_person_or_object(run, tmp_path):
    full = _render(run, tmp_path / "full", "--frames", "0:2", "--alpha")
    plate = _render(run, tmp_path / "plate", "--branches", "scene", "--frames", "0:2", "--alpha")
    assert plate["branches"] == ["scene"]
    person = read_image(tmp_path / "full" / "alpha" / "human" / "000000.png")[..., 0] > 200
    assert person.any()
    a, b = read_image(tmp_path / "full" / "rgb" / "000000.png"), read_image(tmp_path / "plate" / "rgb" / "000000.png")
    assert np.abs(a[person].astype(int) - b[person].astype(int)).mean() > 5  # the person is gone there
    assert sorted(p.name for p in (tmp_path / "plate" / "alpha").iterdir()) == ["scene"]


@pytest.mark.parametrize("args, names", [
    (["--motion", "no/such/motion.npz"], "--motion"),
    (["--frames", "5:999"], "--frames"),
    (["--frames", "banana"], "--frames"),
    (["--object", "hand-right", "--hand-bone", "tail.L"], "--hand-bone"),
    (["--size", "12x"], "--size"),
    (["--branches", "human", "sky"], "--branches"),
    (["--attach-frame", "500", "--object", "hand-left"], "--attach-frame"),
    (["--device", "tpu"], "--device"),
])
def test_bad_options_are_one_line_errors_naming_the_option(run, tmp_path, capsys, args, names):
    assert main(["render", "--run", str(run), "--out", str(tmp_path / "x"), *args]) == 2
    err = capsys.readouterr().err
    assert names in err and "Traceback" not in err
    assert not (tmp_path / "x").exists()  # nothing written


def test_a_camera_path_with_nan_and_an_existing_out_are_refused(run, tmp_path, capsys):
    bad = tmp_path / "nan.json"
    bad.write_text(json.dumps({"frames": [{"world_to_camera": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, float("nan")], [0, 0, 0, 1]]}]}))
    assert main(["render", "--run", str(run), "--out", str(tmp_path / "y"), "--camera", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "--camera" in err and "key 0" in err
    (tmp_path / "taken.mp4").write_bytes(b"")
    assert main(["render", "--run", str(run), "--out", str(tmp_path / "taken.mp4")]) == 2
    assert "--overwrite" in capsys.readouterr().err
    garbage = tmp_path / "g.npz"
    garbage.write_bytes(b"not a zip")
    assert main(["render", "--run", str(run), "--out", str(tmp_path / "z"), "--motion", str(garbage)]) == 2
    assert "--motion" in capsys.readouterr().err


def test_render_and_export_make_no_tensor_on_an_implicit_device(run, tmp_path):
    """With the default device set to `meta`, a tensor made without an explicit device
    (or one taken from the model or its inputs) lands on meta and fails beside the
    model's CPU tensors."""
    torch.set_default_device("meta")
    try:
        assert main(["render", "--run", str(run), "--out", str(tmp_path / "r"), *SIZE, "--camera", "orbit",
                     "--motion", "anny:walk", "--object", "hand-right", "--frames", "0:2", "--depth", "--alpha"]) == 0
        assert main(["export", "--run", str(run), "--out", str(tmp_path / "e"), "--frame", "1"]) == 0
    finally:
        torch.set_default_device("cpu")
    assert len(_frames(tmp_path / "r")) == 2 and (tmp_path / "e" / "reconstruction.glb").is_file()
