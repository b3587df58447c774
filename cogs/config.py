"""Training configuration: the six-stage schedule, loss weights, density control and
learning rates as typed dataclasses, and the named presets.

A preset is a named `TrainConfig` (`paper` = the CoGS paper's iteration counts, `quick` =
scaled for a 2-core CPU); any field can be overridden with `--set path.to.field=value`
on the command line. Every run writes its resolved config to RUN/config.yaml.
"""

from __future__ import annotations

import copy
import dataclasses
import math
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
    """Mean squared second difference of the object's positions (m per frame^2), of its
    departure from the initial keyframed trajectory (``ObjectConfig.smooth_about_initial``)."""
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
    fused_adam: bool = True
    """On CUDA, Adam's update as one fused kernel per parameter group (the host keeps
    torch's default update; see `cogs.train.trainer.make_adam`)."""
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


# -- checking ---------------------------------------------------------------------------
#
# Every setting is checked before anything is written: `check_config` lists what is wrong
# with a TrainConfig; `apply_overrides` (`--set`) and `load_config` (a run's config.yaml)
# are strict about keys and types and raise one `UserError` listing every problem, theirs
# and `check_config`'s together.

CADENCES = (
    "checkpoint_every", "visibility_every", "log_every", "plane_assign_every",
    "human_density.refine_every", "object_density.refine_every", "scene_density.refine_every",
)
"""Settings that are a period in steps: a step count modulo them must exist (>= 1)."""

POSITIVE = CADENCES + (
    "branches.human.n_gaussians", "branches.human.triplane_resolution", "branches.human.triplane_channels",
    "branches.human.mlp_width", "branches.object.hull_resolution", "branches.object.max_gaussians",
    "branches.scene.knn", "branches.color_init_frames", "branches.human.pose_keyframe_every",
    "branches.object.frames_per_keyframe", "branches.scene.plane_loss_scale_m",
)
"""Settings that must be > 0 (every other number must be >= 0, except where noted)."""

SIGNED = ("branches.human.seed_inset_m",)
"""Numbers that may be negative."""

FRACTIONS = ("branches.human.held_out_input_weight", "branches.object.held_out_input_weight", "object_appearance_warmup",
             "branches.object.min_confidence")
"""Settings in [0, 1] besides every `*_fraction`."""

MAX_SH_DEGREE = 3

ADDED: dict[tuple[str, str], str] = {
    ("TrainConfig", "refit"): "the pose refit after stage VI (2026-11-25)",
    ("LossWeights", "compose_rgb"): "the compositional RGB term's weight, 1 before it was a setting (2026-11-25)",
    ("HumanConfig", "visibility_max_frames"): "a bound on the frames visibility is counted on (2026-11-25)",
    ("ObjectConfig", "min_confidence"): "frames whose object mask is not trusted leave the object's supervision; "
                                        "scenes of older runs record no confidence, so every frame is kept (2026-11-26)",
    ("HumanConfig", "held_out_adaptive"): "held-out frames may keep a share of their input's motion decided per bone "
                                          "from the clip's own noise; off, as before (2026-11-27)",
    ("HumanConfig", "held_out_noise_factor"): "the adaptive held-out share's noise multiple (2026-11-27)",
    ("ObjectConfig", "held_out_input_weight"): "held-out frames' object poses may follow a share of their own "
                                               "initial pose; off, as before (models saved before it also count every "
                                               "frame as trained) (2026-11-27)",
    ("ObjectConfig", "held_out_max_gap"): "the reach of a held-out object pose's interpolation (2026-11-27)",
    ("ObjectConfig", "smooth_about_initial"): "the object's acceleration measured about its initial trajectory; a model "
                                              "saved before it has a zero reference, which is the old term (2026-11-28)",
    ("TrainConfig", "fused_adam"): "Adam's fused update on CUDA; the same arithmetic, and the host's is unchanged (2026-11-28)",
}
"""(dataclass, key) of settings added after runs were written: an older config.yaml that
lacks one takes its default, which reproduces what that run did (or, for a new stage,
what `cogs train --resume` then adds)."""

RETIRED: dict[tuple[str, str], str] = {
    ("Density", "reset_opacity_every"): "opacity resets were removed",
}
"""(dataclass, key) of settings older runs' config.yaml may hold that this cogs no longer
has: accepted and ignored when the dataclass has no such field any more."""


def _fields(cls) -> dict[str, Any]:
    """Field name -> its default value (which gives its type; every field has one)."""
    default = cls()
    return {f.name: getattr(default, f.name) for f in dataclasses.fields(cls)}


def _kind(default: Any) -> str:
    if dataclasses.is_dataclass(default):
        return "section"
    for t, name in ((bool, "true or false"), (int, "an integer"), (float, "a number"), (str, "a string")):
        if isinstance(default, t):
            return name
    raise AssertionError(f"config field of unsupported type {type(default).__name__}")


def _coerce(default: Any, value: Any) -> tuple[Any, bool]:
    """`value` as the type of `default` (int <- integral float, float <- int or a numeric
    string, which YAML 1.1 makes of "2e-3"); (value, ok)."""
    if isinstance(default, bool):
        return value, isinstance(value, bool)
    if isinstance(value, bool):
        return value, False
    if isinstance(default, int):
        if isinstance(value, float) and value.is_integer():
            return int(value), True
        if isinstance(value, str):
            try:
                f = float(value)
            except ValueError:
                return value, False
            return (int(f), True) if f.is_integer() else (value, False)
        return value, isinstance(value, int)
    if isinstance(default, float):
        if isinstance(value, str):
            try:
                return float(value), True
            except ValueError:
                return value, False
        return (float(value), True) if isinstance(value, (int, float)) else (value, False)
    if isinstance(default, str):
        return value, isinstance(value, str)
    raise AssertionError(type(default))


def _type_ok(default: Any, value: Any) -> bool:
    """Whether `value`, as it sits in a TrainConfig, has the type of `default`."""
    if isinstance(default, bool) or isinstance(value, bool):
        return isinstance(default, bool) and isinstance(value, bool)
    if isinstance(default, int):
        return isinstance(value, int)
    if isinstance(default, float):
        return isinstance(value, (int, float))
    return isinstance(value, type(default))


def _suggest(key: str, known) -> str:
    import difflib

    close = difflib.get_close_matches(str(key), list(known), n=1)
    return f"; did you mean `{close[0]}`?" if close else ""


def check_config(cfg: TrainConfig) -> list[str]:
    """Every problem with `cfg`: wrong types, sections replaced by values, negative counts,
    cadences below 1, fractions outside [0, 1], non-finite numbers, unknown backend, preset
    or plane loss. Empty = usable. A stage's iteration count of 0 is legal (the stage is
    skipped)."""
    from cogs.geometry.planes import PLANE_LOSS_KINDS
    from cogs.render.api import BACKENDS

    problems: list[str] = []

    def walk(obj: Any, cls, prefix: str) -> None:
        for name, default in _fields(cls).items():
            path = f"{prefix}{name}"
            value = getattr(obj, name, None)
            kind = _kind(default)
            if kind == "section":
                if not isinstance(value, type(default)):
                    problems.append(f"{path}: is a section of settings, got {value!r}")
                else:
                    walk(value, type(default), f"{path}.")
                continue
            if not _type_ok(default, value):
                problems.append(f"{path}: must be {kind}, got {value!r}")
                continue
            if isinstance(value, bool) or isinstance(value, str):
                continue
            if isinstance(value, float) and not math.isfinite(value):
                problems.append(f"{path}: must be a finite number, got {value!r}")
            elif path in CADENCES and value < 1:
                problems.append(f"{path}: must be at least 1 (a period in steps), got {value!r}")
            elif path in POSITIVE and value <= 0:
                problems.append(f"{path}: must be positive, got {value!r}")
            elif path not in SIGNED and value < 0:
                problems.append(f"{path}: must not be negative, got {value!r}")
            elif (name.endswith("_fraction") or path in FRACTIONS) and value > 1:
                problems.append(f"{path}: is a fraction, must be in [0, 1], got {value!r}")

    walk(cfg, TrainConfig, "")
    if isinstance(cfg.backend, str) and cfg.backend not in BACKENDS:
        problems.append(f"backend: unknown {cfg.backend!r}; known: {', '.join(BACKENDS)}")
    if isinstance(cfg.preset, str) and cfg.preset not in PRESETS:
        problems.append(f"preset: unknown {cfg.preset!r}; known: {', '.join(PRESETS)}")
    branches = getattr(cfg, "branches", None)
    for part in ("scene", "object"):
        sh = getattr(getattr(branches, part, None), "sh_degree", 0)
        if isinstance(sh, int) and not isinstance(sh, bool) and sh > MAX_SH_DEGREE:
            problems.append(f"branches.{part}.sh_degree: at most {MAX_SH_DEGREE}, got {sh}")
    kind = getattr(getattr(branches, "scene", None), "plane_loss_kind", "huber")
    if isinstance(kind, str) and kind not in PLANE_LOSS_KINDS:
        problems.append(f"branches.scene.plane_loss_kind: unknown {kind!r}; known: {', '.join(PLANE_LOSS_KINDS)}")
    return problems


def _raise(where: str, problems: list[str]) -> None:
    if problems:
        lines = "\n".join(f"  - {p}" for p in problems)
        raise UserError(f"{where}: {len(problems)} problem(s):\n{lines}")


def validate_config(cfg: TrainConfig, where: str = "config") -> TrainConfig:
    """`cfg` itself, or a `UserError` listing every problem `check_config` finds."""
    _raise(where, check_config(cfg))
    return cfg


# -- overrides and (de)serialisation ------------------------------------------------------


def to_dict(cfg: Any) -> Any:
    return dataclasses.asdict(cfg)


def apply_overrides(cfg: TrainConfig, overrides: list[str]) -> TrainConfig:
    """`path.to.field=value` strings (value parsed as YAML) applied to a copy of cfg; the
    result is checked (`check_config`). One `UserError` lists every problem."""
    cfg = copy.deepcopy(cfg)
    problems: list[str] = []
    for item in overrides:
        if "=" not in item:
            problems.append(f"{item!r}: expected path.to.field=value")
            continue
        path, raw = item.split("=", 1)
        parts = path.strip().split(".")
        obj, cls = cfg, TrainConfig
        for depth, name in enumerate(parts):
            fields = _fields(cls)
            here = ".".join(parts[: depth + 1])
            if name not in fields:
                retired = (cls.__name__, name) in RETIRED
                problems.append(f"{item}: `{here}` is not a setting (no field {name!r} in {cls.__name__})"
                                + (f"; it was removed: {RETIRED[(cls.__name__, name)]}" if retired else _suggest(name, fields)))
                break
            default = fields[name]
            last = depth == len(parts) - 1
            if dataclasses.is_dataclass(default):
                if last:
                    names = ", ".join(_fields(type(default)))
                    problems.append(f"{item}: `{here}` is a section, not a value; set one of its fields "
                                    f"({names}), e.g. --set {here}.{next(iter(_fields(type(default))))}=...")
                    break
                obj, cls = getattr(obj, name), type(default)
                continue
            if not last:
                problems.append(f"{item}: `{here}` is a value, not a section")
                break
            try:
                value = yaml.safe_load(raw)
            except yaml.YAMLError as e:
                problems.append(f"{item}: the value is not valid YAML ({e})")
                break
            coerced, good = _coerce(default, value)
            if not good:
                problems.append(f"{item}: `{here}` must be {_kind(default)}, got {value!r}")
                break
            setattr(obj, name, coerced)
    problems += check_config(cfg)
    _raise("--set", problems)
    return cfg


def from_dict(data: Any, where: str = "config") -> TrainConfig:
    """Inverse of `to_dict`, strict: every setting must be present, known and of its type,
    and the result must pass `check_config`; one `UserError` (prefixed by `where`) lists
    every problem. Settings in `RETIRED` are ignored."""
    problems: list[str] = []
    missing: list[str] = []

    def build(cls, values, prefix: str):
        if not isinstance(values, dict):
            if prefix:
                problems.append(f"{prefix.rstrip('.')}: is a section, expected a mapping of its settings, got {values!r}")
            else:
                problems.append(f"holds {values!r}, not a mapping of settings (a run's config.yaml lists every setting)")
            return cls()
        fields = _fields(cls)
        kwargs = {}
        for key, v in values.items():
            if key not in fields:
                if (cls.__name__, key) in RETIRED:
                    continue
                problems.append(f"{prefix}{key}: unknown setting{_suggest(key, fields)}")
                continue
            default = fields[key]
            if dataclasses.is_dataclass(default):
                kwargs[key] = build(type(default), v, f"{prefix}{key}.")
            else:
                coerced, ok = _coerce(default, v)
                if not ok:
                    problems.append(f"{prefix}{key}: must be {_kind(default)}, got {v!r}")
                    continue
                kwargs[key] = coerced
        missing.extend(f"{prefix}{k}" for k in fields if k not in values and (cls.__name__, k) not in ADDED)
        return cls(**kwargs)

    cfg = build(TrainConfig, data, "")
    if missing and isinstance(data, dict):
        shown = ", ".join(missing[:8]) + (f" and {len(missing) - 8} more" if len(missing) > 8 else "")
        problems.append(f"missing settings: {shown} (a run's config.yaml lists every setting; cogs never fills "
                        "them in from a preset's defaults)")
    problems += check_config(cfg)  # the settings that were read; the others kept their defaults
    _raise(where, problems)
    return cfg


def save_config(cfg: TrainConfig, path) -> None:
    from cogs.data.io import atomic_writer

    with atomic_writer(path) as f:
        yaml.safe_dump(to_dict(cfg), f, sort_keys=False)


def load_config(path) -> TrainConfig:
    """A run's config.yaml, strictly (see `from_dict`); `UserError` naming the file when it
    is missing, unreadable, not YAML, incomplete or wrong."""
    from pathlib import Path

    path = Path(path)
    if path.is_dir():
        raise UserError(f"{path}: is a folder, expected the run's config.yaml")
    try:
        text = path.read_bytes()
    except FileNotFoundError:
        raise UserError(f"{path}: missing (every run folder holds its config.yaml)") from None
    except OSError as e:
        raise UserError(f"{path}: cannot be read ({e.strerror or e})") from None
    try:
        data = yaml.safe_load(text)
    except (yaml.YAMLError, ValueError, RecursionError) as e:
        raise UserError(f"{path}: not valid YAML ({e})") from None
    return from_dict(data, where=str(path))
