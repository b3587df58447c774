"""Will preprocessing fit in memory? Every step holds the whole clip (frames, masks,
keypoints), so a long clip at full size can need more than the machine has; it is
refused before any work with the options that make it fit, instead of meeting the
kernel's out-of-memory killer an hour into the run.

Measured with /usr/bin/time -v on the 2-core machines (the basketball clip with one box
prompt; docs/experiments/2026-11-27-memory-of-preprocessing-and-synthesis.md): 40 frames of
540x960 peaked at 1,490,900 kB, 40 of 270x480 at 1,205,448 kB, 20 of 270x480 at
1,122,708 kB; that is about 1.0 GiB of base, 19 bytes per pixel of every frame and 1.8 MB
per frame besides. The figures below round those up.
"""

from __future__ import annotations

from cogs.errors import UserError
from cogs.memory import GiB, available_bytes
from cogs.preprocess.frames import output_size

BASE_BYTES = int(1.25 * GiB)
"""The process before any frame: MediaPipe's models, torch, the body model, pycolmap."""
FRAME_BYTES = 3_000_000
"""Per kept frame besides its pixels: keypoints, tracks, SfM features, body-fit state."""
PIXEL_BYTES = 24
"""Per pixel of every kept frame: RGB, person and object masks and their working copies."""


def peak_bytes(n_frames: int, width: int, height: int) -> int:
    """The preprocessing peak for n_frames kept at width x height (after --max-side)."""
    return BASE_BYTES + n_frames * (FRAME_BYTES + PIXEL_BYTES * width * height)


def check_fits(source, n_frames: int, source_size: tuple[int, int], max_side: int, stride: int, limit: int | None) -> None:
    """Refuse (UserError) a clip whose preprocessing cannot fit in the memory available,
    naming the --stride, --limit and --max-side that make it fit."""
    w, h = output_size(*source_size, max_side)
    need, have = peak_bytes(n_frames, w, h), available_bytes()
    if have is None or need <= have:
        return
    per_frame = FRAME_BYTES + PIXEL_BYTES * w * h
    fit_frames = max(0, (have - BASE_BYTES) // per_frame)
    hints = []
    if fit_frames >= 2:
        hints.append(f"--stride {stride * -(-n_frames // fit_frames)}")
        hints.append(f"--limit {fit_frames}")
    side = next((s for s in range(max_side - 16, 63, -16) if peak_bytes(n_frames, *output_size(*source_size, s)) <= have), None)
    if side is not None:
        hints.append(f"--max-side {side}")
    raise UserError(f"{source}: preprocessing {n_frames} frames of {w}x{h} needs about {need / GiB:.1f} GiB (every step "
                    f"holds the whole clip), more than the {have / GiB:.1f} GiB available. "
                    + ("Make it fit with " + " or ".join(hints) + "." if hints else "Free some memory first.")
                    + (f" (--stride {stride} and --limit {limit} now.)" if limit else f" (--stride {stride} now.)"))
