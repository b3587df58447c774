"""SMPL -> Anny retargeting, and the SMPL body model (skipped without smplx / a model file)."""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch

from cogs.body import load_body_model
from cogs.body.retarget import (
    SMPL_JOINT_NAMES,
    SMPL_PARENTS,
    SMPL_TO_ANNY,
    RetargetConfig,
    _Chain,
    anny_joints_as_smpl,
    retarget_smpl_joints,
)
from cogs.errors import UserError


@pytest.fixture(scope="module")
def anny():
    return load_body_model("anny")


def smooth_anny_motion(body, T: int, seed: int = 0, sigma: float = 0.3, shape=None):
    """A known Anny motion on the bones the fit may use: keyframes blended linearly."""
    g = torch.Generator().manual_seed(seed)
    chain = _Chain(body, body.canonical(shape).joints.double())
    K = 4
    keys = torch.randn(K, len(chain.free_bones), 3, generator=g) * sigma
    keys[:, 0] = torch.tensor([0.0, 0.0, 1.0]) * torch.linspace(-1.0, 1.0, K)[:, None]  # turn about z (up)
    s = torch.linspace(0, K - 1, T)
    i0 = s.floor().long().clamp(max=K - 2)
    w = (s - i0)[:, None, None]
    pose = torch.zeros(T, body.n_bones, 3)
    pose[:, chain.free_bones] = keys[i0] * (1 - w) + keys[i0 + 1] * w
    transl = torch.stack([torch.linspace(0.0, 0.8, T), torch.zeros(T), torch.full((T,), 0.9)], 1)
    return pose, transl


def test_correspondence_table_covers_every_smpl_joint_with_a_distinct_anny_bone(anny):
    assert list(SMPL_TO_ANNY) == SMPL_JOINT_NAMES
    bones = [anny.bone_index(SMPL_TO_ANNY[n]) for n in SMPL_JOINT_NAMES]
    assert len(set(bones)) == 24
    # An SMPL parent's Anny bone is an ancestor of its child's (the trees agree).
    for j, p in enumerate(SMPL_PARENTS):
        if p < 0:
            continue
        a, b = bones[p], bones[j]
        while b >= 0 and b != a:
            b = anny.bone_parents[b]
        assert b == a, (SMPL_JOINT_NAMES[p], SMPL_JOINT_NAMES[j])


def test_fast_forward_kinematics_matches_anny_bone_transforms(anny):
    pose, transl = smooth_anny_motion(anny, 3, sigma=0.5)
    chain = _Chain(anny, anny.canonical().joints.double())
    from cogs.geometry.rotations import axis_angle_to_rotmat

    P, _ = chain.forward(axis_angle_to_rotmat(pose.double())[:, chain.active], transl.double())
    ref = anny_joints_as_smpl(anny, pose, transl)
    assert torch.allclose(P[:, chain.marker].float(), ref, atol=1e-5)


def test_retargeting_recovers_known_anny_poses_joints_within_2cm(anny):
    shape = anny.default_shape.clone()
    shape[anny.shape_names.index("height")] = 0.62
    pose, transl = smooth_anny_motion(anny, 16, seed=3, shape=shape)
    targets = anny_joints_as_smpl(anny, pose, transl, shape)
    res = retarget_smpl_joints(targets, anny)
    assert abs(float(res.shape[anny.shape_names.index("height")]) - 0.62) < 0.02
    got = anny_joints_as_smpl(anny, res.pose, res.transl, res.shape)
    err = (got - targets).norm(dim=-1)
    assert float(err.mean()) < 0.02, float(err.mean())
    assert float(err.max()) < 0.06, float(err.max())
    assert res.pose.shape == (16, anny.n_bones, 3) and torch.isfinite(res.pose).all()
    assert res.seconds < 16 * 1.0  # < 1 s per frame (generous; reported, not a benchmark)


def test_retargeting_is_invariant_to_the_world_frame(anny):
    pose, transl = smooth_anny_motion(anny, 8, seed=5)
    targets = anny_joints_as_smpl(anny, pose, transl)
    # The same motion in a y-up world, far from the origin (as SMPL datasets store it).
    R = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    moved = targets @ R.T + torch.tensor([5.0, -2.0, 10.0])
    res = retarget_smpl_joints(moved, anny, RetargetConfig(fit_shape=False))
    err = (anny_joints_as_smpl(anny, res.pose, res.transl, res.shape) - moved).norm(dim=-1)
    assert float(err.mean()) < 0.02


# -- SMPL body model ----------------------------------------------------------------------


def write_toy_smpl_model(path, seed: int = 0, V: int = 90) -> dict:
    """A random model in SMPL's file layout (24 joints, SMPL's tree), NOT SMPL itself: it
    exercises the code paths that need a model file without the licensed one."""
    rng = np.random.default_rng(seed)
    Jr = rng.random((24, V))
    Jr /= Jr.sum(1, keepdims=True)
    W = rng.random((V, 24)) ** 6
    W /= W.sum(1, keepdims=True)
    data = dict(
        v_template=rng.normal(size=(V, 3)) * 0.4,
        shapedirs=rng.normal(size=(V, 3, 10)) * 0.02,
        posedirs=rng.normal(size=(V, 3, 207)) * 0.01,
        J_regressor=Jr,
        weights=W,
        kintree_table=np.array([[4294967295] + SMPL_PARENTS[1:], list(range(24))], dtype=np.int64),
        f=rng.integers(0, V, (120, 3)),
    )
    np.savez(path, **data)
    return data


def test_smpl_body_model_matches_smplx_lbs_without_pose_blend_shapes(tmp_path):
    pytest.importorskip("smplx", reason="smplx (optional extra cogs[smpl]) is not installed")
    from smplx.lbs import lbs

    from cogs.body.lbs import lbs_points
    from cogs.body.smpl_body import SmplBody

    d = write_toy_smpl_model(tmp_path / "toy.npz")
    body = SmplBody(tmp_path / "toy.npz")
    g = torch.Generator().manual_seed(1)
    betas = torch.randn(10, generator=g)
    pose = torch.randn(2, 24, 3, generator=g) * 0.4
    transl = torch.randn(2, 3, generator=g)
    f = lambda a: torch.as_tensor(a, dtype=torch.float32)  # noqa: E731
    verts, joints = lbs(betas[None].expand(2, -1), pose.reshape(2, -1), f(d["v_template"]), f(d["shapedirs"]),
                        torch.zeros(207, d["v_template"].size), f(d["J_regressor"]), torch.tensor(SMPL_PARENTS), f(d["weights"]))
    A, J = body.bone_transforms(pose, transl, betas)
    can = body.canonical(betas)
    posed = torch.stack([lbs_points(can.vertices, can.weights, A[i]) for i in range(2)])
    assert torch.allclose(posed, verts + transl[:, None], atol=1e-5)
    assert torch.allclose(J, joints + transl[:, None], atol=1e-5)
    zero_A, _ = body.bone_transforms(torch.zeros(1, 24, 3), torch.zeros(1, 3), betas)
    assert torch.allclose(zero_A, torch.eye(4).expand(1, 24, 4, 4), atol=1e-6)  # canonical = zero pose
    assert torch.allclose(body.betas_from_rest_joints(can.joints), betas, atol=1e-3)


def test_smpl_body_model_without_a_model_file_says_what_to_set(monkeypatch):
    from cogs.body.smpl_body import resolve_smpl_model_file, set_smpl_model_path

    monkeypatch.delenv("COGS_SMPL_MODEL", raising=False)
    set_smpl_model_path(None)
    with pytest.raises(UserError, match="COGS_SMPL_MODEL"):
        resolve_smpl_model_file()
    with pytest.raises(UserError, match="does not exist"):
        resolve_smpl_model_file("/nonexistent/SMPL_NEUTRAL.pkl")


@pytest.mark.skipif(not os.environ.get("COGS_SMPL_MODEL"), reason="no licensed SMPL model: set COGS_SMPL_MODEL to run")
def test_licensed_smpl_model_poses_like_smplx():
    import smplx

    from cogs.body.smpl_body import SmplBody, resolve_smpl_model_file

    body = SmplBody()
    ref = smplx.SMPL(model_path=str(resolve_smpl_model_file()), num_betas=10)
    ref.posedirs.zero_()
    g = torch.Generator().manual_seed(0)
    pose = torch.randn(1, 24, 3, generator=g) * 0.3
    betas = torch.randn(1, 10, generator=g)
    out = ref(betas=betas, global_orient=pose[:, 0], body_pose=pose[:, 1:].reshape(1, -1))
    _, J = body.bone_transforms(pose, torch.zeros(1, 3), betas[0])
    assert torch.allclose(J, out.joints[:, :24], atol=1e-4)
