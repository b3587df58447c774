"""The object branch: one canonical Gaussian set moved rigidly along a keyframed trajectory.

x_world(tau) = R(q(tau)) (x_canonical - c) + t(tau), with t(tau) a cubic Hermite spline
through K keyframes (position p_k, velocity v_k) and q(tau) the SLERP of keyframe
quaternions q_k along the shortest arc (math in cogs.geometry.splines). Time tau is the
frame index. The keyframes start fitted to the noisy initial per-frame poses, which stay
as the pose prior (t̄_t, q̄_t). Where that initial trajectory holds the object still for
several frames (``rest_frames``: on a table before it is picked up, in a hand that pauses),
the trajectory is asked to stay still too (``rest_losses``). The acceleration term holds the
trajectory's shape to that of the initial keyframed one (``smooth_about_initial``): it
resists wiggles that training adds, not the motion the video shows (a bounce, a kick).

Canonical Gaussians start on the surface of a visual hull carved from the object masks
under the initial trajectory (robust voting, so pose noise and occlusion by the person do
not erase the object), coloured from the frames by splatting back.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from cogs.branches.base import Branch, Splats, register
from cogs.branches.gaussians import GaussianSet, guard_set, set_param_groups
from cogs.branches.shading import Irradiance
from cogs.branches.surgery import SetGaussians
from cogs.branches.held_out import detail, lagrange_neighbours
from cogs.geometry.rotations import (
    axis_angle_to_quat,
    quat_geodesic_angle,
    quat_multiply,
    quat_normalize,
    quat_sign_continuous,
    quat_to_rotmat,
)
from cogs.render.sh import sh_to_color
from cogs.geometry.splines import (
    acceleration_penalty,
    fit_keyframes,
    rotation_smoothness,
    sample_trajectory,
    uniform_keyframe_times,
)

log = logging.getLogger(__name__)


@dataclass
class ObjectConfig:
    """Object-branch hyper-parameters."""

    frames_per_keyframe: float = 3.0
    """Keyframe spacing in frames (K = ceil(T / spacing) + 1)."""
    hull_resolution: int = 40
    """Voxels per side of the carving cube."""
    hull_margin: float = 1.6
    """Cube side relative to the object's apparent size (from masks and depth)."""
    hull_keep_fraction: float = 0.75
    """A voxel survives when at least this fraction of the frames that decide it see it
    inside the (dilated) object mask; frames where it falls on the person abstain."""
    hull_dilate_px: int = 2
    min_confidence: float = 0.2
    """Frames whose object-mask confidence (the scene's object.json) is below this are left
    out of everything the object mask supervises: the object stages never draw them, the
    object's mask, crop and colour terms skip them, and the visual hull and the object's
    initial colours ignore them; their trajectory is the keyframes' interpolation, held to
    the initial poses by the pose prior. The classical tracker gives 0 where it lost the
    object, 0.1 where its mask cannot be told from its surroundings (``_Tracker.unclear``)
    and at least 0.3 wherever a cue found it (0.3 for the hand cue alone, the floor of a
    fitted shape); SAM2's and the user's masks give 0 on an empty mask, 1 otherwise: 0.2
    leaves out exactly the frames marked lost or unclear. Chosen on that scale, not tuned on scenes:
    the demo scene and other synthetic scenes record no confidence and are unaffected (bit
    for bit); on the basketball clip it leaves out the two frames where the ball is hidden
    (docs/experiments/2026-11-25-initial-object-pose.md, end to end)."""
    max_gaussians: int = 8000
    init_opacity: float = 0.6
    sh_degree: int = 0
    shading: bool = True
    """Albedo x irradiance of the posed normal (see shading.py): the object turns under
    world-fixed light. Gaussians start as discs tangent to the hull, so they have normals."""
    rest_speed: float = 0.02
    """At rest: the initial trajectory's smoothed speed below this fraction of the object's
    size per frame (see ``rest_frames``)."""
    rest_min_frames: int = 5
    """Shortest run of frames that counts as a rest."""
    held_out_input_weight: float = 0.0
    """How much of a held-out frame's own initial pose its object pose follows, times that
    frame's confidence (none below `min_confidence`): the trajectory at the frame, moved
    by this share of how the frame's initial pose departs from the linear interpolation
    of its training neighbours' initial poses, less the trajectory's own departure from
    its interpolation there (0: the trajectory; 1: the neighbours' fitted poses plus all
    of the input's detail). The keyframed trajectory is smooth; a kick or a bounce
    between training frames is not on it, but it is in that frame's own estimate (its
    tracked mask), together with the estimate's jitter. Only frames outside the training
    split are posed this way. Off by default: on trained runs (quick preset) held-out
    object-crop PSNR at 0 / 0.5 / 1 was 20.11 / 20.10 / 19.08 dB on the demo scene,
    19.91 / 19.54 / 18.76 on `cogs synth --seed 7 --frames 80 --fps 15` (smooth motion:
    the detail is mostly jitter), 14.29 / 14.40 / 14.43 on the basketball clip and
    14.36 / 14.77 / 14.99 on the juggling clip (a kicked ball: the detail is motion), so
    no setting helps on all of them. Set 0.5-1 for a clip whose object moves fast
    against its frame rate (docs/experiments/2026-11-27-held-out-object-poses.md)."""
    smooth_about_initial: bool = True
    """The acceleration term (``LossWeights.acceleration``) penalises how the trajectory's
    acceleration departs from the initial trajectory's (its keyframe fit, sampled every
    frame), not the acceleration itself: it resists the wiggles training would add, not the
    motion the initial poses show. Penalising the acceleration itself (False, as before
    2026-11-28) flattens fast motion: a dribbled basketball at 12 fps costs 1.3 in loss units
    on its initial trajectory against a pose prior of a few hundredths, so training pulled
    the ball up to 65 px (4.6 radii) off its masks at training frames and the object branch
    learned a small blob. Chosen on trained runs (quick preset; held-out full / human crop /
    object crop PSNR, False -> True): the demo scene 31.50 / 25.19 / 20.45 -> 31.97 / 25.55 /
    21.35 dB (object pose error 2.59 -> 2.48 cm, 4.34 -> 3.99 deg); `cogs synth --seed 7
    --frames 80 --fps 15` 31.01 / 24.73 / 20.74 -> 30.93 / 24.76 / 21.18 (2.57 -> 2.29 cm,
    4.16 -> 3.59 deg); the basketball clip 24.16 / 20.19 / 13.66 -> 24.35 / 20.51 / 17.09;
    the other development clips in docs/experiments/2026-11-28-smoothness-about-the-initial-trajectory.md."""
    held_out_max_gap: int = 3
    """Farthest training neighbour (frames) a held-out frame's interpolation may use;
    without one on each side the frame keeps the trajectory."""


@register
class ObjectBranch(Branch):
    name = "object"

    def __init__(
        self,
        gaussians: GaussianSet,
        centre: Tensor,  # [3]
        key_times: Tensor,  # [K]
        p: Tensor,  # [K, 3]
        v: Tensor,  # [K, 3]
        q: Tensor,  # [K, 4]
        prior_t: Tensor,  # [T, 3] initial per-frame translations
        prior_q: Tensor,  # [T, 4]
        cfg: ObjectConfig,
        size: float | None = None,
        rest: Tensor | None = None,  # [T] bool
        trained: Tensor | None = None,  # [T] bool: frames of the training split (None: all)
        confidence: Tensor | None = None,  # [T] the initial poses' confidence (None: ones)
        ref_t: Tensor | None = None,  # [T, 3] the smoothness's reference trajectory (None: the keyframes' own)
    ):
        super().__init__()
        self.cfg = cfg
        self.gaussians = gaussians
        self.register_buffer("centre", centre.float().clone())
        self.register_buffer("key_times", key_times.float().clone())
        self.key_p = torch.nn.Parameter(p.float().clone())
        self.key_v = torch.nn.Parameter(v.float().clone())
        self.key_q = torch.nn.Parameter(q.float().clone())
        self.register_buffer("prior_t", prior_t.float().clone())
        self.register_buffer("prior_q", quat_normalize(prior_q.float()).clone())
        self.shading = Irradiance(device=centre.device)
        # Measured on the initial Gaussians and trajectory, then kept: the object's size
        # (metres) and the frames where the initial trajectory rests.
        size = object_size(gaussians.means.detach(), centre) if size is None else float(size)
        fresh = rest is None
        if fresh:
            rest = rest_frames(self.prior_t, size, cfg.rest_speed, min_run=cfg.rest_min_frames)
        self.register_buffer("size", torch.tensor(size, dtype=torch.float64, device=centre.device))
        self.register_buffer("rest", rest.to(device=centre.device, dtype=torch.bool).clone())
        # Consecutive frames both at rest, as indices (fixed; gathered without a device sync).
        pairs = torch.nonzero(self.rest[:-1] & self.rest[1:]).flatten()
        self._has_rest = bool(len(pairs))
        self.register_buffer("rest_pairs", pairs, persistent=False)
        if fresh and self._has_rest:
            log.info("object: at rest in %d of %d frames (initial trajectory)", int(self.rest.sum()), len(self.rest))
        # Which frames the training fits and how far each initial pose is trusted (saved, so a
        # loaded model poses held-out frames without its scene); a host copy for decisions.
        T = self.n_frames
        trained = torch.ones(T, dtype=torch.bool) if trained is None else trained.bool()
        confidence = torch.ones(T) if confidence is None else confidence.float()
        assert trained.shape == (T,) and confidence.shape == (T,), "one entry per frame"
        self.register_buffer("trained", trained.to(centre.device).clone())
        self.register_buffer("input_confidence", confidence.to(centre.device).clone())
        self._trained = self.trained.tolist()
        # The initial keyframed trajectory, sampled every frame: what the acceleration term
        # measures departures from (``smooth_about_initial``). A model saved before it had
        # none and is smoothed towards straight lines, as it was trained.
        if ref_t is None:
            with torch.no_grad():
                ref_t = self.pose(torch.arange(T, dtype=torch.float32, device=centre.device))[0] if fresh else torch.zeros(T, 3)
        assert ref_t.shape == (T, 3), "one reference position per frame"
        self.register_buffer("ref_t", ref_t.float().to(centre.device).clone())

    def __len__(self) -> int:
        return len(self.gaussians)

    @property
    def n_frames(self) -> int:
        return int(self.prior_t.shape[0])

    @classmethod
    def from_state(cls, state: dict[str, Tensor], cfg, body=None) -> "ObjectBranch":
        g = GaussianSet.from_state(state, "gaussians.params.")
        obj = cls(g, state["centre"], state["key_times"], state["key_p"], state["key_v"], state["key_q"],
                  state["prior_t"], state["prior_q"], cfg.object, size=float(state["size"]), rest=state["rest"],
                  trained=state.get("trained"), confidence=state.get("input_confidence"), ref_t=state.get("ref_t"))
        # A model saved before held-out poses existed: every frame counts as trained (its
        # frames are posed on the trajectory, as they were).
        state = {"trained": obj.trained, "input_confidence": obj.input_confidence, "ref_t": obj.ref_t, **state}
        obj.load_state_dict(state)
        return obj

    # -- trajectory ----------------------------------------------------------------------
    def pose(self, tau: Tensor) -> tuple[Tensor, Tensor]:
        """(translation [T, 3], unit quaternion [T, 4]) at frame times tau [T]."""
        return sample_trajectory(self.key_times, self.key_p, self.key_v, quat_normalize(self.key_q), tau.float())

    def frame_pose(self, t: int) -> tuple[Tensor, Tensor]:
        """(translation [3], quaternion [4]) at frame t: on the trajectory, or for a frame
        outside the training split, moved towards its own initial pose (`held_out_pose`)."""
        tr, q = self.pose(torch.tensor([float(t)], device=self.centre.device))
        if not self._trained[t] and self.cfg.held_out_input_weight > 0:
            return self.held_out_pose(t, tr[0], q[0])
        return tr[0], q[0]

    def frame_poses(self) -> tuple[Tensor, Tensor]:
        """`frame_pose` of every frame: (translations [T, 3], quaternions [T, 4]); the
        trajectory sampled once, then the held-out frames moved."""
        tr, q = self.pose(torch.arange(self.n_frames, dtype=torch.float32, device=self.centre.device))
        if self.cfg.held_out_input_weight > 0:
            tr, q = tr.clone(), q.clone()
            for t in (k for k, trained in enumerate(self._trained) if not trained):
                tr[t], q[t] = self.held_out_pose(t, tr[t], q[t])
        return tr, q

    def held_out_pose(self, t: int, tr: Tensor, q: Tensor) -> tuple[Tensor, Tensor]:
        """The trajectory's pose (tr, q) at held-out frame t moved by w (d_in - d_fit): d_in
        how the frame's initial pose departs from the linear interpolation of its nearest
        training frames' initial poses, d_fit the same for the trajectory, and w =
        `held_out_input_weight` x the frame's confidence (0 below `min_confidence`, or
        without a training frame on each side within `held_out_max_gap`)."""
        conf = float(self.input_confidence[t])
        nb = lagrange_neighbours(t, self._trained, 1, self.cfg.held_out_max_gap)
        if nb is None or conf < self.cfg.min_confidence:
            return tr, q
        w = self.cfg.held_out_input_weight * conf
        frames = torch.tensor(nb[0] + [t], device=self.centre.device)
        fit_t, fit_q = self.pose(frames.float())
        # Both rotation sequences sign-continuous along (neighbours..., t), J = 1 bone.
        fit_q = quat_sign_continuous(quat_normalize(fit_q))[:, None]
        in_q = quat_sign_continuous(self.prior_q[frames])[:, None]
        local = ([0, 1], nb[1])  # the neighbours' rows in these stacks; t is row 2
        d_in, dt_in = detail(in_q, self.prior_t[frames], 2, local)
        d_fit, dt_fit = detail(fit_q, fit_t, 2, local)
        turn = axis_angle_to_quat(w * (d_in[0] - d_fit[0]))
        return tr + w * (dt_in - dt_fit), quat_normalize(quat_multiply(turn, q))

    def posed(self, translation: Tensor, quat: Tensor) -> tuple[Tensor, Tensor]:
        """Canonical Gaussians moved by one rigid pose: (means [N, 3], quats [N, 4])."""
        R = quat_to_rotmat(quat)
        means = (self.gaussians.means - self.centre) @ R.T + translation
        quats = quat_multiply(quat_normalize(quat).expand(len(self), 4), self.gaussians.quats)
        return means, quats

    def splats(self, frame: int, campos: Tensor, pose: tuple[Tensor, Tensor] | None = None, prepared=None) -> Splats:
        """The object at `frame` on its trajectory, or at `pose` = (translation [3], quat [4])."""
        translation, quat = pose if pose is not None else self.frame_pose(frame)
        means, quats = self.posed(translation, quat)
        g = self.gaussians
        # View-dependent colour is defined in the object's own frame: rotate the view ray back.
        if g.sh_degree > 0:
            rgb = sh_to_color(g.sh_degree, (means - campos) @ quat_to_rotmat(quat), g.sh)
        else:
            rgb = g.rgb
        if self.cfg.shading:
            rgb = rgb * self.shading(quat_to_rotmat(quats)[:, :, 2])
        return Splats(means, quats, g.scales, g.opacities, rgb)

    # -- training ------------------------------------------------------------------------
    def param_groups(self, lr, extent: float) -> list[dict]:
        return set_param_groups(self.gaussians, lr, "object", 1.0) + [
            {"params": list(self.shading.parameters()), "lr": lr.shading, "name": "shading"},
            {"params": [self.key_p, self.key_v], "lr": lr.object_trajectory, "name": "trajectory"},
            {"params": [self.key_q], "lr": lr.object_rotation, "name": "rotation"},
        ]

    def density_adapter(self) -> SetGaussians:
        return SetGaussians(self.gaussians)

    def extent(self, scene_extent: float) -> float:
        """The Gaussians' largest distance from their mean (>= 5 cm)."""
        m = self.gaussians.means.detach()
        return max(float((m - m.mean(0)).norm(dim=1).max()), 0.05)

    def guard(self, extent: float) -> None:
        guard_set(self.gaussians, extent)
        with torch.no_grad():
            q = self.key_q
            q.copy_(q / q.norm(dim=1, keepdim=True).clamp_min(1e-8))

    def regularisers(self, weights, frames: Tensor, prepared=None) -> dict[str, Tensor]:
        """The motion terms present in `weights`: the pose prior over the training `frames`
        (translation L1 + lambda_R geodesic), acceleration and rotation smoothness of the
        trajectory, and stillness where the initial trajectory rests."""
        if "pose_prior" not in weights:
            return {}
        terms = {}
        tr, q = self.pose(frames.float())
        terms["prior_translation"] = weights["pose_prior"] * (tr - self.prior_t[frames]).abs().sum(-1).mean()
        terms["prior_rotation"] = weights["pose_prior_rotation"] * quat_geodesic_angle(q, self.prior_q[frames]).mean()
        acc, rot = self.smoothness_losses()
        terms["acceleration"] = weights["acceleration"] * acc
        if "rotation_smoothness" in weights:
            terms["rotation_smoothness"] = weights["rotation_smoothness"] * rot
        if weights.get("rest_translation", 0) > 0 or weights.get("rest_rotation", 0) > 0:
            rest_t, rest_q = self.rest_losses()
            terms["rest_translation"] = weights["rest_translation"] * rest_t
            terms["rest_rotation"] = weights["rest_rotation"] * rest_q
        return terms

    def rest_losses(self) -> tuple[Tensor, Tensor]:
        """(translation m, rotation rad): mean change between consecutive frames that are
        both at rest; zero (with a graph) when there is no rest."""
        tr, q = self.pose(torch.arange(self.n_frames, dtype=torch.float32, device=self.centre.device))
        if not self._has_rest:
            zero = tr.sum() * 0
            return zero, zero
        pair = self.rest_pairs
        dt = (tr[1:] - tr[:-1]).norm(dim=-1)[pair].mean()
        dq = quat_geodesic_angle(q[1:], q[:-1])[pair].mean()
        return dt, dq

    def smoothness_losses(self) -> tuple[Tensor, Tensor]:
        """(acceleration, rotation smoothness) of the trajectory sampled every frame; the
        acceleration of its departure from ``ref_t`` with ``smooth_about_initial``."""
        tr, q = self.pose(torch.arange(self.n_frames, dtype=torch.float32, device=self.centre.device))
        if self.cfg.smooth_about_initial:
            tr = tr - self.ref_t
        # Angular acceleration, not speed: a steady spin in the hand costs nothing.
        return acceleration_penalty(tr), rotation_smoothness(q, order=2)

    # -- outputs -------------------------------------------------------------------------
    def export(self, folder: Path, n_frames: int) -> list[Path]:
        """The canonical Gaussians (3DGS PLY) and the pose at every frame (`frame_pose`)."""
        from cogs.data.io import write_json

        ply, js = folder / "object_canonical.ply", folder / "object_trajectory.json"
        self.gaussians.save_ply(ply)
        assert n_frames == self.n_frames, "the trajectory has one pose per frame"
        with torch.no_grad():
            tr, q = self.frame_poses()
        write_json(js, {
            "centre": self.centre.tolist(),
            "convention": "x_world = R(quat_wxyz) (x_canonical - centre) + translation",
            "keyframe_times": self.key_times.tolist(),
            "frames": [{"quat_wxyz": q[i].tolist(), "translation": tr[i].tolist()} for i in range(len(tr))],
        })
        return [ply, js]


def object_size(means: Tensor, centre: Tensor) -> float:
    """A robust diameter of a Gaussian set (twice the 90th percentile distance of its means
    from ``centre``), metres; 0 for an empty set."""
    if len(means) == 0:
        return 0.0
    return 2.0 * float(torch.quantile((means.float() - centre.float()).norm(dim=-1), 0.9))


def rest_frames(positions: Tensor, size: float, speed: float = 0.02, window: int = 7, min_run: int = 5) -> Tensor:
    """[T] bool: the frames in which a noisy trajectory ``positions`` [T, 3] holds still.

    The positions are median-filtered over ``window`` frames per axis (per-frame jitter of
    an estimate is not motion), the speed at t is |s(t + h) - s(t - h)| / 2h with
    h = window // 2 (one-sided at the ends), and a frame is at rest where that is below
    ``speed`` x ``size`` per frame, in runs of at least ``min_run`` frames.
    """
    T = int(positions.shape[0])
    rest = torch.zeros(T, dtype=torch.bool, device=positions.device)
    if T < max(min_run, 2) or size <= 0:
        return rest
    h = window // 2
    p = positions.detach().double()
    pad = torch.cat([p[:1].expand(h, 3), p, p[-1:].expand(h, 3)])
    smooth = pad.unfold(0, 2 * h + 1, 1).median(dim=-1).values  # [T, 3]
    idx = torch.arange(T, device=positions.device)
    lo, hi = (idx - h).clamp(min=0), (idx + h).clamp(max=T - 1)
    v = (smooth[hi] - smooth[lo]).norm(dim=-1) / (hi - lo).clamp(min=1)
    still = v < speed * size
    t = 0
    while t < T:
        if not still[t]:
            t += 1
            continue
        e = t
        while e < T and still[e]:
            e += 1
        if e - t >= min_run:
            rest[t:e] = True
        t = e
    return rest


def fit_initial_trajectory(prior_t: Tensor, prior_q: Tensor, cfg: ObjectConfig) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Keyframes (times, p, v, q) fitted to the initial per-frame poses."""
    T = prior_t.shape[0]
    frame_times = torch.arange(T, dtype=torch.float64, device=prior_t.device)
    K = max(2, int(np.ceil((T - 1) / cfg.frames_per_keyframe)) + 1)
    key_times = uniform_keyframe_times(frame_times, K)
    # No rotation smoothing in the fit: a handled object can spin by 20 degrees a frame, and
    # the smoothing term flattens such turns (tens of degrees of error); the keyframe spacing
    # already removes per-frame jitter.
    p, v, q = fit_keyframes(frame_times, prior_t.double(), prior_q.double(), keyframe_times=key_times,
                            rotation_smoothing=0.0)
    return key_times, p, v, q


def _dilate(mask: np.ndarray, px: int) -> np.ndarray:
    if px <= 0:
        return mask
    import cv2

    k = np.ones((2 * px + 1, 2 * px + 1), np.uint8)
    return cv2.dilate(mask.astype(np.uint8), k) > 0


def carve_visual_hull(
    object_masks: np.ndarray,  # [T, H, W] bool
    human_masks: np.ndarray,  # [T, H, W] bool
    Ks: np.ndarray,  # [T, 3, 3]
    w2cs: np.ndarray,  # [T, 4, 4]
    translations: np.ndarray,  # [T, 3] object pose per frame
    rotations: np.ndarray,  # [T, 3, 3]
    centre: np.ndarray,  # [3] canonical pivot
    frames: list[int],
    cfg: ObjectConfig,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Canonical surface points [M, 3] of the voted visual hull, their outward normals
    [M, 3] (gradient of the smoothed occupancy), and the voxel size."""
    T, H, W = object_masks.shape
    used = [t for t in frames if object_masks[t].any()]
    if not used:
        return np.zeros((0, 3)), np.zeros((0, 3)), 0.0
    # Apparent size -> metric radius, per frame, from the mask's bounding box and depth.
    radii = []
    for t in used:
        ys, xs = np.nonzero(object_masks[t])
        extent_px = max(xs.max() - xs.min() + 1, ys.max() - ys.min() + 1)
        z = (w2cs[t, :3, :3] @ translations[t] + w2cs[t, :3, 3])[2]
        if z > 0:
            radii.append(0.5 * extent_px / Ks[t, 0, 0] * z)
    half = cfg.hull_margin * float(np.median(radii)) if radii else 0.3
    n = cfg.hull_resolution
    ax = (np.arange(n) + 0.5) / n * 2 * half - half
    grid = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3) + centre
    inside = np.zeros(len(grid))
    decided = np.zeros(len(grid))
    for t in used:
        world = (grid - centre) @ rotations[t].T + translations[t]
        cam = world @ w2cs[t, :3, :3].T + w2cs[t, :3, 3]
        z = cam[:, 2]
        u = Ks[t, 0, 0] * cam[:, 0] / np.maximum(z, 1e-6) + Ks[t, 0, 2]
        v = Ks[t, 1, 1] * cam[:, 1] / np.maximum(z, 1e-6) + Ks[t, 1, 2]
        ok = (z > 1e-3) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        ui, vi = u[ok].astype(int), v[ok].astype(int)
        om = _dilate(object_masks[t], cfg.hull_dilate_px)[vi, ui]
        hm = human_masks[t][vi, ui]
        idx = np.flatnonzero(ok)
        inside[idx] += om
        decided[idx] += om | ~hm  # on the person and not on the object: occluded, abstain
    keep = (decided >= 2) & (inside >= cfg.hull_keep_fraction * decided)
    vox = keep.reshape(n, n, n)
    if not vox.any():
        return np.zeros((0, 3)), np.zeros((0, 3)), 2 * half / n
    pad = np.pad(vox, 1)
    interior = pad[2:, 1:-1, 1:-1] & pad[:-2, 1:-1, 1:-1] & pad[1:-1, 2:, 1:-1] & pad[1:-1, :-2, 1:-1] & pad[1:-1, 1:-1, 2:] & pad[1:-1, 1:-1, :-2]
    surface = (vox & ~interior).reshape(-1)
    from scipy.ndimage import gaussian_filter

    occ = gaussian_filter(vox.astype(np.float64), 1.0)
    grad = np.stack(np.gradient(occ), axis=-1).reshape(-1, 3)[surface]
    normals = -grad / np.maximum(np.linalg.norm(grad, axis=1, keepdims=True), 1e-9)
    return grid[surface], normals, 2 * half / n
