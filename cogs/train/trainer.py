"""The trainer: sequences the six CoGS stages over the branches, with checkpoints.

Stages (iteration counts in `Schedule`):
    I    human base         human alone on a random background: RGB, mask, un-premultiplied
                            colour, visibility anchoring; no human densification
    II   human refinement   + stronger alpha, BCE/Dice and boundary-band edge terms
    III  object base        human frozen; object from its initial trajectory:
                            silhouette-dominant, pose prior, acceleration smoothness
    IV   object polish      + edge, un-premultiplied colour, rotation smoothness and prior;
                            object densification delayed and capped
    V    compositional      fresh scene from the sparse points, full-image loss, scene
         warm-up            densification; human/object topology conservative
    VI   true resume        continues V's optimizers and density state; all terms incl.
                            anchoring, object motion and the delayed plane term
    refit                   every training frame's body pose fitted again against the
                            finished model (`PoseRefit`, `posefit.py`); held-out frames
                            interpolate these poses

The trainer only sequences: losses live in `losses.py` and the branches, density
control in `density.py`, checkpoint files in `checkpoint.py`. Everything random draws from
one seeded generator whose state is checkpointed, so a run killed at any point and
resumed from its last checkpoint ends with the same parameters as an uninterrupted one.
"""

from __future__ import annotations

import logging
import random
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from cogs.branches.build import build_human, build_object, build_scene
from cogs.branches.compositor import Compositor
from cogs.branches.human import compute_visibility
from cogs.config import STAGE_TITLES, STAGES, TrainConfig, save_config
from cogs.data.scene import Scene
from cogs.errors import UserError
from cogs.train import checkpoint as ckpt
from cogs.train import density as dens
from cogs.train import losses as L

log = logging.getLogger(__name__)


@dataclass
class FrameData:
    """Every training input as tensors, loaded once."""

    images: torch.Tensor  # [T, H, W, 3]
    human: torch.Tensor  # [T, H, W, 1] float 0/1
    object: torch.Tensor  # [T, H, W, 1]
    human_band: torch.Tensor  # [T, H, W, 1] boundary bands
    object_band: torch.Tensor
    viewmats: torch.Tensor  # [T, 4, 4]
    Ks: torch.Tensor  # [T, 3, 3]
    width: int
    height: int
    train: list[int]

    @classmethod
    def from_scene(cls, scene: Scene) -> "FrameData":
        hm, om = scene.human_masks, scene.object_masks
        f = lambda a: torch.as_tensor(np.asarray(a, np.float32))[..., None]  # noqa: E731
        return cls(
            images=torch.as_tensor(scene.images).float() / 255.0,
            human=f(hm),
            object=f(om),
            human_band=f(np.stack([L.boundary_band(m) for m in hm])),
            object_band=f(np.stack([L.boundary_band(m) for m in om])),
            viewmats=torch.as_tensor(scene.cameras.world_to_camera, dtype=torch.float32),
            Ks=torch.as_tensor(scene.cameras.K, dtype=torch.float32),
            width=scene.width,
            height=scene.height,
            train=list(scene.split["train"]),
        )


@dataclass
class RunState:
    """Where the run stands; saved in every checkpoint."""

    stage: int = 0  # index into STAGES of the stage in progress
    step: int = 0  # completed steps of that stage
    history: list[dict] = field(default_factory=list)
    stage_seconds: dict[str, float] = field(default_factory=dict)
    density_events: list[dict] = field(default_factory=list)


def stage_names(cfg: TrainConfig) -> list[str]:
    """The stages a run of `cfg` goes through, in order."""
    if cfg.schedule.single_stage:
        names = ["joint"]
    else:
        names = [s for s in STAGES if getattr(cfg.schedule, s) > 0 or s in ("V", "VI")]
    hc = cfg.branches.human
    if cfg.refit.steps > 0 and hc.refine_pose and hc.per_frame_pose:
        names.append("refit")
    return names


def run_is_finished(run: Path) -> bool:
    """Whether `run` went through every stage its config asks for. A run trained before a
    stage was added is not: `cogs train --resume` then runs just the new stage."""
    from cogs.config import load_config
    from cogs.data.io import read_json

    run = Path(run)
    summary, config = run / "train_summary.json", run / "config.yaml"
    if not summary.exists() or not config.exists():
        return False
    return read_json(summary).get("stages") == stage_names(load_config(config))


def scene_extent(viewmats: torch.Tensor) -> float:
    """3DGS's camera extent: 1.1 x the largest camera distance from their centroid (>= 1 m)."""
    centres = -(viewmats[:, :3, :3].transpose(1, 2) @ viewmats[:, :3, 3:])[..., 0]
    return max(1.1 * float((centres - centres.mean(0)).norm(dim=1).max()), 1.0)


class Trainer:
    def __init__(self, scene: Scene, cfg: TrainConfig, out: Path, resume: bool = False, show_progress: bool = True):
        self.scene, self.cfg, self.out = scene, cfg, Path(out)
        self.show_progress = show_progress
        self.data = FrameData.from_scene(scene)
        if not self.data.train:
            raise UserError(f"scene {scene.root}: the split has no training frames")
        self.extent = scene_extent(self.data.viewmats)
        self._object_share = _object_share(self.data)
        # Module initialisers draw from the global generators: seed them too.
        torch.manual_seed(cfg.seed)
        np.random.seed(cfg.seed)
        random.seed(cfg.seed)
        self.gen = torch.Generator().manual_seed(cfg.seed)
        self.state = RunState()
        self.human = self.object = self.scene_branch = None
        self.optimizers: dict[str, torch.optim.Optimizer] = {}
        self.density: dict[str, dict] = {}
        self.out.mkdir(parents=True, exist_ok=True)
        from cogs.render import warmup

        warmup()
        if resume:
            self._resume()
        else:
            save_config(cfg, self.out / "config.yaml")
            from cogs.data.io import write_json

            write_json(self.out / "run.json", {"scene": str(Path(scene.root).resolve()) if scene.root else None, "preset": cfg.preset})

    # -- construction -------------------------------------------------------------------
    def _build_human(self, colors: bool = True):
        seed = None if self.cfg.use_human_seed else _random_human_seed(self.scene, self.cfg)
        if colors:
            return build_human(self.scene, self.cfg.branches, self.cfg.backend, seed=seed)
        return _bare_human(self.scene, self.cfg, seed)

    def _build_object(self):
        obj = build_object(self.scene, self.cfg.branches, self.cfg.backend)
        if obj is not None and not self.cfg.use_object_seed:
            _randomise_object(obj, self.gen)
        return obj

    @property
    def compositor(self) -> Compositor:
        return Compositor(self.human, self.object, self.scene_branch, backend=self.cfg.backend)

    def _branch_extent(self, name: str) -> float:
        if name == "human":
            return 1.0
        if name == "object":
            m = self.object.gaussians.means.detach()
            return max(float((m - m.mean(0)).norm(dim=1).max()), 0.05)
        return self.extent

    # -- optimizers -----------------------------------------------------------------------
    def _human_optimizer(self) -> torch.optim.Optimizer:
        h, lr = self.human, self.cfg.lr
        groups = [
            {"params": [h.means], "lr": lr.human_means, "name": "means"},
            {"params": [h.color_residual], "lr": lr.human_color, "name": "color"},
            {"params": list(h.field.parameters()), "lr": lr.human_field, "name": "field"},
            {"params": list(h.shading.parameters()), "lr": lr.shading, "name": "shading"},
        ]
        if h.cfg.refine_pose:
            groups += [
                {"params": [h.pose_delta, h.frame_pose_delta], "lr": lr.human_pose, "name": "pose"},
                {"params": [h.transl_delta, h.frame_transl_delta], "lr": lr.human_transl, "name": "transl"},
            ]
        return torch.optim.Adam(groups, eps=1e-15)

    def _set_optimizer(self, g, prefix: str, extent: float) -> torch.optim.Optimizer:
        lr = self.cfg.lr
        p = g.params
        groups = [
            {"params": [p["means"]], "lr": getattr(lr, f"{prefix}_means") * (extent if prefix == "scene" else 1.0), "name": "means"},
            {"params": [p["sh0"]], "lr": getattr(lr, f"{prefix}_sh0"), "name": "sh0"},
            {"params": [p["opacities"]], "lr": getattr(lr, f"{prefix}_opacities"), "name": "opacities"},
            {"params": [p["scales"]], "lr": getattr(lr, f"{prefix}_scales"), "name": "scales"},
            {"params": [p["quats"]], "lr": getattr(lr, f"{prefix}_quats"), "name": "quats"},
        ]
        if "shN" in p:
            groups.append({"params": [p["shN"]], "lr": lr.scene_shN, "name": "shN"})
        return torch.optim.Adam(groups, eps=1e-15)

    def _object_optimizer(self, motion: bool) -> torch.optim.Optimizer:
        opt = self._set_optimizer(self.object.gaussians, "object", 1.0)
        opt.add_param_group({"params": list(self.object.shading.parameters()), "lr": self.cfg.lr.shading, "name": "shading"})
        if motion:
            self._add_motion(opt)
        return opt

    def _add_motion(self, opt: torch.optim.Optimizer) -> None:
        o, lr = self.object, self.cfg.lr
        opt.add_param_group({"params": [o.key_p, o.key_v], "lr": lr.object_trajectory, "name": "trajectory"})
        opt.add_param_group({"params": [o.key_q], "lr": lr.object_rotation, "name": "rotation"})

    def _ensure_branches(self, name: str, colors: bool = True) -> None:
        """Create the branches stage `name` needs that do not exist yet."""
        single = name == "joint"
        if self.human is None:
            self.human = self._build_human(colors=colors)
        if (name in ("III", "IV", "V", "VI") or single) and self.object is None:
            self.object = self._build_object()
        if (name in ("V", "VI") or single) and self.scene_branch is None:
            self.scene_branch = build_scene(self.scene, self.cfg.branches)

    def _make_optimizers(self, name: str) -> dict[str, torch.optim.Optimizer]:
        """The optimizers as they exist during stage `name` (VI: V's plus object motion)."""
        single = name == "joint"
        opts: dict[str, torch.optim.Optimizer] = {}
        if name in ("I", "II", "V", "VI") or single:
            opts["human"] = self._human_optimizer()
        if self.object is not None and (name in ("III", "IV", "V", "VI") or single):
            opts["object"] = self._object_optimizer(motion=name in ("III", "IV", "VI") or single)
        if self.scene_branch is not None and (name in ("V", "VI") or single):
            opts["scene"] = self._set_optimizer(self.scene_branch.gaussians, "scene", self.extent)
        return opts

    def _setup_stage(self, name: str) -> None:
        """Branches, optimizers and density state at the start of a stage."""
        self._ensure_branches(name)
        if name == "VI" and "scene" in self.optimizers:
            # True resume: V's optimizers and density state carry on; only the object's
            # motion joins the object optimizer.
            if self.object is not None:
                self._add_motion(self.optimizers["object"])
            return
        self.optimizers = self._make_optimizers(name)
        self.density = {b: dens.new_state(len(getattr(self, _attr(b)))) for b in self._densifying(name)}

    def _densifying(self, name: str) -> list[str]:
        cfg, single = self.cfg, name == "joint"
        out = []
        if cfg.human_density.enabled and (name in ("V", "VI") or single):
            out.append("human")
        if cfg.object_density.enabled and self.object is not None and (name in ("IV", "V", "VI") or single):
            out.append("object")
        if cfg.scene_density.enabled and self.scene_branch is not None and (name in ("V", "VI") or single):
            out.append("scene")
        return out

    # -- losses per stage ------------------------------------------------------------------
    def _background(self) -> torch.Tensor:
        return torch.rand(3, generator=self.gen)

    def _human_terms(self, t: int, refine: bool, terms: dict, align: bool = False) -> torch.Tensor:
        d, w, cfg = self.data, self.cfg.weights, self.cfg
        bg = self._background()
        state = self.human.decode()
        out = self.compositor.render(d.viewmats[t], d.Ks[t], d.width, d.height, t, branches=("human",), background=bg, human_state=state)
        img, hm, om, band = d.images[t], d.human[t], d.object[t], d.human_band[t]
        rgb, alpha = out.rgb, out.alpha
        if cfg.crop_human_losses:  # measure on a padded box around the person (not the whole frame)
            y0, y1, x0, x1 = L.crop_box(hm[..., 0] > 0.5, alpha[..., 0].detach() > 0.05)
            img, hm, om, band, rgb, alpha = (x[y0:y1, x0:x1] for x in (img, hm, om, band, rgb, alpha))
        valid = 1.0 - om  # the object hides the person there: no evidence either way
        target = L.composite_over(img, hm, bg)
        pred = torch.where(om > 0, target, rgb)
        loss = w.human_rgb * L.photometric(pred, target, w.l1, w.dssim)
        terms["rgb"] = _val(loss)
        use_alpha = cfg.use_human_alpha_losses
        if use_alpha:
            m = w.human_mask * L.bce(alpha, hm, valid)
            u = w.human_unpremultiplied * L.unpremultiplied(rgb, alpha, img, hm * valid, bg)
            terms["mask"], terms["unpremult"] = _val(m), _val(u)
            loss = loss + m + u
        if (refine or align) and use_alpha:
            a = w.human_alpha_refine * L.l1(alpha, hm, valid) + w.human_dice * L.dice(alpha * valid, hm * valid) + w.human_edge * L.edge(alpha, hm, band * valid)
            terms["alpha"] = _val(a)
            loss = loss + a
        loss = loss + self._human_regularisers(state, terms)
        self._last_render = ("human", out)
        return loss

    def _human_regularisers(self, state, terms: dict) -> torch.Tensor:
        w = self.cfg.weights
        loss = torch.zeros(())
        if self.cfg.use_anchoring and w.anchor > 0:
            a = w.anchor * self.human.anchor_loss(state, w.anchor_scale, w.anchor_rotation, w.anchor_opacity)
            terms["anchor"] = _val(a)
            loss = loss + a
        if self.human.cfg.refine_pose and w.pose_refine_reg > 0:
            loss = loss + w.pose_refine_reg * self.human.pose_regularizer()
        return loss

    def _object_motion_terms(self, polish: bool, terms: dict) -> torch.Tensor:
        """Pose prior (translation + lambda_R rotation) over the training frames,
        acceleration smoothness and stillness where the object rests; `polish` (IV, VI)
        adds the rotation smoothness term."""
        from cogs.geometry.rotations import quat_geodesic_angle

        w = self.cfg.weights
        o = self.object
        frames = torch.tensor(self.data.train)
        tr, q = o.pose(frames.float())
        loss = w.pose_prior * (tr - o.prior_t[frames]).abs().sum(-1).mean()
        loss = loss + w.pose_prior_rotation * quat_geodesic_angle(q, o.prior_q[frames]).mean()
        acc, rot = o.smoothness_losses()
        loss = loss + w.acceleration * acc
        if polish:
            loss = loss + w.rotation_smoothness * rot
        if w.rest_translation > 0 or w.rest_rotation > 0:
            rest_t, rest_q = o.rest_losses()
            loss = loss + w.rest_translation * rest_t + w.rest_rotation * rest_q
        terms["motion"] = _val(loss)
        return loss

    def _object_terms(self, t: int, polish: bool, terms: dict) -> torch.Tensor:
        d, w = self.data, self.cfg.weights
        bg = self._background()
        with torch.no_grad():
            hstate = self.human.decode()
        out = self.compositor.render(d.viewmats[t], d.Ks[t], d.width, d.height, t, branches=("human", "object"), background=bg, human_state=hstate)
        img, hm, om = d.images[t], d.human[t], d.object[t]
        fg = torch.clamp(hm + om, max=1.0)
        target = L.composite_over(img, fg, bg)
        ao = out.branch_alpha["object"]
        # The object covers a few hundred pixels: its image terms are measured on a padded
        # box around it (mask or render), so that they are not diluted by the whole frame
        # and outweighed by the pose prior.
        y0, y1, x0, x1 = L.crop_box(om[..., 0] > 0.5, ao[..., 0].detach() > 0.05)
        c = lambda x: x[y0:y1, x0:x1]  # noqa: E731
        loss = w.object_rgb * L.photometric(c(out.rgb), c(target), w.l1, w.dssim)
        terms["rgb"] = _val(loss)
        # Dice is unstable on a nearly hidden object (a handful of mask pixels): fade it in.
        dice_w = min(1.0, float(om.sum()) / 200.0)
        sil = w.object_bce * L.bce(c(ao), c(om)) + w.object_dice * dice_w * L.dice(ao, om)
        terms["silhouette"] = _val(sil)
        loss = loss + sil
        if polish:
            e = (w.object_edge * L.edge(c(ao), c(om), c(d.object_band[t]))
                 + w.object_unpremultiplied * L.unpremultiplied(c(out.rgb), c(out.alpha), c(img), c(om), bg))
            terms["edge"] = _val(e)
            loss = loss + e
        loss = loss + self._object_motion_terms(polish=polish, terms=terms)
        self._last_render = ("human+object", out)
        return loss

    def _compose_terms(self, t: int, final: bool, frac: float, terms: dict) -> torch.Tensor:
        d, w, cfg = self.data, self.cfg.weights, self.cfg
        state = self.human.decode()
        out = self.compositor.render(d.viewmats[t], d.Ks[t], d.width, d.height, t, background=torch.zeros(3), human_state=state)
        img = d.images[t]
        loss = L.photometric(out.rgb, img, w.l1, w.dssim)
        terms["rgb"] = _val(loss)
        dec = w.compose_human_mask * L.bce(out.branch_alpha["human"], d.human[t], 1.0 - d.object[t])
        if self.object is not None:
            dec = dec + w.compose_object_mask * L.bce(out.branch_alpha["object"], d.object[t])
        terms["decomp"] = _val(dec)
        loss = loss + dec + self._human_regularisers(state, terms)
        if final and self.object is not None:
            # Full-frame image terms here: scale the motion prior by the object's share of
            # the frame, keeping the prior-to-evidence balance of stages III-IV.
            loss = loss + self._object_share * self._object_motion_terms(polish=True, terms=terms)
        if final and cfg.use_planes and frac >= w.plane_warmup_fraction and w.plane > 0:
            p = w.plane * self.scene_branch.plane_loss()
            terms["plane"] = _val(p)
            loss = loss + p
        self._last_render = ("all", out)
        return loss

    # -- the loop ---------------------------------------------------------------------------
    def _stage_names(self) -> list[str]:
        return stage_names(self.cfg)

    def _stage_length(self, name: str) -> int:
        if name == "joint":
            return self.cfg.schedule.total()
        if name == "refit":  # one step per training frame
            return len(self.data.train)
        return getattr(self.cfg.schedule, name)

    def stage_in_progress(self) -> str | None:
        names = self._stage_names()
        return names[self.state.stage] if self.state.stage < len(names) else None

    def finished(self) -> bool:
        return self.stage_in_progress() is None

    def run(self) -> dict:
        from cogs.log import progress, rate_text

        names = self._stage_names()
        with progress() as bar:
            while self.state.stage < len(names):
                name = names[self.state.stage]
                n = self._stage_length(name)
                if self.state.step == 0:
                    self._setup_stage(name)
                if n == 0:
                    self._end_stage(name)
                    continue
                title = f"{name:>3} {STAGE_TITLES.get(name, 'joint training (no curriculum)')}"
                task = bar.add_task(title, total=n, completed=self.state.step, rate="", info="", visible=self.show_progress)
                started, t0 = time.perf_counter(), self.state.step
                while self.state.step < n:
                    tic = time.perf_counter()
                    info = self._step(name, self.state.step, n)
                    self.state.step += 1
                    self.state.stage_seconds[name] = self.state.stage_seconds.get(name, 0.0) + time.perf_counter() - tic
                    bar.update(task, completed=self.state.step, rate=rate_text(self.state.step - t0, started), info=info)
                    if not bar.console.is_terminal and (self.state.step % 25 == 0 or self.state.step == n):
                        done = self.state.step - t0
                        eta = (time.perf_counter() - started) / max(done, 1) * (n - self.state.step)
                        log.info("stage %s %d/%d  %s  %s  eta %.0f s", name, self.state.step, n, rate_text(done, started).strip(), info, eta)
                    if self.state.step % self.cfg.checkpoint_every == 0 and self.state.step < n:
                        self._checkpoint()
                self._end_stage(name)
        self._export()
        return self.summary()

    def _end_stage(self, name: str) -> None:
        self.state.stage += 1
        self.state.step = 0
        self._checkpoint(tag=f"stage_{name}")

    def _step(self, name: str, it: int, n: int) -> str:
        if name == "refit":
            return self._refit_step(it)
        cfg = self.cfg
        d = self.data
        single = name == "joint"
        human_trains = name in ("I", "II", "V", "VI") or single
        if human_trains and (it == 0 or it % cfg.visibility_every == 0) and cfg.use_anchoring:
            self._update_visibility()
        frac = it / max(n, 1)
        if (name == "VI" or single) and cfg.use_planes and self.scene_branch is not None and frac >= cfg.weights.plane_warmup_fraction and (it % cfg.plane_assign_every == 0 or not getattr(self, "_planes_assigned", False)):
            self.scene_branch.assign_planes()
            self._planes_assigned = True
        self._schedule_lr(name, frac)
        t = d.train[int(torch.randint(len(d.train), (1,), generator=self.gen))]
        terms: dict[str, float] = {}
        for opt in self.optimizers.values():
            opt.zero_grad(set_to_none=True)
        aligning = self._aligning(name, frac)
        if name in ("I", "II"):
            loss = self._human_terms(t, refine=name == "II", terms=terms, align=aligning)
        elif name in ("III", "IV"):
            loss = self._object_terms(t, polish=name == "IV", terms=terms)
        else:
            loss = self._compose_terms(t, final=name == "VI" or single, frac=frac, terms=terms)
        if not torch.isfinite(loss):
            raise FloatingPointError(f"stage {name} step {it} frame {t}: loss is {_val(loss)} ({terms})")
        loss.backward()
        if aligning:  # pose alignment: only the pose corrections move
            self._hold("human", keep=("pose", "transl"))
        if name == "III" and frac < cfg.object_appearance_warmup:  # appearance first, trajectory held
            self._hold("object", drop=("trajectory", "rotation"))
        self._density_statistics()
        for opt in self.optimizers.values():
            opt.step()
        self._guards()
        self._density_step(name, it, n)
        entry = {"stage": name, "step": it, "frame": t, "loss": _val(loss), **terms, **self.counts()}
        if it % cfg.log_every == 0 or it == n - 1:
            self.state.history.append(entry)
        return f"loss {_val(loss):.4f}  G {self.counts()['total']}"

    def _refit_step(self, it: int) -> str:
        """Fit training frame `it`'s body pose against the finished model and keep it as
        that frame's per-frame correction. Draws nothing from the generator, so the
        refit's result is the same whether or not the run was interrupted during it."""
        from cogs.train.posefit import fit_frame_pose

        d, h = self.data, self.human
        t = d.train[it]
        fit = fit_frame_pose(self.compositor, d.images[t], d.viewmats[t], d.Ks[t], t, self.cfg.refit)
        with torch.no_grad():
            h.frame_pose_delta[t] += fit.dpose[0]
            h.frame_transl_delta[t] += fit.dtransl[0]
        self.state.history.append({"stage": "refit", "step": it, "frame": t, "loss": fit.loss_last,
                                   "rgb_before": fit.loss_first, **self.counts()})
        return f"frame {t}  L1 {fit.loss_first:.4f} -> {fit.loss_last:.4f}"

    def counts(self) -> dict[str, int]:
        c = {b: (len(getattr(self, _attr(b))) if getattr(self, _attr(b)) is not None else 0) for b in ("human", "object", "scene")}
        c["total"] = sum(c.values())
        return c

    def _hold(self, branch: str, keep: tuple[str, ...] | None = None, drop: tuple[str, ...] = ()) -> None:
        """Drop this step's gradients of a branch's parameter groups (Adam skips them)."""
        for g in self.optimizers[branch].param_groups:
            if (keep is not None and g["name"] not in keep) or g["name"] in drop:
                for p in g["params"]:
                    p.grad = None

    def _aligning(self, name: str, frac: float) -> bool:
        """Whether this step belongs to a pose-only alignment phase."""
        if self.human is None or not self.human.cfg.refine_pose:
            return False
        return (name == "I" and frac < self.cfg.pose_warmup_fraction) or (name == "II" and frac < self.cfg.pose_realign_fraction)

    def _schedule_lr(self, name: str, frac: float) -> None:
        """Pose corrections fast during the pose alignment and scaled in V-VI; the human's
        canonical positions scaled in I-II; 3DGS's exponential decay of the scene's position
        learning rate (x0.01)."""
        if "human" in self.optimizers:
            boost = self.cfg.pose_warmup_lr_scale if self._aligning(name, frac) else 1.0
            if name in ("V", "VI"):
                boost *= self.cfg.compose_pose_lr_scale
            for g in self.optimizers["human"].param_groups:
                if g["name"] == "pose":
                    g["lr"] = self.cfg.lr.human_pose * boost
                elif g["name"] == "transl":
                    g["lr"] = self.cfg.lr.human_transl * boost
                elif g["name"] == "means":
                    scale = self.cfg.human_stage_means_lr_scale if name in ("I", "II") else 1.0
                    g["lr"] = self.cfg.lr.human_means * scale
        if "scene" not in self.optimizers:
            return
        if name == "V":
            frac_all = frac * self.cfg.schedule.V / max(self.cfg.schedule.V + self.cfg.schedule.VI, 1)
        elif name == "VI":
            V, VI = self.cfg.schedule.V, self.cfg.schedule.VI
            frac_all = (V + frac * VI) / max(V + VI, 1)
        else:
            frac_all = frac
        base = self.cfg.lr.scene_means * self.extent
        for g in self.optimizers["scene"].param_groups:
            if g.get("name") == "means":
                g["lr"] = base * (0.01 ** frac_all)

    def _update_visibility(self) -> None:
        d = self.data
        v = compute_visibility(self.human, d.train, d.viewmats, d.Ks, d.width, d.height,
                               self.scene.human_masks, self.scene.object_masks, backend=self.cfg.backend)
        self.human.visibility.copy_(v)

    def _density_statistics(self) -> None:
        if not self.density:
            return
        kind, out = self._last_render
        raw = out.raw
        if raw.means2d.grad is None:
            return
        for b, st in self.density.items():
            sl = out.slices.get(b)
            if sl is None:
                continue
            dens.accumulate(st, raw.means2d.grad[sl], raw.radii[sl], self.data.width, self.data.height)

    def _density_step(self, name: str, it: int, n: int) -> None:
        for b in list(self.density):
            cfg = getattr(self.cfg, f"{b}_density")
            start, stop = int(cfg.start_fraction * n), int(cfg.stop_fraction * n)
            if it < start or it >= stop or it == 0 or (it + 1) % cfg.refine_every != 0:
                continue
            adapter = dens.adapter_for(getattr(self, _attr(b)))
            opts = [o for o in self.optimizers.values()]
            ev = dens.refine(adapter, self.density[b], cfg, self._branch_extent(b), opts, self.gen)
            if b == "scene":
                self.scene_branch.assignment = torch.full((len(self.scene_branch),), -1, dtype=torch.long)
                self._planes_assigned = False
            self.state.density_events.append({"stage": name, "step": it, "branch": b, **ev})
            if cfg.reset_opacity_every and name != "VI" and (it + 1) % cfg.reset_opacity_every == 0:
                adapter.reset_opacity(2 * cfg.prune_opacity * 10, opts)

    def _guards(self) -> None:
        """Numerical guards after each update: clamp log-scales, repair quaternions."""
        with torch.no_grad():
            for b in ("object", "scene"):
                br = getattr(self, _attr(b))
                if br is None:
                    continue
                p = br.gaussians.params
                p["scales"].clamp_(max=float(np.log(0.5 * self._branch_extent(b) + 1e-6)), min=float(np.log(1e-5)))
                q = p["quats"]
                bad = q.norm(dim=1) < 1e-8
                if bool(bad.any()):
                    q[bad] = torch.tensor([1.0, 0.0, 0.0, 0.0])
            if self.object is not None:
                q = self.object.key_q
                q.copy_(q / q.norm(dim=1, keepdim=True).clamp_min(1e-8))

    # -- checkpoints ----------------------------------------------------------------------------
    def _checkpoint(self, tag: str | None = None) -> None:
        payload = {
            "run_state": self.state,
            "branches": {b: (getattr(self, _attr(b)).state_dict() if getattr(self, _attr(b)) is not None else None) for b in ("human", "object", "scene")},
            "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
            "optimizer_groups": {k: [g.get("name") for g in o.param_groups] for k, o in self.optimizers.items()},
            "density": self.density,
            "rng": {"generator": self.gen.get_state(), "torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()},
            "planes_assigned": getattr(self, "_planes_assigned", False),
        }
        ckpt.save(self.out / "checkpoints", payload, tag)

    def _resume(self) -> None:
        payload = ckpt.load_last(self.out / "checkpoints")
        if payload is None:
            raise UserError(f"--resume: no checkpoint in {self.out / 'checkpoints'} (start without --resume)")
        self.state = payload["run_state"]
        names = self._stage_names()
        br = payload["branches"]
        # Rebuild the branches' structure (no image work), then overwrite every tensor.
        if br["human"] is not None:
            self.human = self._build_human(colors=False)
            ckpt.load_module(self.human, br["human"])
        if br["object"] is not None:
            self.object = self._build_object()
            ckpt.load_module(self.object, br["object"])
        if br["scene"] is not None:
            self.scene_branch = build_scene(self.scene, self.cfg.branches)
            ckpt.load_module(self.scene_branch, br["scene"])
        if self.state.stage < len(names):
            name = names[self.state.stage]
            # Mid-stage: that stage's optimizers. At the V -> VI boundary: V's, which VI
            # continues. Any other boundary starts fresh optimizers in run().
            live = name if self.state.step > 0 else ("V" if name == "VI" else None)
            if live is not None:
                self._ensure_branches(live, colors=False)
                self.optimizers = self._make_optimizers(live)
                for k, sd in payload["optimizers"].items():
                    self.optimizers[k].load_state_dict(sd)
                self.density = payload["density"]
        rng = payload["rng"]
        self.gen.set_state(rng["generator"])
        torch.set_rng_state(rng["torch"])
        np.random.set_state(rng["numpy"])
        random.setstate(rng["python"])
        self._planes_assigned = payload.get("planes_assigned", False)
        if self.state.stage >= len(names):
            log.info("loaded the finished run (%d stages)", len(names))
        else:
            log.info("resumed at stage %s step %d", names[self.state.stage], self.state.step)

    # -- outputs ------------------------------------------------------------------------------------
    def _export(self) -> None:
        from cogs.train.export import export_run

        export_run(self)

    def summary(self) -> dict:
        return {
            "stages": self._stage_names()[: self.state.stage],
            "train_seconds": sum(self.state.stage_seconds.values()),
            "stage_seconds": dict(self.state.stage_seconds),
            "n_gaussians": {k: v for k, v in self.counts().items() if k != "total"},
        }


def _object_share(d: FrameData) -> float:
    """Mean fraction of the frame the object's padded crop box covers (training frames)."""
    fr = []
    for t in d.train:
        m = d.object[t, ..., 0] > 0.5
        if bool(m.any()):
            y0, y1, x0, x1 = L.crop_box(m, m)
            fr.append((y1 - y0) * (x1 - x0) / (d.width * d.height))
    return float(np.mean(fr)) if fr else 1.0


def _val(x) -> float:
    return float(x.detach()) if isinstance(x, torch.Tensor) else float(x)


def load_run(run: Path, scene: Scene | None = None) -> Trainer:
    """A finished (or interrupted) run's branches, loaded from its last checkpoint."""
    from cogs.config import load_config
    from cogs.data.io import read_json
    from cogs.data.scene import load_scene

    run = Path(run)
    if not (run / "config.yaml").exists() or not (run / "checkpoints" / "last.pt").exists():
        raise UserError(f"{run} is not a training run (no config.yaml or checkpoints/last.pt)")
    if scene is None:
        info = read_json(run / "run.json")
        if not info.get("scene") or not Path(info["scene"]).exists():
            raise UserError(f"{run}/run.json names scene {info.get('scene')!r}, which does not exist; pass --scene")
        scene = load_scene(info["scene"])
    return Trainer(scene, load_config(run / "config.yaml"), run, resume=True, show_progress=False)


def _attr(branch: str) -> str:
    return {"human": "human", "object": "object", "scene": "scene_branch"}[branch]


def _bare_human(scene: Scene, cfg: TrainConfig, seed):
    """The human branch's structure without colouring from the images (for resuming)."""
    from cogs.body import load_body_model
    from cogs.branches.human import HumanBranch, sample_human_seed

    body = load_body_model(scene.body.model)
    shape = torch.as_tensor(scene.body.shape, dtype=torch.float32)
    if seed is None:
        seed = sample_human_seed(body, shape, cfg.branches.human, seed=cfg.branches.seed)
    return HumanBranch(body, shape, seed, torch.as_tensor(scene.body.pose), torch.as_tensor(scene.body.transl),
                       cfg.branches.human, train_frames=list(scene.split["train"]))


def _random_human_seed(scene: Scene, cfg: TrainConfig):
    """Ablation "no human prior seed": the same number of Gaussians spread uniformly in the
    canonical body's bounding box, isotropic, with nearest-vertex skinning weights."""
    from cogs.body import load_body_model
    from cogs.branches.human import HumanSeed

    body = load_body_model(scene.body.model)
    can = body.canonical(torch.as_tensor(scene.body.shape, dtype=torch.float32))
    n = cfg.branches.human.n_gaussians
    lo, hi = can.vertices.min(0).values, can.vertices.max(0).values
    g = torch.Generator().manual_seed(cfg.branches.seed)
    means = lo + (hi - lo) * torch.rand(n, 3, generator=g)
    nearest = torch.cdist(means, can.vertices).argmin(1)
    spacing = float(((hi - lo).prod() / n) ** (1 / 3))
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1
    return HumanSeed(means=means, quats=quats, scales=torch.full((n, 3), 0.5 * spacing),
                     opacities=torch.full((n,), 0.1), colors=torch.full((n, 3), 0.5),
                     weights=can.weights[nearest].clone(), normals=torch.zeros(n, 3))


def _randomise_object(obj, gen: torch.Generator) -> None:
    """Ablation "no object seed": a random cloud of the same size around the centre."""
    with torch.no_grad():
        m = obj.gaussians.params["means"]
        r = float((m - obj.centre).norm(dim=1).max())
        d = torch.randn(m.shape, generator=gen)
        m.copy_(obj.centre + r * d / d.norm(dim=1, keepdim=True) * torch.rand(len(m), 1, generator=gen) ** (1 / 3))
        obj.gaussians.params["sh0"].zero_()
