"""Training configuration: the six-stage schedule, loss weights, density control and
learning rates as typed dataclasses, and the named presets.

A preset is a named `TrainConfig` (`paper` = the CoGS paper's iteration counts, `quick` =
scaled for a 2-core CPU); any field can be overridden with `--set path.to.field=value`
on the command line. Every run writes its resolved config to RUN/config.yaml.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass, field
from typing import Any

import yaml

from cogs.branches.build import BranchesConfig
from cogs.errors import UserError

STAGES = ("I", "II", "III", "IV", "V", "VI")  # what each does: cogs.train.stages


@dataclass
class Schedule:
    """Iterations per stage (CoGS: I 0-4k, II to 5k, III 0-4k, IV 4k-6k, V 0-5.5k, VI to 15k)."""

    I: int = 4000
    II: int = 1000
    III: int = 4000
    IV: int = 2000
    V: int = 5500
    VI: int = 9500
    single_stage: bool = False
    """Ablation "no curriculum": skip I-V and train every branch jointly for the sum of
    all iterations with every loss term from the first step."""

    def total(self) -> int:
        return sum(getattr(self, s) for s in STAGES)


@dataclass
class PoseRefit:
    """The training's last step, after stage VI: the body pose of every training frame
    fitted again against the finished model, with the appearance, the object and the
    scene frozen, pulled by the image alone (L1; the input masks are left out, their
    outline noise would pull the pose along). Held-out frames interpolate these poses.

    The poses stages I-II fitted were fitted against an appearance that V-VI then kept
    changing; refitted, they agree with the appearance the held-out frames are rendered
    with. Adopted on the demo scene, seeds 0 and 1 (docs/experiments/
    2026-11-25-curriculum-levers.md). `cogs eval`'s test-time fit uses the same loss and
    options on the held-out frames' own images (reported apart)."""

    steps: int = 20
    """Adam steps per frame; 0 skips the refit."""
    lr: float = 6e-3
    """Learning rate of the bone rotations (radians); the translation's is half of it."""
    reg: float = 0.01
    """Weight of the squared size of the correction (radians^2 summed over bones, plus
    m^2) against the image L1 averaged over the whole frame: without it the fit follows
    the image's noise. Chosen on the demo scene alone (seeds 0 and 1), by the joints'
    distance to the truth after the refit; not yet checked on other scenes."""
    pad: int = 8
    """Pixels around the person's rendered box that the fit renders (exact: nothing
    outside it changes with the pose)."""


@dataclass
class LossWeights:
    """Weights of every loss term (defaults follow 3DGS/HUGS/CoGS where they give one)."""

    l1: float = 0.8
    """RGB L1 (3DGS uses 0.8 L1 + 0.2 D-SSIM)."""
    dssim: float = 0.2
    # -- human (I, II; kept lighter in V, VI) --
    human_rgb: float = 1.0
    """Human-alone render on a random background vs the image outside the mask replaced by
    that background (CoGS: human-separated render)."""
    human_mask: float = 0.5
    """BCE between the human alpha and the human mask."""
    human_alpha_refine: float = 1.0
    """Stage II: extra weight on the human alpha (L1 to the mask)."""
    human_dice: float = 0.5
    human_edge: float = 0.5
    """Stage II: alpha error on a band around the mask boundary."""
    human_unpremultiplied: float = 0.2
    """Colour of the un-premultiplied human render (C / alpha) inside the mask."""
    anchor: float = 0.5
    """Visibility-aware anchoring to the seed (w_i = 1 - v_i)."""
    anchor_scale: float = 1.0
    anchor_rotation: float = 0.01
    anchor_opacity: float = 0.1
    pose_refine_reg: float = 1.0
    """Weight of the squared size of the pose corrections (radians^2 summed over bones, m^2)."""
    # -- object (III, IV; kept lighter in V, VI) --
    object_bce: float = 1.0
    object_dice: float = 1.0
    object_edge: float = 0.5
    object_rgb: float = 0.5
    object_unpremultiplied: float = 0.2
    pose_prior: float = 0.5
    """Translation part of the object pose prior, metres (L1)."""
    pose_prior_rotation: float = 0.02
    """Rotation part (geodesic, radians) of the pose prior."""
    acceleration: float = 50.0
    rotation_smoothness: float = 0.05
    rest_translation: float = 5.0
    """Mean movement (m) between consecutive frames where the initial trajectory is at rest
    (ObjectBranch.rest_frames): an object on a table stays put."""
    rest_rotation: float = 0.5
    """Mean turn (radians) between consecutive frames at rest."""
    # -- composition (V, VI) --
    compose_rgb: float = 1.0
    """Full-frame RGB term of the composite render (L1 + D-SSIM as above)."""
    compose_human_mask: float = 0.1
    compose_object_mask: float = 0.2
    plane: float = 1.0
    """Robust point-to-plane term on assigned scene Gaussians (only after the warm-up)."""
    plane_warmup_fraction: float = 0.3
    """Stage VI fraction before the plane term switches on (CoGS: delayed plane term)."""


@dataclass
class Density:
    """Adaptive density control for one branch (3DGS / gsplat DefaultStrategy semantics)."""

    enabled: bool = True
    grad_threshold: float = 0.0002
    """Mean screen-space positional gradient (NDC units, as 3DGS) above which a Gaussian
    is cloned (small) or split (large)."""
    split_scale: float = 0.01
    """Largest axis, relative to the branch extent, separating clone from split."""
    prune_opacity: float = 0.005
    prune_scale: float = 0.1
    """Prune Gaussians whose largest axis exceeds this fraction of the branch extent."""
    refine_every: int = 100
    start_fraction: float = 0.0
    """Fraction of the stage before density control starts."""
    stop_fraction: float = 0.8
    max_gaussians: int = 200_000
    clone_only: bool = False
    """Never split (conservative topology)."""


@dataclass
class LearningRates:
    scene_means: float = 1.6e-4
    """Times the scene extent, decayed x0.01 over the stage (3DGS)."""
    scene_sh0: float = 2.5e-3
    scene_shN: float = 1.25e-4
    scene_opacities: float = 0.05
    scene_scales: float = 5e-3
    scene_quats: float = 1e-3
    object_means: float = 1e-4
    object_sh0: float = 2.5e-3
    object_opacities: float = 0.05
    object_scales: float = 5e-3
    object_quats: float = 1e-3
    object_trajectory: float = 2e-3
    object_rotation: float = 5e-4
    human_means: float = 2e-4
    human_field: float = 2e-3
    human_color: float = 5e-3
    human_pose: float = 5e-4
    """Radians per step on the keyframed pose corrections."""
    human_transl: float = 2e-4
    shading: float = 2e-3
    """Irradiance coefficients of the human and object branches."""


@dataclass
class TrainConfig:
    preset: str = "paper"
    schedule: Schedule = field(default_factory=Schedule)
    weights: LossWeights = field(default_factory=LossWeights)
    branches: BranchesConfig = field(default_factory=BranchesConfig)
    lr: LearningRates = field(default_factory=LearningRates)
    human_density: Density = field(default_factory=lambda: Density(enabled=True, clone_only=True, max_gaussians=60_000, stop_fraction=0.6))
    object_density: Density = field(default_factory=lambda: Density(enabled=True, start_fraction=0.3, max_gaussians=15_000))
    scene_density: Density = field(default_factory=lambda: Density(enabled=True, max_gaussians=120_000))
    refit: PoseRefit = field(default_factory=PoseRefit)
    pose_warmup_fraction: float = 0.25
    """Stage I opens by aligning the input body poses to the masks with the seed held
    fixed (only the pose corrections step, at `pose_warmup_lr_scale` x their rate), so
    the appearance is learned on aligned poses instead of absorbing their errors."""
    pose_warmup_lr_scale: float = 5.0
    crop_human_losses: bool = True
    """Stages I-II: image terms on a padded box around the person instead of the frame."""
    object_appearance_warmup: float = 0.3
    """Stage III opens with the object's trajectory held: its appearance first settles on
    the initial poses, so that the poses are then refined against a coherent object."""
    pose_realign_fraction: float = 0.0
    """Stage II opens by re-aligning the poses (only they step, at the boosted rate) against
    the full loss, now that the appearance is sharp enough to add photometric evidence."""
    compose_pose_lr_scale: float = 0.0
    """Scale of the pose corrections' learning rates in stages V-VI. The default 0 holds the
    poses the human stages fitted: the full-image loss lets the body pose trade against the
    scene and the object and drift from the truth. 1 refines them at the human stages'
    rate. Chosen on the demo scene alone (held-out joints and human IoU)."""
    human_stage_means_lr_scale: float = 1.0
    """Scale of the human's canonical-position learning rate in stages I-II. Free canonical
    positions take up part of the input poses' error instead of the pose corrections
    (the appearance then fits the wrong pose); 0 keeps the seed's positions there, and
    V-VI train them at the full rate."""
    visibility_every: int = 500
    """Recompute the human visibility scores every this many steps (and at stage starts)."""
    plane_assign_every: int = 500
    checkpoint_every: int = 500
    log_every: int = 10
    backend: str = "auto"
    seed: int = 0
    # Ablation switches (CoGS Table: each removes one component).
    use_human_seed: bool = True
    """False: the human starts from sparse/random points in the body box, not the body surface."""
    use_object_seed: bool = True
    """False: the object starts from a random cloud around its initial centre."""
    use_anchoring: bool = True
    use_human_alpha_losses: bool = True
    use_planes: bool = True


def quick_config() -> TrainConfig:
    """Scaled for a 2-core CPU: the demo trains in about a quarter of an hour."""
    c = TrainConfig(preset="quick")
    c.schedule = Schedule(I=800, II=200, III=600, IV=250, V=600, VI=1200)
    c.branches.human.n_gaussians = 15_000
    c.branches.human.triplane_resolution = 96
    c.branches.object.max_gaussians = 4000
    c.visibility_every = 200
    c.plane_assign_every = 200
    c.checkpoint_every = 200
    for d in (c.human_density, c.object_density, c.scene_density):
        d.refine_every = 50
    c.scene_density.max_gaussians = 60_000
    c.human_density.max_gaussians = 25_000
    c.object_density.max_gaussians = 8000
    return c


def paper_config() -> TrainConfig:
    c = TrainConfig(preset="paper")
    c.branches.human.n_gaussians = 50_000
    c.branches.scene.sh_degree = 3
    return c


PRESETS = {"quick": quick_config, "paper": paper_config}


def preset(name: str) -> TrainConfig:
    if name not in PRESETS:
        raise UserError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
    return PRESETS[name]()


# -- overrides and (de)serialisation ------------------------------------------------------


def to_dict(cfg: Any) -> Any:
    return dataclasses.asdict(cfg)


def apply_overrides(cfg: TrainConfig, overrides: list[str]) -> TrainConfig:
    """`path.to.field=value` strings (value parsed as YAML) applied to a copy of cfg."""
    cfg = copy.deepcopy(cfg)
    for item in overrides:
        if "=" not in item:
            raise UserError(f"--set expects path.to.field=value, got {item!r}")
        path, raw = item.split("=", 1)
        obj = cfg
        parts = path.strip().split(".")
        for p in parts[:-1]:
            if not dataclasses.is_dataclass(obj) or not hasattr(obj, p):
                raise UserError(f"--set {item!r}: no config section {p!r}")
            obj = getattr(obj, p)
        leaf = parts[-1]
        if not dataclasses.is_dataclass(obj) or leaf not in {f.name for f in dataclasses.fields(obj)}:
            raise UserError(f"--set {item!r}: no field {leaf!r} in {type(obj).__name__}")
        old = getattr(obj, leaf)
        value = yaml.safe_load(raw)
        if isinstance(old, bool) and not isinstance(value, bool):
            raise UserError(f"--set {item!r}: {leaf} must be true or false")
        if isinstance(old, (int, float)) and not isinstance(old, bool):
            if isinstance(value, str):  # YAML 1.1 reads "2e-3" as a string
                try:
                    value = float(value)
                except ValueError:
                    pass
            if not isinstance(value, (int, float)) or isinstance(value, bool):
                raise UserError(f"--set {item!r}: {leaf} must be a number")
            value = type(old)(value)
        setattr(obj, leaf, value)
    return cfg


def from_dict(data: dict) -> TrainConfig:
    """Inverse of `to_dict` (used when resuming and evaluating a run)."""

    def build(cls, values):
        kwargs = {}
        for f in dataclasses.fields(cls):
            if f.name not in values:
                continue
            v = values[f.name]
            ftype = f.type if not isinstance(f.type, str) else None
            default = getattr(cls(), f.name) if ftype is None else None
            target = type(default) if default is not None else ftype
            if dataclasses.is_dataclass(target):
                kwargs[f.name] = build(target, v)
            else:
                kwargs[f.name] = v
        return cls(**kwargs)

    return build(TrainConfig, data)


def save_config(cfg: TrainConfig, path) -> None:
    with open(path, "w") as f:
        yaml.safe_dump(to_dict(cfg), f, sort_keys=False)


def load_config(path) -> TrainConfig:
    with open(path) as f:
        return from_dict(yaml.safe_load(f))
