"""`cogs render`: a trained run from any camera path, with any body motion and object
trajectory, any subset of branches; an .mp4 (PyAV, H.264) or a folder of PNG frames.

    cogs render --run RUN --out walk.mp4 --camera orbit --motion anny:walk --object hand-right
    cogs render --run RUN --out plate.mp4 --branches scene          # the clean plate

Every option is checked before any frame is rendered; a bad value is a `UserError`
naming the option. Folder output: OUT/rgb/NNNNNN.png, with --depth OUT/depth.npz
(`depth` [T, H, W] float16 metres, 0 where nothing was hit, as the scene format's
gt/depth.npz) and with --alpha OUT/alpha/<branch>/NNNNNN.png. Video output writes the
depth (colour-mapped) and alphas as videos beside it: OUT.depth.mp4, OUT.alpha-<branch>.mp4.
The resolved options (attach frame, start frame, frame rate, ...) go to OUT/render.json, or
OUT.json beside a video.
"""

from __future__ import annotations

import logging
import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from cogs.errors import UserError
from cogs.use.playback import PlaybackOptions

log = logging.getLogger("cogs")

BRANCH_NAMES = ("human", "object", "scene")


@dataclass(kw_only=True)
class Render(PlaybackOptions):
    """Render a trained run from new cameras, with new body motions and object
    trajectories: a video (.mp4) or a folder of PNG frames."""

    out: Path
    """An .mp4 file, or a folder (created) for PNG frames."""
    camera: str = "train"
    """train | orbit | spiral | novel | PATH.json: the training cameras; a circle or a
    spiral round the person; the synthetic scene's novel-view cameras; a camera path
    (keys in the scene format's convention, interpolated smoothly)."""
    branches: list[str] = field(default_factory=lambda: list(BRANCH_NAMES))
    """Branches to render (`scene` alone is the clean plate: the room without person and object)."""
    frames: str | None = None
    """A:B: render only output frames A..B-1 (Python slice; either end may be left out)."""
    size: str | None = None
    """WxH output size in pixels (default: the scene's image size)."""
    depth: bool = False
    """Also write depth (metres; a colour-mapped video beside an .mp4)."""
    alpha: bool = False
    """Also write each rendered branch's alpha."""
    background: str = "black"
    """black | white | R,G,B in [0, 1]."""
    overwrite: bool = False
    """Replace an existing --out."""

    def run(self) -> int:
        from cogs.data.outdir import claimed

        opts = self._check_options()
        with claimed(self.out):  # a second render into the same --out stops at once
            return render(self, **opts)

    def _check_options(self) -> dict:
        video = self.out.suffix.lower() == ".mp4"
        if self.out.suffix and not video:
            raise UserError(f"--out {self.out}: expected an .mp4 file or a folder (no suffix)")
        if self.out.exists() and not self.overwrite and (video or not self.out.is_dir() or any(self.out.iterdir())):
            raise UserError(f"--out {self.out} exists; choose another path or pass --overwrite")
        unknown = [b for b in self.branches if b not in BRANCH_NAMES]
        if unknown or not self.branches or len(set(self.branches)) != len(self.branches):
            raise UserError(f"--branches {' '.join(self.branches)}: give distinct names among {', '.join(BRANCH_NAMES)}")
        frames = parse_frames(self.frames)
        size = parse_size(self.size)
        background = parse_background(self.background)
        device = self.check_playback_options()
        return {"video": video, "frames": frames, "size": size, "background": background, "device": device}


def parse_frames(spec: str | None) -> tuple[int | None, int | None] | None:
    if spec is None:
        return None
    m = re.fullmatch(r"\s*(-?\d*)\s*:\s*(-?\d*)\s*", spec)
    if not m:
        raise UserError(f"--frames {spec}: expected A:B (e.g. 0:40, 10:, :25)")
    a, b = (int(x) if x else None for x in m.groups())
    if (a is not None and a < 0) or (b is not None and b < 0):
        raise UserError(f"--frames {spec}: frames count from 0")
    return a, b


def parse_size(spec: str | None) -> tuple[int, int] | None:
    if spec is None:
        return None
    m = re.fullmatch(r"(\d+)[xX](\d+)", spec.strip())
    if not m or not (16 <= int(m.group(1)) <= 8192 and 16 <= int(m.group(2)) <= 8192):
        raise UserError(f"--size {spec}: expected WxH in pixels, each 16..8192 (e.g. 640x480)")
    return int(m.group(1)), int(m.group(2))


def parse_background(spec: str) -> tuple[float, float, float]:
    named = {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0)}
    if spec in named:
        return named[spec]
    try:
        rgb = tuple(float(x) for x in spec.split(","))
    except ValueError:
        rgb = ()
    if len(rgb) != 3 or not all(np.isfinite(c) and 0 <= c <= 1 for c in rgb):
        raise UserError(f"--background {spec}: expected black, white or R,G,B with each in [0, 1]")
    return rgb  # type: ignore[return-value]


@torch.no_grad()
def render(cmd: Render, video: bool, frames, size, background, device: str) -> int:
    from cogs.log import track
    from cogs.use.cameras import camera_path
    from cogs.use.motion import select
    from cogs.use.objects import object_path
    from cogs.use.playback import find_scene, load_model, load_playback, timestep_poses

    model = load_model(cmd, device)
    scene = find_scene(cmd.run_dir, cmd.scene)
    have = model.available()
    missing = [b for b in cmd.branches if b not in have]
    if missing:
        raise UserError(f"--branches: the run has no {', '.join(missing)} branch (it has {', '.join(have)})")
    T = model.n_frames
    play = load_playback(cmd, model, scene, want_object="object" in cmd.branches)
    motion, fps, up, obj_spec, attach = play.motion, play.fps, play.up, play.object, play.attach_frame

    if cmd.camera == "novel":  # one output frame per novel camera, at its own time
        cams = camera_path("novel", 0, scene, model, motion, up, size, fps)
        n = len(cams.viewmats)
        if motion is not None:
            idx = (cams.clip_frames if motion.clip_time is not None else np.arange(n)) % len(motion)
            motion = _index(motion, idx)
    else:
        n = len(motion) if motion is not None else (scene.n_frames if scene is not None else T)
        cams = None
    if frames is not None:
        a, b = frames
        a = 0 if a is None else a
        b = n if b is None else b
        if not 0 <= a < b <= n:
            raise UserError(f"--frames {cmd.frames}: out of range, this render has frames 0..{n - 1} "
                            f"({n} at {fps:g} fps)")
        if motion is not None:
            motion = select(motion, a, b)
        if cams is not None:
            cams.viewmats, cams.Ks = cams.viewmats[a:b], cams.Ks[a:b]
        n = b - a
    if cams is None:
        cams = camera_path(cmd.camera, n, scene, model, motion, up, size, fps)
    if size is None and scene is None and cmd.camera in ("orbit", "spiral"):
        log.warning("no scene found: rendering %dx%d (set --size, or --scene for the run's own)", cams.width, cams.height)
    obj = object_path(obj_spec, model, motion, attach, cmd.hand_bone) if motion is not None or obj_spec == "none" else None
    names = tuple(b for b in cmd.branches if not (b == "object" and obj is None))

    # -- render ---------------------------------------------------------------------------
    if cmd.out.exists() and cmd.overwrite:
        shutil.rmtree(cmd.out) if cmd.out.is_dir() else cmd.out.unlink()
    dev = model.device
    bg = torch.tensor(background, dtype=torch.float32, device=dev)
    rgb, depth, alpha = [], [], {b: [] for b in names}
    for k in track(range(n), f"render {cmd.out.name}"):
        frame, poses = timestep_poses(motion, obj, k, T)
        vm = torch.as_tensor(cams.viewmats[k], dtype=torch.float32, device=dev)
        K = torch.as_tensor(cams.Ks[k], dtype=torch.float32, device=dev)
        r = model.render(vm, K, cams.width, cams.height, frame, branches=names, background=bg, poses=poses)
        img = r.rgb.clamp(0, 1).cpu().numpy()
        assert np.isfinite(img).all(), f"frame {k}: the render holds non-finite values"
        rgb.append(img)
        if cmd.depth:
            d = r.depth.where(r.alpha > 0.5, torch.zeros_like(r.depth))  # expected camera z
            depth.append(d[..., 0].cpu().numpy())
        if cmd.alpha:
            for b in names:
                alpha[b].append(r.branch_alpha[b][..., 0].clamp(0, 1).cpu().numpy())
    written = _write(cmd.out, video, fps, rgb, depth if cmd.depth else None, alpha if cmd.alpha else None)
    from cogs.data.io import write_json

    record = {"run": str(cmd.run_dir), "camera": cmd.camera, "motion": cmd.motion, "object": obj_spec,
              "branches": list(names), "frames": n, "fps": fps, "size": [cams.width, cams.height],
              "attach_frame": obj.attach_frame if obj is not None else None,
              "start_frame": (cmd.start_frame if cmd.start_frame is not None else 0)
              if motion is not None and not motion.name == "run" and cmd.motion != "run" else None,
              "world_up": up.tolist(), "files": written}
    meta = cmd.out.with_suffix(".json") if video else cmd.out / "render.json"
    write_json(meta, record)
    log.info("wrote %s (%d frames at %g fps, %dx%d)", cmd.out, n, fps, cams.width, cams.height)
    return 0


def _index(motion, idx: np.ndarray):
    from cogs.use.motion import Motion

    i = torch.as_tensor(idx, dtype=torch.long, device=motion.pose.device)
    return Motion(motion.pose[i], motion.transl[i], motion.fps, motion.name,
                  None if motion.clip_time is None else motion.clip_time[i], motion.in_world)


def _colormap_depth(depth: list[np.ndarray]) -> list[np.ndarray]:
    import matplotlib

    valid = np.concatenate([d[d > 0] for d in depth]) if any((d > 0).any() for d in depth) else np.array([1.0])
    lo, hi = np.percentile(valid, 2), np.percentile(valid, 98)
    cmap = matplotlib.colormaps["turbo"]
    return [np.where((d > 0)[..., None], cmap(np.clip((d - lo) / max(hi - lo, 1e-6), 0, 1))[..., :3], 0.0) for d in depth]


def _write(out: Path, video: bool, fps: float, rgb, depth, alpha) -> list[str]:
    from cogs.data.io import write_image
    from cogs.eval.report import write_video

    files = []
    if video:
        write_video(out, rgb, fps=fps)
        files.append(out.name)
        if depth is not None:
            p = out.with_name(out.stem + ".depth.mp4")
            write_video(p, _colormap_depth(depth), fps=fps)
            files.append(p.name)
        for b, frames in (alpha or {}).items():
            p = out.with_name(f"{out.stem}.alpha-{b}.mp4")
            write_video(p, [np.repeat(a[..., None], 3, -1) for a in frames], fps=fps)
            files.append(p.name)
        return files
    for k, img in enumerate(rgb):
        write_image(out / "rgb" / f"{k:06d}.png", img)
    files.append("rgb/")
    if depth is not None:
        np.savez_compressed(out / "depth.npz", depth=np.stack(depth).astype(np.float16))
        files.append("depth.npz")
    for b, frames in (alpha or {}).items():
        for k, a in enumerate(frames):
            write_image(out / "alpha" / b / f"{k:06d}.png", np.repeat(a[..., None], 3, -1))
        files.append(f"alpha/{b}/")
    return files
