"""A run folder's files, and the rules that keep a user's work safe in it.

    RUN/config.yaml          the resolved TrainConfig (written before training starts)
    RUN/run.json             the scene it trains on and that scene's fingerprint
    RUN/checkpoints/         last.pt, stage_<name>.pt, last.json
    RUN/final/               exported PLYs, body poses, object trajectory
    RUN/train_log.json, train_summary.json, eval/, report.*, report_files/

A new run goes only into a folder that is absent or empty; `--overwrite` removes an
earlier run's files there first, saying which, and refuses a folder holding anything
else. So a run never mixes one run's config with another's checkpoints. The scene
fingerprint lets `cogs eval` refuse a scene that is not the one the run trained on.
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
from pathlib import Path

from cogs.errors import UserError

log = logging.getLogger(__name__)

RUN_ENTRIES = ("config.yaml", "run.json", "checkpoints", "final", "train_log.json", "train_summary.json", "eval",
               "report.html", "report.md", "report_files", "metrics.json", "demo_times.json")
"""What cogs writes into a run folder (the demo's run folder also holds its scene/)."""


def is_run(folder: Path) -> bool:
    folder = Path(folder)
    return (folder / "config.yaml").is_file() and ((folder / "run.json").is_file() or (folder / "checkpoints").is_dir())


def prepare_new_run(out: Path, overwrite: bool, keep: tuple[str, ...] = ()) -> None:
    """Check (and with `overwrite`, clear) `out` for a new run, before anything is written.
    `keep`: entries a caller put there itself (the demo's scene/)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out}: is a file, not a folder; choose a folder for the run")
    if not out.exists():
        return
    present = sorted(p.name for p in out.iterdir() if p.name not in keep)
    if not present:
        return
    ours = [n for n in present if n in RUN_ENTRIES]
    foreign = [n for n in present if n not in RUN_ENTRIES]
    if foreign:
        shown = ", ".join(foreign[:6]) + (", ..." if len(foreign) > 6 else "")
        raise UserError(f"--out {out}: the folder holds files that are not a cogs run ({shown}); "
                        "choose an empty or new folder")
    if not overwrite:
        what = "a finished run" if (out / "train_summary.json").exists() else "an earlier run"
        raise UserError(f"--out {out}: holds {what} ({', '.join(ours)}). Continue it with --resume, "
                        "replace it with --overwrite, or choose another folder")
    for name in ours:
        path = out / name
        shutil.rmtree(path) if path.is_dir() and not path.is_symlink() else path.unlink()
    log.warning("--overwrite: removed the earlier run's %s from %s", ", ".join(ours), out)


def scene_fingerprint(scene) -> dict:
    """What identifies the scene a run trained on: frame count, size on disk, split."""
    split = json.dumps({k: [int(t) for t in v] for k, v in sorted(scene.split.items())}, sort_keys=True)
    width, height = scene.full_size or (scene.width, scene.height)
    return {"frames": int(scene.n_frames), "width": int(width), "height": int(height),
            "split_sha1": hashlib.sha1(split.encode()).hexdigest()[:12]}


def check_fingerprint(run: Path, recorded: dict | None, scene) -> None:
    """Refuse a scene that differs from the one the run trained on (runs trained before the
    fingerprint was recorded are not checked)."""
    if not recorded:
        return
    now = scene_fingerprint(scene)
    diff = [f"{k} {recorded[k]} in the run, {now[k]} in the scene" for k in now if k in recorded and recorded[k] != now[k]]
    if diff:
        raise UserError(f"{run} was trained on another scene than {scene.root}: {'; '.join(diff)}. "
                        "Pass the scene it was trained on with --scene")
