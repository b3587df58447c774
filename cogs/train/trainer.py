"""The trainer: optimisation only. It reads the run's stages (`stages.py`) and, for each,
keeps the optimizers, the density-control state and the checkpoints.

One step of an "optimise" stage:

    refresh the inputs of the anchor and plane terms on their cadences (visibility
    scores, plane assignment); set every group's learning rate from the spec; draw a
    training frame; each branch prepares (the human decodes its field; frozen branches
    without a graph); each of the stage's objectives renders and returns its terms, each
    branch adds its regularisers; the weighted terms are summed; backward; held groups
    drop their gradients; density statistics from the step's renders; Adam; guards;
    density control on its schedule.

Everything random draws from one seeded host generator whose state is checkpointed (as
are the global generators some module initialisers use), so a run killed at any point
and resumed from its last checkpoint ends with the same parameters as an uninterrupted
one. Host-device syncs happen at logging and checkpoint cadence, plus the few the crop
boxes and the guards' extents need.
"""

from __future__ import annotations

import logging
import random
import time
from pathlib import Path

import numpy as np
import torch

from cogs.branches.base import REGISTRY
from cogs.branches.build import build_branch, object_train_frames
from cogs.branches.human import compute_visibility
from cogs.config import STAGES, TrainConfig, save_config, validate_config
from cogs.data.scene import Scene
from cogs.errors import UserError
from cogs.model import Model, _legacy, upgrade_legacy
from cogs.train import checkpoint as ckpt
from cogs.train.checkpoint import RunState
from cogs.train.density import DensityStrategy
from cogs.train.frames import TrainFrames
from cogs.train.memory import check_fits
from cogs.train.objectives import OBJECTIVES, RENDERS, StepInputs
from cogs.train.stages import StageSpec, build_stages, stage_names

log = logging.getLogger(__name__)


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


def _fuses(device: torch.device, fused: bool) -> bool:
    return bool(fused and torch.device(device).type == "cuda")


def make_adam(groups: list[dict], device: torch.device, fused: bool = True) -> torch.optim.Adam:
    """The branches' Adam. On CUDA (with `fused`) the update is one fused kernel per
    parameter group instead of torch's multi-tensor passes: a GPU step is bound by the host
    issuing small kernels (docs/experiments/2026-11-27-gpu-step-profile.md). The host keeps
    torch's default update, so CPU runs stay bit-identical to earlier ones."""
    return torch.optim.Adam(groups, eps=1e-15, fused=True if _fuses(device, fused) else None)


def adopt_fusion(opt: torch.optim.Optimizer, device: torch.device, fused: bool = True) -> None:
    """After `load_state_dict`: the saved groups carry the writer's `fused` flag (a run
    resumed on another device), so set the one this device takes."""
    on = _fuses(device, fused)
    for g in opt.param_groups:
        g["fused"] = on or None
        if on:
            g["foreach"] = None
            for p in g["params"]:  # the fused kernel takes its step count on the parameter's device
                st = opt.state.get(p)
                if st is not None and "step" in st:
                    st["step"] = torch.as_tensor(st["step"], dtype=torch.float32).to(p.device)


class Trainer:
    def __init__(self, scene: Scene, cfg: TrainConfig, out: Path, resume: bool = False, show_progress: bool = True,
                 device: str | torch.device = "cpu", checkpoint: str | None = None, max_side: int | None = None):
        self.scene, self.cfg, self.out = scene, validate_config(cfg), Path(out)
        self.show_progress = show_progress
        self.device = torch.device(device)
        check_fits(scene.n_frames, scene.width, scene.height, cfg, scene.root)
        self.frames = TrainFrames(scene, self.device, cfg.branches.object.min_confidence)
        if not self.frames.train:
            raise UserError(f"scene {scene.root}: the split has no training frames")
        if scene.has_object:
            object_train_frames(scene, cfg.branches.object.min_confidence)  # raises when none is trusted
        self.extent = self.frames.extent()
        self.stages = build_stages(cfg, len(self.frames.train), object_share=self.frames.object_share())
        skipped = [s for s in STAGES if getattr(cfg.schedule, s) == 0 and not cfg.schedule.single_stage]
        if skipped:
            log.info("stage(s) %s set to 0 steps: skipped", ", ".join(skipped))
        # Module initialisers draw from the global generators: seed them too.
        torch.manual_seed(cfg.seed)
        np.random.seed(cfg.seed)
        random.seed(cfg.seed)
        self.gen = torch.Generator(device="cpu").manual_seed(cfg.seed)
        self.state = RunState()
        self.model = Model(backend=cfg.backend)
        self.optimizers: dict[str, torch.optim.Optimizer] = {}
        self.density: dict[str, dict] = {}  # branch -> its density statistics
        self.strategies = {b: DensityStrategy(b, getattr(cfg, f"{b}_density")) for b in REGISTRY}
        self._planes_assigned = False
        self._nonfinite = torch.zeros((), dtype=torch.bool, device=self.device)
        self.out.mkdir(parents=True, exist_ok=True)
        from cogs.render import warmup
        from cogs.ssim import warmup as ssim_warmup

        warmup()
        ssim_warmup()
        if resume:
            self._resume(checkpoint)
        else:
            save_config(cfg, self.out / "config.yaml")
            from cogs.data.io import write_json

            from cogs.train.run_folder import scene_fingerprint

            write_json(self.out / "run.json", {"scene": str(Path(scene.root).resolve()) if scene.root else None,
                                               "preset": cfg.preset, "fingerprint": scene_fingerprint(scene),
                                               "max_side": max_side, "size": [scene.width, scene.height]})

    # -- branches and optimizers ----------------------------------------------------------
    def _ensure_branches(self, spec: StageSpec) -> None:
        """Build (on the host, then moved) the branches the stage renders that do not exist
        yet, in registry order: the human in I, the object in III, the scene in V."""
        need = set()
        for o in spec.objectives:
            need |= set(RENDERS[o] or REGISTRY)
        cfg = self.cfg
        backend = "cpu" if cfg.backend == "gsplat" else cfg.backend  # initialisation runs on the host
        seeded = {"human": cfg.use_human_seed, "object": cfg.use_object_seed}
        for name in REGISTRY:
            if name in need and self.model.get(name) is None:
                branch = build_branch(name, self.scene, cfg.branches, backend, seeded.get(name, True), self.gen)
                if branch is not None:
                    self.model.add(branch.to(self.device))

    def _make_optimizers(self, spec: StageSpec) -> dict[str, torch.optim.Optimizer]:
        opts = {}
        for b in spec.trains:
            branch = self.model.get(b)
            if branch is None:
                continue
            groups = branch.param_groups(self.cfg.lr, self.extent)
            for g in groups:
                g["base_lr"] = g["lr"]
            opts[b] = make_adam(groups, self.device, self.cfg.fused_adam)
        return opts

    def _setup_stage(self, spec: StageSpec) -> None:
        """Branches, optimizers and density state at the start of a stage."""
        if spec.kind == "refit":
            return
        self._ensure_branches(spec)
        if spec.continues and self.optimizers:
            return  # the true resume: the previous stage's optimizers and density state carry on
        self.optimizers = self._make_optimizers(spec)
        self.density = {b: self.strategies[b].initialize_state(len(self.model.get(b)), self.device)
                        for b in spec.density if self.model.get(b) is not None}

    # -- the loop ---------------------------------------------------------------------------
    def stage_in_progress(self) -> str | None:
        return self.stages[self.state.stage].name if self.state.stage < len(self.stages) else None

    def finished(self) -> bool:
        return self.stage_in_progress() is None

    def run(self) -> dict:
        from cogs.log import progress, rate_text

        with progress() as bar:
            while self.state.stage < len(self.stages):
                spec = self.stages[self.state.stage]
                n = spec.steps
                if self.state.step == 0:
                    self._setup_stage(spec)
                if n == 0:
                    log.info("stage %s (%s): 0 steps, skipped", spec.name, spec.title)
                    self._end_stage(spec)
                    continue
                task = bar.add_task(f"{spec.name:>3} {spec.title}", total=n, completed=self.state.step, rate="", info="",
                                    visible=self.show_progress)
                started, t0 = time.perf_counter(), self.state.step
                info = ""
                while self.state.step < n:
                    tic, cpu = time.perf_counter(), time.process_time()
                    it = self.state.step
                    logged = self._refit_step(it) if spec.kind == "refit" else self._step(spec, it)
                    self.state.step += 1
                    st = self.state
                    st.stage_seconds[spec.name] = st.stage_seconds.get(spec.name, 0.0) + time.perf_counter() - tic
                    st.stage_cpu_seconds[spec.name] = st.stage_cpu_seconds.get(spec.name, 0.0) + time.process_time() - cpu
                    info = logged or info
                    bar.update(task, completed=self.state.step, rate=rate_text(self.state.step - t0, started), info=info)
                    if not bar.console.is_terminal and (self.state.step % 25 == 0 or self.state.step == n):
                        done = self.state.step - t0
                        eta = (time.perf_counter() - started) / max(done, 1) * (n - self.state.step)
                        log.info("stage %s %d/%d  %s  %s  eta %.0f s", spec.name, self.state.step, n,
                                 rate_text(done, started).strip(), info, eta)
                    if self.state.step % self.cfg.checkpoint_every == 0 and self.state.step < n:
                        self._checkpoint()
                self._end_stage(spec)
        self._export()
        return self.summary()

    def _end_stage(self, spec: StageSpec) -> None:
        self.state.stage += 1
        self.state.step = 0
        self._checkpoint(tag=f"stage_{spec.name}")

    def _step(self, spec: StageSpec, it: int) -> str | None:
        """One optimisation step; returns the progress line at logging cadence."""
        cfg, model, n = self.cfg, self.model, spec.steps
        frac = it / max(n, 1)
        phases = spec.active_phases(frac)
        weights = spec.weights_at(frac)
        self._refresh(spec, it, weights)
        self._schedule_lr(spec, frac, phases)
        train = self.frames.pool(spec.objectives)
        t = train[int(torch.randint(len(train), (1,), generator=self.gen, device="cpu"))]
        for opt in self.optimizers.values():
            opt.zero_grad(set_to_none=True)
        prepared = {}
        for name in model.available():
            with torch.set_grad_enabled(name in spec.trains):
                prepared[name] = model.get(name).prepare()
        inputs = StepInputs(model, self.frames.frame(t), weights, prepared, self._background, cfg.crop_human_losses)
        terms, renders = {}, []
        for objective in spec.objectives:
            image_terms, render = OBJECTIVES[objective](inputs)
            terms.update({f"{objective}.{k}": v for k, v in image_terms.items()})
            if render is not None:
                renders.append(render)
        for name, branch in model.branches.items():
            scale = spec.scales.get(name)
            for k, v in branch.regularisers(weights, self.frames.train_tensor, prepared.get(name)).items():
                terms[f"{name}.{k}"] = v if scale is None else scale * v
        loss = sum(terms.values())
        self._nonfinite |= ~torch.isfinite(loss.detach())
        log_now = it % cfg.log_every == 0 or it == n - 1
        if log_now:
            self._check_finite(spec, it, t, terms)
        loss.backward()
        self._hold(spec, phases)
        for b, st in self.density.items():
            for r in renders:
                self.strategies[b].step_post_backward(st, r, self.frames.width, self.frames.height)
        for opt in self.optimizers.values():
            opt.step()
        for branch in model.branches.values():
            branch.guard(branch.extent(self.extent))
        self._density_step(spec, it)
        if not log_now:
            return None
        counts = model.counts()
        entry = {"stage": spec.name, "step": it, "frame": t, "loss": float(loss.detach()),
                 **{k: float(v.detach()) for k, v in terms.items()}, **counts, "total": sum(counts.values())}
        self.state.history.append(entry)
        return f"loss {entry['loss']:.4f}  G {entry['total']}"

    def _background(self) -> torch.Tensor:
        """A random background colour [3] on the training device (drawn on the host)."""
        return torch.rand(3, generator=self.gen, device="cpu").to(self.device)

    def _check_finite(self, spec: StageSpec, it: int, t: int, terms: dict) -> None:
        """Raise if any loss since the last check was not finite (one device sync)."""
        if bool(self._nonfinite):
            vals = {k: float(v.detach()) for k, v in terms.items()}
            raise FloatingPointError(f"stage {spec.name} step {it} frame {t}: a non-finite loss since the last "
                                     f"check (every {self.cfg.log_every} steps); this step's terms: {vals}")

    def _refresh(self, spec: StageSpec, it: int, weights: dict) -> None:
        """Inputs of two loss terms, recomputed on their cadences: the human's visibility
        scores (anchoring) and which scene Gaussians the plane term acts on."""
        cfg, model = self.cfg, self.model
        if "anchor" in weights and "human" in spec.trains and model.human is not None \
                and (it == 0 or it % cfg.visibility_every == 0):
            f = self.frames
            v = compute_visibility(model.human, f.train, f.viewmats, f.Ks, f.width, f.height, f.person_mask,
                                   backend=cfg.backend)
            model.human.visibility.copy_(v)
        if "plane" in weights and model.scene is not None \
                and (it % cfg.plane_assign_every == 0 or not self._planes_assigned):
            model.scene.assign_planes()
            self._planes_assigned = True

    def _schedule_lr(self, spec: StageSpec, frac: float, phases) -> None:
        """Each group's base rate times the stage's and active phases' scales, and the
        stage's exponential decays (3DGS: the scene's positions x0.01 over V-VI)."""
        if spec.decay_window is None:
            frac_all = frac
        else:
            offset, span = spec.decay_window
            frac_all = (offset + frac * spec.steps) / span
        for b, opt in self.optimizers.items():
            for g in opt.param_groups:
                key = f"{b}.{g['name']}"
                lr = g["base_lr"]
                factors = [p.lr_scales[key] for p in phases if key in p.lr_scales]
                if key in spec.lr_scales:
                    factors.append(spec.lr_scales[key])
                if factors:
                    scale = 1.0
                    for f in factors:
                        scale *= f
                    lr = lr * scale
                if key in spec.decay:
                    lr = lr * (spec.decay[key] ** frac_all)
                g["lr"] = lr

    def _hold(self, spec: StageSpec, phases) -> None:
        """Drop this step's gradients of the held parameter groups (Adam skips them)."""
        for b, opt in self.optimizers.items():
            drop = set(spec.hold.get(b, ()))
            only = None
            for p in phases:
                drop |= set(p.hold.get(b, ()))
                if b in p.only:
                    only = set(p.only[b])
            for g in opt.param_groups:
                if g["name"] in drop or (only is not None and g["name"] not in only):
                    for p in g["params"]:
                        p.grad = None

    def _density_step(self, spec: StageSpec, it: int) -> None:
        for b in list(self.density):
            strategy = self.strategies[b]
            if not strategy.due(it, spec.steps):
                continue
            branch = self.model.get(b)
            ev = strategy.step_refine(self.density[b], branch.density_adapter(), branch.extent(self.extent),
                                      list(self.optimizers.values()), self.gen)
            if b == "scene":
                branch.clear_assignment()
                self._planes_assigned = False
            self.state.density_events.append({"stage": spec.name, "step": it, "branch": b, **ev})

    def _refit_step(self, it: int) -> str:
        """Fit training frame `it`'s body pose against the finished model and keep it as
        that frame's per-frame correction. Draws nothing from the generator, so the
        refit's result is the same whether or not the run was interrupted during it."""
        from cogs.train.posefit import fit_frame_pose

        f, h = self.frames, self.model.human
        t = f.train[it]
        fit = fit_frame_pose(self.model, f.image(t), f.viewmats[t], f.Ks[t], t, self.cfg.refit)
        with torch.no_grad():
            h.frame_pose_delta[t] += fit.dpose[0]
            h.frame_transl_delta[t] += fit.dtransl[0]
        counts = self.model.counts()
        self.state.history.append({"stage": "refit", "step": it, "frame": t, "loss": fit.loss_last,
                                   "rgb_before": fit.loss_first, **counts, "total": sum(counts.values())})
        return f"frame {t}  L1 {fit.loss_first:.4f} -> {fit.loss_last:.4f}"

    # -- checkpoints ----------------------------------------------------------------------------
    def _checkpoint(self, tag: str | None = None) -> None:
        payload = {
            "run_state": self.state,
            **self.model.payload(),
            "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
            "optimizer_groups": {k: [g.get("name") for g in o.param_groups] for k, o in self.optimizers.items()},
            "density": self.density,
            "rng": {"generator": self.gen.get_state(), "torch": torch.get_rng_state(), "numpy": np.random.get_state(),
                    "python": random.getstate()},
            "planes_assigned": self._planes_assigned,
        }
        ckpt.save(self.out / "checkpoints", payload, tag)

    def _resume(self, name: str | None = None) -> None:
        folder = self.out / "checkpoints"
        payload = ckpt.load_last(folder, name)
        if payload is None:
            raise UserError(f"--resume: no checkpoint in {folder} (start without --resume)")
        self.state = payload["run_state"]
        branches, body = payload["branches"], payload.get("body_model")
        if _legacy(branches):
            branches, body = upgrade_legacy(self.out, self.cfg, branches)
        self.model = Model.from_payload(branches, body, self.cfg, self.device)
        if self.state.stage < len(self.stages):
            spec = self.stages[self.state.stage]
            # Mid-stage, or at the start of a stage that continues the previous one's
            # optimizers (VI): those optimizers and density state. Any other stage start
            # builds fresh ones in run().
            if spec.kind == "optimise" and (self.state.step > 0 or spec.continues):
                self.optimizers = self._make_optimizers(spec)
                for k, sd in payload["optimizers"].items():
                    try:
                        self.optimizers[k].load_state_dict(sd)
                        adopt_fusion(self.optimizers[k], self.device, self.cfg.fused_adam)
                    except (KeyError, ValueError) as e:
                        raise UserError(f"--resume: {folder / 'last.pt'} was written by an older cogs whose "
                                        f"optimizers differ ({e}); evaluate it as it is, or retrain") from None
                self.density = {b: {k: v.to(self.device) for k, v in st.items()} for b, st in payload["density"].items()}
        rng = payload["rng"]
        self.gen.set_state(rng["generator"])
        torch.set_rng_state(rng["torch"])
        np.random.set_state(rng["numpy"])
        random.setstate(rng["python"])
        self._planes_assigned = payload.get("planes_assigned", False)
        if self.finished():
            log.info("loaded the finished run (%d stages)", len(self.stages))
        else:
            log.info("resumed at stage %s step %d", self.stage_in_progress(), self.state.step)

    # -- outputs ------------------------------------------------------------------------------------
    def _export(self) -> None:
        from cogs.data.io import write_json

        self.model.export(self.out / "final", self.scene.n_frames)
        write_json(self.out / "train_log.json", {"history": self.state.history, "density": self.state.density_events})
        write_json(self.out / "train_summary.json", self.summary())

    def summary(self) -> dict:
        return {
            "stages": [s.name for s in self.stages[: self.state.stage]],
            "train_seconds": sum(self.state.stage_seconds.values()),
            "stage_seconds": dict(self.state.stage_seconds),
            "stage_cpu_utilisation": {k: round(self.state.stage_cpu_seconds[k] / v, 3)
                                      for k, v in self.state.stage_seconds.items() if v > 0 and k in self.state.stage_cpu_seconds},
            "n_gaussians": self.model.counts(),
        }
