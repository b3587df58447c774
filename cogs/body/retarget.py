"""SMPL -> Anny retargeting, so SMPL-annotated datasets and SMPL-family motions work without
the (licensed) SMPL model: from joint positions (`retarget_smpl_joints`, below) and from
joint rotations (`retarget_smpl_rotations`, at the end).

Public benchmarks describe the person with SMPL parameters and, often, the 24 SMPL joint
positions they produce. Anny (the free default body model) has a different rig: 104 bones,
z up, an A-pose rest. This module fits Anny poses whose joints land on the given SMPL joint
positions, frame by frame but batched over the whole sequence:

1. Correspondence: each SMPL joint is matched to the head of one Anny bone
   (`SMPL_TO_ANNY`, chosen by anatomy; see docs/datasets.md for the table).
2. Shape (optional): Anny's `height` phenotype is chosen so its limb and torso lengths match
   the median SMPL segment lengths of the sequence (a 1-D golden-section search).
3. Initialisation, analytic: the root rotation by Kabsch on the torso joints (about the
   pelvis), then each limb bone, parents first, swung so the next joint points at its target.
4. Refinement: Adam on per-bone local rotations (axis-angle, `local-ref` convention of
   `cogs.body.anny_body`) and the world translation, with a temporal smoothness term and a
   weak pull of rotations towards zero. Optionally (`fit_offsets`), one constant offset per
   joint in its parent bone's frame, shared by all frames and pulled to zero, for where
   SMPL's regressed joints and Anny's bone heads sit differently.

Forward kinematics here is a re-implementation of Anny's local-ref chain on the bones that
matter (tested against `AnnyBody.bone_transforms`): G_child = G_parent D_child,
head_child = head_parent + G_parent (rest_child - rest_parent), root head + transl.

Joint positions fix a limb's direction but not its twist about its own axis, and SMPL's
head and hand joints do not show how the head or the hands are turned; those rotations stay
near the rest pose (see "open problems" in docs/datasets.md).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import torch
from torch import Tensor

from cogs.body.base import BodyModel
from cogs.geometry.rotations import axis_angle_to_rotmat, rotmat_from_two_vectors, rotmat_to_axis_angle

log = logging.getLogger(__name__)

# The 24 SMPL joints, in SMPL's order, and their kinematic parents (public constants of the
# SMPL skeleton).
SMPL_JOINT_NAMES: list[str] = [
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar",
    "right_collar", "head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
    "left_wrist", "right_wrist", "left_hand", "right_hand",
]
SMPL_PARENTS: list[int] = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21]

# SMPL joint -> the Anny bone whose head stands for it. "left" is the person's left (+x in
# both models' rest poses).
SMPL_TO_ANNY: dict[str, str] = {
    "pelvis": "root",
    "left_hip": "upperleg01.L",
    "right_hip": "upperleg01.R",
    "spine1": "spine03",
    "left_knee": "lowerleg01.L",
    "right_knee": "lowerleg01.R",
    "spine2": "spine02",
    "left_ankle": "foot.L",
    "right_ankle": "foot.R",
    "spine3": "spine01",
    "left_foot": "toe3-1.L",
    "right_foot": "toe3-1.R",
    "neck": "neck01",
    "left_collar": "shoulder01.L",
    "right_collar": "shoulder01.R",
    "head": "head",
    "left_shoulder": "upperarm01.L",
    "right_shoulder": "upperarm01.R",
    "left_elbow": "lowerarm01.L",
    "right_elbow": "lowerarm01.R",
    "left_wrist": "wrist.L",
    "right_wrist": "wrist.R",
    "left_hand": "finger3-1.L",
    "right_hand": "finger3-1.R",
}

# Bones on the path to a mapped joint whose rotation is left at rest: the mid-limb twist
# bones (bending there would fold a limb between its joints), the pelvis halves and the
# lowest spine bone (the pelvis is rigid, and with them free the root rotation and the
# hip offsets would trade off against each other), and the middle finger's metacarpal
# (the hand joint is reached through the wrist).
_FIXED_BONES = {
    f"{name}.{side}"
    for name in ("upperleg02", "lowerleg02", "upperarm02", "lowerarm02", "metacarpal2", "pelvis")
    for side in ("L", "R")
} | {"spine05"}

# Initial swings, parents first: (Anny bone that rotates, SMPL joint it should point at).
_SWING_EDGES: list[tuple[str, str]] = [
    ("spine04", "spine1"), ("spine03", "spine2"), ("spine02", "spine3"), ("spine01", "neck"),
    ("neck01", "head"),
    ("upperleg01.L", "left_knee"), ("lowerleg01.L", "left_ankle"), ("foot.L", "left_foot"),
    ("upperleg01.R", "right_knee"), ("lowerleg01.R", "right_ankle"), ("foot.R", "right_foot"),
    ("clavicle.L", "left_collar"), ("shoulder01.L", "left_shoulder"), ("upperarm01.L", "left_elbow"),
    ("lowerarm01.L", "left_wrist"), ("wrist.L", "left_hand"),
    ("clavicle.R", "right_collar"), ("shoulder01.R", "right_shoulder"), ("upperarm01.R", "right_elbow"),
    ("lowerarm01.R", "right_wrist"), ("wrist.R", "right_hand"),
]
_TORSO = ["pelvis", "left_hip", "right_hip", "spine1", "spine2", "spine3", "neck", "left_collar", "right_collar"]
# Segments whose lengths choose Anny's height: (from, to) SMPL joints.
# Only segments between joints both models place alike (knee, ankle, shoulder, elbow,
# wrist): SMPL's pelvis sits ~9 cm above its hips where Anny's root is level with them, so
# the thigh and the torso would bias the height.
_LENGTH_SEGMENTS = [
    ("left_knee", "left_ankle"), ("right_knee", "right_ankle"),
    ("left_shoulder", "left_elbow"), ("right_shoulder", "right_elbow"), ("left_elbow", "left_wrist"),
    ("right_elbow", "right_wrist"),
]


@dataclass
class RetargetConfig:
    """Hyper-parameters of the fit (defaults tuned on Anny-generated targets, see tests)."""

    iterations: int = 400
    """Adam steps over the whole sequence at once."""
    lr_rotation: float = 0.03
    """Adam step for the per-bone axis-angle rotations (radians)."""
    lr_translation: float = 0.01
    """Adam step for the world translation (metres)."""
    lr_offset: float = 0.003
    """Adam step for the per-joint marker offsets (metres)."""
    smooth_weight: float = 1e-3
    """Weight of the squared frame-to-frame change of each rotation (rad^2) against the
    squared joint error (m^2)."""
    rotation_prior: float = 1e-5
    """Weight of the squared rotation magnitude: a tie-breaker between redundant bones."""
    offset_prior: float = 0.05
    """Weight of the squared marker offsets (m^2); offsets are what SMPL and Anny disagree on
    about where a joint sits, shared by all frames."""
    fit_offsets: bool = False
    """Fit the per-joint marker offsets. Off by default: with little root rotation in a
    clip they trade off against the translation (measured on Anny motion with SMPL-like
    joint placements: 15 mm mean joint error without them, 37 mm with)."""
    fit_shape: bool = True
    """Choose Anny's `height` phenotype from the sequence's median segment lengths."""


@dataclass
class RetargetResult:
    shape: Tensor  # [S] Anny phenotypes
    pose: Tensor  # [T, J, 3] axis-angle, Anny local-ref
    transl: Tensor  # [T, 3]
    offsets: Tensor  # [24, 3] fitted marker offsets (canonical frame of each joint's parent bone)
    joint_error_m: Tensor  # [T, 24] distance between Anny's mapped bone heads and the targets
    seconds: float

    @property
    def mean_error_m(self) -> float:
        return float(self.joint_error_m.mean())


def anny_bone_indices(body: BodyModel) -> list[int]:
    """Index of the Anny bone standing for each SMPL joint, in SMPL order."""
    return [body.bone_index(SMPL_TO_ANNY[n]) for n in SMPL_JOINT_NAMES]


def anny_joints_as_smpl(body: BodyModel, pose: Tensor, transl: Tensor, shape: Tensor | None = None) -> Tensor:
    """Posed Anny joints [B, 24, 3] read through the correspondence table (SMPL order)."""
    _, joints = body.bone_transforms(pose, transl, shape)
    return joints[:, anny_bone_indices(body)]


class _Chain:
    """Forward kinematics on the Anny bones that move a mapped joint, batched by depth."""

    def __init__(self, body: BodyModel, rest_joints: Tensor):
        parents = body.bone_parents
        mapped = anny_bone_indices(body)
        ancestors: set[int] = set()
        for b in mapped:
            p = parents[b]
            while p >= 0:
                ancestors.add(p)
                p = parents[p]
        active = sorted(ancestors | set(mapped))  # Anny numbers parents before children
        assert all(parents[b] < b for b in active[1:]) and parents[active[0]] < 0
        self.active = active
        pos = {b: i for i, b in enumerate(active)}
        self.parent = [pos[parents[b]] if parents[b] >= 0 else -1 for b in active]
        fixed = {body.bone_index(n) for n in _FIXED_BONES}
        self.free = [i for i, b in enumerate(active) if b in ancestors and b not in fixed]
        self.free_bones = [active[i] for i in self.free]
        self.marker = [pos[b] for b in mapped]
        self.rest = rest_joints[active]  # [A, 3]
        depth = [0] * len(active)
        for i in range(1, len(active)):
            depth[i] = depth[self.parent[i]] + 1
        self.levels = [[i for i in range(len(active)) if depth[i] == d] for d in range(max(depth) + 1)]

    def rotations(self, omega: Tensor) -> Tensor:
        """Free-bone axis-angles [T, F, 3] -> local rotations of all active bones [T, A, 3, 3]."""
        T = omega.shape[0]
        eye = torch.eye(3, dtype=omega.dtype).expand(T, len(self.active), 3, 3)
        D = eye.clone()
        D[:, self.free] = axis_angle_to_rotmat(omega)
        return D

    def forward(self, D: Tensor, transl: Tensor) -> tuple[Tensor, Tensor]:
        """Local rotations [T, A, 3, 3], transl [T, 3] -> (heads [T, A, 3], global rots)."""
        T = D.shape[0]
        G: list[Tensor | None] = [None] * len(self.active)
        P: list[Tensor | None] = [None] * len(self.active)
        G[0] = D[:, 0]
        P[0] = self.rest[0].expand(T, 3) + transl
        for level in self.levels[1:]:
            par = [self.parent[i] for i in level]
            Gp = torch.stack([G[p] for p in par], 1)  # [T, L, 3, 3]
            Pp = torch.stack([P[p] for p in par], 1)
            off = self.rest[level] - self.rest[par]  # [L, 3]
            heads = Pp + (Gp @ off[None, :, :, None])[..., 0]
            rots = Gp @ D[:, level]
            for k, i in enumerate(level):
                G[i], P[i] = rots[:, k], heads[:, k]
        return torch.stack(P, 1), torch.stack(G, 1)

    def markers(self, P: Tensor, G: Tensor, offsets: Tensor | None) -> Tensor:
        """Positions [T, 24, 3] standing for the SMPL joints: mapped bone heads, plus each
        joint's offset carried by the bone that moves it (its parent; the root's own)."""
        heads = P[:, self.marker]
        if offsets is None:
            return heads
        carrier = [self.parent[m] if self.parent[m] >= 0 else m for m in self.marker]
        return heads + (G[:, carrier] @ offsets[None, :, :, None])[..., 0]


def _kabsch_about(src: Tensor, dst: Tensor) -> Tensor:
    """Rotations R [T, 3, 3] minimising sum |R src_i - dst_i|^2 (points already centred)."""
    H = src.transpose(-1, -2) @ dst  # [T, 3, 3]: sum_i src_i dst_i^T
    U, _, Vt = torch.linalg.svd(H)
    d = torch.sign(torch.linalg.det(Vt.transpose(-1, -2) @ U.transpose(-1, -2)))
    S = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1))
    return Vt.transpose(-1, -2) @ S @ U.transpose(-1, -2)


def _fit_height(body: BodyModel, targets: Tensor, base_shape: Tensor) -> Tensor:
    """Anny shape whose `height` makes its segment lengths best match the targets'."""
    idx = {n: i for i, n in enumerate(SMPL_JOINT_NAMES)}
    a = [idx[s] for s, _ in _LENGTH_SEGMENTS]
    b = [idx[e] for _, e in _LENGTH_SEGMENTS]
    goal = (targets[:, a] - targets[:, b]).norm(dim=-1).median(dim=0).values  # [S]
    bones = anny_bone_indices(body)
    k = body.shape_names.index("height")

    def cost(h: float) -> float:
        shape = base_shape.clone()
        shape[k] = h
        j = body.canonical(shape).joints.double()[bones]
        return float(((j[a] - j[b]).norm(dim=-1) - goal).square().sum())

    lo, hi = 0.0, 1.0
    g = (math.sqrt(5.0) - 1.0) / 2.0
    x1, x2 = hi - g * (hi - lo), lo + g * (hi - lo)
    f1, f2 = cost(x1), cost(x2)
    for _ in range(10):  # bracket shrinks to 0.6^10 ~ 0.008 of the range
        if f1 < f2:
            hi, x2, f2 = x2, x1, f1
            x1 = hi - g * (hi - lo)
            f1 = cost(x1)
        else:
            lo, x1, f1 = x1, x2, f2
            x2 = lo + g * (hi - lo)
            f2 = cost(x2)
    shape = base_shape.clone()
    shape[k] = 0.5 * (lo + hi)
    return shape


def _initialise(chain: _Chain, body: BodyModel, targets: Tensor) -> tuple[Tensor, Tensor]:
    """Analytic start: Kabsch root rotation, then limb swings parents first."""
    T = targets.shape[0]
    dtype = targets.dtype
    idx = {n: i for i, n in enumerate(SMPL_JOINT_NAMES)}
    A = len(chain.active)
    D = torch.eye(3, dtype=dtype).expand(T, A, 3, 3).clone()
    pelvis = targets[:, idx["pelvis"]]
    rest_markers = chain.rest[chain.marker]  # [24, 3]
    torso = [idx[n] for n in _TORSO]
    src = (rest_markers[torso] - rest_markers[idx["pelvis"]]).expand(T, -1, -1)
    dst = targets[:, torso] - pelvis[:, None]
    D[:, 0] = _kabsch_about(src, dst)
    transl = pelvis - chain.rest[0]
    pos = {b: i for i, b in enumerate(chain.active)}
    for bone, joint in _SWING_EDGES:
        i = pos[body.bone_index(bone)]
        P, G = chain.forward(D, transl)
        pivot = P[:, i]
        u = P[:, chain.marker[idx[joint]]] - pivot
        v = targets[:, idx[joint]] - pivot
        ok = (u.norm(dim=-1) > 1e-6) & (v.norm(dim=-1) > 1e-6)
        S = rotmat_from_two_vectors(u, v)
        S = torch.where(ok[:, None, None], S, torch.eye(3, dtype=dtype).expand_as(S))
        Gp = G[:, chain.parent[i]]
        # New global rotation S G_i = G_p D_i'  =>  D_i' = G_p^T S G_p D_i.
        D[:, i] = Gp.transpose(-1, -2) @ S @ Gp @ D[:, i]
    omega = rotmat_to_axis_angle(D[:, chain.free])
    return omega, transl


def retarget_smpl_joints(
    joints: Tensor,
    body: BodyModel,
    config: RetargetConfig | None = None,
    shape: Tensor | None = None,
) -> RetargetResult:
    """Fit Anny to SMPL joint positions.

    Args:
        joints: [T, 24, 3] SMPL joints in SMPL order, world coordinates in metres (any
            orientation: the root rotation is fitted). Must be finite.
        body: an Anny `BodyModel` (e.g. `load_body_model("anny")`).
        config: fit hyper-parameters.
        shape: Anny phenotypes [6] to use (or to start the height search from).
    Returns a `RetargetResult` whose pose/transl/shape form an Anny `BodyTrack`.
    """
    # The fit is thousands of tiny tensor ops: one thread avoids intra-op scheduling that
    # costs far more than it saves (5-8x slower with 2 threads on a busy 2-core machine).
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return _retarget(joints, body, config or RetargetConfig(), shape)
    finally:
        torch.set_num_threads(threads)


def _retarget(joints: Tensor, body: BodyModel, cfg: RetargetConfig, shape: Tensor | None) -> RetargetResult:
    t0 = time.perf_counter()
    targets = joints.detach().double().cpu()
    assert targets.ndim == 3 and targets.shape[1:] == (24, 3), targets.shape
    assert torch.isfinite(targets).all(), "targets must be finite"
    base = (body.default_shape if shape is None else shape).detach().double().cpu().clone()
    fitted_shape = _fit_height(body, targets, base) if cfg.fit_shape else base
    rest = body.canonical(fitted_shape.float()).joints.double()
    chain = _Chain(body, rest)

    with torch.no_grad():
        omega0, transl0 = _initialise(chain, body, targets)
    omega = omega0.clone().requires_grad_(True)
    transl = transl0.clone().requires_grad_(True)
    offsets = torch.zeros(24, 3, dtype=torch.float64, requires_grad=cfg.fit_offsets)
    groups = [{"params": [omega], "lr": cfg.lr_rotation}, {"params": [transl], "lr": cfg.lr_translation}]
    if cfg.fit_offsets:
        groups.append({"params": [offsets], "lr": cfg.lr_offset})
    opt = torch.optim.Adam(groups)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(cfg.iterations, 1), eta_min=0.0)
    T = targets.shape[0]
    for it in range(cfg.iterations):
        opt.zero_grad(set_to_none=True)
        P, G = chain.forward(chain.rotations(omega), transl)
        m = chain.markers(P, G, offsets if cfg.fit_offsets else None)
        loss = (m - targets).square().sum(-1).mean()
        loss = loss + cfg.rotation_prior * omega.square().sum(-1).mean()
        if T > 1 and cfg.smooth_weight > 0:
            loss = loss + cfg.smooth_weight * (omega[1:] - omega[:-1]).square().sum(-1).mean()
        if cfg.fit_offsets:
            loss = loss + cfg.offset_prior * offsets.square().sum(-1).mean()
        loss.backward()
        opt.step()
        sched.step()

    with torch.no_grad():
        J = body.n_bones
        pose = torch.zeros(T, J, 3, dtype=torch.float64)
        pose[:, chain.free_bones] = omega.detach()
        P, _ = chain.forward(chain.rotations(omega.detach()), transl.detach())
        err = (P[:, chain.marker] - targets).norm(dim=-1)
    seconds = time.perf_counter() - t0
    log.debug("retargeted %d frames in %.2f s, mean joint error %.1f mm", T, seconds, 1e3 * float(err.mean()))
    return RetargetResult(
        shape=fitted_shape.float(),
        pose=pose.float(),
        transl=transl.detach().float(),
        offsets=offsets.detach().float(),
        joint_error_m=err.float(),
        seconds=seconds,
    )


# -- SMPL-family rotations -> Anny, by mapping joint rotations ------------------------------

# SMPL's canonical frame (x the person's left, y up, z front) -> Anny's (x left, z up, -y
# front): a quarter turn about x.
SMPL_TO_ANNY_AXES = ((1.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0))

# The limbs whose rest directions differ between the two rigs (SMPL rests in a T-pose,
# Anny in an A-pose): SMPL joint -> (the joint its rotation points at, that limb's rest
# direction in SMPL's canonical frame, an idealised T-pose: legs straight down, arms
# straight out, feet forward and 27 degrees down as Anny's). Other joints (pelvis, spine,
# neck, head, collars) are taken to rest alike in both.
SMPL_LIMB_REST: dict[str, tuple[str, tuple[float, float, float]]] = {
    "left_hip": ("left_knee", (0.0, -1.0, 0.0)), "right_hip": ("right_knee", (0.0, -1.0, 0.0)),
    "left_knee": ("left_ankle", (0.0, -1.0, 0.0)), "right_knee": ("right_ankle", (0.0, -1.0, 0.0)),
    "left_ankle": ("left_foot", (0.0, -0.45, 0.89)), "right_ankle": ("right_foot", (0.0, -0.45, 0.89)),
    "left_shoulder": ("left_elbow", (1.0, 0.0, 0.0)), "right_shoulder": ("right_elbow", (-1.0, 0.0, 0.0)),
    "left_elbow": ("left_wrist", (1.0, 0.0, 0.0)), "right_elbow": ("right_wrist", (-1.0, 0.0, 0.0)),
    "left_wrist": ("left_hand", (1.0, 0.0, 0.0)), "right_wrist": ("right_hand", (-1.0, 0.0, 0.0)),
}
SMPL_BODY_JOINTS = 22
"""Joints read from an SMPL-family pose vector: the root and 21 body joints (SMPL's two
hand joints and SMPL-H/X finger joints follow them and are left out)."""


def smpl_global_rotations(poses: Tensor) -> Tensor:
    """SMPL-family axis-angle poses [T, >= 66] -> each body joint's rotation from the
    canonical frame to the world, [T, 22, 3, 3] (float64)."""
    T = poses.shape[0]
    local = axis_angle_to_rotmat(poses[:, : 3 * SMPL_BODY_JOINTS].double().reshape(T, SMPL_BODY_JOINTS, 3))
    G: list[Tensor] = []
    for j in range(SMPL_BODY_JOINTS):
        p = SMPL_PARENTS[j]
        G.append(local[:, j] if p < 0 else G[p] @ local[:, j])
    return torch.stack(G, 1)


def retarget_smpl_rotations(poses: Tensor, trans: Tensor, body: BodyModel, shape: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Retarget an SMPL-family sequence (AMASS style: axis-angle `poses` [T, >= 66], root
    first; `trans` [T, 3]) onto Anny by mapping joint rotations: no SMPL model file needed.

    Each SMPL joint's world rotation G_j is carried to its Anny bone (`SMPL_TO_ANNY`) as
    G_j C^T S_b, where C turns SMPL's canonical axes into Anny's and S_b turns the Anny
    limb's rest direction onto SMPL's (`SMPL_LIMB_REST`, identity elsewhere), so every
    limb points where the SMPL limb points; Anny bones between mapped ones keep their
    rest rotation. The translation is SMPL's (the pelvis' offset from SMPL's origin, a
    constant, is left in). Returns Anny (pose [T, J, 3] local-ref axis-angle, transl
    [T, 3]) in the sequence's own world.
    """
    assert poses.ndim == 2 and poses.shape[1] >= 3 * SMPL_BODY_JOINTS, poses.shape
    G = smpl_global_rotations(poses)  # [T, 22, 3, 3]
    T = G.shape[0]
    C = torch.tensor(SMPL_TO_ANNY_AXES, dtype=torch.float64, device=G.device)
    joints = body.canonical(shape).joints.detach().double().to(G.device)
    names = SMPL_JOINT_NAMES
    anny = {n: body.bone_index(SMPL_TO_ANNY[n]) for n in names[:SMPL_BODY_JOINTS]}
    S = {}
    for n, (child, d_s) in SMPL_LIMB_REST.items():
        d_a = joints[body.bone_index(SMPL_TO_ANNY[child])] - joints[anny[n]]
        target = C @ torch.tensor(d_s, dtype=torch.float64, device=G.device)
        S[n] = rotmat_from_two_vectors(d_a, target)
    eye = torch.eye(3, dtype=torch.float64, device=G.device)
    Ga = {anny[n]: G[:, j] @ C.T @ S.get(n, eye) for j, n in enumerate(names[:SMPL_BODY_JOINTS])}
    pose = torch.zeros(T, body.n_bones, 3, dtype=torch.float64, device=G.device)
    parents = body.bone_parents
    for b, Gb in Ga.items():
        p = parents[b]
        while p >= 0 and p not in Ga:  # bones in between rest: the nearest mapped ancestor
            p = parents[p]
        pose[:, b] = rotmat_to_axis_angle(Gb if p < 0 else Ga[p].transpose(-1, -2) @ Gb)
    return pose.float(), trans.to(pose.device).float()
