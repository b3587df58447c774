"""Object trajectories for `cogs render --object`.

    run                   the trained trajectory (at the run's frame each output frame shows)
    hand-left|hand-right  rigidly attached to a hand bone, keeping the offset it has at the
                          reference frame (`--attach-frame`), so it follows any motion
    static                held at the reference frame's pose
    none                  removed
    PATH.json             a trajectory in the scene format's object.json convention

Poses follow the object branch: x_world = R(quat) (x_canonical - centre) + translation.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from cogs.errors import UserError
from cogs.geometry.rotations import quat_geodesic_angle, quat_normalize, quat_to_rotmat, rotmat_to_quat, slerp

HAND_BONES = {"anny": ("wrist.L", "wrist.R"), "smpl": ("left_wrist", "right_wrist")}
CHOICES = ("run", "hand-left", "hand-right", "static", "none")


@dataclass
class ObjectPath:
    translation: Tensor  # [T, 3]
    quat: Tensor  # [T, 4] wxyz
    attach_frame: int | None = None


def _matrix(tr: Tensor, q: Tensor) -> Tensor:
    X = torch.zeros(*tr.shape[:-1], 4, 4, dtype=tr.dtype, device=tr.device)
    X[..., :3, :3] = quat_to_rotmat(q)
    X[..., :3, 3] = tr
    X[..., 3, 3] = 1.0
    return X


def hand_bone(body, side: str, name: str | None) -> int:
    """The bone the object attaches to: `name` (--hand-bone), or the body model's wrist."""
    if name is None:
        if body.name not in HAND_BONES:
            raise UserError(f"--hand-bone: the body model {body.name!r} has no default hand bone; name one")
        name = HAND_BONES[body.name][0 if side == "left" else 1]
    if name not in body.bone_names:
        raise UserError(f"--hand-bone {name}: the body model {body.name!r} has no such bone "
                        f"(e.g. {', '.join(HAND_BONES.get(body.name, body.bone_names[:2]))})")
    return body.bone_index(name)


@torch.no_grad()
def _hand_transforms(human, bone: int, pose: Tensor, transl: Tensor) -> Tensor:
    """[T, 4, 4] the hand bone's skinning transform (canonical -> world) per frame."""
    out = [human.body.bone_transforms(pose[k : k + 1], transl[k : k + 1], human.shape)[0][0, bone] for k in range(len(pose))]
    return torch.stack(out).double()


@torch.no_grad()
def auto_attach_frame(model, bone: int, window: int = 3) -> int:
    """The run's frame where the object sits most rigidly in the hand: the smallest change
    of its pose relative to the hand bone over +-`window` frames (translation plus the
    rotation angle times the object's size)."""
    h, o = model.human, model.object
    T = h.n_frames
    poses = [h.frame_pose(t) for t in range(T)]
    A = _hand_transforms(h, bone, torch.cat([p for p, _ in poses]), torch.cat([t for _, t in poses]))
    tr, q = o.pose(torch.arange(T, dtype=torch.float32, device=o.centre.device))
    rel = torch.linalg.inv(A) @ _matrix(tr.double(), q.double())
    size = float(o.size)
    score = torch.full((T,), float("inf"), dtype=torch.float64, device=rel.device)
    for t in range(T):
        s = list(range(max(0, t - window), min(T, t + window + 1)))
        dt = (rel[s, :3, 3] - rel[t, :3, 3]).norm(dim=-1)
        dq = quat_geodesic_angle(rotmat_to_quat(rel[s, :3, :3]), rotmat_to_quat(rel[t, :3, :3]).expand(len(s), 4))
        score[t] = (dt + size * dq).mean()
    return int(torch.argmin(score))


def object_path(spec: str, model, motion, attach_frame: int | None, hand: str | None) -> ObjectPath | None:
    """The object's pose at every frame of `motion` (already placed in the run's world)."""
    o = model.object
    n = len(motion)
    if spec == "none":
        return None
    if o is None or len(o) == 0:
        raise UserError(f"--object {spec}: the run has no object branch (use --object none)")
    dev = o.centre.device
    T = o.n_frames
    if attach_frame is not None and not 0 <= attach_frame < T:
        raise UserError(f"--attach-frame {attach_frame}: out of range, the run has frames 0..{T - 1}")
    with torch.no_grad():
        if spec == "run":
            tau = motion.clip_time if motion.clip_time is not None else torch.arange(n, dtype=torch.float32, device=dev).clamp(max=T - 1)
            tr, q = o.pose(tau.float())
            return ObjectPath(tr, q)
        if spec == "static":
            f = 0 if attach_frame is None else attach_frame
            tr, q = o.frame_pose(f)
            return ObjectPath(tr.expand(n, 3).clone(), q.expand(n, 4).clone(), f)
        if spec in ("hand-left", "hand-right"):
            h = model.human
            if h is None:
                raise UserError(f"--object {spec}: the run has no human branch")
            bone = hand_bone(h.body, spec.split("-")[1], hand)
            f = auto_attach_frame(model, bone) if attach_frame is None else attach_frame
            A_f = _hand_transforms(h, bone, *h.frame_pose(f))[0]
            offset = torch.linalg.inv(A_f) @ _matrix(*[x.double() for x in o.frame_pose(f)])
            X = _hand_transforms(h, bone, motion.pose, motion.transl) @ offset
            return ObjectPath(X[:, :3, 3].float(), rotmat_to_quat(X[:, :3, :3]).float(), f)
    path = Path(spec)
    if path.suffix != ".json" or not path.is_file():
        raise UserError(f"--object {spec}: expected one of {', '.join(CHOICES)} or a trajectory .json file (object.json convention)")
    return _from_json(path, n, dev)


def _from_json(path: Path, n: int, dev) -> ObjectPath:
    try:
        data = json.loads(path.read_text())
        frames = data["frames"]
        tr = np.array([f["translation"] for f in frames], np.float64)
        q = np.array([f["quat_wxyz"] for f in frames], np.float64)
        at = [f.get("frame") for f in frames]
    except (ValueError, KeyError, TypeError) as e:
        raise UserError(f"--object {path}: not a trajectory ({{\"frames\": [{{\"translation\": [x, y, z], \"quat_wxyz\": "
                        f"[w, x, y, z], \"frame\": k}}, ...]}}): {type(e).__name__} {e}") from None
    if len(frames) == 0 or tr.shape != (len(frames), 3) or q.shape != (len(frames), 4):
        raise UserError(f"--object {path}: every entry needs a 3-vector translation and a 4-vector quat_wxyz")
    bad = ~(np.isfinite(tr).all(1) & np.isfinite(q).all(1) & (np.linalg.norm(q, axis=1) > 1e-8))
    if bad.any():
        raise UserError(f"--object {path}: entry {int(np.argmax(bad))} is not finite (or its quaternion is zero)")
    times = _key_times(at, len(frames), n, f"--object {path}")
    k = torch.arange(n, dtype=torch.float64, device="cpu")
    return ObjectPath(*[x.float().to(dev) for x in _interp_poses(torch.from_numpy(times), torch.from_numpy(tr),
                                                                   quat_normalize(torch.from_numpy(q)), k)])


def _key_times(at: list, n_keys: int, n: int, what: str) -> np.ndarray:
    """Output frame of each key: its "frame" where every key has one, else spread evenly."""
    if all(a is not None for a in at):
        t = np.array(at, np.float64)
        if not np.isfinite(t).all() or (np.diff(t) <= 0).any():
            raise UserError(f"{what}: the keys' \"frame\" values must be finite and increasing")
        return t
    if any(a is not None for a in at):
        raise UserError(f"{what}: give \"frame\" on every key or on none")
    return np.linspace(0.0, max(n - 1, 0), n_keys) if n_keys > 1 else np.zeros(1)


def _interp_poses(times: Tensor, tr: Tensor, q: Tensor, at: Tensor) -> tuple[Tensor, Tensor]:
    """Translations linear and rotations SLERPed between keys, held beyond the ends."""
    if len(times) == 1:
        return tr.expand(len(at), 3), q.expand(len(at), 4)
    at = at.clamp(float(times[0]), float(times[-1]))
    i = (torch.searchsorted(times, at, right=True) - 1).clamp(0, len(times) - 2)
    u = ((at - times[i]) / (times[i + 1] - times[i])).clamp(0, 1)
    return tr[i] + u[:, None] * (tr[i + 1] - tr[i]), slerp(q[i], q[i + 1], u)
