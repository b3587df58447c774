"""The synthetic clip's choreography: body pose, object trajectory and camera path.

A 10-second script (stretched to the clip length) in the room of `room.py`:

    0.0 - 2.6 s  walk along +x towards the low table, decelerating
    3.0 - 4.0 s  bend at hips, spine and knees; the right hand reaches the box
    4.2 s        grasp: from here the box moves rigidly with the right wrist
    4.4 - 5.4 s  straighten up, bringing the box in front of the chest
    5.5 - 7.5 s  turn in place three quarters to the left (back, then left side, then
                 front to the camera)
    7.5 - 10 s   walk diagonally across the rug carrying the box; from 8.4 s the right
                 forearm twists, turning the box in the hand

Everything is procedural and smooth: keyframes are interpolated with monotone cubics
(PCHIP), the gait is sinusoidal in a phase driven by the distance walked, and arms are
placed by two-bone inverse kinematics towards hand targets (hanging and swinging,
reaching the box, carrying it). Feet are kept on the floor by lifting the root so the
lowest body vertex is at z = 0 in every frame. The box rests on the table until the grasp,
where it is placed so that the palm touches its side; afterwards its pose is
`wrist transform(t) @ grasp offset`, so it stays in contact with the hand.

Pose convention is the body model's (Anny local-ref): per-bone axis-angle rotations in the
parent's frame, a world translation added after forward kinematics. In the body's
canonical frame x is the body's left, -y its front and z up; the root's yaw psi makes the
body face (sin psi, -cos psi).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.interpolate import PchipInterpolator
from scipy.ndimage import gaussian_filter1d

from cogs.body.base import BodyModel
from cogs.geometry.camera import look_at
from cogs.geometry.rotations import axis_angle_to_rotmat, rotmat_from_two_vectors, rotmat_to_axis_angle
from cogs.data.synth.room import TABLE_TOP_Z
from cogs.data.synth.textures import BOX_SIZE

SCRIPT_SECONDS = 10.0
GRASP_TIME = 4.2

# Root keyframes: script time (s), world x, y (m), yaw (deg; 90 = facing +x, 0 = facing -y).
ROOT_KEYS = np.array([
    [0.0, -1.65, 0.25, 90.0],
    [2.6, 0.02, 0.25, 90.0],
    [5.5, 0.02, 0.25, 90.0],
    [7.5, 0.06, 0.16, 360.0],
    [9.4, 0.32, -0.30, 395.0],
    [10.0, 0.36, -0.34, 400.0],
])

# Box at rest on the table: centre (x, y) and yaw (deg); it sits on TABLE_TOP_Z.
BOX_REST_XY = np.array([0.50, 0.14])
BOX_REST_YAW_DEG = 12.0

# Camera eye keyframes: script time (s), world x, y, z (m). It looks at the person (and,
# before the pickup, partly at the box), smoothed over ~1 s.
CAMERA_KEYS = np.array([
    [0.0, -0.70, -2.05, 1.50],
    [5.0, 0.50, -2.25, 1.65],
    [10.0, 1.90, -2.15, 1.50],
])


@dataclass
class Script:
    """The keyframes one clip follows: ``ROOT_KEYS``, the box's resting place and heading,
    ``CAMERA_KEYS``."""

    root_keys: np.ndarray  # [6, 4] script time, x, y, yaw (deg)
    box_rest_xy: np.ndarray  # [2]
    box_rest_yaw_deg: float
    camera_keys: np.ndarray  # [3, 4] script time, x, y, z


def script(variant: int = 0) -> Script:
    """The keyframes of choreography ``variant``: 0 is the reference script (the module's
    constants, the scene every number of the project was measured on); any other number
    draws, from a generator seeded by it, the same story told differently:

    - the box rests up to 5 cm further along the table's near edge and 8 cm across it,
      turned up to 20 deg either way; the spot the person picks it up from and their
      heading there turn and move with it, so the reach and the grasp are the reference's;
    - the walk in starts up to 0.3 m nearer or 0.2 m further and 0.35 m to either side;
    - after the pickup the person turns left to face a walk out whose direction lies
      anywhere between the reference's and 40 deg nearer the camera's side (away from the
      table), 0.8-1.15x as long;
    - each camera keyframe moves up to 0.3 m sideways, 0.2 m in depth and 0.15 m in height.

    The ranges keep the person on the rug, clear of the table, and in view."""
    if variant == 0:
        return Script(ROOT_KEYS.copy(), BOX_REST_XY.copy(), BOX_REST_YAW_DEG, CAMERA_KEYS.copy())
    rng = np.random.default_rng([int(variant), 0xC065])
    dxy = rng.uniform([-0.05, -0.08], [0.05, 0.08])
    dyaw = float(rng.uniform(-20.0, 20.0))
    box_xy = BOX_REST_XY + dxy
    turn = _rot("z", np.deg2rad(dyaw))[:2, :2]
    # The pickup spot and the first steps after it, carried with the box.
    stand = box_xy + turn @ (ROOT_KEYS[1, 1:3] - BOX_REST_XY)
    after = box_xy + turn @ (ROOT_KEYS[3, 1:3] - BOX_REST_XY)
    start = np.array([ROOT_KEYS[0, 1] + rng.uniform(-0.2, 0.3), stand[1] + rng.uniform(-0.35, 0.35)])
    towards = stand - start
    approach_yaw = float(np.degrees(np.arctan2(towards[1], towards[0]))) + 90.0  # facing (sin, -cos) of the yaw
    ref_out = ROOT_KEYS[4, 1:3] - ROOT_KEYS[3, 1:3]
    ref_angle = float(np.degrees(np.arctan2(ref_out[1], ref_out[0])))
    out_angle = ref_angle - float(rng.uniform(0.0, 40.0))  # clockwise: towards -x, away from the table
    scale = float(rng.uniform(0.8, 1.15))

    def step(length: float, angle: float) -> np.ndarray:
        a = np.radians(angle)
        return after + scale * length * np.array([np.cos(a), np.sin(a)])

    end_ref = ROOT_KEYS[5, 1:3] - ROOT_KEYS[3, 1:3]
    end_angle = out_angle + float(np.degrees(np.arctan2(end_ref[1], end_ref[0]))) - ref_angle
    final_yaw = ROOT_KEYS[5, 3] + (out_angle - ref_angle)  # the reference's heading, turned with the walk
    root = np.array([
        [ROOT_KEYS[0, 0], *start, approach_yaw],
        [ROOT_KEYS[1, 0], *stand, ROOT_KEYS[1, 3] + dyaw],
        [ROOT_KEYS[2, 0], *stand, ROOT_KEYS[2, 3] + dyaw],
        [ROOT_KEYS[3, 0], *after, final_yaw - (ROOT_KEYS[5, 3] - ROOT_KEYS[3, 3])],
        [ROOT_KEYS[4, 0], *step(np.linalg.norm(ref_out), out_angle), final_yaw - (ROOT_KEYS[5, 3] - ROOT_KEYS[4, 3])],
        [ROOT_KEYS[5, 0], *step(np.linalg.norm(end_ref), end_angle), final_yaw],
    ])
    camera = CAMERA_KEYS.copy()
    camera[:, 1:] += rng.uniform([-0.3, -0.2, -0.15], [0.3, 0.2, 0.15], size=(len(camera), 3))
    return Script(root, box_xy, BOX_REST_YAW_DEG + dyaw, camera)


@dataclass
class Motion:
    times: np.ndarray  # [T] script seconds of each frame
    pose: np.ndarray  # [T, J, 3] axis-angle (body model convention)
    transl: np.ndarray  # [T, 3] metres
    box_R: np.ndarray  # [T, 3, 3] box local -> world rotation
    box_t: np.ndarray  # [T, 3] world position of the box centre
    grasp_frame: int  # first frame at which the box moves with the hand
    camera_w2c: np.ndarray  # [T, 4, 4] world_to_camera (OpenCV)
    look_targets: np.ndarray  # [T, 3] the points the camera looks at


def smoothstep(t, t0, t1):
    """C2 ease from 0 (t <= t0) to 1 (t >= t1)."""
    x = np.clip((np.asarray(t, dtype=np.float64) - t0) / (t1 - t0), 0.0, 1.0)
    return x * x * x * (x * (6 * x - 15) + 10)


def _pchip(keys: np.ndarray, t: np.ndarray) -> np.ndarray:
    return PchipInterpolator(keys[:, 0], keys[:, 1:], axis=0)(np.clip(t, keys[0, 0], keys[-1, 0]))


def _rot(axis: str, angle) -> np.ndarray:
    """[..., 3, 3] rotation about a canonical axis by angle (radians, broadcast)."""
    a = np.asarray(angle, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    if axis == "x":
        m = [o, z, z, z, c, -s, z, s, c]
    elif axis == "y":
        m = [c, z, s, z, o, z, -s, z, c]
    else:
        m = [c, -s, z, s, c, z, z, z, o]
    return np.stack(m, axis=-1).reshape(a.shape + (3, 3))


def _aa(R: np.ndarray) -> np.ndarray:
    return rotmat_to_axis_angle(torch.from_numpy(np.ascontiguousarray(R))).numpy()


def _rmin(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return rotmat_from_two_vectors(torch.from_numpy(a), torch.from_numpy(b)).numpy()


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


class _Rig:
    """Bone indices, rest geometry and batched forward kinematics of one body shape."""

    def __init__(self, model: BodyModel, shape: np.ndarray):
        self.model = model
        self.shape = torch.as_tensor(shape, dtype=torch.float32, device=model.device)
        can = model.canonical(self.shape)
        self.vertices = can.vertices.double()
        self.weights = can.weights.double()
        self.joints = can.joints.double().numpy()
        self.J = model.n_bones
        self.idx = {n: i for i, n in enumerate(model.bone_names)}
        self.parents = model.bone_parents
        # Vertices that can touch the floor (legs and feet): enough for the contact lift.
        self.low = np.flatnonzero(can.vertices[:, 2].numpy() < can.vertices[:, 2].min().item() + 0.6)

    def i(self, name: str) -> int:
        return self.idx[name]

    def transforms(self, pose: np.ndarray, transl: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            A, _ = self.model.bone_transforms(torch.from_numpy(pose), torch.from_numpy(transl), self.shape)
        return A.double().numpy()

    def vertices_posed(self, A: np.ndarray, subset: np.ndarray | None = None) -> np.ndarray:
        """[T, V, 3] skinned vertices (the body model's LBS, batched over frames)."""
        v = self.vertices if subset is None else self.vertices[subset]
        w = self.weights if subset is None else self.weights[subset]
        with torch.no_grad():
            blend = torch.einsum("vj,tjk->tvk", w, torch.from_numpy(A[:, :, :3, :]).reshape(len(A), self.J, 12))
            blend = blend.reshape(len(A), -1, 3, 4)
            return (torch.einsum("tvij,vj->tvi", blend[..., :3], v) + blend[..., 3]).numpy()


def _leg_squat(rig: _Rig, side: str, alpha: np.ndarray):
    """Hip flexion alpha with the knee bent so the ankle stays under the hip.

    Returns (hip, knee, ankle) rotations about the body's x axis (radians).
    """
    hip = rig.joints[rig.i(f"upperleg01.{side}")]
    knee = rig.joints[rig.i(f"lowerleg01.{side}")]
    ankle = rig.joints[rig.i(f"foot.{side}")]
    lt, ls = np.linalg.norm(knee - hip), np.linalg.norm(ankle - knee)
    beta = np.arcsin(np.clip(lt * np.sin(alpha) / ls, -1, 1))
    return -alpha, alpha + beta, -beta


def _arm_ik(rig: _Rig, A: np.ndarray, side: str, target: np.ndarray, pole: np.ndarray, twist: np.ndarray):
    """Two-bone IK of an arm (`two_bone_ik` on upperarm01, lowerarm01 and wrist)."""
    bones = (rig.i(f"upperarm01.{side}"), rig.i(f"lowerarm01.{side}"), rig.i(f"wrist.{side}"))
    return two_bone_ik(rig, A, bones, target, pole, twist)


def two_bone_ik(rig: _Rig, A: np.ndarray, bones: tuple[int, int, int], target: np.ndarray, pole: np.ndarray,
                twist: np.ndarray):
    """Two-bone IK: local rotations of an upper, a lower and an end bone (arm: upperarm01,
    lowerarm01, wrist; leg: upperleg01, lowerleg01, foot) placing the end bone's head at
    `target` [T, 3] with the middle joint towards `pole` [T, 3] and the end twisted by
    `twist` [T] radians about the lower bone. Bones between them (the twist bones) keep
    their rest rotation. A: transforms of a pass with the upper bone's parent posed.
    Returns {bone index: axis-angle [T, 3]}."""
    iu, ie, iw = bones
    ip = rig.parents[iu]
    S0, E0, W0 = rig.joints[iu], rig.joints[ie], rig.joints[iw]
    L1, L2 = np.linalg.norm(E0 - S0), np.linalg.norm(W0 - E0)
    du0, df0 = (E0 - S0) / L1, (W0 - E0) / L2
    Dp = A[:, ip, :3, :3]
    S = A[:, ip, :3, :3] @ S0 + A[:, ip, :3, 3]
    d = target - S
    dist = np.clip(np.linalg.norm(d, axis=-1), 0.15, 0.995 * (L1 + L2))
    n = _unit(d)
    cos_a = np.clip((L1 ** 2 + dist ** 2 - L2 ** 2) / (2 * L1 * dist), -1, 1)
    sin_a = np.sqrt(1 - cos_a ** 2)
    p = _unit(pole - (pole * n).sum(-1, keepdims=True) * n)
    E = S + L1 * (cos_a[:, None] * n + sin_a[:, None] * p)
    Wp = S + dist[:, None] * n
    du, df = _unit(E - S), _unit(Wp - E)
    Du = _rmin(Dp @ du0, du) @ Dp
    Df = _rmin(Du @ df0, df) @ Du
    tw = np.stack([axis_angle_to_rotmat(torch.from_numpy(df[t] * twist[t])).numpy() for t in range(len(df))])
    Dw = tw @ Df
    return {
        iu: _aa(np.swapaxes(Dp, 1, 2) @ Du),
        ie: _aa(np.swapaxes(Du, 1, 2) @ Df),
        iw: _aa(np.swapaxes(Df, 1, 2) @ Dw),
    }


def _box_signed_distance(points: np.ndarray, R: np.ndarray, c: np.ndarray, half: np.ndarray) -> np.ndarray:
    q = np.abs((points - c) @ R) - half
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=-1)
    return outside + np.minimum(q.max(axis=-1), 0.0)


class Choreography:
    """Evaluates the script at arbitrary times for one body model and shape."""

    def __init__(self, model: BodyModel, shape: np.ndarray, variant: int = 0):
        self.script = script(variant)
        self.rig = _Rig(model, shape)
        rig = self.rig
        names = model.bone_names
        self.hand_r = np.array([n.endswith(".R") and n.startswith(("wrist", "finger", "metacarpal")) for n in names])
        w = rig.weights.numpy()
        self.hand_r_vertices = w[:, self.hand_r].sum(1) > 0.5
        self.box_half = BOX_SIZE / 2
        self.box_rest_R = _rot("z", np.deg2rad(self.script.box_rest_yaw_deg))
        xy = self.script.box_rest_xy
        self.box_rest_c = np.array([xy[0], xy[1], TABLE_TOP_Z + self.box_half[2]])
        self.grasp_target = self._solve_grasp()

    # -- root, gait and torso ----------------------------------------------------------------
    def _root(self, t):
        k = _pchip(self.script.root_keys, t)
        return k[:, :2], np.deg2rad(k[:, 2])

    def _gait(self, t):
        """Walking phase and amplitude, integrated on a fine grid so any t is consistent."""
        grid = np.linspace(0.0, SCRIPT_SECONDS, 2001)
        xy, yaw = self._root(grid)
        dt = grid[1] - grid[0]
        speed = np.linalg.norm(np.gradient(xy, dt, axis=0), axis=1) + 0.25 * np.abs(np.gradient(yaw, dt))
        phase = 2 * np.pi * np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * dt)]) / 1.05
        amp = np.clip(speed / 0.55, 0.0, 1.0)
        return np.interp(t, grid, phase), np.interp(t, grid, amp)

    def _torso_pose(self, t):
        rig = self.rig
        T = len(t)
        pose = np.zeros((T, rig.J, 3))
        xy, yaw = self._root(t)
        phase, amp = self._gait(t)
        bend = smoothstep(t, 3.0, 4.0) - smoothstep(t, 4.4, 5.4)
        # Yaw wrapped to (-pi, pi]: the stored rotation vector has angle <= pi, as any
        # rotation-matrix -> axis-angle conversion (and so the noisy input) gives.
        wrapped = np.angle(np.exp(1j * yaw))
        pose[:, rig.i("root")] = np.stack([0 * yaw, 0 * yaw, wrapped], -1)
        spine = np.deg2rad(48.0) * bend
        for name, frac in (("spine05", 0.45), ("spine04", 0.3), ("spine03", 0.25)):
            pose[:, rig.i(name), 0] = frac * spine
        # Slight counter-rotation of the chest while walking, and a look down at the box.
        pose[:, rig.i("spine02"), 2] = np.deg2rad(5.0) * amp * np.sin(phase)
        pose[:, rig.i("neck01"), 0] = np.deg2rad(18.0) * bend + np.deg2rad(6.0) * smoothstep(t, 5.4, 6.0)
        squat = np.deg2rad(22.0) * bend
        for side, off in (("L", 0.0), ("R", np.pi)):
            h, k, a = _leg_squat(rig, side, squat)
            s = np.sin(phase + off)
            swing = np.clip(np.cos(phase + off), 0.0, None)
            hip = h - np.deg2rad(24.0) * amp * s
            knee = k + amp * (np.deg2rad(6.0) + np.deg2rad(52.0) * swing ** 2)
            ankle = a - 0.35 * amp * (np.deg2rad(52.0) * swing ** 2) + np.deg2rad(8.0) * amp * s
            pose[:, rig.i(f"upperleg01.{side}"), 0] = hip
            pose[:, rig.i(f"lowerleg01.{side}"), 0] = knee
            pose[:, rig.i(f"foot.{side}"), 0] = ankle
        transl = np.concatenate([xy, np.zeros((T, 1))], axis=1)
        return pose, transl, yaw, phase, amp

    # -- arms --------------------------------------------------------------------------------
    def _arm_targets(self, t, A, yaw, phase, amp):
        rig = self.rig
        T = len(t)
        R_yaw = _rot("z", yaw)
        reach = smoothstep(t, 3.0, 4.0) - smoothstep(t, 4.4, 5.4)
        carry = smoothstep(t, 4.4, 5.4)
        out = {}
        for side, sgn, off in (("L", 1.0, np.pi), ("R", -1.0, 0.0)):
            iu = rig.i(f"upperarm01.{side}")
            ip = rig.parents[iu]
            S = np.einsum("tij,j->ti", A[:, ip, :3, :3], rig.joints[iu]) + A[:, ip, :3, 3]
            L = np.linalg.norm(rig.joints[rig.i(f"lowerarm01.{side}")] - rig.joints[iu]) + \
                np.linalg.norm(rig.joints[rig.i(f"wrist.{side}")] - rig.joints[rig.i(f"lowerarm01.{side}")])
            swing = 0.16 * amp * np.sin(phase + off)
            local = np.stack([sgn * 0.10 + 0 * t, -swing, 0 * t], -1)
            hang = S + np.einsum("tij,tj->ti", R_yaw, local) + np.array([0, 0, -0.94 * L])
            pole_hang = np.einsum("tij,j->ti", R_yaw, np.array([sgn * 0.3, 1.0, 0.0]))
            target, pole, twist = hang, pole_hang, np.zeros(T)
            if side == "R":
                carry_local = np.array([0.06, -0.38, -0.30])
                carry_t = S + np.einsum("tij,j->ti", R_yaw, carry_local) + \
                    np.array([0, 0, 0.012]) * np.sin(2 * phase)[:, None] * amp[:, None]
                pole_carry = np.einsum("tij,j->ti", R_yaw, np.array([-1.0, 0.35, -0.6]))
                w_h = 1.0 - reach - carry
                target = w_h[:, None] * hang + reach[:, None] * self.grasp_target + carry[:, None] * carry_t
                pole = _unit(w_h[:, None] * pole_hang + reach[:, None] * pole_carry + carry[:, None] * pole_carry)
                twist = np.deg2rad(-55.0) * (smoothstep(t, 8.4, 9.6))
            out[side] = (target, pole, twist)
        return out

    def _pose(self, t, grasp_target=None):
        """Full pose and translation at script times t [T] (feet on the floor)."""
        rig = self.rig
        pose, transl, yaw, phase, amp = self._torso_pose(t)
        # Feet on the floor: lift the root so the lowest vertex is at z = 0. The arms
        # (posed next) never reach below the feet, so the torso-only pass decides it.
        A = rig.transforms(pose, transl)
        transl[:, 2] = -rig.vertices_posed(A, rig.low)[:, :, 2].min(axis=1)
        A[:, :, 2, 3] += transl[:, 2:3]
        if grasp_target is not None:
            self.grasp_target = grasp_target
        targets = self._arm_targets(t, A, yaw, phase, amp)
        for side, (target, pole, twist) in targets.items():
            for b, aa in _arm_ik(rig, A, side, target, pole, twist).items():
                pose[:, b] = aa
        A = rig.transforms(pose, transl)
        return pose, transl, A, rig.vertices_posed(A)

    def _solve_grasp(self) -> np.ndarray:
        """Wrist target at the grasp time so the right palm rests on the box's -y side."""
        R, c, half = self.box_rest_R, self.box_rest_c, self.box_half
        n_face = R @ np.array([0.0, -1.0, 0.0])
        target = c + R @ np.array([-0.02, -half[1] - 0.035, 0.05])
        t = np.array([GRASP_TIME])
        for _ in range(4):
            _, _, _, V = self._pose(t, grasp_target=target[None])
            sd = _box_signed_distance(V[0][self.hand_r_vertices], R, c, half)
            # Fingertips just touching: the deepest hand vertex 4 mm inside the box.
            err = sd.min() + 0.004
            target = target - err * n_face
        return target[None]

    # -- public ------------------------------------------------------------------------------
    def evaluate(self, n_frames: int) -> Motion:
        t = np.arange(n_frames) * SCRIPT_SECONDS / n_frames
        tg = np.concatenate([t, [GRASP_TIME]])
        pose, transl, A, _ = self._pose(tg)
        iw = self.rig.i("wrist.R")
        X_rest = np.eye(4)
        X_rest[:3, :3], X_rest[:3, 3] = self.box_rest_R, self.box_rest_c
        offset = np.linalg.inv(A[-1, iw]) @ X_rest
        attached = t > GRASP_TIME
        X = np.where(attached[:, None, None], A[:-1, iw] @ offset, X_rest)
        grasp_frame = int(np.argmax(attached)) if attached.any() else n_frames
        body_xy = transl[:-1, :2]
        look = np.concatenate([body_xy, np.full((n_frames, 1), 0.85)], axis=1)
        box_weight = 0.35 * (1.0 - smoothstep(t, 3.0, 5.0))
        look = (1 - box_weight)[:, None] * look + box_weight[:, None] * X[:, :3, 3]
        sigma = max(0.6 * n_frames / SCRIPT_SECONDS, 1e-3)
        look = gaussian_filter1d(look, sigma, axis=0, mode="nearest")
        eye = _pchip(self.script.camera_keys, t)
        w2c = np.stack([look_at(eye[i], look[i]) for i in range(n_frames)])
        return Motion(
            times=t,
            pose=pose[:-1],
            transl=transl[:-1],
            box_R=X[:, :3, :3],
            box_t=X[:, :3, 3],
            grasp_frame=grasp_frame,
            camera_w2c=w2c,
            look_targets=look,
        )


def novel_cameras(centres: np.ndarray, n_per_ring: int, free_space, train_centres: np.ndarray,
                  radius: float = 2.4, look_z: float = 0.9) -> np.ndarray:
    """Rings of cameras around the person, off the training path.

    centres: [R, 3] person root positions, one ring each. Camera k of a ring sits at angle
    22.5 deg + k * 360 / n (so none lies on the training path's side by construction),
    alternately 1.15 m and 1.75 m high, at `radius` or closer where walls or furniture are
    nearer (`free_space(points) -> bool`), and at least 0.3 m from every training camera.
    Returns world_to_camera [R * n, 4, 4], ring-major.
    """
    out = []
    for c in centres:
        for k in range(n_per_ring):
            a = np.deg2rad(22.5) + 2 * np.pi * k / n_per_ring
            h = 1.15 if k % 2 == 0 else 1.75
            eye = None
            for r in np.arange(radius, 1.19, -0.1):
                cand = np.array([c[0] + r * np.cos(a), c[1] + r * np.sin(a), h])
                far = np.linalg.norm(train_centres - cand, axis=1).min() >= 0.3
                if free_space(cand[None])[0] and far:
                    eye = cand
                    break
            if eye is None:  # cornered: fall back to the closest ring point (still in the room)
                eye = np.array([c[0] + 1.2 * np.cos(a), c[1] + 1.2 * np.sin(a), h])
            out.append(look_at(eye, np.array([c[0], c[1], look_z])))
    return np.stack(out)
