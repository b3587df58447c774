"""Keyframed object trajectories: Hermite translation, SLERP rotation, fitting, smoothness."""

from __future__ import annotations

import math

import pytest
import torch

from cogs.geometry.rotations import (
    axis_angle_to_quat,
    quat_geodesic_angle,
    quat_multiply,
    random_quat,
    slerp,
)
from cogs.geometry.splines import (
    acceleration_penalty,
    fit_keyframes,
    hermite_positions,
    rotation_smoothness,
    sample_trajectory,
    slerp_rotations,
    uniform_keyframe_times,
)

DT = torch.float64


def _keyframes(k: int = 5, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    # Non-uniform keyframe spacing on purpose.
    times = torch.cumsum(0.3 + torch.rand(k, generator=g, dtype=DT), 0)
    p = torch.randn(k, 3, generator=g, dtype=DT)
    v = torch.randn(k, 3, generator=g, dtype=DT)
    q = random_quat(k, g, DT)
    return times, p, v, q


def _smooth_motion(tau: torch.Tensor):
    x = torch.stack(
        [
            0.5 * torch.sin(1.3 * tau) + 0.1 * tau,
            0.3 * torch.cos(0.9 * tau),
            0.2 * torch.sin(2.1 * tau + 0.5),
        ],
        -1,
    )
    q = axis_angle_to_quat(torch.stack([0.6 * torch.sin(0.7 * tau), 0.4 * tau, 0.3 * torch.cos(1.1 * tau)], -1))
    return x, q


# --------------------------------------------------------------------------------------
# Hermite


def test_hermite_interpolates_keyframe_positions():
    times, p, v, _ = _keyframes()
    x = hermite_positions(times, p, v, times)
    assert torch.allclose(x, p, atol=1e-12)


def test_hermite_derivative_equals_keyframe_velocity():
    times, p, v, _ = _keyframes()
    h = 1e-6
    # One-sided differences at the ends (queries outside the range are clamped).
    inner = times[1:-1]
    d = (hermite_positions(times, p, v, inner + h) - hermite_positions(times, p, v, inner - h)) / (2 * h)
    # Central differences straddle a jump in x'', so they are only O(h) accurate here.
    assert torch.allclose(d, v[1:-1], atol=1e-5)
    d0 = (hermite_positions(times, p, v, times[:1] + h) - p[:1]) / h
    d1 = (p[-1:] - hermite_positions(times, p, v, times[-1:] - h)) / h
    assert torch.allclose(d0, v[:1], atol=1e-4) and torch.allclose(d1, v[-1:], atol=1e-4)


def test_hermite_is_c1_at_keyframes():
    times, p, v, _ = _keyframes(seed=1)
    h = 1e-7
    for t in times[1:-1]:
        def x(s):
            return hermite_positions(times, p, v, s.view(1))

        left = (x(t - h) - x(t - 2 * h)) / h  # one-sided, from the segment before
        right = (x(t + 2 * h) - x(t + h)) / h  # one-sided, from the segment after
        assert torch.allclose(left, right, atol=1e-4)
        assert torch.allclose(x(t - 1e-12), x(t + 1e-12), atol=1e-9)


def test_hermite_clamps_outside_the_keyframe_range():
    times, p, v, q = _keyframes()
    x, r = sample_trajectory(times, p, v, q, torch.stack([times[0] - 5, times[-1] + 5]).to(DT))
    assert torch.allclose(x[0], p[0]) and torch.allclose(x[1], p[-1])
    assert float(quat_geodesic_angle(r[0], q[0])) < 1e-6 and float(quat_geodesic_angle(r[1], q[-1])) < 1e-6


def test_hermite_is_differentiable_in_positions_and_velocities():
    times, p, v, _ = _keyframes(k=4, seed=2)
    tau = torch.linspace(float(times[0]), float(times[-1]), 9, dtype=DT)
    p = p.clone().requires_grad_(True)
    v = v.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: hermite_positions(times, a, b, tau), (p, v))


# --------------------------------------------------------------------------------------
# SLERP


def test_slerp_trajectory_is_unit_and_exact_at_keyframes():
    times, p, v, q = _keyframes(k=6, seed=3)
    tau = torch.linspace(float(times[0]), float(times[-1]), 101, dtype=DT)
    r = slerp_rotations(times, q, tau)
    assert torch.allclose(r.norm(dim=-1), torch.ones(101, dtype=DT), atol=1e-12)
    at_k = slerp_rotations(times, q, times)
    assert quat_geodesic_angle(at_k, q).max() < 1e-6


def test_slerp_takes_the_shortest_arc_whatever_the_sign():
    g = torch.Generator().manual_seed(4)
    q0, q1 = random_quat(2, g, DT)
    u = torch.linspace(0, 1, 11, dtype=DT)
    a = slerp(q0.expand(11, 4), q1.expand(11, 4), u)
    b = slerp(q0.expand(11, 4), (-q1).expand(11, 4), u)
    assert quat_geodesic_angle(a, b).max() < 1e-6
    total = float(quat_geodesic_angle(q0, q1))
    assert total <= math.pi / 2 * 2 + 1e-9
    # The path length equals the geodesic distance (no detour through the long arc).
    steps = quat_geodesic_angle(a[:-1], a[1:]).sum()
    assert float(steps) == pytest.approx(total, abs=1e-6)


def test_slerp_has_constant_angular_speed():
    q0 = axis_angle_to_quat(torch.tensor([0.1, -0.2, 0.3], dtype=DT))
    q1 = axis_angle_to_quat(torch.tensor([1.2, 0.5, -0.7], dtype=DT))
    u = torch.linspace(0, 1, 21, dtype=DT)
    r = slerp(q0.expand(21, 4), q1.expand(21, 4), u)
    steps = quat_geodesic_angle(r[:-1], r[1:])
    assert torch.allclose(steps, steps.mean().expand_as(steps), atol=1e-9)
    assert float(quat_geodesic_angle(r[0], q0)) < 1e-7 and float(quat_geodesic_angle(r[-1], q1)) < 1e-7


def test_trajectory_rotation_is_differentiable_in_keyframe_quaternions():
    times = torch.tensor([0.0, 1.0, 2.5], dtype=DT)
    q = axis_angle_to_quat(torch.tensor([[0.0, 0.0, 0.0], [0.4, -0.2, 0.1], [0.9, 0.3, -0.5]], dtype=DT))
    q = q.clone().requires_grad_(True)
    tau = torch.tensor([0.2, 0.7, 1.3, 2.2], dtype=DT)
    assert torch.autograd.gradcheck(lambda k: slerp_rotations(times, k, tau), (q,))


# --------------------------------------------------------------------------------------
# Fitting


def test_fit_reproduces_a_known_smooth_motion():
    tau = torch.linspace(0, 4, 120, dtype=DT)
    x, q = _smooth_motion(tau)
    times = uniform_keyframe_times(tau, 12)
    p, v, qk = fit_keyframes(tau, x, q, keyframe_times=times)
    dense = torch.linspace(0, 4, 400, dtype=DT)
    xs, qs = sample_trajectory(times, p, v, qk, dense)
    x_true, q_true = _smooth_motion(dense)
    assert (xs - x_true).norm(dim=-1).max() < 3e-3  # metres
    assert torch.rad2deg(quat_geodesic_angle(qs, q_true)).max() < 1.0
    # Keyframes come out sign-continuous for SLERP.
    assert ((qk[1:] * qk[:-1]).sum(-1) >= 0).all()


def test_fit_with_nonuniform_keyframes_and_n_keyframes_shortcut():
    tau = torch.linspace(0, 4, 120, dtype=DT)
    x, q = _smooth_motion(tau)
    times = torch.tensor([0.0, 0.3, 1.0, 1.6, 2.9, 3.3, 4.0], dtype=DT)
    p, v, qk = fit_keyframes(tau, x, q, keyframe_times=times)
    xs, _ = sample_trajectory(times, p, v, qk, tau)
    assert (xs - x).norm(dim=-1).max() < 0.02
    p2, _, _ = fit_keyframes(tau, x, q, n_keyframes=7)
    p3, _, _ = fit_keyframes(tau, x, q, keyframe_times=uniform_keyframe_times(tau, 7))
    assert torch.allclose(p2, p3)


def test_fitting_noisy_poses_reduces_error_versus_raw_input():
    tau = torch.linspace(0, 4, 120, dtype=DT)
    x, q = _smooth_motion(tau)
    g = torch.Generator().manual_seed(5)
    x_noisy = x + 0.02 * torch.randn(120, 3, generator=g, dtype=DT)
    q_noisy = quat_multiply(q, axis_angle_to_quat(math.radians(3) * torch.randn(120, 3, generator=g, dtype=DT)))
    # A few gross outliers, as a failed per-frame pose estimate would give.
    x_noisy[::19] += 0.5
    q_noisy[::17] = random_quat(len(range(0, 120, 17)), g, DT)
    times = uniform_keyframe_times(tau, 12)
    p, v, qk = fit_keyframes(tau, x_noisy, q_noisy, keyframe_times=times)
    xs, qs = sample_trajectory(times, p, v, qk, tau)
    raw_t = (x_noisy - x).norm(dim=-1).mean()
    fit_t = (xs - x).norm(dim=-1).mean()
    raw_r = quat_geodesic_angle(q_noisy, q).mean()
    fit_r = quat_geodesic_angle(qs, q).mean()
    assert fit_t < 0.4 * raw_t and fit_t < 0.02
    assert fit_r < 0.4 * raw_r and torch.rad2deg(fit_r) < 2.5


def test_fit_rejects_bad_input_with_a_message():
    tau = torch.linspace(0, 1, 10, dtype=DT)
    x, q = _smooth_motion(tau)
    with pytest.raises(ValueError, match="strictly increasing"):
        fit_keyframes(tau, x, q, keyframe_times=torch.tensor([0.0, 0.5, 0.5, 1.0], dtype=DT))
    x_bad = x.clone()
    x_bad[3, 0] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        fit_keyframes(tau, x_bad, q, n_keyframes=3)
    with pytest.raises(ValueError, match="n_keyframes or keyframe_times"):
        fit_keyframes(tau, x, q)


def test_fit_returns_translations_dtype():
    tau = torch.linspace(0, 1, 20)
    x, q = _smooth_motion(tau.double())
    p, v, qk = fit_keyframes(tau, x.float(), q.float(), n_keyframes=4)
    assert p.dtype == v.dtype == qk.dtype == torch.float32
    assert p.shape == v.shape == (4, 3) and qk.shape == (4, 4)


# --------------------------------------------------------------------------------------
# Smoothness penalties


def test_acceleration_penalty_is_zero_for_linear_motion_and_grows_with_curvature():
    s = torch.linspace(0, 1, 20, dtype=DT)[:, None]
    line = s * torch.tensor([1.0, -2.0, 0.5], dtype=DT) + 0.3
    assert float(acceleration_penalty(line)) == pytest.approx(0.0, abs=1e-20)
    quad = line + torch.cat([s**2, 0 * s, 0 * s], -1)
    quad2 = line + torch.cat([3 * s**2, 0 * s, 0 * s], -1)
    a1, a2 = float(acceleration_penalty(quad)), float(acceleration_penalty(quad2))
    step = 1 / 19
    assert a1 == pytest.approx((2 * step**2) ** 2, rel=1e-9)  # second difference of s^2 is 2 h^2
    assert a2 == pytest.approx(9 * a1, rel=1e-9)


def test_rotation_smoothness_order1_measures_speed_and_order2_acceleration():
    axis = torch.tensor([0.0, 0.0, 1.0], dtype=DT)
    angles = torch.linspace(0, 1.0, 11, dtype=DT)
    spin = axis_angle_to_quat(angles[:, None] * axis)
    assert float(rotation_smoothness(spin, order=1)) == pytest.approx(0.1, abs=1e-9)
    assert float(rotation_smoothness(spin, order=2)) == pytest.approx(0.0, abs=1e-7)
    accel = axis_angle_to_quat((angles**2)[:, None] * axis)  # angle increments grow by 0.02
    assert float(rotation_smoothness(accel, order=2)) == pytest.approx(0.02, abs=1e-7)
    # Sign flips of individual samples change nothing.
    flipped = spin.clone()
    flipped[::2] *= -1
    assert float(rotation_smoothness(flipped, order=1)) == pytest.approx(0.1, abs=1e-9)


def test_smoothness_terms_have_gradients():
    g = torch.Generator().manual_seed(6)
    t = torch.randn(8, 3, generator=g, dtype=DT, requires_grad=True)
    acceleration_penalty(t).backward()
    assert t.grad.abs().sum() > 0
    q = random_quat(8, g, DT).requires_grad_(True)
    (rotation_smoothness(q) + rotation_smoothness(q, order=2)).backward()
    assert torch.isfinite(q.grad).all() and q.grad.abs().sum() > 0
