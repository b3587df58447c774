"""The human branch: canonical Gaussians posed by linear blend skinning of a body model.

Pieces (CoGS, with the field of HUGS):

* `sample_human_seed` — the canonical seed G^H_0: Gaussians spread area-uniformly on the
  body model's zero-pose surface, flat discs tangent to it, sized from the sample spacing,
  with barycentric skinning weights. The anchor loss pulls weakly observed Gaussians back
  to it.
* `TriplaneField` — three feature planes over the canonical body box, sampled bilinearly
  at each canonical Gaussian and decoded by small MLPs into residuals of colour, opacity,
  scale, rotation and skinning weights over the seed. Every head's last layer starts at
  zero, so the untrained field reproduces the seed exactly.
* `HumanBranch` — the trainable module: free canonical positions, the field, optional
  per-frame body-pose refinements, and the per-Gaussian visibility scores v_i used by the
  anchor loss (w_i = 1 - v_i).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from cogs.body import BodyModel, lbs_gaussians, load_body_model
from cogs.branches.base import Branch, Splats, register
from cogs.branches.gaussians import GaussianSet, inverse_sigmoid, rgb_to_sh0
from cogs.branches.held_out import as_tensors, blend, detail, lagrange_neighbours
from cogs.branches.shading import Irradiance
from cogs.branches.surgery import SPLIT_SHRINK, BranchGaussians, Geometry
from cogs.geometry.rotations import (
    axis_angle_to_quat,
    quat_geodesic_angle,
    quat_multiply,
    quat_normalize,
    quat_sign_continuous,
    rotmat_from_two_vectors,
    quat_to_rotmat,
    rotmat_to_quat,
    quat_to_axis_angle,
)


@dataclass
class HumanConfig:
    """Human-branch hyper-parameters (defaults: CoGS/HUGS values scaled for CPU)."""

    n_gaussians: int = 20_000
    """Seed size: Gaussians sampled on the canonical body surface (paper: 20k-100k)."""
    seed_opacity: float = 0.8
    """Initial opacity of the seed."""
    seed_thickness: float = 0.3
    """Seed discs' extent along the surface normal, relative to their tangent extent."""
    seed_scale_factor: float = 0.6
    """Tangent standard deviation as a fraction of the mean sample spacing."""
    seed_inset_m: float = 0.015
    """Seed centres sit this far inside the body surface, along its normal (metres). Discs
    centred on the surface stick out of the silhouette where it is seen edge-on, so the
    seed renders wider than the body and biases the mask-driven pose alignment of stage
    I. 0 puts them on the surface (the HUGS seed). Chosen on the demo scene alone (the
    seed posed with the true poses against the true masks); not yet checked on others."""
    triplane_resolution: int = 128
    triplane_channels: int = 16
    triplane_padding_m: float = 0.1
    """Margin around the canonical body box covered by the triplane."""
    mlp_width: int = 64
    max_log_scale_change: float = 1.5
    """Bound on the decoded log-scale residual (the field cannot grow a Gaussian by more
    than e^1.5 = 4.5x nor shrink it more)."""
    per_gaussian_color: bool = True
    """Add a free per-Gaussian colour residual to the field's colour (sharper texture for
    the same triplane resolution; the field alone is the HUGS formulation)."""
    shading: bool = True
    """Albedo x irradiance of the posed normal (light fixed in the world; see shading.py)."""
    refine_pose: bool = True
    """Learn corrections of the input body pose and translation."""
    per_frame_pose: bool = True
    """Also learn a per-frame residual on top of the keyframed correction, for the
    estimator's frame-to-frame jitter. Only training frames are fitted; a held-out frame
    takes the pose its fitted neighbours interpolate to (`held_out_pose`), so it is posed
    consistently with the frames the appearance was learned on and never fitted to its
    own image. Adopted on the demo scene (held-out human IoU and crop)."""
    held_out_neighbours: int = 2
    """Fitted training frames used on each side of a held-out frame (within
    `held_out_max_gap` frames): 2 gives a cubic interpolation, 1 a linear one."""
    held_out_max_gap: int = 3
    """Farthest neighbour (frames) a held-out frame's interpolation may use."""
    held_out_input_weight: float = 0.3
    """How much of the held-out frame's own input motion its pose keeps (with
    `held_out_adaptive`, at least): the neighbours' interpolated fits, turned by this
    fraction of the rotation (and moved by this fraction of the translation) by which the
    frame's input departs from its neighbours' interpolated inputs. That departure is the
    motion the interpolation misses (signal) plus the estimator's jitter on that frame
    (noise), so the best weight is a shrinkage between 0 (the neighbours alone) and 1 (all
    of the input's detail, all of its jitter). Chosen by leave-one-out on the demo scene's
    training frames alone (joints against the truth); on the three scenes of
    `held_out_adaptive` it beat 0 at their own frame rates, and 1 on the demo scene (not
    re-chosen on three scenes; docs/experiments/2026-11-27-held-out-poses.md)."""
    held_out_adaptive: bool = False
    """Where a held-out frame's input departs from its neighbours by far more than the
    estimator's jitter, keep more of the frame's own motion: per refined bone and frame the
    share is max(`held_out_input_weight`, 1 - c s^2 / |d|^2) (c = `held_out_noise_factor`),
    d the frame's input departure from its neighbours (as above) and s^2 the estimator's
    noise on that bone: the mean squared disagreement between the input's and the fitted
    poses' departures over the training frames, each left out of its own neighbours (a
    positive-part James-Stein shrinkage); the translation likewise. Bones the training
    never corrects, and clips with too few fitted training frames, keep the fixed share.
    Turn it on for clips whose motion is fast against the frame rate (a swing subsampled
    with `--stride`): on the demo scene, `cogs synth --seed 7 --frames 80 --fps 15` and
    the basketball clip with their training frames thinned to every 2nd-3rd it posed the
    held-out frames better on all three; at their own frame rates it was even on the
    synthetic scenes and worse on the basketball clip (an estimator's occasional large
    error looks like motion), hence off by default
    (docs/experiments/2026-11-27-held-out-poses.md)."""
    held_out_noise_factor: float = 4.0
    """c above: how many times the estimated noise a departure's square must exceed before
    more than the fixed share of it is kept. Chosen with `held_out_adaptive` on the same
    runs thinned to every 2nd-3rd frame (2, 4, 6, 8 tried)."""
    pose_keyframe_every: float = 12.0
    """The corrections are a smooth function of time: linear between keyframes this many
    frames apart. Every training view then updates the correction of its neighbours too,
    and held-out frames get the interpolated correction without ever being fitted. The
    estimator's error is a slow drift plus per-frame jitter (which `per_frame_pose`
    takes), so the spacing should match the drift's time scale. Chosen on the demo scene
    alone, whose synthetic estimator drifts on a ~10-frame time scale (held-out joints
    after stage II, whole-run human IoU): it is fitted to that generator's drift. On
    footage whose estimator drifts faster, lower it."""
    visibility_epsilon: float = 0.01
    """chi_it needs the Gaussian's summed compositing weight inside the human mask (in
    pixel units) above this."""
    visibility_max_frames: int = 120
    """The visibility scores are counted on at most this many training frames, evenly
    spaced (counts scaled to the whole), so refreshing them costs a bounded number of
    renders however long the clip; 0 counts on every frame. A cost bound, not a tuned
    value (the demo's 84 training frames are all used)."""
    visibility_full_frames: int = 5
    """v_i = min(1, training frames that see Gaussian i / this): a Gaussian seen in this many
    frames counts as observed and is free, and only parts few frames see are held to the
    seed. 0 gives CoGS's fraction of the training frames, whose anchor weight 1 - v_i
    depends on the clip's length (a Gaussian seen in half of a long clip's frames stays
    held at half weight). Chosen on the demo scene alone (held-out and novel-view human);
    not yet checked on others."""


@dataclass
class HumanSeed:
    """The canonical seed G^H_0 (all float32, activated values)."""

    means: Tensor  # [N, 3] canonical
    quats: Tensor  # [N, 4] wxyz, z axis along the surface normal
    scales: Tensor  # [N, 3] metres
    opacities: Tensor  # [N]
    colors: Tensor  # [N, 3]
    weights: Tensor  # [N, J] skinning weights
    normals: Tensor  # [N, 3]
    face_index: Tensor | None = None  # [N] the body triangle each was sampled on


def sample_human_seed(body: BodyModel, shape: Tensor | None, cfg: HumanConfig, seed: int = 0) -> HumanSeed:
    """Area-uniform samples on the canonical surface with barycentric skinning weights.

    Sampled on the host from a seeded generator (the same seed on every device), returned
    on the body model's device."""
    can = body.canonical(shape)
    dev = can.vertices.device
    cpu = torch.device("cpu")
    V, Fc = can.vertices.double().to(cpu), can.faces.to(cpu)
    a, b, c = V[Fc[:, 0]], V[Fc[:, 1]], V[Fc[:, 2]]
    cross = torch.linalg.cross(b - a, c - a, dim=-1)
    area = 0.5 * cross.norm(dim=-1)
    g = torch.Generator(device=cpu).manual_seed(seed)
    n = cfg.n_gaussians
    face = torch.multinomial(area / area.sum(), n, replacement=True, generator=g)
    r1 = torch.rand(n, generator=g, dtype=torch.float64, device=cpu)
    r2 = torch.rand(n, generator=g, dtype=torch.float64, device=cpu)
    s = r1.sqrt()
    bary = torch.stack([1 - s, s * (1 - r2), s * r2], dim=1)  # uniform on the triangle
    tri = Fc[face]
    normals = F.normalize(cross[face], dim=-1)
    means = (bary[:, :, None] * V[tri]).sum(1) - cfg.seed_inset_m * normals
    weights = (bary[:, :, None] * can.weights.double().to(cpu)[tri]).sum(1)
    weights = weights / weights.sum(1, keepdim=True)
    spacing = float(torch.sqrt(area.sum() / n))
    tangent = cfg.seed_scale_factor * spacing
    scales = torch.tensor([tangent, tangent, cfg.seed_thickness * tangent], device=cpu).expand(n, 3)
    R = rotmat_from_two_vectors(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64, device=cpu).expand(n, 3), normals)
    return HumanSeed(
        means=means.float().to(dev),
        quats=rotmat_to_quat(R).float().to(dev),
        scales=scales.float().clone().to(dev),
        opacities=torch.full((n,), cfg.seed_opacity, device=dev),
        colors=torch.full((n, 3), 0.5, device=dev),
        weights=weights.float().to(dev),
        normals=normals.float().to(dev),
        face_index=face.to(dev),
    )


class TriplaneField(torch.nn.Module):
    """Triplane features over a canonical box, decoded into residual attributes."""

    def __init__(self, box_min: Tensor, box_max: Tensor, n_bones: int, cfg: HumanConfig):
        super().__init__()
        R, C, W = cfg.triplane_resolution, cfg.triplane_channels, cfg.mlp_width
        self.register_buffer("box_min", box_min.float().clone())
        self.register_buffer("box_max", box_max.float().clone())
        dev = box_min.device
        cpu = torch.device("cpu")  # drawn on the host: the same planes on every device
        planes = 0.1 * torch.randn(3, C, R, R, generator=torch.Generator(device=cpu).manual_seed(0), device=cpu)
        self.planes = torch.nn.Parameter(planes.to(dev))

        def mlp(out: int) -> torch.nn.Sequential:
            net = torch.nn.Sequential(torch.nn.Linear(3 * C, W, device=dev), torch.nn.ReLU(), torch.nn.Linear(W, out, device=dev))
            torch.nn.init.zeros_(net[2].weight)
            torch.nn.init.zeros_(net[2].bias)
            return net

        self.appearance = mlp(3)  # colour residual
        self.geometry = mlp(1 + 3 + 3)  # opacity logit, log-scale, rotation (axis-angle) residuals
        self.deformation = mlp(n_bones)  # skinning-weight logit residuals

    def features(self, x: Tensor) -> Tensor:
        """x [N, 3] canonical -> [N, 3C] bilinear samples of the xy, xz and yz planes."""
        u = 2.0 * (x - self.box_min) / (self.box_max - self.box_min) - 1.0
        grids = torch.stack([u[:, [0, 1]], u[:, [0, 2]], u[:, [1, 2]]])  # [3, N, 2]
        f = F.grid_sample(self.planes, grids[:, :, None, :], mode="bilinear", padding_mode="border", align_corners=True)
        return f[..., 0].permute(2, 0, 1).reshape(x.shape[0], -1)  # [N, 3C]

    def forward(self, x: Tensor) -> dict[str, Tensor]:
        f = self.features(x)
        geo = self.geometry(f)
        return {
            "color": self.appearance(f),
            "opacity": geo[:, 0],
            "log_scale": geo[:, 1:4],
            "rotation": geo[:, 4:7],
            "skinning": self.deformation(f),
        }


@dataclass
class HumanState:
    """Decoded canonical attributes of every human Gaussian (activated)."""

    means: Tensor  # [N, 3] canonical
    quats: Tensor  # [N, 4]
    scales: Tensor  # [N, 3]
    opacities: Tensor  # [N]
    colors: Tensor  # [N, 3]
    weights: Tensor  # [N, J]


@register
class HumanBranch(Branch):
    """Canonical human Gaussians, their field, pose refinements and visibility."""

    name = "human"
    # Per-Gaussian tensors density control must gather together.
    PER_GAUSSIAN_PARAMS = ("means", "color_residual")
    PER_GAUSSIAN_BUFFERS = ("seed_means", "seed_quats", "seed_scales", "seed_opacities", "seed_colors", "seed_weights", "visibility")

    def __init__(
        self,
        body: BodyModel,
        shape: Tensor,
        seed: HumanSeed,
        base_pose: Tensor,  # [T, J, 3] input poses
        base_transl: Tensor,  # [T, 3]
        cfg: HumanConfig,
        train_frames: list[int] | None = None,  # frames the training may fit (None: all)
    ):
        super().__init__()
        dev = seed.means.device
        # Not registered as a submodule: the body model is shared, rebuilt from its name,
        # and must not enter checkpoints.
        object.__setattr__(self, "body", body)
        self.cfg = cfg
        self.register_buffer("shape", shape.float().clone())
        self.means = torch.nn.Parameter(seed.means.clone())
        self.color_residual = torch.nn.Parameter(torch.zeros_like(seed.colors))
        self.register_buffer("seed_means", seed.means.clone())
        self.register_buffer("seed_quats", seed.quats.clone())
        self.register_buffer("seed_scales", seed.scales.clone())
        self.register_buffer("seed_opacities", seed.opacities.clone())
        self.register_buffer("seed_colors", seed.colors.clone())
        self.register_buffer("seed_weights", seed.weights.clone())
        self.register_buffer("visibility", torch.zeros(len(seed.means), device=dev))
        self.shading = Irradiance(device=dev)
        pad = cfg.triplane_padding_m
        self.field = TriplaneField(seed.means.min(0).values - pad, seed.means.max(0).values + pad, body.n_bones, cfg)
        T = base_pose.shape[0]
        self.register_buffer("base_pose", base_pose.float().clone())
        self.register_buffer("base_transl", base_transl.float().clone())
        K = max(2, int(np.ceil((T - 1) / cfg.pose_keyframe_every)) + 1)
        key_times = torch.linspace(0.0, float(T - 1), K, device="cpu")
        # The pose keyframe times, also on the host: frame-time lookups need no device sync.
        self._key_times = key_times.numpy()
        self.register_buffer("pose_key_times", key_times.to(dev))
        major = torch.tensor([body.bone_index(b) for b in body.major_bones], device=dev)
        self.register_buffer("refined_bones", major)
        self.pose_delta = torch.nn.Parameter(torch.zeros(K, len(major), 3, device=dev))
        self.transl_delta = torch.nn.Parameter(torch.zeros(K, 3, device=dev))
        self.frame_pose_delta = torch.nn.Parameter(torch.zeros(T, len(major), 3, device=dev))
        self.frame_transl_delta = torch.nn.Parameter(torch.zeros(T, 3, device=dev))
        # Which frames the training fits (saved, so a loaded model poses held-out frames
        # without its scene), and the same as a host list for per-frame decisions.
        self._trained = [False] * T
        for t in (range(T) if train_frames is None else train_frames):
            self._trained[int(t)] = True
        self.register_buffer("trained", torch.tensor(self._trained, dtype=torch.bool, device=dev))

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def n_frames(self) -> int:
        return int(self.base_pose.shape[0])

    @classmethod
    def from_state(cls, state: dict[str, Tensor], cfg, body=None) -> "HumanBranch":
        """The branch rebuilt from a state dict (its `BranchesConfig` and body model given)."""
        assert body is not None, "the human branch needs its body model"
        seed = HumanSeed(means=state["seed_means"], quats=state["seed_quats"], scales=state["seed_scales"],
                         opacities=state["seed_opacities"], colors=state["seed_colors"],
                         weights=state["seed_weights"], normals=torch.zeros_like(state["seed_means"]))
        train = torch.nonzero(state["trained"]).flatten().tolist()
        human = cls(body, state["shape"], seed, state["base_pose"], state["base_transl"], cfg.human, train_frames=train)
        human.load_state_dict(state)
        return human

    # -- canonical attributes ----------------------------------------------------------
    def decode(self) -> HumanState:
        """Seed + field residuals at the current canonical positions."""
        r = self.field(self.means)
        scales = self.seed_scales * torch.exp(self.cfg.max_log_scale_change * torch.tanh(r["log_scale"] / self.cfg.max_log_scale_change))
        quats = quat_normalize(quat_multiply(self.seed_quats, axis_angle_to_quat(r["rotation"])))
        opacities = torch.sigmoid(inverse_sigmoid(self.seed_opacities) + r["opacity"])
        colors = self.seed_colors + r["color"]
        if self.cfg.per_gaussian_color:
            colors = colors + self.color_residual
        weights = torch.softmax(torch.log(self.seed_weights.clamp_min(1e-8)) + r["skinning"], dim=-1)
        return HumanState(self.means, quats, scales, opacities, colors.clamp(0.0, 1.0), weights)

    def prepare(self) -> HumanState:
        return self.decode()

    # -- pose --------------------------------------------------------------------------
    def frame_pose(self, t: float) -> tuple[Tensor, Tensor]:
        """Body pose [1, J, 3] and translation [1, 3] at frame t, corrections included.

        The smooth correction is interpolated between pose keyframes; a training frame adds
        its own residual (`per_frame_pose`), and a held-out frame then takes its
        neighbours' fitted poses instead (`held_out_pose`). No test image is ever fitted.
        """
        if not self.cfg.refine_pose:
            return self.base_pose[t : t + 1], self.base_transl[t : t + 1]
        if self.cfg.per_frame_pose and not self._trained[t]:
            return self.held_out_pose(t)
        dp, dt = self._refinement(float(t))
        if self.cfg.per_frame_pose:
            dp = dp + self.frame_pose_delta[t : t + 1]
            dt = dt + self.frame_transl_delta[t : t + 1]
        pose = self.base_pose[t : t + 1].index_add(1, self.refined_bones, dp)
        return pose, self.base_transl[t : t + 1] + dt

    @torch.no_grad()
    def held_out_pose(self, t: int) -> tuple[Tensor, Tensor]:
        """Pose [1, J, 3] and translation [1, 3] of a frame the training never fitted.

        Every bone and the translation are interpolated from the fitted poses (input,
        smooth correction and per-frame residual) of the nearest training frames on each
        side: the Lagrange polynomial through up to `held_out_neighbours` of them per side,
        quaternions blended per bone. A share of the frame's own input detail (its input
        against the same interpolation of its neighbours' inputs) is added back: decided
        per bone from the clip's own noise (`held_out_adaptive`), or the fixed
        `held_out_input_weight`. A frame without a training neighbour on both sides within
        `held_out_max_gap` (the clip's ends) keeps its corrected input. No image of frame t
        is looked at; its input pose is, as an estimator's output for every frame.
        """
        nb = lagrange_neighbours(t, self._trained, self.cfg.held_out_neighbours, self.cfg.held_out_max_gap)
        if nb is None:
            dp, dt = self._refinement(float(t))
            return self.base_pose[t : t + 1].index_add(1, self.refined_bones, dp), self.base_transl[t : t + 1] + dt
        quats, transl = self._fitted_poses()
        q_in = quat_sign_continuous(axis_angle_to_quat(self.base_pose))
        q, tr = blend(quats, transl, *as_tensors(nb, transl))
        d, d_t = detail(q_in, self.base_transl, t, nb)
        w, w_t = self._input_shares(d, d_t)
        q = quat_multiply(axis_angle_to_quat(w[:, None] * d), q)
        return quat_to_axis_angle(q)[None], (tr + w_t * d_t)[None]

    def _input_shares(self, detail: Tensor, detail_t: Tensor) -> tuple[Tensor, Tensor]:
        """Share of a held-out frame's input detail kept per bone [J] and for the
        translation [] (see `held_out_adaptive`)."""
        fixed = detail.new_full(detail.shape[:1], self.cfg.held_out_input_weight)
        fixed_t = detail_t.new_tensor(self.cfg.held_out_input_weight)
        noise = self._input_noise() if self.cfg.held_out_adaptive else None
        if noise is None:
            return fixed, fixed_t
        c = self.cfg.held_out_noise_factor
        s2, s2_t = noise
        shrink = lambda d2, s: (1.0 - c * s / d2.clamp_min(1e-20)).clamp(0.0, 1.0)  # noqa: E731
        w = fixed.clone()
        major = self.refined_bones
        w[major] = shrink(detail[major].square().sum(-1), s2).clamp_min(self.cfg.held_out_input_weight)
        return w, shrink(detail_t.square().sum(), s2_t).clamp_min(self.cfg.held_out_input_weight)

    @torch.no_grad()
    def _input_noise(self) -> tuple[Tensor, Tensor] | None:
        """The input estimator's noise in a frame's departure from its neighbours, per
        refined bone [B] (radians^2) and for the translation [] (m^2): the mean squared
        difference between the input's and the fitted poses' departures over the training
        frames, each interpolated from its own training neighbours (itself left out).
        None with fewer than `_MIN_NOISE_FRAMES` such frames. Cached until a pose
        parameter, the training frames or the neighbour settings change."""
        key = (tuple(self._trained), self.cfg.held_out_neighbours, self.cfg.held_out_max_gap,
               *(p._version for p in (self.pose_delta, self.transl_delta, self.frame_pose_delta,
                                      self.frame_transl_delta, self.base_pose, self.base_transl)))
        cached = getattr(self, "_noise_cache", None)
        if cached is not None and cached[0] == key:
            return cached[1]
        quats, transl = self._fitted_poses()
        q_in = quat_sign_continuous(axis_angle_to_quat(self.base_pose))
        major = self.refined_bones
        sq, sq_t, n = torch.zeros_like(quats[0, major, 0]), transl.new_zeros(()), 0
        for t in (k for k, trained in enumerate(self._trained) if trained):
            others = list(self._trained)
            others[t] = False
            nb = lagrange_neighbours(t, others, self.cfg.held_out_neighbours, self.cfg.held_out_max_gap)
            if nb is None:
                continue
            d_in, dt_in = detail(q_in, self.base_transl, t, nb)
            d_fit, dt_fit = detail(quats, transl, t, nb)
            sq += (d_in[major] - d_fit[major]).square().sum(-1)
            sq_t += (dt_in - dt_fit).square().sum()
            n += 1
        noise = (sq / n, sq_t / n) if n >= _MIN_NOISE_FRAMES else None
        object.__setattr__(self, "_noise_cache", (key, noise))
        return noise

    def _fitted_poses(self) -> tuple[Tensor, Tensor]:
        """Every frame's bone rotations [T, J, 4] (wxyz, sign-continuous along time per
        bone) and translations [T, 3] as the training has them: input, smooth correction
        and per-frame residual (zero on frames never fitted)."""
        refs = [self._refinement(float(k)) for k in range(self.n_frames)]
        dp = torch.cat([r[0] for r in refs])
        dt = torch.cat([r[1] for r in refs])
        aa = self.base_pose.index_add(1, self.refined_bones, dp + self.frame_pose_delta)
        return quat_sign_continuous(axis_angle_to_quat(aa)), self.base_transl + dt + self.frame_transl_delta

    def _refinement(self, t: float) -> tuple[Tensor, Tensor]:
        times = self._key_times  # float32, host: the same arithmetic as on the buffer, no sync
        k = int(np.clip(np.searchsorted(times, np.float32(t), side="right"), 1, len(times) - 1)) - 1
        u = min(max((t - float(times[k])) / float(times[k + 1] - times[k]), 0.0), 1.0)
        return (
            (1 - u) * self.pose_delta[k : k + 1] + u * self.pose_delta[k + 1 : k + 2],
            (1 - u) * self.transl_delta[k : k + 1] + u * self.transl_delta[k + 1 : k + 2],
        )

    def _apply(self, fn, *args, **kwargs):
        # The body model is kept out of the module tree (shared, not checkpointed): moving the
        # branch on its own (the trainer moves each branch it builds) must move it along.
        out = super()._apply(fn, *args, **kwargs)
        dev = self.means.device
        if self.body.device != dev:
            object.__setattr__(self, "body", load_body_model(self.body.name, dev))
        return out

    def posed(self, pose: Tensor, transl: Tensor, state: HumanState | None = None) -> HumanState:
        """Skin the canonical Gaussians into the world for one pose ([1, J, 3], [1, 3])."""
        state = self.decode() if state is None else state
        A, _ = self.body.bone_transforms(pose, transl, self.shape)
        means, quats = lbs_gaussians(state.means, state.quats, state.weights, A[0])
        colors = state.colors
        if self.cfg.shading:
            colors = colors * self.shading(quat_to_rotmat(quats)[:, :, 2])  # seed discs: local z = normal
        return HumanState(means, quats, state.scales, state.opacities, colors, state.weights)

    def posed_frame(self, t: int, state: HumanState | None = None) -> HumanState:
        pose, transl = self.frame_pose(t)
        return self.posed(pose, transl, state)

    def splats(self, frame: int, campos: Tensor, pose: tuple[Tensor, Tensor] | None = None,
               prepared: HumanState | None = None) -> Splats:
        """The posed human at `frame`, or in `pose` = (body pose [1, J, 3], translation [1, 3])."""
        p = self.posed(*pose, prepared) if pose is not None else self.posed_frame(frame, prepared)
        return Splats(p.means, p.quats, p.scales, p.opacities, p.colors)

    # -- training ------------------------------------------------------------------------
    def param_groups(self, lr, extent: float) -> list[dict]:
        groups = [
            {"params": [self.means], "lr": lr.human_means, "name": "means"},
            {"params": [self.color_residual], "lr": lr.human_color, "name": "color"},
            {"params": list(self.field.parameters()), "lr": lr.human_field, "name": "field"},
            {"params": list(self.shading.parameters()), "lr": lr.shading, "name": "shading"},
        ]
        if self.cfg.refine_pose:
            groups += [
                {"params": [self.pose_delta, self.frame_pose_delta], "lr": lr.human_pose, "name": "pose"},
                {"params": [self.transl_delta, self.frame_transl_delta], "lr": lr.human_transl, "name": "transl"},
            ]
        return groups

    def density_adapter(self) -> "HumanGaussians":
        return HumanGaussians(self)

    def extent(self, scene_extent: float) -> float:
        return 1.0  # metres: a body's size

    def regularisers(self, weights, frames: Tensor, prepared: HumanState | None = None) -> dict[str, Tensor]:
        """`anchor`: visibility-aware anchoring of the decoded state `prepared` to the seed;
        `pose_reg`: the size of the pose corrections."""
        terms = {}
        if weights.get("anchor", 0) > 0:
            terms["anchor"] = weights["anchor"] * self.anchor_loss(prepared, weights["anchor_scale"], weights["anchor_rotation"],
                                                                   weights["anchor_opacity"])
        if self.cfg.refine_pose and weights.get("pose_refine_reg", 0) > 0:
            terms["pose_reg"] = weights["pose_refine_reg"] * self.pose_regularizer()
        return terms

    def anchor_loss(self, state: HumanState, lambda_s: float = 1.0, lambda_q: float = 0.1, lambda_a: float = 0.1) -> Tensor:
        """CoGS visibility-aware anchoring, mean over Gaussians:

        w_i (|mu_i - mu0_i|_1 + lambda_s |s_i - s0_i|_1 + lambda_q d_R(q_i, q0_i)
        + lambda_a |alpha_i - alpha0_i|), with w_i = 1 - v_i detached.
        """
        w = (1.0 - self.visibility).detach()
        term = (
            (state.means - self.seed_means).abs().sum(-1)
            + lambda_s * (state.scales - self.seed_scales).abs().sum(-1)
            + lambda_q * quat_geodesic_angle(state.quats, self.seed_quats)
            + lambda_a * (state.opacities - self.seed_opacities).abs()
        )
        return (w * term).mean()

    def pose_regularizer(self) -> Tensor:
        """Keep the corrections small: squared angle per bone summed over the bones, and the
        squared translation (metres), averaged over keyframes."""
        reg = self.pose_delta.square().sum((1, 2)).mean() + self.transl_delta.square().sum(1).mean()
        if self.cfg.per_frame_pose:  # the jitter residual is held tighter than the smooth correction
            reg = reg + 4.0 * (self.frame_pose_delta.square().sum((1, 2)).mean() + self.frame_transl_delta.square().sum(1).mean())
        return reg

    # -- outputs -------------------------------------------------------------------------
    @torch.no_grad()
    def canonical_set(self) -> GaussianSet:
        """The decoded canonical human as a plain GaussianSet (raw parameters)."""
        st = self.decode()
        return GaussianSet({
            "means": st.means, "quats": st.quats, "scales": torch.log(st.scales),
            "opacities": inverse_sigmoid(st.opacities), "sh0": rgb_to_sh0(st.colors),
        }, 0)

    def export(self, folder: Path, n_frames: int) -> list[Path]:
        """The canonical Gaussians (3DGS PLY) and every frame's refined body pose."""
        ply, npz = folder / "human_canonical.ply", folder / "body_refined.npz"
        self.canonical_set().save_ply(ply)
        with torch.no_grad():
            poses = [self.frame_pose(t) for t in range(n_frames)]
        np.savez_compressed(npz, pose=torch.cat([p for p, _ in poses]).cpu().numpy(),
                            transl=torch.cat([t for _, t in poses]).cpu().numpy())
        return [ply, npz]


class HumanGaussians(BranchGaussians):
    """Density adapter of the human: its free positions and colour residuals with the seed
    buffers beside them; geometry decoded from the field."""

    def __init__(self, human: HumanBranch):
        super().__init__(human, {k: (human, k) for k in HumanBranch.PER_GAUSSIAN_PARAMS}, HumanBranch.PER_GAUSSIAN_BUFFERS)
        self.human = human

    def geometry(self) -> Geometry:
        with torch.no_grad():
            st = self.human.decode()
        return Geometry(st.means.detach(), st.scales.detach(), st.quats.detach(), st.opacities.detach())

    def split_children(self, sel: Tensor, offsets: Tensor) -> dict[str, Tensor]:
        h = self.human
        rep = lambda t: t.detach()[sel].repeat(2, *([1] * (t.dim() - 1)))  # noqa: E731
        out = {"means": rep(h.means) + offsets, "color_residual": rep(h.color_residual)}
        for name in self.buffers:
            out[name] = rep(getattr(h, name))
        out["seed_means"] = out["seed_means"] + offsets  # the prior moves with the child
        out["seed_scales"] = out["seed_scales"] / SPLIT_SHRINK
        return out


_MIN_NOISE_FRAMES = 5
"""Training frames with neighbours on both sides needed to estimate the input's noise
(`HumanBranch._input_noise`); below it the fixed `held_out_input_weight` applies."""


def visibility_indicator(
    contribution: Tensor,  # [N] summed compositing weight inside (human mask & not object mask)
    means2d: Tensor,  # [N, 2] pixel coordinates of the posed centres
    depth_ok: Tensor,  # [N] bool, in front of the camera
    mask: Tensor,  # [H, W] bool: human mask and not object mask
    epsilon: float,
) -> Tensor:
    """chi_it for one frame: inside the human mask, outside the object mask, and a human
    opacity contribution above epsilon."""
    H, W = mask.shape
    px = means2d.detach().floor().long()
    inside = (px[:, 0] >= 0) & (px[:, 0] < W) & (px[:, 1] >= 0) & (px[:, 1] < H) & depth_ok
    hit = torch.zeros_like(inside)
    hit[inside] = mask[px[inside, 1], px[inside, 0]]
    return hit & (contribution > epsilon)


def compute_visibility(
    human: "HumanBranch",
    frames: list[int],
    viewmats: Tensor,  # [T, 4, 4]
    Ks: Tensor,  # [T, 3, 3]
    width: int,
    height: int,
    person_mask: Callable[[int], Tensor],  # t -> [H, W] bool: human mask and not object mask
    backend: str = "auto",
) -> Tensor:
    """v_i = (1/|T|) sum_t chi_it over the given training frames (CoGS Sec. visibility),
    or min(1, sum_t chi_it / N) with `visibility_full_frames` = N > 0; counted on at most
    `visibility_max_frames` of them, evenly spaced, scaled to the whole.

    The human is rendered alone; its compositing weights are gathered inside
    (human mask and not object mask) by one backward pass per frame.
    """
    from cogs.branches.splatback import splat_statistics

    every = list(frames)
    cap = human.cfg.visibility_max_frames
    if cap > 0 and len(every) > cap:
        frames = [every[i] for i in np.linspace(0, len(every) - 1, cap).round().astype(int)]
    with torch.no_grad():
        state = human.decode()
    counts = torch.zeros(len(human), device=human.means.device)
    for t in frames:
        with torch.no_grad():
            posed = human.posed_frame(t, state)
        mask = person_mask(t)
        contrib, _, means2d = splat_statistics(
            posed.means, posed.quats, posed.scales, posed.opacities, viewmats[t], Ks[t],
            width, height, weight=mask.float(), backend=backend,
        )
        depth = (posed.means @ viewmats[t][:3, :3].T + viewmats[t][:3, 3])[:, 2]
        counts += visibility_indicator(contrib, means2d, depth > 0, mask, human.cfg.visibility_epsilon).float()
    n_full = human.cfg.visibility_full_frames
    if n_full <= 0:  # the fraction of the frames (a subset's estimates the whole's)
        return counts / max(len(frames), 1)
    if len(frames) < len(every):  # a subset's count stands for every training frame's
        counts = counts * (len(every) / len(frames))
    return (counts / n_full).clamp(max=1.0)
