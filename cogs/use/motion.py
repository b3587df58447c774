"""Body motions for `cogs render --motion`: where they come from, their rate, their place.

    run            the run's own refined poses, frame by frame (already in its world)
    anny:walk[:N]  the walk cycle shipped inside the anny package, N cycles (default 2)
    synth:NAME     the synthetic generator's choreography, whole (`full`) or a part of it
                   (`walk`, `pickup`, `turn`, `carry`)
    PATH.npz       a native scene's body.npz (`pose` [T, J, 3], `transl`, `model`), kept in
                   its world; or an SMPL-family sequence (AMASS style: axis-angle `poses`
                   [T, >= 66] and `trans` [T, 3], optional `mocap_framerate`), retargeted
                   onto the run's body model by mapping joint rotations

A motion from elsewhere is *placed*: its first frame stands where the run's person stands
at a reference frame (`--start-frame`), facing the same way, feet on the same floor
(`place`). Every motion is resampled to the output frame rate (per-bone SLERP).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from cogs.errors import UserError
from cogs.geometry.rotations import (
    axis_angle_to_quat,
    axis_angle_to_rotmat,
    quat_sign_continuous,
    quat_to_axis_angle,
    rotmat_to_axis_angle,
    slerp,
)

# Parts of the synthetic script (seconds of its 10-second timeline, cogs.data.synth.motion).
SYNTH_PARTS = {"full": (0.0, 10.0), "walk": (0.0, 2.6), "pickup": (2.6, 5.5), "turn": (5.5, 7.5), "carry": (7.5, 10.0)}


@dataclass
class Motion:
    """A body motion in the run's body-model convention."""

    pose: Tensor  # [T, J, 3] axis-angle
    transl: Tensor  # [T, 3]
    fps: float
    name: str
    clip_time: Tensor | None = None  # [T] the run's frame time each frame shows (motion "run")
    in_world: bool = False  # already in the run's world (no placement)

    def __len__(self) -> int:
        return int(self.pose.shape[0])


def load_motion(spec: str, model, fps_run: float, option: str = "--motion") -> Motion:
    """The motion `spec` names (see the module docstring), on the model's device, at its
    native rate. Every problem is a UserError naming `option`."""
    h = model.human
    if h is None:
        raise UserError(f"{option} {spec}: the run has no human branch to move")
    dev = h.device
    if spec == "run":
        with torch.no_grad():
            poses = [h.frame_pose(t) for t in range(h.n_frames)]
        return Motion(torch.cat([p for p, _ in poses]), torch.cat([t for _, t in poses]), fps_run, "run",
                      clip_time=torch.arange(h.n_frames, dtype=torch.float32, device=dev), in_world=True)
    if spec.startswith("anny:"):
        from cogs.use.walk import BLENDER_FPS, walk_cycle

        parts = spec.split(":")
        if parts[1] != "walk" or len(parts) > 3:
            raise UserError(f"{option} {spec}: the anny package ships one motion, `anny:walk` (or `anny:walk:N` for N cycles)")
        cycles = 2.0
        if len(parts) == 3:
            try:
                cycles = float(parts[2])
            except ValueError:
                cycles = -1.0
            if not (np.isfinite(cycles) and 0 < cycles <= 100):
                raise UserError(f"{option} {spec}: the number of cycles must be a number in (0, 100]")
        pose, transl = walk_cycle(h.body, h.shape, BLENDER_FPS, cycles)
        return Motion(torch.from_numpy(pose).to(dev), torch.from_numpy(transl).to(dev), BLENDER_FPS, spec)
    if spec.startswith("synth:"):
        return _synth(spec, h, option)
    path = Path(spec)
    if not path.is_file():
        raise UserError(f"{option} {spec}: no such file, and not one of run, anny:walk, synth:NAME "
                        f"({', '.join(SYNTH_PARTS)})")
    return _from_file(path, h, fps_run, option)


def _synth(spec: str, h, option: str) -> Motion:
    from cogs.data.synth.motion import SCRIPT_SECONDS, Choreography

    name = spec.split(":", 1)[1]
    if name not in SYNTH_PARTS:
        raise UserError(f"{option} {spec}: the synthetic generator's motions are {', '.join('synth:' + p for p in SYNTH_PARTS)}")
    if h.body.name != "anny":
        raise UserError(f"{option} {spec}: the synthetic choreography is written for the Anny body model; this run's is {h.body.name!r}")
    fps = 24.0
    n = int(round(SCRIPT_SECONDS * fps))
    m = Choreography(h.body, h.shape.detach().cpu().numpy()).evaluate(n)
    a, b = SYNTH_PARTS[name]
    keep = (m.times >= a - 1e-9) & (m.times <= b + 1e-9)
    dev = h.device
    return Motion(torch.from_numpy(m.pose[keep]).float().to(dev), torch.from_numpy(m.transl[keep]).float().to(dev), fps, spec)


def _from_file(path: Path, h, fps_run: float, option: str) -> Motion:
    try:
        data = dict(np.load(path, allow_pickle=False))
    except Exception as e:  # not an npz, damaged, or holding pickled objects
        raise UserError(f"{option} {path}: not a readable .npz of arrays ({type(e).__name__}: {str(e)[:120]})") from None
    dev = h.device
    J = h.body.n_bones
    if "pose" in data and "transl" in data:  # a native scene's body.npz
        model = str(data.get("model", h.body.name))
        pose = np.asarray(data["pose"], np.float32)
        transl = np.asarray(data["transl"], np.float32)
        if model != h.body.name or pose.ndim != 3 or pose.shape[1:] != (J, 3):
            raise UserError(f"{option} {path}: a body.npz of model {model!r} with pose {list(pose.shape)}; this run's body "
                            f"model is {h.body.name!r} with {J} bones (an SMPL-family sequence needs `poses` and `trans`)")
        if transl.shape != (len(pose), 3):
            raise UserError(f"{option} {path}: transl is {list(transl.shape)}, expected [{len(pose)}, 3]")
        _finite(path, option, pose=pose, transl=transl)
        fps = float(data["fps"]) if "fps" in data else fps_run
        return Motion(torch.from_numpy(pose).to(dev), torch.from_numpy(transl).to(dev), fps, path.name, in_world=True)
    if "poses" in data and "trans" in data:  # AMASS style
        poses = np.asarray(data["poses"], np.float32)
        trans = np.asarray(data["trans"], np.float32)
        if poses.ndim != 2 or poses.shape[1] < 66 or poses.shape[1] % 3:
            raise UserError(f"{option} {path}: `poses` is {list(poses.shape)}; an SMPL-family sequence has [T, 72] "
                            "(SMPL) or longer (SMPL-H/X), axis-angle, root first")
        if trans.shape != (len(poses), 3) or len(poses) == 0:
            raise UserError(f"{option} {path}: `trans` is {list(trans.shape)}, expected [{len(poses)}, 3] (T > 0)")
        _finite(path, option, poses=poses, trans=trans)
        fps = float(data.get("mocap_framerate", data.get("mocap_frame_rate", fps_run)))
        P, tr = torch.from_numpy(poses).to(dev), torch.from_numpy(trans).to(dev)
        if h.body.name == "smpl":
            pose = P[:, :72].reshape(-1, 24, 3) if P.shape[1] >= 72 else torch.cat([P[:, :66], P.new_zeros(len(P), 6)], 1).reshape(-1, 24, 3)
            return Motion(pose, tr, fps, path.name)
        if h.body.name != "anny":
            raise UserError(f"{option} {path}: retargeting SMPL-family motion onto {h.body.name!r} is not supported (anny, smpl)")
        from cogs.body.retarget import retarget_smpl_rotations

        pose, transl = retarget_smpl_rotations(P, tr, h.body, h.shape)
        return Motion(pose.to(dev), transl.to(dev), fps, path.name)
    raise UserError(f"{option} {path}: holds {sorted(data)[:8]}; expected a body.npz (`pose`, `transl`) or an "
                    "SMPL-family sequence (`poses`, `trans`)")


def _finite(path: Path, option: str, **arrays: np.ndarray) -> None:
    for k, a in arrays.items():
        bad = ~np.isfinite(a)
        if bad.any():
            frame = int(np.argwhere(bad)[0][0])
            raise UserError(f"{option} {path}: `{k}` is not finite at frame {frame}")


# -- time -------------------------------------------------------------------------------


def resample(m: Motion, fps: float) -> Motion:
    """The motion at `fps`: frame k shows time k / fps of it (per-bone SLERP and linear
    translation between its frames), as long as it lasts."""
    if abs(fps - m.fps) < 1e-9 or len(m) == 1:
        return m
    n = int(np.floor((len(m) - 1) * fps / m.fps + 1e-9)) + 1
    src = torch.arange(n, dtype=torch.float64, device=m.pose.device) * (m.fps / fps)
    i0 = src.floor().long().clamp(max=len(m) - 1)
    i1 = (i0 + 1).clamp(max=len(m) - 1)
    u = (src - i0).float()
    q = quat_sign_continuous(axis_angle_to_quat(m.pose.transpose(0, 1))).transpose(0, 1)  # [T, J, 4]
    pose = quat_to_axis_angle(slerp(q[i0], q[i1], u[:, None].expand(-1, q.shape[1])))
    transl = m.transl[i0] + u[:, None] * (m.transl[i1] - m.transl[i0])
    clip = None
    if m.clip_time is not None:
        clip = m.clip_time[i0] + u * (m.clip_time[i1] - m.clip_time[i0])
    return Motion(pose, transl, fps, m.name, clip, m.in_world)


def select(m: Motion, a: int, b: int) -> Motion:
    return Motion(m.pose[a:b], m.transl[a:b], m.fps, m.name, None if m.clip_time is None else m.clip_time[a:b], m.in_world)


# -- place ------------------------------------------------------------------------------


def _facing(body, shape) -> tuple[np.ndarray, np.ndarray]:
    """(canonical up, canonical front) of a body model."""
    from cogs.use.posing import canonical_up, snap_axis

    up = canonical_up(body, shape)
    joints = body.canonical(shape).joints.detach().cpu().double().numpy()
    for left, right in (("upperleg01.L", "upperleg01.R"), ("left_hip", "right_hip")):
        if left in body.bone_names and right in body.bone_names:
            lr = joints[body.bone_index(left)] - joints[body.bone_index(right)]
            return up, snap_axis(np.cross(lr, up), 90.0)
    raise UserError(f"the body model {body.name!r} names no hips to tell its front from")


def _heading(R: np.ndarray, front_c: np.ndarray, up: np.ndarray) -> np.ndarray:
    """[3, 3] with columns (front, left, up): the heading of root rotation R about `up`."""
    f = R @ front_c
    f = f - (f @ up) * up
    if np.linalg.norm(f) < 1e-6:
        raise UserError("the body faces straight up or down at the reference frame: no heading to align a motion to")
    f = f / np.linalg.norm(f)
    return np.stack([f, np.cross(up, f), up], axis=1)


@torch.no_grad()
def place(m: Motion, human, start_frame: int, up_world: np.ndarray) -> Motion:
    """Move a motion into the run's world: its first frame's root at the person's root at
    `start_frame`, turned about the vertical to face the same way, its lowest joint over
    the motion on the lowest the person's joints reach over the clip (the floor)."""
    body, shape = human.body, human.shape
    up_c, front_c = _facing(body, shape)
    dev = m.pose.device
    # The motion's own up: the canonical up turned by its root, averaged.
    R_m = axis_angle_to_rotmat(m.pose[:, 0].double()).cpu().numpy()  # [T, 3, 3]
    from cogs.use.posing import snap_axis

    up_m = snap_axis((R_m @ up_c).mean(0))
    _, J_m = body.bone_transforms(m.pose, m.transl, shape)
    J_m = J_m.double().cpu().numpy()
    pose_r, transl_r = human.frame_pose(start_frame)
    _, J_r = body.bone_transforms(pose_r, transl_r, shape)
    R_ref = axis_angle_to_rotmat(pose_r[0, 0].double()).cpu().numpy()
    floor_r = min(float((body.bone_transforms(*human.frame_pose(t), shape)[1][0].double().cpu().numpy() @ up_world).min())
                  for t in range(human.n_frames))
    floor_m = float((J_m @ up_m).min())
    W = _heading(R_ref, front_c, up_world) @ _heading(R_m[0], front_c, up_m).T
    p_m = J_m[:, 0]  # root joints
    p_ref = J_r[0, 0].double().cpu().numpy()
    p = p_ref + (p_m - p_m[0]) @ W.T
    p = p + np.outer((p_m @ up_m - floor_m) + floor_r - p @ up_world, up_world)
    rest_root = body.canonical(shape).joints[0].detach().double().cpu().numpy()
    pose = m.pose.clone()
    pose[:, 0] = rotmat_to_axis_angle(torch.from_numpy(W @ R_m)).to(pose)
    transl = torch.from_numpy(p - rest_root).to(m.transl)
    assert torch.isfinite(pose).all() and torch.isfinite(transl).all()
    return Motion(pose.to(dev), transl.to(dev), m.fps, m.name, m.clip_time, True)
