"""Keyframed rigid trajectories: cubic-Hermite translation, SLERP rotation (CoGS object branch).

A trajectory is K keyframes at strictly increasing (not necessarily uniform) times
``times_k [K]``, each with a position ``p [K, 3]``, a velocity ``v [K, 3]`` (metres per unit
of time) and a unit quaternion ``q [K, 4]`` (wxyz). Between keyframes k and k+1, with
``D = times_k[k+1] - times_k[k]`` and ``u = (tau - times_k[k]) / D``::

    x(tau) = h00(u) p_k + h10(u) D v_k + h01(u) p_{k+1} + h11(u) D v_{k+1}
    q(tau) = slerp(q_k, q_{k+1}, u)        (shortest arc, constant angular speed)

so x passes through p_k with derivative v_k at every keyframe (C1 everywhere). Query times
outside ``[times_k[0], times_k[-1]]`` are clamped (the object holds its end pose).

Everything is a pure torch function, batched over query times and differentiable with
respect to p, v and q; the object branch owns the parameters and calls these.
"""

from __future__ import annotations

import math
import torch
from torch import Tensor

from cogs.geometry.rotations import (
    axis_angle_to_quat,
    quat_conjugate,
    quat_geodesic_angle,
    quat_multiply,
    quat_normalize,
    quat_sign_continuous,
    quat_to_axis_angle,
    slerp,
)

__all__ = [
    "hermite_basis",
    "segment_coordinates",
    "hermite_positions",
    "slerp_rotations",
    "sample_trajectory",
    "uniform_keyframe_times",
    "fit_keyframes",
    "acceleration_penalty",
    "rotation_smoothness",
]


def hermite_basis(u: Tensor) -> Tensor:
    """[...] -> [..., 4]: (h00, h10, h01, h11) at u."""
    u2 = u * u
    u3 = u2 * u
    return torch.stack([2 * u3 - 3 * u2 + 1, u3 - 2 * u2 + u, -2 * u3 + 3 * u2, u3 - u2], dim=-1)


def segment_coordinates(times_k: Tensor, tau: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Segment index k [T] (long), local coordinate u [T] in [0, 1] and length D [T].

    tau is clamped to the keyframe range. With a single keyframe, k = 0, u = 0, D = 1.
    """
    times_k = times_k.to(tau.dtype)
    n = times_k.shape[0]
    if n == 1:
        zeros = torch.zeros_like(tau)
        return torch.zeros(tau.shape, dtype=torch.long, device=tau.device), zeros, torch.ones_like(tau)
    tau = tau.clamp(times_k[0], times_k[-1])
    k = torch.searchsorted(times_k.detach().contiguous(), tau.detach().contiguous(), right=True) - 1
    k = k.clamp(0, n - 2)
    t0, t1 = times_k[k], times_k[k + 1]
    delta = t1 - t0
    return k, (tau - t0) / delta, delta


def hermite_positions(times_k: Tensor, p: Tensor, v: Tensor, tau: Tensor) -> Tensor:
    """Cubic Hermite positions [T, 3] at query times tau [T] (clamped to the keyframe range)."""
    k, u, delta = segment_coordinates(times_k.to(p.dtype), tau.to(p.dtype))
    if p.shape[0] == 1:
        return p[:1].expand(tau.shape[0], -1)
    h = hermite_basis(u)
    d = delta.unsqueeze(-1)
    return (
        h[:, :1] * p[k] + h[:, 1:2] * d * v[k] + h[:, 2:3] * p[k + 1] + h[:, 3:4] * d * v[k + 1]
    )


def slerp_rotations(times_k: Tensor, q: Tensor, tau: Tensor) -> Tensor:
    """Unit quaternions [T, 4] at tau [T]: SLERP between neighbouring keyframes, shortest arc.

    The sign of the result is not continuous across a keyframe whose neighbours have a
    negative dot product; use sign-invariant measures (geodesic angle) on it.
    """
    k, u, _ = segment_coordinates(times_k.to(q.dtype), tau.to(q.dtype))
    if q.shape[0] == 1:
        return quat_normalize(q[:1]).expand(tau.shape[0], -1)
    return slerp(q[k], q[k + 1], u)


def sample_trajectory(
    times_k: Tensor, p: Tensor, v: Tensor, q: Tensor, tau: Tensor
) -> tuple[Tensor, Tensor]:
    """Translation [T, 3] and unit rotation [T, 4] of the keyframed trajectory at times tau [T]."""
    return hermite_positions(times_k, p, v, tau), slerp_rotations(times_k, q, tau)


# --------------------------------------------------------------------------------------
# Fitting keyframes to noisy per-frame poses


def _hermite_design(times_k: Tensor, tau: Tensor) -> Tensor:
    """Linear map from stacked control values [p (K); v (K)] to positions at tau: [T, 2K]."""
    n = times_k.shape[0]
    k, u, delta = segment_coordinates(times_k, tau)
    h = hermite_basis(u)
    A = tau.new_zeros(tau.shape[0], 2 * n)
    rows = torch.arange(tau.shape[0], device=tau.device)
    if n == 1:
        A[:, 0] = 1.0
        return A
    A[rows, k] += h[:, 0]
    A[rows, n + k] += h[:, 1] * delta
    A[rows, k + 1] += h[:, 2]
    A[rows, n + k + 1] += h[:, 3] * delta
    return A


def _bending_rows(times_k: Tensor) -> Tensor:
    """Rows R [2(K-1), 2K] with ||R c||^2 = integral of |x''(t)|^2 dt (exact, 2-point Gauss)."""
    n = times_k.shape[0]
    g = 0.5 / math.sqrt(3.0)
    rows = []
    for k in range(n - 1):
        delta = float(times_k[k + 1] - times_k[k])
        for u in (0.5 - g, 0.5 + g):
            # Second derivatives of the basis w.r.t. u, divided by D^2 for d/dt; quadrature
            # weight D/2 on [0, D].
            r = times_k.new_zeros(2 * n)
            r[k] = 12 * u - 6
            r[n + k] = (6 * u - 4) * delta
            r[k + 1] = -12 * u + 6
            r[n + k + 1] = (6 * u - 2) * delta
            rows.append(r * math.sqrt(delta / 2) / delta**2)
    return torch.stack(rows) if rows else times_k.new_zeros(0, 2 * n)


def uniform_keyframe_times(frame_times: Tensor, n_keyframes: int) -> Tensor:
    """n_keyframes (>= 2) evenly spaced times from the first to the last frame time."""
    if n_keyframes < 2:
        raise ValueError(f"need at least 2 keyframes, got {n_keyframes}")
    lo, hi = float(frame_times.min()), float(frame_times.max())
    return torch.linspace(lo, hi, n_keyframes, dtype=frame_times.dtype, device=frame_times.device)


def _fit_positions(
    times_k: Tensor, tau: Tensor, x: Tensor, w: Tensor, smoothness: float, robust_iters: int
) -> tuple[Tensor, Tensor]:
    n = times_k.shape[0]
    # Work in normalised time s = (t - t0) / T so the smoothness weight is unit-free:
    # the bending energy then has units of metres^2 like the data term.
    t0 = times_k[0]
    span = (times_k[-1] - times_k[0]).clamp_min(1e-12) if n > 1 else times_k.new_tensor(1.0)
    sk = (times_k - t0) / span
    s = (tau - t0) / span
    A = _hermite_design(sk, s)  # [F, 2K]
    R = _bending_rows(sk)  # energy over s in [0, 1]
    # A tiny ridge keeps the system definite when some segment holds no frame.
    ridge = 1e-9 * torch.eye(2 * n, dtype=A.dtype, device=A.device)
    weights = w / w.sum()
    for it in range(robust_iters + 1):
        Aw = A * weights[:, None]
        lhs = A.T @ Aw + smoothness * (R.T @ R) + ridge
        rhs = Aw.T @ x
        c = torch.linalg.solve(lhs, rhs)  # [2K, 3]
        if it == robust_iters:
            break
        # Cauchy IRLS from the least-squares start: a frame's weight falls as
        # 1 / (1 + (r / c)^2), so far outliers lose their pull almost entirely.
        res = (A @ c - x).norm(dim=-1)
        # Residuals under 1 mm are never treated as outlying (exact data stays exact).
        sigma = (1.4826 * res.median()).clamp_min(1e-3)
        c_cauchy = 2.385 * sigma
        weights = w / (1.0 + (res / c_cauchy) ** 2)
        weights = weights / weights.sum()
    p, v_s = c[:n], c[n:]
    return p, v_s / span  # velocities back to metres per unit of the caller's time


def _robust_rotation_keyframes(
    times_k: Tensor, tau: Tensor, quats: Tensor, w: Tensor, robust_iters: int
) -> Tensor:
    """Local-linear robust average of the per-frame rotations around each keyframe.

    For keyframe k: frames get Gaussian weights in time (sigma = the local keyframe
    spacing); a reference rotation r is the weighted chordal L2 mean (principal
    eigenvector of sum w q q^T, sign-invariant, Markley et al. 2007); every frame is mapped
    to the tangent space at r (log of r^-1 q_f) and a weighted line omega(t) = a + b (t -
    tau_k) is fitted, with Cauchy IRLS weights on the residual angles so outlier frames
    fade. The keyframe is r exp(a). The local line (not a local mean) removes the bias of
    one-sided windows at the trajectory ends.
    """
    n = times_k.shape[0]
    qs = quat_normalize(quats)
    out = []
    for k in range(n):
        left = times_k[k] - times_k[k - 1] if k > 0 else times_k[min(k + 1, n - 1)] - times_k[k]
        right = times_k[k + 1] - times_k[k] if k < n - 1 else left
        spacing = float(torch.maximum(left, right)) if n > 1 else float(tau.max() - tau.min()) + 1.0
        dt = tau - times_k[k]
        kern = w * torch.exp(-0.5 * (dt / spacing) ** 2)
        # Ensure enough support: at least the 4 nearest frames count.
        if int((kern > 1e-3 * kern.max()).sum()) < 4:
            nearest = dt.abs().argsort()[:4]
            kern = kern.clone()
            kern[nearest] = kern[nearest].clamp_min(1e-3 * float(kern.max()) + 1e-12)
        M = (qs * kern[:, None]).T @ qs
        r = torch.linalg.eigh(M).eigenvectors[:, -1]
        rinv = quat_conjugate(r)
        rel = quat_multiply(rinv.expand_as(qs), qs)
        rel = torch.where(rel[:, :1] < 0, -rel, rel)  # same hemisphere as the identity
        omega = quat_to_axis_angle(rel)  # [F, 3]
        X = torch.stack([torch.ones_like(dt), dt / spacing], dim=-1)  # [F, 2]
        rob = torch.ones_like(kern)
        for it in range(robust_iters + 1):
            ww = kern * rob
            lhs = X.T @ (X * ww[:, None]) + 1e-9 * torch.eye(2, dtype=X.dtype, device=X.device)
            coef = torch.linalg.solve(lhs, X.T @ (omega * ww[:, None]))  # [2, 3]
            if it == robust_iters:
                break
            res = (X @ coef - omega).norm(dim=-1)
            sel = kern > 1e-3 * kern.max()
            scale = 1.4826 * res[sel].median().clamp_min(1e-4)
            c = 2.385 * scale
            rob = 1.0 / (1.0 + (res / c) ** 2)  # Cauchy weights
        out.append(quat_multiply(r, axis_angle_to_quat(coef[0])))
    q = quat_normalize(torch.stack(out))
    return _sign_continuous(q)


def _sign_continuous(q: Tensor) -> Tensor:
    """Flip signs so consecutive quaternions have non-negative dot products, first w >= 0."""
    q = q.clone()
    if q[0, 0] < 0:
        q[0] = -q[0]
    return quat_sign_continuous(q)


def _refine_rotations(
    times_k: Tensor,
    tau: Tensor,
    quats: Tensor,
    w: Tensor,
    q0: Tensor,
    iters: int,
    smoothness: float,
) -> Tensor:
    """Minimise a robust geodesic error of the SLERP trajectory to the per-frame rotations.

    Keyframes are updated as q_k exp(delta_k) with delta [K, 3] found by L-BFGS. The error per
    frame is e = 1 - <q(tau_f), q_f>^2 = sin^2(angle / 2) (sign-invariant, smooth), passed
    through a Cauchy rho with a scale of ~5 degrees so outlier frames have bounded pull.
    ``smoothness`` weighs the discrete bending energy of the keyframe angular velocities
    omega_k = log(q_{k+1} q_k^-1) / D_k in normalised time, sum |omega_k - omega_{k-1}|^2 /
    mean(D_{k-1}, D_k), which keeps the keyframes from chasing per-frame noise.
    """
    if iters <= 0:
        return q0
    target = quat_normalize(quats).detach()
    delta = torch.zeros(q0.shape[0], 3, dtype=q0.dtype, device=q0.device, requires_grad=True)
    c2 = math.sin(math.radians(5.0) / 2) ** 2
    weights = (w / w.sum()).detach()
    d_s = (times_k[1:] - times_k[:-1]) / (times_k[-1] - times_k[0])
    opt = torch.optim.LBFGS([delta], lr=1.0, max_iter=iters, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        qk = quat_multiply(q0, axis_angle_to_quat(delta))
        q_t = slerp_rotations(times_k, qk, tau)
        e = 1.0 - (q_t * target).sum(-1) ** 2
        loss = (weights * c2 * torch.log1p(e / c2)).sum()
        if smoothness > 0 and qk.shape[0] > 2:
            inc = quat_multiply(qk[1:], quat_conjugate(qk[:-1]))
            omega = quat_to_axis_angle(inc) / d_s[:, None]
            bend = ((omega[1:] - omega[:-1]) ** 2).sum(-1) / (0.5 * (d_s[1:] + d_s[:-1]))
            loss = loss + smoothness * bend.sum()
        loss.backward()
        return loss

    opt.step(closure)
    with torch.no_grad():
        q = quat_normalize(quat_multiply(q0, axis_angle_to_quat(delta)))
    return _sign_continuous(q)


def fit_keyframes(
    frame_times: Tensor,
    translations: Tensor,
    quats: Tensor,
    n_keyframes: int | None = None,
    keyframe_times: Tensor | None = None,
    *,
    frame_weights: Tensor | None = None,
    smoothness: float = 1e-8,
    robust_iters: int = 5,
    refine_iters: int = 50,
    rotation_smoothing: float = 1e-6,
) -> tuple[Tensor, Tensor, Tensor]:
    """Keyframe control values (p [K, 3], v [K, 3], q [K, 4]) fitted to per-frame poses.

    frame_times [F], translations [F, 3], quats [F, 4] wxyz: the (noisy) initial per-frame
    object poses. Keyframes are at ``keyframe_times`` [K] if given, else at
    ``uniform_keyframe_times(frame_times, n_keyframes)`` (call it yourself to get the times).
    ``frame_weights`` [F] >= 0 down-weights unreliable frames (default all 1).

    Translation: p and v jointly solve the weighted linear least squares
    ``mean_w |x(tau_f) - t_f|^2 + smoothness * integral |x''(s)|^2 ds`` in normalised time
    s in [0, 1] (so ``smoothness`` is unit-free: the default 1e-8 only steadies segments
    with few frames; 1e-6 already smooths at the centimetre level for metre-scale motion),
    a smoothing spline restricted to the keyframe space, followed by ``robust_iters``
    Cauchy IRLS re-solves so outlier frames lose their pull (residuals under 1 mm are never
    down-weighted).

    Rotation: a robust local-linear average of the nearby per-frame rotations at each
    keyframe (see ``_robust_rotation_keyframes``), then ``refine_iters`` L-BFGS iterations
    minimising a Cauchy-robust geodesic error (in sin^2(angle/2)) of the SLERP trajectory to
    all frames plus ``rotation_smoothing`` times the bending energy of the keyframe angular
    velocities (see ``_refine_rotations``; without it the refinement chases per-frame
    noise, with 1e-5 or more it flattens real turns). Keyframes should be dense enough that
    the object turns well under 180 degrees between neighbours: SLERP always takes the
    shorter arc. Returned quaternions are sign-continuous (<q_k, q_k+1> >= 0).

    Returns tensors in the dtype of ``translations`` (computed in float64). No gradient flows
    through the fit; it initialises parameters.
    """
    out_dtype = translations.dtype
    dev = translations.device
    tau = frame_times.detach().cpu().to(torch.float64)
    x = translations.detach().cpu().to(torch.float64)
    qf = quats.detach().cpu().to(torch.float64)
    if tau.ndim != 1 or x.shape != (tau.shape[0], 3) or qf.shape != (tau.shape[0], 4):
        raise ValueError(
            f"fit_keyframes: expected frame_times [F], translations [F, 3], quats [F, 4]; got "
            f"{tuple(tau.shape)}, {tuple(x.shape)}, {tuple(qf.shape)}"
        )
    if not (torch.isfinite(x).all() and torch.isfinite(qf).all() and torch.isfinite(tau).all()):
        raise ValueError("fit_keyframes: non-finite frame times or poses")
    if keyframe_times is None:
        if n_keyframes is None:
            raise ValueError("fit_keyframes: give n_keyframes or keyframe_times")
        tk = uniform_keyframe_times(tau, n_keyframes)
    else:
        tk = keyframe_times.detach().cpu().to(torch.float64)
    if tk.ndim != 1 or tk.numel() < 1 or (tk.numel() > 1 and not bool((tk[1:] > tk[:-1]).all())):
        raise ValueError("fit_keyframes: keyframe times must be a strictly increasing 1-D tensor")
    w = torch.ones_like(tau) if frame_weights is None else frame_weights.detach().cpu().to(torch.float64)
    if bool((w < 0).any()) or float(w.sum()) <= 0:
        raise ValueError("fit_keyframes: frame_weights must be >= 0 and not all zero")

    p, v = _fit_positions(tk, tau, x, w, smoothness, robust_iters)
    q = _robust_rotation_keyframes(tk, tau, qf, w, robust_iters)
    if tk.numel() > 1:
        with torch.enable_grad():
            q = _refine_rotations(tk, tau, qf, w, q, refine_iters, rotation_smoothing)
    return p.to(dev, out_dtype), v.to(dev, out_dtype), q.to(dev, out_dtype)


# --------------------------------------------------------------------------------------
# Smoothness penalties on sampled trajectories


def acceleration_penalty(t_samples: Tensor) -> Tensor:
    """Mean squared second difference of positions sampled at uniform time steps.

    t_samples [T, 3] -> scalar: mean over the T-2 interior samples of
    |t_{i+1} - 2 t_i + t_{i-1}|^2 (m^2 per step^2; divide by step^4 for (m/s^2)^2).
    Zero (with a graph) for fewer than three samples.
    """
    if t_samples.shape[0] < 3:
        return (t_samples * 0).sum()
    acc = t_samples[2:] - 2 * t_samples[1:-1] + t_samples[:-2]
    return (acc * acc).sum(-1).mean()


def rotation_smoothness(q_samples: Tensor, order: int = 1) -> Tensor:
    """Rotation smoothness of unit quaternions [T, 4] sampled at uniform time steps (radians).

    order=1 (default): mean geodesic angle between consecutive samples (penalises angular
    speed; the CoGS rotation-smoothness term). order=2: mean geodesic angle between
    consecutive world-frame increments r_i = q_{i+1} q_i^-1 (penalises angular
    acceleration; a constant-speed spin costs nothing). Sign-invariant; zero with a graph
    when there are too few samples.
    """
    q = quat_normalize(q_samples)
    if order == 1:
        if q.shape[0] < 2:
            return (q_samples * 0).sum()
        return quat_geodesic_angle(q[:-1], q[1:]).mean()
    if order == 2:
        if q.shape[0] < 3:
            return (q_samples * 0).sum()
        inc = quat_multiply(q[1:], quat_conjugate(q[:-1]))
        return quat_geodesic_angle(inc[:-1], inc[1:]).mean()
    raise ValueError(f"order must be 1 or 2, got {order}")
