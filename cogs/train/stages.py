"""The training curriculum as data: one `StageSpec` per stage, read by one loop.

A spec says what trains (branches with optimizers, parameter groups held), what renders
and which loss terms count with which weights (its image objectives, `objectives.py`, and
the branches' own regularisers), the learning-rate scales and decays, which branches'
density control runs, and whether it continues the previous stage's optimizers. A
`Phase` changes the spec over part of a stage (a fraction of its steps): stage I opens
with a pose-only alignment, III with the trajectory held, VI switches the plane term on
late. The CoGS curriculum (`build_stages`):

    I    human base         human alone on a random background: RGB, mask, un-premultiplied
                            colour, anchoring; opens with a pose alignment (poses only)
    II   human refinement   + alpha L1, Dice and boundary-band edge terms
    III  object base        human frozen; object from its initial trajectory:
                            silhouette-dominant, pose prior, acceleration, stillness;
                            opens with the trajectory held (appearance first)
    IV   object polish      + edge, un-premultiplied colour, rotation smoothness;
                            object densification
    V    compositional      fresh scene from the sparse points, full-image loss, scene
         warm-up            densification; body poses and object motion held
    VI   true resume        continues V's optimizers and density state; + object motion
                            (scaled by the object's share of the frame), plane term late
    refit                   every training frame's body pose fitted again against the
                            finished model (`posefit.py`)

The ablations are edits of these specs (`ablate`): a removed component drops its terms;
"single-stage joint training" replaces I-VI by one stage running every term of every
stage from its first step.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Mapping

from cogs.config import STAGES, TrainConfig

TITLES = {
    "I": "human base",
    "II": "human alpha/boundary refinement",
    "III": "object pose and appearance",
    "IV": "object silhouette/rotation polish",
    "V": "compositional warm-up",
    "VI": "true-resume refinement",
    "joint": "joint training (no curriculum)",
    "refit": "body poses of the training frames, fitted again",
}

# Loss terms by the component the ablations remove (names of `LossWeights` fields).
HUMAN_ALPHA_TERMS = ("human_mask", "human_unpremultiplied", "human_alpha_refine", "human_dice", "human_edge")
ANCHOR_TERMS = ("anchor", "anchor_scale", "anchor_rotation", "anchor_opacity")
PLANE_TERMS = ("plane",)


@dataclass(frozen=True)
class Phase:
    """A part of a stage, [start, stop) as fractions of its steps, that adds loss terms,
    scales learning rates ("branch.group" -> factor, multiplying the stage's), steps only
    some parameter groups (`only`) or holds some (`hold`)."""

    start: float = 0.0
    stop: float = 1.0
    weights: Mapping[str, float] = field(default_factory=dict)
    lr_scales: Mapping[str, float] = field(default_factory=dict)
    only: Mapping[str, tuple[str, ...]] = field(default_factory=dict)
    hold: Mapping[str, tuple[str, ...]] = field(default_factory=dict)

    def active(self, frac: float) -> bool:
        return self.start <= frac < self.stop


@dataclass(frozen=True)
class StageSpec:
    name: str
    steps: int
    kind: str = "optimise"
    """"optimise" (the loop's gradient step) or "refit" (one pose fit per training frame)."""
    objectives: tuple[str, ...] = ()
    """Image objectives run each step, each with its own render (`objectives.OBJECTIVES`):
    "human" (the human alone on a random background), "object" (human and object on a
    random background), "compose" (every branch, the full frame)."""
    trains: tuple[str, ...] = ()
    """Branches with optimizers; the others are rendered frozen."""
    weights: Mapping[str, float] = field(default_factory=dict)
    """Loss terms and their weights (`LossWeights` names); a term absent is off."""
    hold: Mapping[str, tuple[str, ...]] = field(default_factory=dict)
    """Parameter groups of a training branch that do not step in this stage."""
    lr_scales: Mapping[str, float] = field(default_factory=dict)
    """"branch.group" -> factor on the group's base learning rate."""
    decay: Mapping[str, float] = field(default_factory=dict)
    """"branch.group" -> the factor its learning rate reaches at the end of `decay_window`,
    exponentially (3DGS: the scene's positions x0.01)."""
    decay_window: tuple[int, int] | None = None
    """(offset, span) in steps: the decay runs over a window wider than the stage (V-VI
    together); None: over the stage."""
    density: tuple[str, ...] = ()
    """Branches whose density control runs."""
    continues: bool = False
    """Keep the previous stage's optimizers and density state (VI, the true resume)."""
    scales: Mapping[str, float] = field(default_factory=dict)
    """branch -> factor on all its regularisers (VI: the object's motion terms times the
    object's share of the frame, since the image terms are full-frame again; this keeps
    the prior-to-evidence balance of stages III-IV, whose object terms are cropped)."""
    phases: tuple[Phase, ...] = ()

    @property
    def title(self) -> str:
        return TITLES.get(self.name, self.name)

    def active_phases(self, frac: float) -> list[Phase]:
        return [p for p in self.phases if p.active(frac)]

    def weights_at(self, frac: float) -> dict[str, float]:
        w = dict(self.weights)
        for p in self.active_phases(frac):
            w.update(p.weights)
        return w


def _pick(w, *names: str) -> dict[str, float]:
    return {n: getattr(w, n) for n in names}


def build_stages(cfg: TrainConfig, n_train: int = 0, object_share: float = 1.0) -> list[StageSpec]:
    """The run's stages in order: the CoGS curriculum (or the joint ablation) and the pose
    refit, with the config's ablation switches applied. Two numbers come from the data:
    `n_train` (training frames) sets the refit's length, `object_share` (the mean share of
    the frame the object's padded box covers) scales VI's motion terms."""
    w, s, h = cfg.weights, cfg.schedule, cfg.branches.human
    human_img = _pick(w, "l1", "dssim", "human_rgb", "human_mask", "human_unpremultiplied")
    human_alpha = _pick(w, "human_alpha_refine", "human_dice", "human_edge")
    human_reg = _pick(w, *ANCHOR_TERMS, "pose_refine_reg")
    object_img = _pick(w, "l1", "dssim", "object_rgb", "object_bce", "object_dice")
    object_polish = _pick(w, "object_edge", "object_unpremultiplied")
    motion = _pick(w, "pose_prior", "pose_prior_rotation", "acceleration", "rest_translation", "rest_rotation")
    compose = _pick(w, "l1", "dssim", "compose_rgb", "compose_human_mask", "compose_object_mask")
    pose_groups = ("pose", "transl")

    def align(stop: float) -> tuple[Phase, ...]:
        """Pose-only alignment at the opening of a human stage (with the boundary terms)."""
        if not h.refine_pose or stop <= 0:
            return ()
        boost = cfg.pose_warmup_lr_scale
        return (Phase(stop=stop, weights=human_alpha, lr_scales={"human.pose": boost, "human.transl": boost},
                      only={"human": pose_groups}),)

    means_scale = {"human.means": cfg.human_stage_means_lr_scale}
    held_poses = {"human.pose": cfg.compose_pose_lr_scale, "human.transl": cfg.compose_pose_lr_scale}
    plane_late = (Phase(start=w.plane_warmup_fraction, weights={"plane": w.plane}),)
    V, VI = s.V, s.VI
    span = max(V + VI, 1)
    curriculum = [
        StageSpec("I", s.I, objectives=("human",), trains=("human",), weights={**human_img, **human_reg},
                  lr_scales=means_scale, phases=align(cfg.pose_warmup_fraction)),
        StageSpec("II", s.II, objectives=("human",), trains=("human",), weights={**human_img, **human_alpha, **human_reg},
                  lr_scales=means_scale, phases=align(cfg.pose_realign_fraction)),
        StageSpec("III", s.III, objectives=("object",), trains=("object",), weights={**object_img, **motion},
                  phases=(Phase(stop=cfg.object_appearance_warmup, hold={"object": ("trajectory", "rotation")}),)),
        StageSpec("IV", s.IV, objectives=("object",), trains=("object",),
                  weights={**object_img, **object_polish, **motion, "rotation_smoothness": w.rotation_smoothness},
                  density=("object",)),
        StageSpec("V", V, objectives=("compose",), trains=("human", "object", "scene"), weights={**compose, **human_reg},
                  hold={"object": ("trajectory", "rotation")}, lr_scales=held_poses, decay={"scene.means": 0.01},
                  decay_window=(0, span), density=("human", "object", "scene")),
        StageSpec("VI", VI, objectives=("compose",), trains=("human", "object", "scene"),
                  weights={**compose, **human_reg, **motion, "rotation_smoothness": w.rotation_smoothness},
                  lr_scales=held_poses, decay={"scene.means": 0.01}, decay_window=(V, span),
                  density=("human", "object", "scene"), continues=True, scales={"object": object_share}, phases=plane_late),
    ]
    # A stage without steps is skipped, except V-VI: V builds the scene that VI continues.
    stages = [st for st in curriculum if st.steps > 0 or st.name in ("V", "VI")]
    if s.single_stage:
        stages = [joint_stage(curriculum, s.total())]
    stages = [ablate(st, cfg) for st in stages]
    stages = [_with_density(st, cfg) for st in stages]
    if cfg.refit.steps > 0 and h.refine_pose and h.per_frame_pose:
        stages.append(StageSpec("refit", n_train, kind="refit"))
    return stages


def joint_stage(curriculum: list[StageSpec], steps: int) -> StageSpec:
    """Ablation "single-stage joint training": every branch, every objective and every
    loss term of every stage (phases' terms included) from the first step, for the
    curriculum's total length; no phases, nothing held; the scene's positions decay over
    the stage."""
    weights: dict[str, float] = {}
    for st in curriculum:
        weights.update(st.weights)
        for p in st.phases:
            weights.update(p.weights)
    return StageSpec("joint", steps, objectives=("human", "object", "compose"), trains=("human", "object", "scene"),
                     weights=weights, decay={"scene.means": 0.01}, density=("human", "object", "scene"))


def ablate(st: StageSpec, cfg: TrainConfig) -> StageSpec:
    """The config's ablation switches as edits of a stage: drop the removed component's terms."""
    drop: tuple[str, ...] = ()
    if not cfg.use_anchoring:
        drop += ANCHOR_TERMS
    if not cfg.use_human_alpha_losses:
        drop += HUMAN_ALPHA_TERMS
    if not cfg.use_planes:
        drop += PLANE_TERMS
    if not drop:
        return st
    keep = lambda m: {k: v for k, v in m.items() if k not in drop}  # noqa: E731
    return replace(st, weights=keep(st.weights), phases=tuple(replace(p, weights=keep(p.weights)) for p in st.phases))


def _with_density(st: StageSpec, cfg: TrainConfig) -> StageSpec:
    """Drop the branches whose density control the config disables."""
    return replace(st, density=tuple(b for b in st.density if getattr(cfg, f"{b}_density").enabled))


def stage_names(cfg: TrainConfig) -> list[str]:
    """The stages a run of `cfg` goes through, in order."""
    return [st.name for st in build_stages(cfg)]


__all__ = ["STAGES", "TITLES", "Phase", "StageSpec", "build_stages", "joint_stage", "ablate", "stage_names"]
