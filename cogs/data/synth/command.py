"""`cogs synth`: write the synthetic benchmark scene."""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

from cogs.data.synth.config import NoiseConfig
from cogs.errors import UserError


@dataclass
class Synth:
    """Write the synthetic benchmark scene (an Anny person picking up a box in a room)."""

    out: Path
    """Output scene folder. An earlier synthetic scene there is replaced; anything else only
    with --overwrite. Written in a temporary folder first: OUT is replaced only once the new
    scene is complete."""
    frames: int = 100
    """Number of frames (the 10-second choreography is stretched to the clip)."""
    width: int = 256
    """Image width in pixels."""
    height: int = 192
    """Image height in pixels."""
    fps: float = 10.0
    """Frame rate recorded in scene.json."""
    seed: int = 0
    """Seed of all noise and sampling: the same seed writes the same files (the rendered video is the same at every seed)."""
    variant: int = 0
    """Choreography variant: 0 is the reference video (the demo scene); another number renders another video of the
    same story (the box's place on the table, the walk in and out, the camera path drawn from it)."""
    preview: bool = False
    """Also write OUT/preview.png: a contact sheet of images, masks, depth and the noisy inputs."""
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    """Noise on the inputs (body poses, object trajectory, cameras, masks, points)."""
    overwrite: bool = False
    """Replace whatever OUT holds (an earlier synthetic scene is replaced without it)."""

    def check_options(self) -> None:
        """UserError naming the option, before any work."""
        from cogs.data.outdir import check_out_folder

        if self.frames < 2 or self.width < 16 or self.height < 16:
            raise UserError(f"synth needs at least 2 frames of 16x16 pixels, got {self.frames} frames of "
                            f"{self.width}x{self.height}")
        if not math.isfinite(self.fps) or self.fps <= 0:
            raise UserError(f"--fps must be a positive number of frames per second, got {self.fps:g}")
        if self.seed < 0:
            raise UserError(f"--seed must be >= 0, got {self.seed}")
        if self.variant < 0:
            raise UserError(f"--variant must be >= 0, got {self.variant}")
        for f in dataclasses.fields(NoiseConfig):
            v = getattr(self.noise, f.name)
            if not isinstance(v, bool) and (not math.isfinite(v) or v < 0):
                raise UserError(f"--noise.{f.name.replace('_', '-')} must be >= 0, got {v:g}")
        if self.noise.mask_morph_prob > 1:
            raise UserError(f"--noise.mask-morph-prob is a probability (0..1), got {self.noise.mask_morph_prob:g}")
        check_out_folder(self.out, overwrite=self.overwrite or is_synthetic_scene(self.out))
        self.check_memory()

    def config(self):
        from cogs.data.synth.config import SynthConfig

        return SynthConfig(frames=self.frames, width=self.width, height=self.height, fps=self.fps, seed=self.seed,
                           variant=self.variant, noise=self.noise)

    def check_memory(self) -> None:
        """Refuse (UserError, before any work) a scene whose generation cannot fit in the
        memory available, naming the frame count and the sizes that fit."""
        from cogs.data.synth.generate import peak_bytes
        from cogs.memory import GiB, available_bytes

        cfg = self.config()
        need, have = peak_bytes(cfg), available_bytes()
        if have is None or need <= have:
            return
        lo, hi = 1, self.frames  # the most frames that fit: in [lo, hi), lo = none
        while hi - lo > 1:
            mid = (lo + hi) // 2
            lo, hi = (mid, hi) if peak_bytes(dataclasses.replace(cfg, frames=mid)) <= have else (lo, mid)
        fit = [lo] if lo >= 2 else []
        scale = next((s / 100 for s in range(95, 4, -5)
                      if peak_bytes(dataclasses.replace(cfg, width=max(16, round(self.width * s / 100)),
                                                        height=max(16, round(self.height * s / 100)))) <= have), None)
        hints = [f"--frames {fit[0]}" if fit else None,
                 f"--width {round(self.width * scale)} --height {round(self.height * scale)}" if scale else None]
        hints = [h for h in hints if h]
        raise UserError(f"--frames {self.frames} at {self.width}x{self.height} needs about {need / GiB:.1f} GiB while the "
                        f"scene is generated (every frame is held until it is written), more than the {have / GiB:.1f} "
                        f"GiB available. " + ("Make it fit with " + " or ".join(hints) + "." if hints else
                                              "Not even the smallest scene fits: free some memory."))

    def run(self) -> int:
        from cogs.data.outdir import staged
        from cogs.data.scene import save_scene
        from cogs.data.synth.generate import generate_scene
        from cogs.log import console

        self.check_options()
        cfg = self.config()
        t0 = time.perf_counter()
        scene = generate_scene(cfg)
        t1 = time.perf_counter()
        with staged(self.out) as st:
            save_scene(scene, st.path)
            if self.preview:
                from cogs.data.synth.preview import write_preview

                write_preview(scene, st.path / "preview.png")
        scene.root = self.out
        if st.replaced:
            console.print(f"replaced {st.replaced} in {self.out}", markup=False, highlight=False)
        t2 = time.perf_counter()
        console.print(
            f"[green]wrote[/green] {self.out}: {scene.n_frames} frames {scene.width}x{scene.height}, "
            f"{len(scene.points_xyz)} points, {len(scene.gt.novel.frames)} novel views; "
            f"generated in {t1 - t0:.1f} s, written in {t2 - t1:.1f} s"
            + (f"; preview: {self.out / 'preview.png'}" if self.preview else ""),
            highlight=False,
        )
        return 0


def is_synthetic_scene(path: Path) -> bool:
    """Whether `path` holds a scene this generator wrote (its scene.json's
    `source.generator`; the check of the scene itself is separate)."""
    from cogs.data.io import read_json
    from cogs.data.synth.generate import GENERATOR

    try:
        meta = read_json(Path(path) / "scene.json")
    except (OSError, ValueError, RecursionError):
        return False
    return isinstance(meta, dict) and isinstance(meta.get("source"), dict) and meta["source"].get("generator") == GENERATOR


def reusable_synthetic_scene(path: Path, option: str = "--out") -> bool:
    """For `cogs demo`: True when `path` holds a valid synthetic scene to reuse, False when
    nothing (or an empty folder) is there and one may be written. A scene the generator did
    not write, or one that fails `cogs check`, is never replaced: UserError saying what is
    there and what to do."""
    from cogs.data.outdir import describe, is_empty_folder
    from cogs.data.validate import check_scene

    path = Path(path)
    if not path.exists() and not path.is_symlink():
        return False
    if not path.is_dir():
        raise UserError(f"{path} is a file, where the demo keeps its synthetic scene; choose another {option}, "
                        "or move the file away")
    if is_empty_folder(path):
        return False
    if not is_synthetic_scene(path):
        raise UserError(f"{path} holds {describe(path)}, which the demo did not write; the demo keeps its own synthetic "
                        f"scene there. Choose another {option}, or delete {path} to let the demo write one")
    problems = check_scene(path)
    if problems:
        raise UserError(f"{path} holds a synthetic scene that fails cogs check ({len(problems)} problem(s); the first: "
                        f"{problems[0]}). The demo does not replace it: delete {path} to let the demo write a fresh one, "
                        f"or choose another {option}")
    return True
