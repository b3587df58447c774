"""Sub-commands of the method: train, eval, demo, ablate, render-init.

Each is a dataclass whose fields are its documented options (tyro turns them into
flags) and whose `run()` does the work; `cogs.cli` lists them.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import tyro

from cogs.devices import check_device
from cogs.errors import UserError

log = logging.getLogger("cogs")


def _resolved_config(preset: str, overrides: list[str]):
    from cogs.config import apply_overrides, preset as get_preset

    return apply_overrides(get_preset(preset), overrides)


def _synthesize(out: Path, frames: int = 100, seed: int = 0, preview: bool = False) -> None:
    from cogs.data.synth.command import Synth

    Synth(out=out, frames=frames, seed=seed, preview=preview).run()


@dataclass
class Train:
    """Train the three branches on a scene with the six-stage curriculum."""

    scene: Path
    """Scene folder (native format; `cogs check` must accept it)."""
    out: Path
    """Run folder: config.yaml, checkpoints/, final/ (PLYs, trajectory), train_log.json."""
    preset: Literal["quick", "paper"] = "quick"
    """`quick`: iteration counts scaled for a 2-core CPU; `paper`: the CoGS paper's."""
    set: list[str] = field(default_factory=list)
    """Overrides, e.g. `--set schedule.VI=2000 weights.anchor=1.0` (see cogs/config.py)."""
    resume: bool = False
    """Continue from the run's last checkpoint (parameters, optimizer moments, density
    state, step and random state are restored)."""
    overwrite: bool = False
    """Replace an earlier run in --out (its files are removed, and listed, once every
    option and the scene have been checked). Without it, a non-empty --out is refused."""
    checkpoint: str | None = None
    """With --resume: continue from this file of RUN/checkpoints (e.g. `stage_IV.pt`)
    instead of the newest, `last.pt`."""
    print_config: bool = False
    """Print the fully resolved config as YAML and exit."""
    device: str = "cpu"
    """Where to train: `cpu`, or `cuda` / `cuda:N` (rasterizes with gsplat; needs the cuda extra)."""
    max_side: int | None = None
    """Train at a reduced resolution: frames, masks and intrinsics scaled so the longer side
    is at most this many pixels (the files are untouched; `cogs eval` then evaluates at
    this resolution unless `--full-resolution`). With --resume, the run's own setting holds."""

    def run(self) -> int:
        import yaml

        from cogs.config import load_config, to_dict
        from cogs.data.outdir import claimed
        from cogs.data.scene import load_scene
        from cogs.train.trainer import Trainer

        from cogs.train.run_folder import prepare_new_run

        if self.resume and self.overwrite:
            raise UserError("--resume continues the run in --out and --overwrite replaces it: choose one")
        if self.checkpoint and not self.resume:
            raise UserError("--checkpoint names the checkpoint --resume continues from: add --resume")
        if self.resume:
            if not (self.out / "config.yaml").exists():
                raise UserError(f"--resume: {self.out} has no config.yaml (was it trained there?)")
            cfg = load_config(self.out / "config.yaml")
            if self.set:
                raise UserError("--resume keeps the run's own config; drop --set (or start a new run)")
        else:
            cfg = _resolved_config(self.preset, self.set)
        if self.print_config:
            print(yaml.safe_dump(to_dict(cfg), sort_keys=False))
            return 0
        device = check_device(self.device)
        max_side = check_max_side(self.max_side)
        if self.resume:
            from cogs.data.io import read_json

            info = self.out / "run.json"
            recorded = read_json(info).get("max_side") if info.is_file() else None
            if max_side is not None and max_side != recorded:
                raise UserError(f"--max-side {max_side}: the run in {self.out} trains at {recorded or 'full resolution'}; "
                                "--resume keeps it (drop --max-side)")
            max_side = recorded
        scene = load_scene(self.scene, ground_truth=False, max_side=max_side)
        with claimed(self.out):
            if not self.resume:
                prepare_new_run(self.out, self.overwrite)
            t0 = time.perf_counter()
            summary = Trainer(scene, cfg, self.out, resume=self.resume, device=device, checkpoint=self.checkpoint,
                              max_side=max_side).run()
        log.info("trained in %.0f s (%s); Gaussians %s", time.perf_counter() - t0,
                 ", ".join(f"{k} {v:.0f}s" for k, v in summary["stage_seconds"].items()), summary["n_gaussians"])
        return 0


@dataclass
class Eval:
    """Evaluate a run with its scene's protocol; writes RUN/eval/metrics.json and renders."""

    run_dir: Annotated[Path, tyro.conf.arg(name="run")]
    """Run folder written by `cogs train`."""
    out: Path | None = None
    """Output folder (default RUN/eval)."""
    scene: Path | None = None
    """The scene the run was trained on, where run.json's path no longer holds it (moved).
    It must match the run (frames, size, split)."""
    checkpoint: str | None = None
    """Evaluate this file of RUN/checkpoints (e.g. `stage_VI.pt`) instead of the newest."""
    full_resolution: bool = False
    """For a run trained with --max-side: evaluate at the scene's full resolution (the
    model rendered with the full-size cameras) instead of the training resolution."""
    renders: bool = True
    """Save composite, per-branch, ground-truth and error images of the held-out frames."""
    pose_fit_steps: int = 40
    """Also report metrics after fitting each held-out frame's body pose to that frame
    (`test_time_pose_fit`, the Anim-NeRF/InstantAvatar protocol); 0 = strict numbers only."""
    device: str = "cpu"
    """Where to render: `cpu`, or `cuda` / `cuda:N`."""

    def run(self) -> int:
        from cogs.eval.evaluate import EVAL_ENTRIES, evaluate

        if self.pose_fit_steps < 0:
            raise UserError(f"--pose-fit-steps must be 0 or more, got {self.pose_fit_steps}")
        if self.out is not None and self.out.exists():
            if not self.out.is_dir():
                raise UserError(f"--out {self.out}: is a file; --out names the folder metrics.json and renders go in")
            foreign = sorted(p.name for p in self.out.iterdir() if p.name not in EVAL_ENTRIES)
            if foreign:
                raise UserError(f"--out {self.out}: holds files that are not an evaluation's ({', '.join(foreign[:6])}); "
                                "choose an empty or new folder")
        m = evaluate(self.run_dir, self.out, save_renders=self.renders, pose_fit_steps=self.pose_fit_steps,
                     device=check_device(self.device), scene_dir=self.scene, checkpoint=self.checkpoint,
                     full_resolution=self.full_resolution)
        # The per-frame rows stay in the file: the console gets the means.
        print(json.dumps({k: v for k, v in m.items() if k != "per_frame"}, indent=1))
        return 0


@dataclass
class Demo:
    """The main job: synthesize the benchmark scene, train (quick preset), evaluate, report.

    Re-running continues where it stopped: an existing valid scene is reused and an
    interrupted training resumes from its last checkpoint."""

    out: Path = Path("demo_out")
    """Output folder: scene/, the run (checkpoints, final/, eval/), metrics.json, report.html."""
    preset: Literal["quick", "paper"] = "quick"
    set: list[str] = field(default_factory=list)
    """Training config overrides (see `cogs train --help`)."""
    frames: int = 100
    seed: int = 0
    videos: bool = True
    """Render the camera-path and orbit videos into the report."""
    device: str = "cpu"
    """Where to train, evaluate and render: `cpu`, or `cuda` / `cuda:N`."""

    def run(self) -> int:
        from cogs.data.outdir import claimed

        t_all = time.perf_counter()
        # Every option is checked before any work; a scene the demo did not write is never replaced.
        if self.out.exists() and not self.out.is_dir():
            raise UserError(f"--out {self.out} is an existing file; --out names the demo's folder")
        _resolved_config(self.preset, self.set)
        with claimed(self.out):  # a second demo in the same folder stops here
            return self._run(t_all)

    def _run(self, t_all: float) -> int:
        from cogs.data.synth.command import Synth, reusable_synthetic_scene
        from cogs.data.validate import check_scene
        from cogs.log import console

        times: dict[str, float] = {}
        scene_dir = self.out / "scene"
        synth = Synth(out=scene_dir, frames=self.frames, seed=self.seed, preview=True)
        reuse = reusable_synthetic_scene(scene_dir)
        if not reuse:
            synth.check_options()
        t0 = time.perf_counter()
        if reuse:
            log.info("reusing the synthetic scene in %s", scene_dir)
            _warn_if_scene_differs(scene_dir, self.frames, self.seed)
        else:
            synth.run()
            problems = check_scene(scene_dir)
            if problems:  # the generator's own output: a bug in cogs
                raise AssertionError(f"the synthesized scene failed validation: {problems[0]}")
        times["synth"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        from cogs.train.trainer import run_is_finished

        device = check_device(self.device)
        if not run_is_finished(self.out):
            from cogs.config import load_config
            from cogs.data.scene import load_scene
            from cogs.train.run_folder import prepare_new_run
            from cogs.train.trainer import Trainer

            resume = (self.out / "checkpoints" / "last.pt").exists()
            if resume:
                cfg = load_config(self.out / "config.yaml")
            else:  # the demo's own folder: a start that never reached a checkpoint is redone
                cfg = _resolved_config(self.preset, self.set)
                prepare_new_run(self.out, overwrite=True, keep=("scene",))
            Trainer(load_scene(scene_dir, ground_truth=False), cfg, self.out, resume=resume, device=device).run()
        times["train"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        from cogs.eval.evaluate import evaluate
        from cogs.eval.report import write_report

        metrics = evaluate(self.out, device=device)
        shutil.copyfile(self.out / "eval" / "metrics.json", self.out / "metrics.json")
        times["eval"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        html = write_report(self.out, title="cogs demo: synthetic human-object scene",
                            extra={"preset": self.preset}, videos=self.videos, device=device)
        times["report"] = time.perf_counter() - t0
        times["total"] = time.perf_counter() - t_all
        (self.out / "demo_times.json").write_text(json.dumps(times, indent=1))
        console.print(f"[green]done[/green] in {times['total']:.0f} s: {self.out / 'metrics.json'}, {html}")
        f, h, d = metrics["full"], metrics["human_crop"], metrics.get("decomposition") or {}
        console.print(f"full PSNR {f['psnr']:.2f} dB, SSIM {f['ssim']:.3f}; human-crop PSNR {h['psnr']:.2f} dB; "
                      f"human IoU {_fmt(d.get('human_iou'))}, object IoU {_fmt(d.get('object_iou'))}", highlight=False)
        return 0


@dataclass
class RenderInit:
    """Render the initialised branches (no training) over several frames beside the
    ground truth into one PNG: the seeds in place and the object on its noisy trajectory."""

    scene: Path
    out: Path = Path("init.png")
    """The PNG (or JPEG) to write."""
    frames: int = 4
    """How many frames (spread over the clip)."""
    preset: Literal["quick", "paper"] = "quick"

    def run(self) -> int:
        import numpy as np

        from cogs.data.outdir import check_out_file

        if self.frames < 1:
            raise UserError(f"--frames must be at least 1, got {self.frames}")
        check_out_file(self.out, (".png", ".jpg", ".jpeg"))

        from cogs.branches.base import REGISTRY
        from cogs.branches.build import build_branch
        from cogs.data.io import write_image
        from cogs.data.scene import load_scene
        from cogs.eval.evaluate import _numpy, render_frame
        from cogs.eval.report import _label
        from cogs.model import Model

        scene = load_scene(self.scene)
        cfg = _resolved_config(self.preset, [])
        built = [build_branch(name, scene, cfg.branches, cfg.backend) for name in REGISTRY]
        model = Model({b.name: b for b in built if b is not None}, backend=cfg.backend)
        rows = []
        for t in np.linspace(0, scene.n_frames - 1, self.frames).round().astype(int):
            cells = [_label(scene.images[t], f"GT frame {t}")]
            cells.append(_label(_numpy(render_frame(model, scene, int(t)).rgb), "composite (init)"))
            for b in model.available():
                cells.append(_label(_numpy(render_frame(model, scene, int(t), branches=(b,)).rgb), b))
            rows.append(np.concatenate(cells, axis=1))
        write_image(self.out, np.concatenate(rows, axis=0))
        log.info("wrote %s", self.out)
        return 0


def check_max_side(value: int | None) -> int | None:
    if value is not None and value < 32:
        raise UserError(f"--max-side must be at least 32 (pixels of the longer side), got {value}")
    return value


def _warn_if_scene_differs(scene_dir: Path, frames: int, seed: int) -> None:
    from cogs.data.io import read_json

    cfg = read_json(scene_dir / "scene.json").get("source", {}).get("config", {})
    if isinstance(cfg, dict) and (cfg.get("frames"), cfg.get("seed")) != (frames, seed):
        log.warning("the existing scene has %s frames and seed %s (asked: %d and %d); it is reused as it is: "
                    "delete %s to have it written again", cfg.get("frames"), cfg.get("seed"), frames, seed, scene_dir)


def _fmt(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.3f}"


ABLATIONS: dict[str, list[str]] = {
    "full": [],
    "no human prior seed": ["use_human_seed=false"],
    "no object seed": ["use_object_seed=false"],
    "no visibility anchoring": ["use_anchoring=false"],
    "no human alpha/boundary losses": ["use_human_alpha_losses=false"],
    "no delayed planar regularization": ["use_planes=false"],
    "single-stage joint training": ["schedule.single_stage=true"],
}


@dataclass
class Ablate:
    """The paper's ablations on a scene: one training run per removed component and seed, one table."""

    out: Path = Path("ablation_out")
    scene: Path | None = None
    """Scene to use (default: synthesize the benchmark scene into OUT/scene)."""
    preset: Literal["quick", "paper"] = "quick"
    only: list[str] = field(default_factory=list)
    """Run only these variants (names as in the table; default all)."""
    seeds: list[int] = field(default_factory=lambda: [0])
    """Train every variant once per seed (e.g. 0 1): the table gives mean ± half-range."""
    device: str = "cpu"
    """Where to train and evaluate: `cpu`, or `cuda` / `cuda:N`."""

    def run(self) -> int:
        from cogs.data.validate import check_scene
        from cogs.eval.ablation import run_ablation

        unknown = set(self.only) - set(ABLATIONS)
        if unknown:  # before any work
            raise UserError(f"unknown ablation(s) {sorted(unknown)}; known: {list(ABLATIONS)}")
        if not self.seeds or len(set(self.seeds)) != len(self.seeds) or min(self.seeds) < 0:
            raise UserError(f"--seeds must be distinct non-negative integers, got {self.seeds}")
        variants = {k: v for k, v in ABLATIONS.items() if not self.only or k in self.only}
        scene = self.scene
        if scene is None:
            scene = self.out / "scene"
            if not ((scene / "scene.json").exists() and not check_scene(scene)):
                _synthesize(scene, preview=False)
        run_ablation(scene, self.out, self.preset, variants, seeds=tuple(self.seeds), device=check_device(self.device))
        return 0
