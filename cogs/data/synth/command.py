"""`cogs synth`: write the synthetic benchmark scene."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

from cogs.data.synth.config import NoiseConfig


@dataclass
class Synth:
    """Write the synthetic benchmark scene (an Anny person picking up a box in a room)."""

    out: Path
    """Output scene folder (created; existing files are overwritten)."""
    frames: int = 100
    """Number of frames (the 10-second choreography is stretched to the clip)."""
    width: int = 256
    """Image width in pixels."""
    height: int = 192
    """Image height in pixels."""
    fps: float = 10.0
    """Frame rate recorded in scene.json."""
    seed: int = 0
    """Seed of all noise and sampling: the same seed writes the same files."""
    preview: bool = False
    """Also write OUT/preview.png: a contact sheet of images, masks, depth and the noisy inputs."""
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    """Noise on the inputs (body poses, object trajectory, cameras, masks, points)."""

    def run(self) -> int:
        from cogs.data.scene import save_scene
        from cogs.data.synth.config import SynthConfig
        from cogs.data.synth.generate import generate_scene
        from cogs.errors import UserError
        from cogs.log import console

        if self.frames < 2 or self.width < 16 or self.height < 16:
            raise UserError(f"synth needs at least 2 frames of 16x16 pixels, got {self.frames} frames of "
                            f"{self.width}x{self.height}")
        if self.out.exists() and not self.out.is_dir():
            raise UserError(f"--out {self.out} exists and is not a folder")
        cfg = SynthConfig(frames=self.frames, width=self.width, height=self.height, fps=self.fps, seed=self.seed,
                          noise=self.noise)
        t0 = time.perf_counter()
        scene = generate_scene(cfg)
        t1 = time.perf_counter()
        save_scene(scene, self.out)
        t2 = time.perf_counter()
        console.print(
            f"[green]wrote[/green] {self.out}: {scene.n_frames} frames {scene.width}x{scene.height}, "
            f"{len(scene.points_xyz)} points, {len(scene.gt.novel.frames)} novel views; "
            f"generated in {t1 - t0:.1f} s, written in {t2 - t1:.1f} s",
            highlight=False,
        )
        if self.preview:
            from cogs.data.synth.preview import write_preview

            path = write_preview(scene, self.out / "preview.png")
            console.print(f"preview: {path} ({time.perf_counter() - t2:.1f} s)", highlight=False)
        return 0
