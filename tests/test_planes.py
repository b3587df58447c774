"""Planar primitives: RANSAC recovery, assignment gates, robust point-to-plane loss."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from cogs.geometry.planes import (
    Plane,
    assign_to_planes,
    fit_plane_lstsq,
    planes_to_tensors,
    point_to_plane_loss,
    ransac_planes,
)


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def _room(n_per_plane: int = 3000, clutter: int = 1000, noise_m: float = 0.005, seed: int = 0):
    """Floor z=0, walls x=0 and y=3, in a randomly rotated and shifted world frame.

    Returns the points [P, 3], per-point labels (0, 1, 2 = plane, -1 = clutter) and the true
    planes as (normal [3], offset) in the world frame.
    """
    rng = np.random.default_rng(seed)
    u = rng.random((n_per_plane, 2))
    floor = np.c_[4 * u[:, 0], 3 * u[:, 1], np.zeros(n_per_plane)]
    u = rng.random((n_per_plane, 2))
    wall_x = np.c_[np.zeros(n_per_plane), 3 * u[:, 0], 2.5 * u[:, 1]]
    u = rng.random((n_per_plane, 2))
    wall_y = np.c_[4 * u[:, 0], np.full(n_per_plane, 3.0), 2.5 * u[:, 1]]
    clutter_pts = rng.random((clutter, 3)) * [4, 3, 2.5]
    pts = np.concatenate([floor, wall_x, wall_y, clutter_pts])
    pts[: 3 * n_per_plane] += noise_m * rng.standard_normal((3 * n_per_plane, 3))
    labels = np.repeat([0, 1, 2, -1], [n_per_plane] * 3 + [clutter])
    local = [(np.array([0.0, 0, 1]), 0.0), (np.array([1.0, 0, 0]), 0.0), (np.array([0.0, 1, 0]), -3.0)]
    R, t = _random_rotation(rng), rng.standard_normal(3)
    world = pts @ R.T + t
    # n.x + d = 0 in local -> (R n).(y) + d - (R n).t = 0 in world.
    planes = [(R @ n, d - (R @ n) @ t) for n, d in local]
    perm = rng.permutation(len(world))
    return world[perm], labels[perm], planes


def _angle_deg(n1: np.ndarray, n2: np.ndarray) -> float:
    return math.degrees(math.acos(min(1.0, abs(float(n1 @ n2)))))


def test_ransac_recovers_floor_and_two_walls_within_2_degrees_and_2_cm():
    pts, labels, truth = _room()
    planes = ransac_planes(pts, max_planes=6, threshold_m=0.02, seed=0)
    assert 3 <= len(planes) <= 6
    for k, (n_true, d_true) in enumerate(truth):
        on_plane = pts[labels == k]
        # The found plane that best matches: smallest angle to the true normal.
        best = min(planes, key=lambda p: _angle_deg(p.normal, n_true))
        assert _angle_deg(best.normal, n_true) < 2.0
        # Distance of the true plane's points to the found plane, on average and worst case.
        dist = np.abs(on_plane @ best.normal + best.offset)
        assert np.median(dist) < 0.02 and np.percentile(dist, 99) < 0.04
        # Most of the found plane's inliers are true points of that plane.
        assert np.mean(labels[best.inliers] == k) > 0.95
        assert np.linalg.norm(best.normal) == pytest.approx(1.0)


def test_ransac_finds_no_plane_in_pure_clutter():
    rng = np.random.default_rng(1)
    pts = rng.random((2000, 3)) * 4
    assert ransac_planes(pts, seed=0) == []


def test_ransac_is_deterministic_for_a_seed_and_inliers_do_not_overlap():
    pts, _, _ = _room(n_per_plane=1000, clutter=300, seed=2)
    a = ransac_planes(pts, seed=7)
    b = ransac_planes(pts, seed=7)
    assert len(a) == len(b) >= 3
    for pa, pb in zip(a, b):
        assert np.array_equal(pa.normal, pb.normal) and pa.offset == pb.offset
        assert np.array_equal(pa.inliers, pb.inliers)
    all_inliers = np.concatenate([p.inliers for p in a])
    assert len(np.unique(all_inliers)) == len(all_inliers)


def test_ransac_normals_point_towards_the_point_cloud():
    pts, _, _ = _room(n_per_plane=1000, clutter=0, seed=3)
    centroid = pts.mean(axis=0)
    for p in ransac_planes(pts, seed=0):
        assert p.normal @ centroid + p.offset > 0


def test_fit_plane_lstsq_is_exact_on_exact_points():
    rng = np.random.default_rng(4)
    n = rng.standard_normal(3)
    n /= np.linalg.norm(n)
    basis = np.linalg.svd(n[None])[2][1:]  # two directions in the plane
    pts = rng.standard_normal((50, 2)) @ basis - 0.7 * n
    fn, fd = fit_plane_lstsq(pts)
    assert _angle_deg(fn, n) < 1e-6
    assert np.abs(pts @ fn + fd).max() < 1e-10


# --------------------------------------------------------------------------------------
# Assignment


def _floor_and_wall():
    return [
        Plane(normal=np.array([0.0, 0.0, 1.0]), offset=0.0, inliers=np.zeros(0, np.int64)),
        Plane(normal=np.array([1.0, 0.0, 0.0]), offset=-2.0, inliers=np.zeros(0, np.int64)),
    ]


def test_assignment_respects_distance_gate_and_picks_the_nearest_plane():
    planes = _floor_and_wall()
    means = np.array(
        [
            [0.5, 0.0, 0.01],  # 1 cm above floor
            [0.5, 0.0, 0.08],  # 8 cm above floor: too far
            [1.97, 0.0, 0.5],  # 3 cm from wall
            [1.99, 0.0, 0.02],  # near both: wall is 1 cm, floor 2 cm -> wall
        ]
    )
    out = assign_to_planes(means, None, planes, max_distance_m=0.05, max_angle_deg=20)
    assert out.tolist() == [0, -1, 1, 1]
    assert out.dtype == np.int64


def test_assignment_respects_normal_angle_gate_ignoring_normal_sign():
    planes = _floor_and_wall()
    means = np.array([[0.5, 0.0, 0.01]] * 4 + [[1.99, 0.0, 0.02]])
    tilt = math.radians(10)
    normals = np.array(
        [
            [0.0, 0.0, 1.0],  # aligned
            [0.0, 0.0, -3.0],  # flipped and unnormalised: still the floor's line
            [0.0, math.sin(tilt), math.cos(tilt)],  # 10 deg off: inside 20 deg
            [1.0, 0.0, 0.0],  # perpendicular: rejected
            [0.0, 0.0, 1.0],  # near both planes, but only the floor's normal matches
        ]
    )
    out = assign_to_planes(
        torch.tensor(means), torch.tensor(normals), planes, max_distance_m=0.05, max_angle_deg=20
    )
    assert isinstance(out, torch.Tensor) and out.dtype == torch.long
    assert out.tolist() == [0, 0, 0, -1, 0]
    narrow = assign_to_planes(means, normals, planes, max_distance_m=0.05, max_angle_deg=5)
    assert narrow.tolist() == [0, 0, -1, -1, 0]


def test_assignment_with_no_planes_is_all_unassigned():
    assert assign_to_planes(np.zeros((3, 3)), None, [], 0.1, 10).tolist() == [-1, -1, -1]


# --------------------------------------------------------------------------------------
# Loss


def _loss_setup(dtype=torch.float64):
    planes = _floor_and_wall()
    normals, offsets = planes_to_tensors(planes, dtype=dtype)
    return normals, offsets


@pytest.mark.parametrize("kind", ["huber", "cauchy"])
def test_loss_is_zero_for_points_on_their_plane(kind):
    normals, offsets = _loss_setup()
    means = torch.tensor([[0.3, 1.0, 0.0], [2.0, 5.0, 1.0], [9.0, 9.0, 9.0]], dtype=torch.float64)
    loss = point_to_plane_loss(means, normals, offsets, torch.tensor([0, 1, -1]), kind=kind)
    assert float(loss) == 0.0


@pytest.mark.parametrize("kind", ["huber", "cauchy"])
def test_loss_grows_with_distance(kind):
    normals, offsets = _loss_setup()
    vals = []
    for z in [0.001, 0.005, 0.02, 0.1, 1.0]:
        means = torch.tensor([[0.0, 0.0, z]], dtype=torch.float64)
        vals.append(float(point_to_plane_loss(means, normals, offsets, torch.tensor([0]), kind=kind, scale=0.01)))
    assert all(b > a for a, b in zip(vals, vals[1:]))
    # Symmetric in the side of the plane.
    m_below = torch.tensor([[0.0, 0.0, -0.02]], dtype=torch.float64)
    below = point_to_plane_loss(m_below, normals, offsets, torch.tensor([0]), kind=kind)
    assert float(below) == pytest.approx(vals[2])


def test_huber_loss_grows_linearly_and_cauchy_logarithmically_far_from_the_plane():
    normals, offsets = _loss_setup()
    s = 0.01

    def loss(kind, r):
        m = torch.tensor([[0.0, 0.0, r]], dtype=torch.float64)
        return float(point_to_plane_loss(m, normals, offsets, torch.tensor([0]), kind=kind, scale=s))

    # Quadratic inside the scale.
    assert loss("huber", 0.004) == pytest.approx(0.5 * 0.004**2)
    # Linear beyond it: equal steps give equal increments of s * step.
    assert loss("huber", 2.0) - loss("huber", 1.0) == pytest.approx(s * 1.0)
    assert loss("huber", 3.0) - loss("huber", 2.0) == pytest.approx(s * 1.0)
    # Cauchy: increments shrink; a 10x farther outlier costs only about s^2 log(100) / 2 more.
    c1, c10, c100 = loss("cauchy", 1.0), loss("cauchy", 10.0), loss("cauchy", 100.0)
    assert c10 - c1 == pytest.approx(0.5 * s * s * math.log(100), rel=1e-3)
    assert c100 - c10 < 1.01 * (c10 - c1)
    assert c100 < loss("huber", 100.0) / 100


def test_loss_averages_over_assigned_points_only():
    normals, offsets = _loss_setup()
    m = torch.tensor([[0.0, 0.0, 0.004], [2.004, 0.0, 1.0], [0.0, 0.0, 5.0]], dtype=torch.float64)
    loss = point_to_plane_loss(m, normals, offsets, torch.tensor([0, 1, -1]), kind="huber", scale=0.01)
    assert float(loss) == pytest.approx(0.5 * 0.004**2, rel=1e-6)


def test_loss_with_no_assigned_point_is_zero_and_backpropagates():
    normals, offsets = _loss_setup()
    m = torch.randn(4, 3, dtype=torch.float64, requires_grad=True)
    loss = point_to_plane_loss(m, normals, offsets, torch.full((4,), -1))
    assert float(loss.detach()) == 0.0
    loss.backward()
    assert torch.equal(m.grad, torch.zeros_like(m))


@pytest.mark.parametrize("kind", ["huber", "cauchy"])
def test_loss_gradients_match_finite_differences(kind):
    g = torch.Generator().manual_seed(0)
    # Residuals spread across the quadratic and linear/log regimes, away from the kink.
    means = torch.randn(12, 3, generator=g, dtype=torch.float64) * 0.03
    n = torch.randn(3, 3, generator=g, dtype=torch.float64)
    normals = (n / n.norm(dim=-1, keepdim=True)).requires_grad_(True)
    offsets = (0.01 * torch.randn(3, generator=g, dtype=torch.float64)).requires_grad_(True)
    means.requires_grad_(True)
    assignment = torch.tensor([0, 1, 2, -1] * 3)
    assert torch.autograd.gradcheck(
        lambda m, nn_, d: point_to_plane_loss(m, nn_, d, assignment, kind=kind, scale=0.02),
        (means, normals, offsets),
    )


def test_loss_pulls_points_onto_their_plane_under_gradient_descent():
    normals, offsets = _loss_setup(torch.float32)
    m = torch.tensor([[0.3, 0.2, 0.05], [1.9, 1.0, 1.0]], requires_grad=True)
    opt = torch.optim.SGD([m], lr=1.0)
    for _ in range(200):
        opt.zero_grad()
        point_to_plane_loss(m, normals, offsets, torch.tensor([0, 1]), kind="huber", scale=0.01).backward()
        opt.step()
    m = m.detach()
    assert abs(float(m[0, 2])) < 1e-3 and abs(float(m[1, 0]) - 2.0) < 1e-3
    # Only the normal component moved.
    assert float(m[0, 0]) == pytest.approx(0.3) and float(m[1, 2]) == pytest.approx(1.0)


def test_unknown_loss_kind_is_rejected():
    normals, offsets = _loss_setup()
    with pytest.raises(ValueError, match="huber"):
        point_to_plane_loss(torch.zeros(1, 3, dtype=torch.float64), normals, offsets, torch.tensor([0]), kind="l2")
