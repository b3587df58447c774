"""What one entry's steps do, as plain functions (no Ray here): prepare, train, eval.

    OUT/NAME/batch.json     the entry as the manifest stated it and each step's outcome
    OUT/NAME/scene/         the prepared scene (a `scene:` entry is used where it is)
    OUT/NAME/run/           the training run (config, checkpoints, final/, eval/metrics.json)
    OUT/NAME/log.txt        everything the steps logged, tracebacks included

A step is done when batch.json says so for the entry as it stands now and its output is
still there (prepare: the scene's scene.json, written last; train: the run went through
every stage; eval: metrics.json, newer than the training). A re-run does the first step
that is not done and every step after it; training that was killed resumes from its last
checkpoint. Each step function takes `report(stage)`, called with what it is doing now.
"""

from __future__ import annotations

import logging
import shutil
import threading
from pathlib import Path
from typing import Callable

from cogs.batch.manifest import Entry
from cogs.errors import UserError

log = logging.getLogger(__name__)

STEPS = ("prepare", "train", "eval")
RECORD = "batch.json"

Report = Callable[[str], None]


def scene_dir(entry: Entry, edir: Path) -> Path:
    return entry.source if entry.kind == "scene" else edir / "scene"


def run_dir(edir: Path) -> Path:
    return edir / "run"


def read_record(edir: Path) -> dict | None:
    from cogs.data.io import read_json

    path = edir / RECORD
    return read_json(path) if path.is_file() else None


def done_steps(entry: Entry, edir: Path, record: dict | None) -> list[str]:
    """The steps of `entry` whose results in `edir` stand (see the module docstring)."""
    from cogs.train.trainer import run_is_finished

    steps = (record or {}).get("steps", {})

    def recorded(step: str) -> bool:
        r = steps.get(step) or {}
        return r.get("status") == "done" and r.get("spec") == entry.step_spec(step)

    done = []
    if not (recorded("prepare") and (scene_dir(entry, edir) / "scene.json").is_file()):
        return done
    done.append("prepare")
    run = run_dir(edir)
    if not run_is_finished(run):
        return done
    done.append("train")
    metrics, summary = run / "eval" / "metrics.json", run / "train_summary.json"
    if recorded("eval") and metrics.is_file() and metrics.stat().st_mtime >= summary.stat().st_mtime:
        done.append("eval")
    return done


def conflict(entry: Entry, edir: Path, record: dict | None) -> str | None:
    """Why `edir` cannot hold `entry`'s work without losing or silently reusing other work
    (None when it can): a folder cogs batch did not write, or a run trained for another
    version of the entry (resuming it would continue the old config)."""
    if not edir.exists():
        return None
    if not edir.is_dir():
        return f"{edir} is a file"
    if record is None:
        if any(edir.iterdir()):
            return f"{edir} holds files that cogs batch did not write (no {RECORD})"
        return None
    if (run_dir(edir) / "config.yaml").exists():
        old = ((record.get("steps") or {}).get("train") or {}).get("spec") or record.get("spec")
        old = {k: old.get(k) for k in ("source", "options", "train")} if old else None
        if old != entry.step_spec("train"):
            changed = [k for k in ("source", "options", "train") if (old or {}).get(k) != entry.spec[k]]
            return (f"{edir}/run was trained for another version of entry {entry.name!r} (its {', '.join(changed)} "
                    "changed in the manifest)")
    return None


# -- the steps ------------------------------------------------------------------------------


def prepare(entry: Entry, edir: Path, report: Report, device: str = "cpu") -> dict:
    """Make (or check) the entry's scene; raises UserError with the scene's problems.
    (`device` is unused: preparing runs on the host.)"""
    from cogs.data.validate import check_scene

    scene = scene_dir(entry, edir)
    if entry.kind == "scene":
        report("check")
    elif entry.kind == "video":
        from cogs.preprocess.command import Preprocess
        from cogs.preprocess.pipeline import run_preprocess

        report("preprocess")
        # Into the scene folder itself: its .cache/ lets a re-run resume the pipeline.
        run_preprocess(Preprocess(input=entry.source, out=scene, progress=False, **entry.options))
    else:
        partial = edir / "scene.partial"  # a new scene replaces the old one whole, or not at all
        if partial.exists():
            shutil.rmtree(partial)
        if entry.kind == "synth":
            from cogs.data.scene import save_scene
            from cogs.data.synth.config import NoiseConfig, SynthConfig
            from cogs.data.synth.generate import generate_scene

            report("synth")
            opts = dict(entry.options)
            noise = NoiseConfig(**opts.pop("noise", {}))
            save_scene(generate_scene(SynthConfig(**opts, noise=noise), show_progress=False), partial)
        else:
            from cogs.preprocess.importers import IMPORTERS

            report(f"import {entry.kind}")
            opts = dict(entry.options)
            if opts.get("smpl_model") is not None:
                from cogs.body.smpl_body import set_smpl_model_path

                set_smpl_model_path(opts["smpl_model"])
            IMPORTERS[entry.kind](entry.source, partial, **opts)
        if scene.exists():
            shutil.rmtree(scene)
        partial.rename(scene)
    report("check")
    problems = check_scene(scene)
    if problems:
        more = f" (and {len(problems) - 1} more; `cogs check {scene}` lists them)" if len(problems) > 1 else ""
        raise UserError(f"scene {scene}: {problems[0]}{more}")
    log.info("scene %s is valid", scene)
    return {"scene": str(scene)}


def train(entry: Entry, edir: Path, report: Report, device: str = "cpu") -> dict:
    """Train the entry's run, resuming it from its last checkpoint where one exists."""
    from cogs.config import apply_overrides, load_config, preset
    from cogs.data.scene import load_scene
    from cogs.train.run_folder import prepare_new_run
    from cogs.train.trainer import Trainer

    from cogs.data.io import read_json
    from cogs.train.trainer import run_is_finished

    run = run_dir(edir)
    if run_is_finished(run):  # its scene was prepared again: the run stands
        return {"resumed": False, "train_seconds": read_json(run / "train_summary.json")["train_seconds"]}
    _smpl_path(entry)
    report("start")
    resume = (run / "checkpoints" / "last.pt").exists()
    if resume:
        cfg = load_config(run / "config.yaml")
        log.info("resuming %s from its last checkpoint", run)
    else:  # the batch's own folder: a start that never reached a checkpoint is redone
        cfg = apply_overrides(preset(entry.preset), list(entry.overrides))
        prepare_new_run(run, overwrite=True)
    trainer = Trainer(load_scene(scene_dir(entry, edir), ground_truth=False), cfg, run, resume=resume, show_progress=False, device=device)
    stop = threading.Event()
    watcher = threading.Thread(target=_watch, args=(trainer, report, stop), daemon=True)
    watcher.start()
    try:
        summary = trainer.run()
    finally:
        stop.set()
        watcher.join()
    return {"resumed": resume, "train_seconds": summary["train_seconds"]}


def _watch(trainer, report: Report, stop: threading.Event, every_s: float = 1.0) -> None:
    """Report the trainer's stage and step until `stop` (the loop has no callback, and
    needs none: two integers are read)."""
    while not stop.wait(every_s):
        i, step = trainer.state.stage, trainer.state.step
        if i < len(trainer.stages):
            spec = trainer.stages[i]
            report(f"{spec.name} {step}/{spec.steps}")


def evaluate(entry: Entry, edir: Path, report: Report, device: str = "cpu") -> dict:
    """Evaluate the entry's run; returns the metrics (also in RUN/eval/metrics.json)."""
    from cogs.eval.evaluate import evaluate as evaluate_run

    _smpl_path(entry)
    report("metrics")
    return evaluate_run(run_dir(edir), save_renders=entry.eval["renders"], pose_fit_steps=entry.eval["pose_fit_steps"],
                        show_progress=False, device=device, scene_dir=scene_dir(entry, edir))


def _smpl_path(entry: Entry) -> None:
    if entry.options.get("smpl_model") is not None:
        from cogs.body.smpl_body import set_smpl_model_path

        set_smpl_model_path(entry.options["smpl_model"])


STEP_FUNCTIONS = {"prepare": prepare, "train": train, "eval": evaluate}
