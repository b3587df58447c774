"""Step 5: the body model fitted to every frame, placed in the scene's metric world.

Inputs are MediaPipe's 2D keypoints (pixels + visibility) and metric 3D "world" landmarks
(hip-centred, camera-aligned axes), the cameras, and optionally the ground plane. Outputs
a ``BodyTrack`` (Anny by default): one shape for the whole clip, a pose and a translation
per frame.

1. **Shape** (``choose_shape``): an average adult of a given stature (``ADULT_STATURE_M``
   unless the user knows it). The stature sets the scene's metric scale; MediaPipe's own
   metric size is not trusted for it, nor its limb ratios for the proportions.
2. **Camera-space initialisation** (``init_camera_space``): the root orientation from the
   3D torso frame; the root position by the linear perspective solve that places the
   metric 3D landmarks on their 2D keypoints (this is where depth comes from: the body's
   metric size).
3. **Joint fit** (``fit_body``, Adam over all frames at once) of the per-frame rotations
   of the main bones and the translation, minimising

   - robust 2D reprojection error of mapped joints, in fractions of the person's height
     in pixels, weighted by keypoint visibility;
   - ``1 - cos`` between fitted and MediaPipe 3D limb directions (the 3D prior; it fixes
     what 2D alone leaves ambiguous: which way a limb points in depth);
   - joint acceleration over time (temporal smoothness) and a small pose-size prior;
   - with a ground plane: no foot below it, and the lowest foot near it, on the frames
     where a foot is seen (``FOOT_SEEN``).

Mapped joints: MediaPipe's shoulders, elbows, wrists, index and pinky knuckles, hips,
knees, ankles, foot tips and eyes, to Anny's bone heads (``MP_TO_ANNY``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch

from cogs.data.scene import BodyTrack
from cogs.geometry.rotations import axis_angle_to_rotmat, rotmat_to_axis_angle
from cogs.preprocess.world import FOOT_LANDMARKS

log = logging.getLogger(__name__)

# (MediaPipe landmark index, body-model bone whose head matches it)
MP_TO_ANNY: list[tuple[int, str]] = [
    (11, "upperarm01.L"), (12, "upperarm01.R"),
    (13, "lowerarm01.L"), (14, "lowerarm01.R"),
    (15, "wrist.L"), (16, "wrist.R"),
    (17, "finger5-1.L"), (18, "finger5-1.R"),
    (19, "finger2-1.L"), (20, "finger2-1.R"),
    (23, "upperleg01.L"), (24, "upperleg01.R"),
    (25, "lowerleg01.L"), (26, "lowerleg01.R"),
    (27, "foot.L"), (28, "foot.R"),
    (31, "toe2-3.L"), (32, "toe2-3.R"),
    (2, "eye.L"), (5, "eye.R"),
]  # fmt: skip
# Limbs whose 3D direction MediaPipe's world landmarks constrain (pairs of MediaPipe indices).
LIMBS = [
    (11, 13), (13, 15), (12, 14), (14, 16), (23, 25), (25, 27), (24, 26), (26, 28),
    (11, 12), (23, 24), (23, 11), (24, 12), (27, 31), (28, 32), (15, 19), (16, 20), (2, 5),
]  # fmt: skip
# Bones whose rotation is fitted; every other bone keeps its rest rotation.
ACTIVE_BONES = [
    "root", "spine04", "spine03", "spine02", "spine01", "neck01", "head",
    "upperarm01.L", "upperarm01.R", "lowerarm01.L", "lowerarm01.R", "wrist.L", "wrist.R",
    "upperleg01.L", "upperleg01.R", "lowerleg01.L", "lowerleg01.R", "foot.L", "foot.R",
]  # fmt: skip
FOOT_BONES = ["foot.L", "foot.R", "toe2-3.L", "toe2-3.R"]
# The ground terms hold on a frame only where MediaPipe sees a heel or a foot tip at least
# this surely (its own threshold of a visible landmark). A clip cut at the knees (the
# guitar) has its feet guessed at 0.05-0.3, its ground then placed through the guessed
# feet (``world.align_sfm``'s fallback) at the wrong height, and "no foot below it" bent
# the fitted legs out sideways across the room to keep the feet above it: 2D error 0.056
# of the height, 0.015 without. Checked on the six development clips and the synthetic
# video benchmark (docs/experiments/2026-11-29-ground-where-the-feet-are-seen.md).
FOOT_SEEN = 0.5
_L_SH, _R_SH, _L_HIP, _R_HIP = 11, 12, 23, 24


@dataclass
class FitWeights:
    """Relative weights of the body-fit terms (documented in the module docstring)."""

    reprojection: float = 1.0
    direction_3d: float = 0.01
    smooth: float = 0.05  # on accelerations in units of a SMOOTH_STATURE_M body
    pose_prior: float = 1e-4
    ground_penetration: float = 10.0
    ground_contact: float = 0.05
    robust_scale: float = 0.05  # 2D residuals beyond ~5% of the person's height count less


@dataclass
class BodyFit:
    track: BodyTrack
    joints_world: np.ndarray  # [T, J, 3] posed bone heads
    reprojection_error: np.ndarray  # [T] mean 2D error of the mapped joints / person height (NaN if undetected)


def poor_fit_warning(mean_error: float, scale_note: str | None) -> str | None:
    """What to tell the user when the fitted body lies far off MediaPipe's keypoints on
    average (more than ``bodymasks.MAX_FIT_ERROR`` of the person's height; good fits are
    0.01-0.06 on the development clips and the synthetic video): the world the body was
    fitted in is then most likely wrong (the guitar clip at 0.128 with its scale 41x off,
    0.38 before the scale came from the person's motion), or None."""
    from cogs.preprocess.bodymasks import MAX_FIT_ERROR

    if not mean_error > MAX_FIT_ERROR:
        return None
    return (f"the fitted body lies {mean_error:.2f} of the person's height off MediaPipe's keypoints on average (good "
            f"fits: 0.01-0.06), so the world it was fitted in is likely wrong (its scale: {scale_note or 'from the floor'}); "
            "the masks step will not use the body and training may fail. A clip that shows the floor round the person's "
            "feet gives the world its scale; `source.body_fit` in scene.json says what was found")


def _mapped(model) -> tuple[np.ndarray, np.ndarray]:
    mp_idx = np.array([m for m, _ in MP_TO_ANNY])
    bones = np.array([model.bone_index(b) for _, b in MP_TO_ANNY])
    return mp_idx, bones


def fill_missing(a: np.ndarray) -> np.ndarray:
    """Linearly interpolate NaN frames of [T, ...] over time (nearest value beyond the ends)."""
    a = a.copy()
    T = len(a)
    flat = a.reshape(T, -1)
    ok = np.isfinite(flat).all(axis=1)
    if ok.all() or not ok.any():
        return a
    t = np.arange(T)
    for j in range(flat.shape[1]):
        flat[~ok, j] = np.interp(t[~ok], t[ok], flat[ok, j])
    return flat.reshape(a.shape)


def person_height_px(kp2d: np.ndarray) -> np.ndarray:
    """[T] vertical extent of the confident keypoints (pixels), a robust size per frame."""
    out = np.full(len(kp2d), np.nan)
    for t, k in enumerate(kp2d):
        if not np.isfinite(k).all():
            continue
        sel = k[:, 2] > 0.3
        if sel.sum() < 4:
            sel = np.ones(len(k), bool)
        out[t] = max(k[sel, 1].max() - k[sel, 1].min(), 10.0)
    return out


# An adult of typical stature: between the usual adult male (~1.75 m) and female (~1.62 m)
# means. MediaPipe's metric landmarks cannot give a person's size (one view cannot tell a
# tall person far away from a short one near): its limbs made the 1.80 m synthetic person
# 1.63 m, and the adults of the real development clips 1.22-1.62 m. The stature sets the
# scene's metric scale, so every depth is off by its error; a user who knows the height
# gives it (``cogs preprocess --person-height``). A population figure, not fitted to a clip;
# checked on the synthetic benchmark's default and 60-frame clips (a 1.80 m person: depth
# scale 1.13 -> 1.07) and the six real development clips, whose adults MediaPipe had made
# 1.22-1.62 m (docs/experiments/2026-11-27-stature-and-carried-positions.md).
ADULT_STATURE_M = 1.70
ADULT_AGE = 2.0 / 3.0  # Anny's "young" (adult) age anchor; 0.5 is between child and young
SMOOTH_STATURE_M = 1.625  # body accelerations are smoothed in units of this height (Anny's default, where the weight was set)
STATURE_RANGE_M = (1.30, 2.38)  # what ``with_stature`` reaches at ADULT_AGE (``stature_range``, tested)


def stature(model, shape: np.ndarray) -> float:
    """Standing height (metres) of a phenotype: the rest pose's vertical extent."""
    z = model.canonical(torch.tensor(shape, dtype=torch.float32)).vertices[:, 2]
    return float(z.max() - z.min())


def _average_adult(model) -> np.ndarray:
    """Anny's young age anchor, every other phenotype parameter at its midpoint."""
    s = model.default_shape.numpy().astype(np.float64)
    s[list(model.shape_names).index("age")] = ADULT_AGE
    return s


def stature_range(model) -> tuple[float, float]:
    """Shortest and tallest adult ``choose_shape`` can make (metres)."""
    k = list(model.shape_names).index("height")
    lo, hi = _average_adult(model), _average_adult(model)
    lo[k], hi[k] = 0.0, 1.0
    return stature(model, lo), stature(model, hi)


def with_stature(model, shape: np.ndarray, height_m: float, tol_m: float = 1e-4) -> np.ndarray:
    """``shape`` with its height parameter set so that the body stands ``height_m`` tall.

    The stature is piecewise linear in the parameter (linear blends between Anny's anchors),
    so false position on the bracketing interval lands on it in a few evaluations."""
    k = list(model.shape_names).index("height")
    s = shape.copy()

    def at(x: float) -> float:
        s[k] = x
        return stature(model, s) - height_m

    lo, hi = 0.0, 1.0
    f_lo, f_hi = at(lo), at(hi)
    assert f_lo <= f_hi, "stature must grow with the height parameter"
    if f_lo >= 0.0 or f_hi <= 0.0:  # out of reach: the nearest end (the command checks the range)
        s[k] = lo if f_lo >= 0.0 else hi
        return s
    x = lo
    for _ in range(40):
        x = lo - f_lo * (hi - lo) / (f_hi - f_lo)
        f = at(x)
        if abs(f) < tol_m:
            break
        if f < 0.0:
            lo, f_lo = x, f
        else:
            hi, f_hi = x, f
        if abs(f_hi) > 2 * abs(f_lo):  # keep false position from stalling on one end
            f_hi *= 0.5
        elif abs(f_lo) > 2 * abs(f_hi):
            f_lo *= 0.5
    s[k] = x
    return s


def choose_shape(model, height_m: float = ADULT_STATURE_M) -> np.ndarray:
    """Adult phenotype [S], ``height_m`` tall: Anny's young age anchor, its other phenotype
    parameters at their midpoints, the height parameter set to the stature.

    MediaPipe's limb ratios do not choose the proportions. Chosen over gender x proportions
    by scale-free limb ratios, they picked phenotypes at the grid's edges and, on 12 frames
    of the real basketball clip, a body with 1.8x the neutral one's 2D error (0.052 against
    0.029 of the height); over 3 proportions at gender 0.5 (the earlier grid), no better
    than neutral (within 0.0001 of the height, or worse) on the 2 synthetic clips, 4 real
    development clips and that one
    (docs/experiments/2026-11-27-stature-and-carried-positions.md)."""
    return with_stature(model, _average_adult(model), height_m)


def _torso_rotation(kp3d_t: np.ndarray) -> np.ndarray:
    """Rotation taking the model's canonical axes (x = person's left, z = up, y = back)
    to the camera-aligned MediaPipe frame, from one frame's 3D landmarks."""
    left = 0.5 * ((kp3d_t[_L_HIP] - kp3d_t[_R_HIP]) + (kp3d_t[_L_SH] - kp3d_t[_R_SH]))
    up = 0.5 * (kp3d_t[_L_SH] + kp3d_t[_R_SH]) - 0.5 * (kp3d_t[_L_HIP] + kp3d_t[_R_HIP])
    left = left / max(np.linalg.norm(left), 1e-9)
    up = up - left * (up @ left)
    up = up / max(np.linalg.norm(up), 1e-9)
    back = np.cross(up, left)  # canonical: left x up = forward, so up x left = back
    return np.stack([left, back, up], axis=1)


def init_camera_space(kp2d: np.ndarray, kp3d: np.ndarray, K: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame root rotation R_cam [T, 3, 3] (canonical -> camera) and root position t_cam [T, 3].

    t solves, in least squares over confident keypoints i, the perspective equations
    (u_i - cx) (Z_i + t_z) = f (X_i + t_x) (and likewise for v) with X = scale * kp3d
    (hip-centred), i.e. the metric skeleton placed where it projects onto the keypoints.
    """
    T = len(kp2d)
    kp2d_f, kp3d_f = fill_missing(kp2d), fill_missing(kp3d)
    f, cx, cy = K[0, 0], K[0, 2], K[1, 2]
    R = np.zeros((T, 3, 3))
    t = np.zeros((T, 3))
    for i in range(T):
        if not np.isfinite(kp3d_f[i]).all():
            R[i], t[i] = np.eye(3), [0.0, 0.0, 3.0]
            continue
        R[i] = _torso_rotation(kp3d_f[i])
        X = scale * kp3d_f[i]
        u, v, w = kp2d_f[i].T
        sel = w > 0.5
        if sel.sum() < 4:
            sel = np.argsort(-w)[:8]
        a = (u[sel] - cx) / f
        b = (v[sel] - cy) / f
        Xs, Ys, Zs = X[sel].T
        # x: tx - a tz = a Z - X ; y: ty - b tz = b Z - Y
        n = len(a)
        A = np.zeros((2 * n, 3))
        rhs = np.zeros(2 * n)
        A[:n, 0], A[:n, 2], rhs[:n] = 1.0, -a, a * Zs - Xs
        A[n:, 1], A[n:, 2], rhs[n:] = 1.0, -b, b * Zs - Ys
        sol, *_ = np.linalg.lstsq(A, rhs, rcond=None)
        if sol[2] <= 0.2:  # behind or at the camera: a degenerate solve
            sol[2] = 3.0
        t[i] = sol
    return R, t


def limb_scale(model, shape: np.ndarray, kp3d: np.ndarray) -> float:
    """Ratio of the model's skeleton to MediaPipe's: summed limb lengths (so the landmarks
    can be used at model size). The landmarks' positions are MediaPipe's own (its hands and
    feet are 24-37 % shorter than the model's bones), so the long limbs should set it: a
    median of per-limb ratios moved the scene's scale by 2 % when two hand limbs were added."""
    mp_idx, bones = _mapped(model)
    lookup = {m: b for m, b in zip(mp_idx, bones)}
    limbs = [(a, b) for a, b in LIMBS if (a, b) != (2, 5)]
    J = model.canonical(torch.tensor(shape, dtype=torch.float32)).joints.numpy()
    ok = np.isfinite(kp3d).all(axis=(1, 2))
    if not ok.any():
        return 1.0
    mp_len = np.array([np.median(np.linalg.norm(kp3d[ok, a] - kp3d[ok, b], axis=-1)) for a, b in limbs])
    ln = np.array([np.linalg.norm(J[lookup[a]] - J[lookup[b]]) for a, b in limbs])
    return float(ln.sum() / max(mp_len.sum(), 1e-6))


def foot_sole_offsets(model, shape: np.ndarray) -> np.ndarray:
    """Height [4] of each FOOT_BONES head above the sole in the rest pose (metres)."""
    can = model.canonical(torch.tensor(shape, dtype=torch.float32))
    sole = float(can.vertices[:, 2].min())
    return np.array([float(can.joints[model.bone_index(b), 2]) - sole for b in FOOT_BONES])


def fit_body(
    model,
    kp2d: np.ndarray,
    kp3d: np.ndarray,
    K: np.ndarray,
    world_to_camera: np.ndarray,
    shape: np.ndarray,
    init_R_world: np.ndarray,
    init_root_world: np.ndarray,
    ground: tuple[np.ndarray, float] | None = None,
    iterations: int = 300,
    weights: FitWeights | None = None,
    on_step=None,
    seed: int = 0,
) -> BodyFit:
    """Fit per-frame poses and translations (shape fixed) to all frames jointly.

    kp2d [T, 33, 3], kp3d [T, 33, 3] (NaN where undetected); K [3, 3]; world_to_camera
    [T, 4, 4]; shape [S]; init_R_world [T, 3, 3] root orientation and init_root_world
    [T, 3] root position; ground = (unit normal pointing up, offset) with n.x + d = 0.
    ``on_step(i, loss)`` reports progress.
    """
    w = weights or FitWeights()
    torch.manual_seed(seed)
    T = len(kp2d)
    dt = torch.float64
    J = model.n_bones
    active = [model.bone_index(b) for b in ACTIVE_BONES]
    mp_idx, bones = _mapped(model)
    shape_t = torch.tensor(shape, dtype=torch.float32)

    det = np.isfinite(kp2d).all(axis=(1, 2))
    k2 = torch.tensor(np.nan_to_num(kp2d[:, mp_idx, :2]), dtype=dt)  # [T, M, 2]
    vis = torch.tensor(np.nan_to_num(kp2d[:, mp_idx, 2]).clip(0, 1) * det[:, None], dtype=dt)
    height = torch.tensor(np.nan_to_num(person_height_px(kp2d), nan=1.0), dtype=dt)
    Kt = torch.tensor(K, dtype=dt)
    Rwc = torch.tensor(world_to_camera[:, :3, :3], dtype=dt)
    twc = torch.tensor(world_to_camera[:, :3, 3], dtype=dt)

    # 3D prior: unit limb directions in camera axes, per frame.
    lookup = {int(m): int(b) for m, b in zip(mp_idx, bones)}
    limb_a = [lookup[a] for a, b in LIMBS]
    limb_b = [lookup[b] for a, b in LIMBS]
    d3 = np.stack([kp3d[:, b] - kp3d[:, a] for a, b in LIMBS], axis=1)  # [T, L, 3]
    d3 = d3 / np.maximum(np.linalg.norm(d3, axis=-1, keepdims=True), 1e-9)
    det3 = np.isfinite(d3).all(axis=(1, 2))
    dir_w = torch.tensor(det3, dtype=dt)
    d3t = torch.tensor(np.nan_to_num(d3), dtype=dt)

    # Parameters: root rotation (axis-angle in world axes), other active bones, root position.
    root = model.bone_index("root")
    rest_pelvis = model.canonical(shape_t).joints[root].double()  # root head in canonical space
    root_aa = rotmat_to_axis_angle(torch.tensor(init_R_world, dtype=dt)).clone().requires_grad_(True)
    others = [a for a in active if a != root]
    body_aa = torch.zeros(T, len(others), 3, dtype=dt, requires_grad=True)
    root_pos = torch.tensor(init_root_world, dtype=dt).clone().requires_grad_(True)

    # Scale-free smoothness: a taller body (or a larger world) moves its joints further for
    # the same motion; in metres the term weighed 1.4x more on a 1.70 m body than on a
    # 1.42 m one (the real loading clip's 2D error at 1.70 m: 0.0327 -> 0.0319 of the height).
    body_scale = stature(model, shape) / SMOOTH_STATURE_M
    foot_idx = [model.bone_index(b) for b in FOOT_BONES]
    sole = torch.tensor(foot_sole_offsets(model, shape), dtype=dt)
    if ground is not None:
        g_n = torch.tensor(ground[0], dtype=dt)
        g_d = float(ground[1])
        seen = np.nan_to_num(kp2d[:, FOOT_LANDMARKS, 2]).max(1) >= FOOT_SEEN
        g_w = torch.tensor(seen & det, dtype=dt)  # [T] frames the ground terms hold on
        n_seen = g_w.sum().clamp_min(1.0)

    def full_pose():
        pose = torch.zeros(T, J, 3, dtype=dt)
        pose = pose.index_put((torch.arange(T)[:, None], torch.tensor(others)[None, :]), body_aa)
        pose[:, root] = root_aa
        return pose

    def posed():
        pose = full_pose()
        # transl places the rotated root head at root_pos: rotation is about the root head.
        transl = root_pos - rest_pelvis
        _, joints = model.bone_transforms(pose.float(), transl.float(), shape_t)
        return pose, transl, joints.double()

    def loss_fn(stage: int):
        pose, transl, joints = posed()
        cam = torch.einsum("tij,tnj->tni", Rwc, joints) + twc[:, None, :]  # [T, J, 3]
        pts = cam[:, bones]
        z = pts[..., 2].clamp_min(1e-3)
        uv = torch.stack([Kt[0, 0] * pts[..., 0] / z + Kt[0, 2], Kt[1, 1] * pts[..., 1] / z + Kt[1, 2]], -1)
        r = (uv - k2).norm(dim=-1) / height[:, None]
        s2 = w.robust_scale**2
        rho = s2 * torch.log1p(r**2 / s2)  # Cauchy: quadratic near 0, bounded pull beyond
        e2d = (vis * rho).sum() / vis.sum().clamp_min(1.0)
        da = cam[:, limb_b] - cam[:, limb_a]
        da = da / da.norm(dim=-1, keepdim=True).clamp_min(1e-9)
        e3d = ((1.0 - (da * d3t).sum(-1)).mean(-1) * dir_w).sum() / dir_w.sum().clamp_min(1.0)
        loss = w.direction_3d * e3d
        if stage >= 1:
            loss = loss + w.reprojection * e2d
        if T >= 3:
            acc = joints[2:] - 2 * joints[1:-1] + joints[:-2]
            loss = loss + w.smooth * ((acc / body_scale) ** 2).sum(-1).mean()
        loss = loss + w.pose_prior * (body_aa**2).sum(-1).mean()
        if ground is not None and stage >= 1:
            h = joints[:, foot_idx] @ g_n + g_d - sole  # [T, 4] sole heights above ground
            loss = loss + w.ground_penetration * ((torch.relu(-h) ** 2).mean(1) * g_w).sum() / n_seen
            lowest = -0.02 * torch.logsumexp(-h / 0.02, dim=1)  # soft minimum over the feet
            loss = loss + w.ground_contact * (lowest**2 * g_w).sum() / n_seen
        return loss, e2d

    # Stage 0: limbs from the 3D prior alone (root fixed) - a good start for the 2D fit.
    opt0 = torch.optim.Adam([body_aa], lr=0.05)
    n0 = max(20, iterations // 4)
    for i in range(n0):
        opt0.zero_grad()
        loss, _ = loss_fn(0)
        loss.backward()
        opt0.step()
        if on_step:
            on_step(i + 1, loss.detach().item())
    opt = torch.optim.Adam(
        [{"params": [body_aa, root_aa], "lr": 0.02}, {"params": [root_pos], "lr": 0.01}]
    )
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=iterations, eta_min=1e-3)
    for i in range(iterations):
        opt.zero_grad()
        loss, _ = loss_fn(1)
        loss.backward()
        opt.step()
        sched.step()
        if on_step:
            on_step(n0 + i + 1, loss.detach().item())

    with torch.no_grad():
        pose, transl, joints = posed()
        cam = torch.einsum("tij,tnj->tni", Rwc, joints) + twc[:, None, :]
        pts = cam[:, bones]
        z = pts[..., 2].clamp_min(1e-3)
        uv = torch.stack([Kt[0, 0] * pts[..., 0] / z + Kt[0, 2], Kt[1, 1] * pts[..., 1] / z + Kt[1, 2]], -1)
        err = ((uv - k2).norm(dim=-1) * vis).sum(-1) / vis.sum(-1).clamp_min(1e-9) / height
    err = err.numpy()
    err[~det] = np.nan
    track = BodyTrack(model=model.name, shape=shape.astype(np.float32), pose=pose.float().numpy(), transl=transl.float().numpy())
    return BodyFit(track=track, joints_world=joints.float().numpy(), reprojection_error=err)


def camera_to_world_init(R_cam: np.ndarray, t_cam: np.ndarray, world_to_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Root rotation and position from camera space to world space, per frame."""
    R = world_to_camera[:, :3, :3]
    tt = world_to_camera[:, :3, 3]
    R_world = np.einsum("tji,tjk->tik", R, R_cam)  # R^T R_cam
    pos = np.einsum("tji,tj->ti", R, t_cam - tt)  # R^T (x - t)
    return R_world, pos


def posed_vertices(model, track: BodyTrack, frames: list[int] | None = None) -> np.ndarray:
    """[F, V, 3] mesh vertices of the fitted body (for previews and object depth)."""
    frames = list(range(len(track))) if frames is None else frames
    pose = torch.tensor(track.pose[frames], dtype=torch.float32)
    transl = torch.tensor(track.transl[frames], dtype=torch.float32)
    with torch.no_grad():
        return model.posed_vertices(pose, transl, torch.tensor(track.shape, dtype=torch.float32)).numpy()


__all__ = [
    "ACTIVE_BONES",
    "BodyFit",
    "FitWeights",
    "LIMBS",
    "MP_TO_ANNY",
    "axis_angle_to_rotmat",
    "camera_to_world_init",
    "choose_shape",
    "fill_missing",
    "fit_body",
    "foot_sole_offsets",
    "init_camera_space",
    "limb_scale",
    "person_height_px",
    "posed_vertices",
]
