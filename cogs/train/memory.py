"""Will a run fit in memory? An estimate of its peak, checked before anything is written.

A run holds its clip compactly (uint8 frames, bool masks: 5 bytes per pixel per frame),
plus what one step works on (proportional to the pixels of one frame), the Gaussians with
their gradients and Adam moments, and a fixed base (the interpreter, torch, numba's
kernels, the body model). A run whose estimate exceeds the memory available is refused
up front with the options that make it fit, instead of meeting the kernel's
out-of-memory killer hours later.

The per-pixel and base figures were measured with /usr/bin/time -v on 2-core machines
(docs/experiments/2026-11-25-memory-and-scale.md) and round up.
"""

from __future__ import annotations

from dataclasses import dataclass

from cogs.errors import UserError
from cogs.memory import GiB, available_bytes

BASE_BYTES = int(1.6 * GiB)
"""The process before any frame: Python, torch, numba's compiled kernels, the body model."""
STEP_BYTES_PER_PIXEL = 700
"""One step's working set per pixel of a frame: the render's buffers and their gradients,
the loss maps (SSIM's blurred moments), and the visibility pass's renders."""
FRAME_BYTES_PER_PIXEL = 5
"""What the run holds per pixel of every frame: RGB uint8 and two bool masks."""
GAUSSIAN_BYTES = 2_000
"""One Gaussian with its raw parameters (SH degree 3 at most), gradients, Adam moments,
density statistics and the human's seed buffers, rounded up."""


@dataclass
class Estimate:
    frames: int
    frame_bytes: int
    step_bytes: int
    gaussian_bytes: int
    base_bytes: int = BASE_BYTES

    @property
    def total(self) -> int:
        return self.frame_bytes + self.step_bytes + self.gaussian_bytes + self.base_bytes

    def describe(self) -> str:
        g = lambda b: f"{b / GiB:.1f} GiB"  # noqa: E731
        return (f"{g(self.total)} ({self.frames} frames held {g(self.frame_bytes)}, a step {g(self.step_bytes)}, "
                f"the Gaussians {g(self.gaussian_bytes)}, the process {g(self.base_bytes)})")


def estimate(n_frames: int, width: int, height: int, cfg) -> Estimate:
    """The peak memory of training `cfg` on n_frames of width x height."""
    px = width * height
    caps = (cfg.human_density.max_gaussians + cfg.object_density.max_gaussians + cfg.scene_density.max_gaussians)
    return Estimate(frames=n_frames, frame_bytes=n_frames * px * FRAME_BYTES_PER_PIXEL,
                    step_bytes=px * STEP_BYTES_PER_PIXEL, gaussian_bytes=caps * GAUSSIAN_BYTES)


def check_fits(n_frames: int, width: int, height: int, cfg, scene_path) -> Estimate:
    """Refuse (UserError, before any work) a run whose estimate exceeds what is available,
    naming the options that shrink it."""
    est = estimate(n_frames, width, height, cfg)
    have = available_bytes()
    if have is not None and est.total > have:
        side = max(width, height)
        fit_side = _largest_side_that_fits(n_frames, width, height, cfg, have)
        hint = [f"--max-side {fit_side} (train at a reduced resolution)" if fit_side else None,
                f"fewer frames (`cogs import ... --stride 2` or `--limit`, or a shorter clip; {n_frames} now)",
                "lower Gaussian caps (--set scene_density.max_gaussians=...)"]
        raise UserError(f"{scene_path}: training {n_frames} frames of {width}x{height} needs about {est.describe()}, "
                        f"more than the {have / GiB:.1f} GiB available. Make it fit with "
                        + "; or ".join(h for h in hint if h) + f". (Longer side now {side} px.)")
    return est


def _largest_side_that_fits(n_frames: int, width: int, height: int, cfg, have: int) -> int | None:
    side = max(width, height)
    for s in range(side, 31, -16):
        w, h = max(1, round(width * s / side)), max(1, round(height * s / side))
        if estimate(n_frames, w, h, cfg).total <= have:
            return s
    return None
