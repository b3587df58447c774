"""What `cogs render` and `cogs view` share: a run played under a body motion and an object
trajectory.

`PlaybackOptions` are the options both commands take (the run, `--motion`, `--object` and
their helpers, `--fps`, `--scene`, `--checkpoint`, `--device`); `load_playback` turns them
into the timeline both play: the model, its scene (when found), the motion resampled and
placed in the run's world, and what the object needs (which source, which frame its hand
offset comes from). `object_path` (objects.py) then gives the object's pose on that
timeline, and `timestep_poses` the poses `Model.render` / `Model.splats` take at one step.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import tyro

from cogs.errors import UserError


@dataclass(kw_only=True)
class PlaybackOptions:
    """The run and what moves in it (fields shared by `cogs render` and `cogs view`)."""

    run_dir: Annotated[Path, tyro.conf.arg(name="run")]
    """Run folder written by `cogs train`."""
    motion: str = "run"
    """run | anny:walk[:N] | synth:NAME | PATH.npz: the run's body poses; the walk cycle
    shipped with anny (N cycles, default 2); the synthetic generator's choreography
    (full, walk, pickup, turn, carry); a native body.npz, or an SMPL-family sequence
    (AMASS `poses` [T, >=66] and `trans`) retargeted onto the run's body model."""
    object: str = "run"
    """run | hand-left | hand-right | static | none | PATH.json: the trained trajectory;
    rigidly attached to a hand with the offset it has at --attach-frame; held at that
    frame's pose; removed; a trajectory in the object.json convention."""
    fps: float | None = None
    """Frames per second the motion plays at: the video's rate, the viewer's timeline steps
    (default: the motion's own; the run's clip rate for `--motion run`)."""
    attach_frame: int | None = None
    """The run's frame whose object-to-hand offset --object hand-* keeps, or whose pose
    --object static holds (default: the frame where the object sits most rigidly in the
    hand; 0 for static)."""
    hand_bone: str | None = None
    """The bone --object hand-* attaches to (default: the body model's wrist)."""
    start_frame: int | None = None
    """Where a motion from elsewhere starts: at the person's place and heading in this
    frame of the run (default 0: it takes the clip's place from its start)."""
    scene: Path | None = None
    """The run's scene, where run.json's path no longer holds it (needed for the training
    cameras, and for the default size, frame rate and orbit radius)."""
    checkpoint: str | None = None
    """Use this file of RUN/checkpoints instead of the newest."""
    device: str = "cpu"
    """Where to pose and render: `cpu`, or `cuda` / `cuda:N`."""

    def check_playback_options(self) -> str:
        """Check the shared options before any work; returns the checked device."""
        from cogs.devices import check_device

        if self.fps is not None and not (np.isfinite(self.fps) and 0 < self.fps <= 240):
            raise UserError(f"--fps {self.fps}: must be in (0, 240]")
        for name in ("attach_frame", "start_frame"):
            v = getattr(self, name)
            if v is not None and v < 0:
                raise UserError(f"--{name.replace('_', '-')} {v}: must be a frame of the run (>= 0)")
        if self.checkpoint is not None and not (self.run_dir / "checkpoints" / self.checkpoint).is_file():
            raise UserError(f"--checkpoint {self.checkpoint}: no such file in {self.run_dir / 'checkpoints'}")
        return check_device(self.device)


@dataclass
class Playback:
    """A run's timeline under one motion: what `load_playback` resolves."""

    model: Any  # cogs.model.Model
    scene: Any  # cogs.data.scene.Scene (metadata and cameras; no image read), or None
    motion: Any  # cogs.use.motion.Motion in the run's world, at `fps`; None without a human
    fps: float
    up: np.ndarray  # [3] the world's up
    object: str  # the object source to play ("none" where the object is not wanted)
    attach_frame: int | None  # resolved for hand-*; as given otherwise


def find_scene(run_dir: Path, scene: Path | None):
    """The run's scene (metadata and cameras; no image is read): `scene` (--scene), else the
    one run.json names where it still exists; None when there is none."""
    from cogs.data.io import read_json
    from cogs.data.scene import load_scene
    from cogs.train.run_folder import check_fingerprint

    info = run_dir / "run.json"
    path = scene
    if path is None:
        named = read_json(info).get("scene") if info.is_file() else None
        path = Path(named) if named and Path(named).exists() else None
    elif not (path / "scene.json").is_file():
        raise UserError(f"--scene {path}: no scene.json there")
    if path is None:
        return None
    found = load_scene(path, validate=False)
    if info.is_file():
        check_fingerprint(run_dir, read_json(info).get("fingerprint"), found)
    return found


def load_model(opts: PlaybackOptions, device: str):
    from cogs.model import Model

    ckpt = opts.run_dir / "checkpoints" / opts.checkpoint if opts.checkpoint else None
    return Model.load(opts.run_dir, device=device, checkpoint=ckpt)


def load_playback(opts: PlaybackOptions, model, scene, want_object: bool = True) -> Playback:
    """The motion `--motion` names, resampled to `--fps` (default its own) and placed where
    the person stands at `--start-frame`; the object source (`--object`, or "none" where
    `want_object` is False) with its attach frame resolved. Every bad value is a UserError
    naming its option, raised before any long work."""
    from cogs.use.export import run_fps
    from cogs.use.motion import load_motion, place, resample
    from cogs.use.objects import auto_attach_frame, hand_bone
    from cogs.use.posing import world_up

    h = model.human
    T = model.n_frames
    for name in ("attach_frame", "start_frame"):
        v = getattr(opts, name)
        if v is not None and v >= T:
            raise UserError(f"--{name.replace('_', '-')} {v}: out of range, the run has frames 0..{T - 1}")
    fps_run = scene.fps if scene is not None else run_fps(opts.run_dir)
    want_object = want_object and opts.object != "none"
    if opts.object.startswith("hand-") and want_object and h is not None:
        hand_bone(h.body, opts.object.split("-")[1], opts.hand_bone)  # a bad bone fails before any work
    elif opts.hand_bone is not None and h is not None:
        hand_bone(h.body, "right", opts.hand_bone)

    motion = load_motion(opts.motion, model, fps_run) if h is not None else None
    up = world_up(h) if h is not None else np.array([0.0, 0.0, 1.0])
    fps = opts.fps or (motion.fps if motion is not None else fps_run)
    if motion is not None:
        motion = resample(motion, fps)
    attach = opts.attach_frame
    obj_spec = opts.object if want_object else "none"
    if obj_spec.startswith("hand-") and attach is None:
        if model.object is None:
            raise UserError(f"--object {obj_spec}: the run has no object branch (use --object none)")
        attach = auto_attach_frame(model, hand_bone(h.body, obj_spec.split("-")[1], opts.hand_bone))
    if motion is not None and not motion.in_world:
        start = opts.start_frame if opts.start_frame is not None else 0
        motion = place(motion, h, start, up)
    return Playback(model, scene, motion, fps, up, obj_spec, attach)


def timestep_poses(motion, obj, k: int, n_run_frames: int) -> tuple[int, dict]:
    """(the run's frame step k shows, the poses `Model.render` takes there): the body in
    the motion's pose, the object on its path (where either is given)."""
    poses = {}
    if motion is not None:
        poses["human"] = (motion.pose[k : k + 1], motion.transl[k : k + 1])
    if obj is not None:
        poses["object"] = (obj.translation[k], obj.quat[k])
    clip_time = motion.clip_time if motion is not None else None
    frame = int(round(float(clip_time[k]))) if clip_time is not None else min(k, n_run_frames - 1)
    return frame, poses
