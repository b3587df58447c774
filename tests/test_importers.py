"""Benchmark importers on small fixtures written here in the public layouts.

No SMPL model exists here, so the "SMPL" joints of the fixtures come from posing Anny and
reading its joints through the SMPL->Anny correspondence table: that also gives the ground
truth the imported (retargeted) body is compared with.
"""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch
from PIL import Image

from cogs.body import load_body_model
from cogs.cli import main
from cogs.body.retarget import anny_joints_as_smpl
from cogs.data.scene import load_scene
from cogs.data.validate import check_scene
from cogs.errors import UserError
from cogs.geometry.camera import look_at, project_points
from cogs.geometry.rotations import axis_angle_to_rotmat, rotmat_to_quat
from cogs.preprocess.importers import import_humannerf, import_neuman
from cogs.preprocess.importers.common import FrameSelection, hosnerf16_split, neuman_split

W, H = 64, 48
K = np.array([[70.0, 0.0, 31.5], [0.0, 70.0, 24.5], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="module")
def motion():
    """(ground-truth SMPL-order world joints [T, 24, 3] in metres, z up, cameras w2c [T, 4, 4])."""
    from tests.test_retarget import smooth_anny_motion

    body = load_body_model("anny")
    T = 25
    pose, transl = smooth_anny_motion(body, T, seed=7, sigma=0.25)
    joints = anny_joints_as_smpl(body, pose, transl).double().numpy()
    w2c = np.stack([
        look_at([0.4 + 0.6 * np.sin(0.1 * t), -3.2, 1.0], joints[t, 0], up=(0.0, 0.0, 1.0)) for t in range(T)
    ])
    return joints, w2c


def render(joints: np.ndarray, w2c: np.ndarray, t: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A synthetic frame: textured background and the person as disks on the joints."""
    yy, xx = np.mgrid[0:H, 0:W]
    rgb = np.stack([(xx * 4) % 256, (yy * 5) % 256, np.full_like(xx, 90 + 5 * t)], -1).astype(np.uint8)
    pix, _ = project_points(joints, w2c, K)
    person = np.zeros((H, W), bool)
    for u, v in pix:
        person |= (xx + 0.5 - u) ** 2 + (yy + 0.5 - v) ** 2 < 3.0**2
    rgb[person] = (200, 60, 40)
    return rgb, person


# -- NeuMan ---------------------------------------------------------------------------------

COLMAP_UNITS_PER_METRE = 2.0


def write_neuman(root, joints, w2c, with_joints=True, distortion=0.0, four_d=False):
    """A NeuMan sequence: COLMAP text model, segmentations (person = 0), SMPL fits."""
    T = len(joints)
    k = COLMAP_UNITS_PER_METRE
    (root / "images").mkdir(parents=True)
    (root / "segmentations").mkdir()
    (root / "sparse").mkdir()
    names = [f"{i:05d}.png" for i in range(T)]
    for t, name in enumerate(names):
        rgb, person = render(joints[t], w2c[t], t)
        Image.fromarray(rgb).save(root / "images" / name)
        Image.fromarray(np.where(person, 0, 255).astype(np.uint8)).save(root / "segmentations" / name)
    model = "PINHOLE" if distortion == 0 else "SIMPLE_RADIAL"
    params = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]] if distortion == 0 else [K[0, 0], K[0, 2], K[1, 2], distortion]
    (root / "sparse" / "cameras.txt").write_text(
        "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
        f"# Number of cameras: 1\n1 {model} {W} {H} " + " ".join(f"{p:.10g}" for p in params) + "\n")
    lines = ["# Image list with two lines of data per image:", "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
             "#   POINTS2D[] as (X, Y, POINT3D_ID)", f"# Number of images: {T}, mean observations per image: 1"]
    for t in reversed(range(T)):  # not in video order on purpose
        R = w2c[t, :3, :3]
        q = rotmat_to_quat(torch.from_numpy(R)).numpy()
        tv = w2c[t, :3, 3] * k
        lines.append(f"{t + 1} " + " ".join(f"{x:.12g}" for x in [*q, *tv]) + f" 1 {names[t]}")
        lines.append("10.5 20.5 1" if t % 2 else "")
    (root / "sparse" / "images.txt").write_text("\n".join(lines) + "\n")
    rng = np.random.default_rng(0)
    pts = np.concatenate([rng.uniform([-2, -1, -0.05], [3, 3, 0.0], (60, 3)), rng.uniform([-2, 2.5, 0], [3, 2.6, 2], (40, 3))])
    (root / "sparse" / "points3D.txt").write_text(
        "# 3D point list with one line of data per point:\n#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
        "# Number of points: 100, mean track length: 2\n"
        + "".join(f"{i + 1} {x * k:.9g} {y * k:.9g} {z * k:.9g} 120 130 140 0.5 1 0 2 0\n" for i, (x, y, z) in enumerate(pts)))
    # SMPL output frame: a rotated, shifted copy of the world, at NeuMan's scale (COLMAP units).
    R_al = axis_angle_to_rotmat(torch.tensor([0.3, -1.1, 0.5], dtype=torch.float64)).numpy()
    t_al = np.array([1.0, -0.5, 4.0])
    y = np.einsum("ji,tkj->tki", R_al, k * joints - t_al) / k  # SMPL-output joints
    poses = rng.normal(size=(T, 72)) * 0.1
    if four_d:
        # HUGS: world = scale * SMPL + transl, with R = I: bake R_al into the joints.
        y4 = (k * joints - t_al) / k
        np.savez(root / "4d_humans_tmp.npz", global_orient=poses[:, :3], body_pose=poses[:, 3:], betas=np.zeros((T, 10)),
                 transl=np.tile(t_al, (T, 1)), scale=np.full(T, k), **({"joints": y4} if with_joints else {}))
        (root / "4d_humans").mkdir()
        (root / "4d_humans_tmp.npz").rename(root / "4d_humans" / "smpl_optimized_aligned_scale.npz")
        return names
    person = {"pose": [p.astype(np.float32) for p in poses], "betas": [np.zeros(10, np.float32)] * T}
    if with_joints:
        person["joints"] = y.astype(np.float32)
    (root / "smpl_output_optimized.pkl").write_bytes(pickle.dumps({1: person}))
    A = np.concatenate([(k * R_al).T, t_al[None]], 0)  # world = [y, 1] @ A
    np.save(root / "alignments.npy", np.array({n: A for n in names}, dtype=object), allow_pickle=True)
    return names


def anny_world_joints(scene) -> np.ndarray:
    body = load_body_model("anny")
    b = scene.body
    return anny_joints_as_smpl(body, torch.from_numpy(b.pose), torch.from_numpy(b.transl), torch.from_numpy(b.shape)).double().numpy()


def test_neuman_import_gives_a_valid_scene_with_the_benchmark_split_and_metric_body(tmp_path, motion):
    joints, w2c = motion
    src = tmp_path / "bike"
    names = write_neuman(src, joints, w2c)
    out = import_neuman(src, tmp_path / "scene")
    assert check_scene(out) == []
    s = load_scene(out)
    T = len(names)
    assert s.frame_ids == [n[:-4] for n in names] and not s.has_object and s.body.model == "anny"
    # NeuMan's rule for 25 frames: every 5th from 2 held out; the first half (rounded down) is test.
    assert s.split["test"] == [2, 7] and s.source["val"] == [12, 17, 22]
    assert s.split["train"] == [i for i in range(T) if i not in (2, 7, 12, 17, 22)]
    # Masks: the person is black in NeuMan's segmentations, white in cogs'.
    _, person = render(joints[3], w2c[3], 3)
    assert np.array_equal(s.human_masks[3], person)
    # Cameras: a COLMAP-world point projects to the same pixel before and after import.
    X = np.array([[0.3, 0.2, 1.1], [-0.5, 1.0, 0.4]]) * COLMAP_UNITS_PER_METRE
    for t in (0, 13):
        pc = X @ w2c[t, :3, :3].T + w2c[t, :3, 3] * COLMAP_UNITS_PER_METRE  # COLMAP: R x + t
        colmap_px = pc[:, :2] / pc[:, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]
        ours, _ = project_points(X / COLMAP_UNITS_PER_METRE, s.cameras.world_to_camera[t], s.cameras.K[t])
        assert np.allclose(ours, colmap_px, atol=1e-6)
    colmap_pts = np.loadtxt(src / "sparse" / "points3D.txt", comments="#")[:, 1:4]
    assert np.allclose(s.points_xyz, colmap_pts / COLMAP_UNITS_PER_METRE, atol=1e-5)  # points in metres
    # The retargeted body lands on the ground-truth joints (the imported world is metric).
    err = np.linalg.norm(anny_world_joints(s) - joints, axis=-1)
    assert err.mean() < 0.02, err.mean()


def test_neuman_hugs_variant_and_radial_distortion(tmp_path, motion):
    joints, w2c = motion
    src = tmp_path / "lab"
    write_neuman(src, joints, w2c, four_d=True, distortion=0.02)
    out = import_neuman(src, tmp_path / "scene")
    s = load_scene(out)
    assert "4d_humans" in s.source["smpl_fits"]
    assert np.allclose(s.cameras.K[0], [[K[0, 0], 0, K[0, 2]], [0, K[0, 0], K[1, 2]], [0, 0, 1]])
    err = np.linalg.norm(anny_world_joints(s) - joints, axis=-1)
    assert err.mean() < 0.02


def test_neuman_fits_without_joints_and_no_smpl_model_are_refused_clearly(tmp_path, motion):
    joints, w2c = motion
    src = tmp_path / "seq"
    write_neuman(src, joints, w2c, with_joints=False)
    with pytest.raises(UserError, match=r"smpl_output_optimized\.pkl.*joints"):
        import_neuman(src, tmp_path / "scene")


@pytest.mark.parametrize("missing", ["sparse/images.txt", "alignments.npy", "segmentations/00004.png", "images/00000.png"])
def test_neuman_missing_files_are_user_errors_naming_them(tmp_path, motion, missing):
    joints, w2c = motion
    src = tmp_path / "seq"
    write_neuman(src, joints[:12], w2c[:12])
    (src / missing).unlink()
    with pytest.raises(UserError, match=missing.split("/")[-1].replace(".", r"\.")):
        import_neuman(src, tmp_path / "scene")


def test_neuman_split_rule_is_the_benchmarks():
    for n in (25, 37, 42, 102, 103, 104, 500):
        train, val, test = neuman_split(n)
        held = list(range(2, n, 5))
        assert test == held[: len(held) // 2] and val == held[len(held) // 2 :]
        assert sorted(train + val + test) == list(range(n))
    # Short clips follow the same formula, whose spacing is then not 5.
    assert neuman_split(12) == ([0, 1, 2, 4, 5, 6, 7, 8, 10, 11], [9], [3])


def test_hosnerf16_split():
    train, test = hosnerf16_split(100)
    assert test == list(range(0, 100, 6))[:16] and len(train) == 84
    assert hosnerf16_split(12) == ([1, 3, 5, 7, 9, 11], [0, 2, 4, 6, 8, 10])


# -- HumanNeRF / HOSNeRF --------------------------------------------------------------------


def write_humannerf(root, joints, w2c, T=12, with_object=True):
    """HumanNeRF's layout (in-the-wild preparation): body coordinates with the pelvis at the
    origin, world = R(Rh) x_body + Th; integer pixel centres in K."""
    for d in ("images", "masks") + (("object_masks",) if with_object else ()):
        (root / d).mkdir(parents=True)
    rng = np.random.default_rng(1)
    cams, mesh = {}, {}
    K_hn = K.copy()
    K_hn[:2, 2] -= 0.5
    for t in range(T):
        f = f"frame_{t:06d}"
        rgb, person = render(joints[t], w2c[t], t)
        Image.fromarray(rgb).save(root / "images" / f"{f}.png")
        Image.fromarray(np.repeat(person[..., None] * np.uint8(255), 3, -1)).save(root / "masks" / f"{f}.png")
        if with_object:
            pix, _ = project_points(joints[t, 23:24], w2c[t], K)
            yy, xx = np.mgrid[0:H, 0:W]
            obj = (xx + 0.5 - pix[0, 0]) ** 2 + (yy + 0.5 - pix[0, 1]) ** 2 < 4.0**2
            Image.fromarray(obj.astype(np.uint8) * 255).save(root / "object_masks" / f"{f}.png")
        Rh = rng.normal(size=3) * 0.5
        R = axis_angle_to_rotmat(torch.from_numpy(Rh)).numpy()
        Th = joints[t, 0]
        cams[f] = {"intrinsics": K_hn.astype(np.float32), "extrinsics": w2c[t].astype(np.float32),
                   "distortions": np.zeros(5, np.float32)}
        mesh[f] = {"Rh": Rh.astype(np.float32), "Th": Th.astype(np.float32),
                   "poses": rng.normal(size=72).astype(np.float32) * 0.1,
                   "joints": ((joints[t] - Th) @ R).astype(np.float32),
                   "tpose_joints": np.zeros((24, 3), np.float32)}
    (root / "cameras.pkl").write_bytes(pickle.dumps(cams))
    (root / "mesh_infos.pkl").write_bytes(pickle.dumps(mesh))
    (root / "canonical_joints.pkl").write_bytes(pickle.dumps({"joints": np.zeros((24, 3), np.float32)}))


def test_humannerf_import_with_object_masks(tmp_path, motion):
    joints, w2c = motion
    src = tmp_path / "subject"
    write_humannerf(src, joints, w2c)
    out = import_humannerf(src, tmp_path / "scene")
    assert check_scene(out) == []
    s = load_scene(out)
    assert s.n_frames == 12 and s.has_object and s.split == {"train": [1, 3, 5, 7, 9, 11], "test": [0, 2, 4, 6, 8, 10]}
    # HumanNeRF's pixel (i, j) is centred at integer coordinates, cogs' at +0.5.
    X = joints[4, [0, 15]]
    K_hn = K - np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])
    px_hn, _ = project_points(X, w2c[4], K_hn)
    ours, _ = project_points(X, s.cameras.world_to_camera[4], s.cameras.K[4])
    assert np.allclose(ours, px_hn + 0.5, atol=1e-4)
    err = np.linalg.norm(anny_world_joints(s) - joints[:12], axis=-1)
    assert err.mean() < 0.02, err.mean()
    # Object: initial guess near the right hand; its pixels are not the person's.
    assert np.linalg.norm(s.object.translations - joints[:12, 23], axis=1).max() < 0.05
    assert not (s.human_masks & s.object_masks).any() and s.object_masks.any()
    # Sparse points: guessed on a plane 3 cm under the lowest foot joint, across the mean
    # pelvis->neck direction (this fixture's random spine poses tilt it away from z).
    up = (joints[:12, 12] - joints[:12, 0]).mean(0)
    up /= np.linalg.norm(up)
    ground = (joints[:12, [7, 8, 10, 11]].reshape(-1, 3) @ up).min() - 0.03
    assert len(s.points_xyz) > 50 and np.allclose(s.points_xyz @ up, ground, atol=1e-3)


def test_humannerf_missing_files_are_user_errors_naming_them(tmp_path, motion):
    joints, w2c = motion
    src = tmp_path / "subject"
    write_humannerf(src, joints, w2c, T=4, with_object=False)
    (src / "mesh_infos.pkl").unlink()
    with pytest.raises(UserError, match=r"mesh_infos\.pkl"):
        import_humannerf(src, tmp_path / "scene")
    with pytest.raises(UserError, match="not a folder"):
        import_humannerf(tmp_path / "nowhere", tmp_path / "scene")


def test_humannerf_smpl_body_keeps_smpl_params_with_rh_th_folded_in(tmp_path, motion):
    pytest.importorskip("smplx", reason="smplx (optional extra cogs[smpl]) is not installed")
    from smplx.lbs import lbs

    from cogs.body.retarget import SMPL_PARENTS
    from cogs.body.smpl_body import SmplBody
    from tests.test_retarget import write_toy_smpl_model

    joints, w2c = motion
    src = tmp_path / "subject"
    write_humannerf(src, joints, w2c, T=4, with_object=False)
    model = write_toy_smpl_model(tmp_path / "toy.npz")
    # canonical_joints.pkl holds the mean shape's rest joints: betas are recovered from them.
    betas = np.linspace(-1, 1, 10)
    toy = SmplBody(tmp_path / "toy.npz")
    rest = toy.canonical(torch.tensor(betas, dtype=torch.float32)).joints.numpy()
    (src / "canonical_joints.pkl").write_bytes(pickle.dumps({"joints": rest}))
    out = import_humannerf(src, tmp_path / "scene", body_model="smpl", smpl_model=tmp_path / "toy.npz")
    assert check_scene(out) == []
    s = load_scene(out)
    assert s.body.model == "smpl" and s.body.pose.shape == (4, 24, 3)
    assert np.allclose(s.body.shape, betas, atol=1e-3)
    # Expected: world = R(Rh) (SMPL(poses) - J0) + Th (HumanNeRF's in-the-wild body coordinates).
    mesh = pickle.loads((src / "mesh_infos.pkl").read_bytes())
    f = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    _, J = toy.bone_transforms(torch.from_numpy(s.body.pose), torch.from_numpy(s.body.transl), torch.from_numpy(s.body.shape))
    for t, name in enumerate(sorted(mesh)):
        m = mesh[name]
        _, Js = lbs(f(betas)[None], f(m["poses"])[None], f(model["v_template"]), f(model["shapedirs"]),
                    torch.zeros(207, model["v_template"].size), f(model["J_regressor"]), torch.tensor(SMPL_PARENTS), f(model["weights"]))
        R = axis_angle_to_rotmat(f(m["Rh"])).numpy()
        expected = (Js[0].numpy() - rest[0]) @ R.T + m["Th"]
        assert np.allclose(J[t].numpy(), expected, atol=1e-4)


def test_import_never_writes_over_an_existing_scene_unless_told_to(tmp_path, motion):
    from tests.fixtures import make_tiny_scene, tree_hash

    joints, w2c = motion
    src = tmp_path / "subject"
    write_humannerf(src, joints, w2c, T=4, with_object=False)
    scene = make_tiny_scene(tmp_path / "scene")
    before = tree_hash(scene)
    with pytest.raises(UserError, match=r"already holds a cogs scene 'tiny' \(6 frames\).*--overwrite"):
        import_humannerf(src, scene)
    assert tree_hash(scene) == before
    import_humannerf(src, scene, overwrite=True)
    assert load_scene(scene).n_frames == 4  # replaced whole: none of the old scene's frames are left
    assert sorted(p.name for p in (scene / "images").iterdir()) == [f"frame_{i:06d}.png" for i in range(4)]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene", "subject"]


def test_cli_import_reports_errors_without_traceback(tmp_path, motion, capsys):
    from cogs.cli import main

    assert main(["import", "neuman", str(tmp_path / "nowhere"), "--out", str(tmp_path / "scene")]) == 2
    joints, w2c = motion
    src = tmp_path / "seq"
    write_neuman(src, joints[:12], w2c[:12])
    assert main(["import", "neuman", str(src), "--out", str(tmp_path / "scene")]) == 0
    assert check_scene(tmp_path / "scene") == []


def test_import_keeps_the_frames_asked_for_at_the_size_asked_for(tmp_path, motion):
    """--start/--stride/--limit keep those frames of the sequence (its split rule applied to
    them), --max-side resizes frames and masks and scales the intrinsics: a point projects
    where it did, scaled."""
    joints, w2c = motion
    src = tmp_path / "subject"
    write_humannerf(src, joints, w2c, T=12)
    full = load_scene(import_humannerf(src, tmp_path / "full"))
    sel = FrameSelection(start=1, stride=2, limit=5, max_side=W // 2)
    s = load_scene(import_humannerf(src, tmp_path / "half", select=sel))
    kept = [1, 3, 5, 7, 9]
    assert s.frame_ids == [full.frame_ids[i] for i in kept] and s.n_frames == 5
    assert (s.width, s.height) == (W // 2, round(H * (W // 2) / W))
    assert s.split == {"train": [1, 3], "test": [0, 2, 4]}  # hosnerf-16's rule on 5 frames
    assert s.source["selection"]["frames_of_the_sequence"] == kept
    X = joints[5, [0, 15, 23]]
    sx, sy = s.width / full.width, s.height / full.height
    for i, t in enumerate(kept):
        ours, _ = project_points(X, s.cameras.world_to_camera[i], s.cameras.K[i])
        theirs, _ = project_points(X, full.cameras.world_to_camera[t], full.cameras.K[t])
        assert np.allclose(ours, theirs * [sx, sy], atol=1e-6)
        # the mask, reduced, is the full mask averaged over each new pixel
        area = full.human_masks[t].reshape(s.height, full.height // s.height, s.width, full.width // s.width).mean((1, 3))
        assert ((area > 0.5) == s.human_masks[i]).mean() > 0.99
    nm = tmp_path / "bike"
    names = write_neuman(nm, joints, w2c)
    s = load_scene(import_neuman(nm, tmp_path / "neuman", select=FrameSelection(stride=2)))
    assert s.frame_ids == [n[:-4] for n in names][::2] and s.split["test"] == neuman_split(len(names[::2]))[2]


@pytest.mark.parametrize("option, value", [("--stride", "0"), ("--start", "-1"), ("--limit", "0"), ("--max-side", "8")])
def test_import_selection_options_are_checked_before_work(tmp_path, motion, option, value, capsys):
    joints, w2c = motion
    write_humannerf(tmp_path / "subject", joints, w2c, T=4, with_object=False)
    assert main(["import", "humannerf", str(tmp_path / "subject"), "--out", str(tmp_path / "s"), option, value]) == 2
    assert f"{option} must be at least" in capsys.readouterr().err and not (tmp_path / "s").exists()
