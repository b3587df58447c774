"""The body-model layer: canonical space, forward kinematics and LBS on the real Anny."""

from __future__ import annotations

import math

import torch

from cogs.body import lbs_gaussians, lbs_points
from cogs.geometry.rotations import axis_angle_to_rotmat, quat_to_rotmat, random_quat


def test_anny_exposes_labels_as_data(body_model):
    assert body_model.n_bones == 104 == len(body_model.bone_parents)
    assert body_model.bone_parents[0] == -1
    assert body_model.shape_names == ["gender", "age", "muscle", "weight", "height", "proportions"]
    can = body_model.canonical()
    assert can.vertices.shape == (13718, 3) and can.faces.shape == (27420, 3)
    torch.testing.assert_close(can.weights.sum(1), torch.ones(13718))


def test_rest_pose_returns_the_canonical_set(body_model):
    can = body_model.canonical()
    pose, transl = body_model.zero_pose()
    A, joints = body_model.bone_transforms(pose, transl)
    torch.testing.assert_close(A[0], torch.eye(4).expand(104, 4, 4), atol=1e-6, rtol=0)
    torch.testing.assert_close(lbs_points(can.vertices, can.weights, A[0]), can.vertices, atol=1e-6, rtol=0)
    torch.testing.assert_close(joints[0], can.joints, atol=1e-6, rtol=0)


def test_translation_moves_every_vertex(body_model):
    pose, _ = body_model.zero_pose()
    v = body_model.posed_vertices(pose, torch.tensor([[0.5, -1.0, 0.87]]))[0]
    torch.testing.assert_close(v - body_model.canonical().vertices, torch.tensor([0.5, -1.0, 0.87]).expand_as(v), atol=1e-5, rtol=0)


def test_single_bone_rotation_moves_its_points_and_gaussian_orientations(body_model):
    can = body_model.canonical()
    j = body_model.bone_index("lowerarm01.R")
    angle = math.pi / 2
    pose, transl = body_model.zero_pose()
    pose[0, j] = torch.tensor([0.0, 0.0, angle])  # world-aligned axes (local-ref)
    A, joints = body_model.bone_transforms(pose, transl)
    head = can.joints[j]
    # A vertex skinned only to this bone (or its children) rotates rigidly about the bone head.
    w = can.weights
    only = torch.nonzero(w[:, j] > 0.999).flatten()
    assert len(only) > 20
    Rz = axis_angle_to_rotmat(torch.tensor([0.0, 0.0, angle]))
    expected = (can.vertices[only] - head) @ Rz.T + head
    got = lbs_points(can.vertices, w, A[0])[only]
    torch.testing.assert_close(got, expected, atol=1e-4, rtol=0)
    # Vertices not influenced by the arm chain do not move.
    side = torch.sign(head[0])
    far = torch.nonzero(can.vertices[:, 0] * side < -0.1).flatten()  # the other half of the body
    torch.testing.assert_close(lbs_points(can.vertices, w, A[0])[far], can.vertices[far], atol=1e-5, rtol=0)
    # Gaussian orientations are rotated by the same rotation.
    q = random_quat(len(only))
    _, q_posed = lbs_gaussians(can.vertices[only], q, w[only], A[0])
    torch.testing.assert_close(quat_to_rotmat(q_posed), Rz @ quat_to_rotmat(q), atol=1e-4, rtol=0)


def test_our_lbs_matches_annys_own_skinning(body_model):
    g = torch.Generator().manual_seed(1)
    pose = 0.25 * torch.randn(1, 104, 3, generator=g)
    transl = torch.tensor([[0.1, 0.2, 0.9]])
    ours = body_model.posed_vertices(pose, transl)[0]
    deltas = torch.zeros(1, 104, 4, 4, dtype=torch.float64)
    deltas[:, :, :3, :3] = axis_angle_to_rotmat(pose.double())
    deltas[:, :, 3, 3] = 1
    theirs = body_model._anny(pose_parameters=deltas)["vertices"][0].float() + transl
    assert (ours - theirs).norm(dim=-1).max() < 5e-3  # metres


def test_gradients_flow_to_pose_translation_and_canonical_points(body_model):
    can = body_model.canonical()
    pose, transl = body_model.zero_pose()
    pose = (0.1 * torch.randn_like(pose)).requires_grad_(True)
    transl = transl.clone().requires_grad_(True)
    pts = can.vertices[:500].clone().requires_grad_(True)
    A, _ = body_model.bone_transforms(pose, transl)
    out = lbs_points(pts, can.weights[:500], A[0])
    out.square().sum().backward()
    for name, t in (("pose", pose), ("transl", transl), ("points", pts)):
        assert t.grad is not None and torch.isfinite(t.grad).all() and t.grad.abs().sum() > 0, name
