"""The `cogs preprocess` sub-command: its options and entry point."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro


@dataclass
class Preprocess:
    """Turn a raw video (or a folder of frames) into a native cogs scene, on a CPU.

    Steps (each cached under OUT/.cache, so a re-run resumes where it stopped): frames,
    person masks and keypoints (MediaPipe), object masks from a box prompt, cameras and
    sparse points (pycolmap, rotation-only fallback), body fit, initial object trajectory,
    planes; then the scene and OUT/preview.png. See docs/preprocess.md.
    """

    input: tyro.conf.Positional[Path]
    """Video file (anything FFmpeg reads) or a folder of frames (sorted by name)."""

    out: Path
    """Scene folder to write. The run works in OUT.partial and renames it to OUT once cogs
    check accepts the scene; OUT/.cache holds the intermediate steps."""

    stride: int = 1
    """Keep every stride-th input frame."""

    start: int = 0
    """First input frame to consider."""

    limit: int | None = None
    """Keep at most this many frames (after start and stride)."""

    max_side: int = 960
    """Shrink frames so their longer side is at most this many pixels (never enlarged)."""

    track_side: int = 0
    """Track the object on frames shrunk to this longer side (pixels) and bring the masks
    back to the frames' size: faster, but the masks change (at 640 on the synthetic video
    at 1280x960 the tracker ran 3.8x faster and the object masks lost 0.03-0.04 IoU; see
    docs/preprocess.md). 0 tracks at the frames' size."""

    focal_factor: float = 1.2
    """Focal-length prior in pixels = focal_factor x the longer image side (a phone's main
    camera is about 1.2). Held fixed during SfM."""

    focal_px: float | None = None
    """Focal length in pixels of the processed frames; overrides --focal-factor."""

    object_box: Annotated[tuple[float, ...] | tuple[tuple[float, ...], ...] | None,
                          tyro.conf.arg(constructor=tuple[tuple[float, ...], ...], metavar="[FRAME] X0 Y0 X1 Y1"),
                          tyro.conf.UseAppendAction] = ()
    """Object prompt: a box X0 Y0 X1 Y1 around the object, in pixels of the input video, on
    frame --object-box-frame. Repeat it as --object-box FRAME X0 Y0 X1 Y1, one per frame,
    to prompt several frames (e.g. where the tracker lost the object): the tracker restarts
    from each box, and between two boxes an object held in a hand is also followed by its
    outline's edges (a transparent bottle). Beyond the first box and the last, and between
    two whose outlines do not meet, a box's outline is followed alone: while a hand that
    holds the box holds it, where the colour cues doubt their finds; and as far as it
    returns to the box when followed back, where they lost an object coloured like the
    person in front of the person (a white racket before a white shirt)."""

    object_box_frame: int | None = None
    """Index (among the kept frames) of the frame the single box X0 Y0 X1 Y1 is drawn on
    (default 0). Boxes given as FRAME X0 Y0 X1 Y1 name their own frames."""

    object_negative_box: Annotated[tuple[float, ...] | tuple[tuple[float, ...], ...] | None,
                                   tyro.conf.arg(constructor=tuple[tuple[float, ...], ...], metavar="FRAME X0 Y0 X1 Y1"),
                                   tyro.conf.UseAppendAction] = ()
    """A region that is not the object on frame FRAME (e.g. the shorts a track drifted to),
    in pixels of the input video. The tracker never takes its pixels on that
    frame, and its colours count against the object in the whole clip."""

    person_box: Annotated[tuple[float, ...] | None, tyro.conf.arg(metavar="[FRAME] X0 Y0 X1 Y1")] = None
    """The person to reconstruct when several are in view: a box around them, in pixels of
    the input video, on frame FRAME (default 0). That person alone is followed from frame
    to frame; the others become part of the scene. Without it, when several people are in
    view, the one whose hands are nearest the first --object-box (else the one nearest
    the centre) is followed, with a warning naming the box. When the person detector
    finds nobody (it needs the face), the body is tracked from this box (else from the
    whole first frame) without the face."""

    object_masks: Path | None = None
    """Folder of ready-made object masks (one image per frame, sorted by name; white =
    object), instead of --object-box."""

    body_model: str = "anny"
    """Body model fitted to the person. Only anny: SMPL-family scenes come from `cogs
    import`."""

    sfm: Literal["auto", "colmap", "rotation"] = "auto"
    """Camera estimation: colmap, the rotation-only fallback, or auto (colmap, falling back
    when too few frames register; when the camera barely translates, COLMAP's rotations or
    the fallback's, whichever explains the static background better)."""

    matching: Literal["auto", "exhaustive", "sequential"] = "auto"
    """SfM feature matching: every pair, neighbouring frames only, or auto (exhaustive up to
    --exhaustive-max-frames frames)."""

    exhaustive_max_frames: int = 120
    """auto: the longest clip matched exhaustively (the cost grows with frames squared)."""

    min_registered: float = 0.6
    """auto: fall back to rotation-only when SfM poses fewer than this fraction of frames
    (or triangulates fewer than max(100, 5 per posed frame) points). Below it the mapper
    first runs again with two more seeds, keeping the model that poses the most frames."""

    min_parallax: float = 0.04
    """auto: keep SfM's rotations but fix the camera centre when the camera centres spread
    less than this fraction of the scene depth (points without usable depth); those
    rotations are then weighed against the homography chain's. Chosen on the synthetic
    video benchmark (0.3), the guitar clip (0.056: its COLMAP cameras are worth 2 dB) and
    the tennis clip (0.020-0.030 in every COLMAP run, each worse than rotation-only; at
    0.0201 1.6 dB on the object crop): docs/experiments/2026-12-04-c-a-higher-parallax-gate.md."""

    mask_dilate_px: int = 8
    """Grow the person and object masks by this many pixels before hiding them from SfM."""

    person_threshold: float = 0.5
    """Threshold on MediaPipe's soft person mask."""

    refine_person_masks: bool = False
    """Sharpen MediaPipe's (low-resolution, upsampled) person mask with GrabCut in a band of
    2 % of the person's height around its boundary. Off by default: on the synthetic
    benchmark's H.264-encoded frames it lowered the mask IoU (0.906 -> 0.887), on clean
    frames it raised it (to 0.916)."""

    body_iterations: int = 300
    """Optimiser iterations of the joint body fit."""

    person_height: float | None = None
    """The person's standing height in metres, if you know it. It sets the scene's metric
    scale (every depth, the object's size): one view cannot tell a tall person far away
    from a short one near. Default: 1.70 m, a typical adult."""

    max_planes: int = 4
    """At most this many planes from RANSAC on the sparse points (besides the ground)."""

    sam2_checkpoint: Path | None = None
    """Optional SAM2 checkpoint: with the `sam2` package installed, SAM2 segments the person
    and propagates the object box instead of the classical tracker."""

    sam2_config: str = "configs/sam2.1/sam2.1_hiera_t.yaml"
    """SAM2 model config matching --sam2-checkpoint."""

    preview_frames: int = 12
    """Frames shown in OUT/preview.png."""

    name: str | None = None
    """Scene name (default: the input's file name)."""

    force: bool = False
    """Recompute every step, ignoring OUT/.cache."""

    overwrite: bool = False
    """Replace the scene OUT already holds (its cached steps are reused), once the new one
    is complete. Without it an existing OUT is refused."""

    progress: bool = True
    """Show progress bars."""

    def object_prompts(self):
        """(positive box prompts sorted by frame, negative ones): `cogs.preprocess.prompts`;
        UserError naming the option when one is malformed."""
        from cogs.preprocess.prompts import parse_prompts

        return parse_prompts(self.object_box, self.object_box_frame, self.object_negative_box)

    def person_prompt(self):
        """The --person-box prompt or None; UserError naming the option when malformed."""
        from cogs.preprocess.prompts import parse_person_box

        return parse_person_box(self.person_box)

    def check_options(self) -> None:
        """UserError naming the option, before any work or any file is written."""
        import math

        from cogs.body import MODELS
        from cogs.data.outdir import check_out_folder
        from cogs.errors import UserError

        src = Path(self.input)
        if not src.exists():
            raise UserError(f"input {src} does not exist")
        positive = {"--stride": self.stride, "--max-side": self.max_side, "--body-iterations": self.body_iterations,
                    "--preview-frames": self.preview_frames, "--exhaustive-max-frames": self.exhaustive_max_frames}
        if self.limit is not None:
            positive["--limit"] = self.limit
        for option, v in positive.items():
            if v < 1:
                raise UserError(f"{option} must be at least 1, got {v}")
        if self.max_side < 64:
            raise UserError(f"--max-side {self.max_side} is too small: frames need at least 64 pixels on their longer "
                            "side for the person to be found")
        if self.track_side != 0 and self.track_side < 64:
            raise UserError(f"--track-side {self.track_side} is too small: the tracker needs frames of at least 64 pixels "
                            "on their longer side (0 tracks at the frames' size)")
        for option, v in {"--start": self.start,
                          "--mask-dilate-px": self.mask_dilate_px, "--max-planes": self.max_planes}.items():
            if v < 0:
                raise UserError(f"{option} must be >= 0, got {v}")
        for option, v in {"--focal-factor": self.focal_factor, "--focal-px": self.focal_px}.items():
            if v is not None and (not math.isfinite(v) or v <= 0):
                raise UserError(f"{option} must be a positive number, got {v:g}")
        for option, v, lo, hi in (("--min-registered", self.min_registered, 0.0, 1.0),
                                  ("--person-threshold", self.person_threshold, 0.0, 1.0)):
            if not (math.isfinite(v) and lo <= v <= hi):
                raise UserError(f"{option} must be between {lo:g} and {hi:g}, got {v:g}")
        if self.person_height is not None:
            from cogs.preprocess.bodyfit import STATURE_RANGE_M

            lo, hi = STATURE_RANGE_M
            if not (math.isfinite(self.person_height) and lo <= self.person_height <= hi):
                raise UserError(f"--person-height is in metres, between {lo:g} and {hi:g} for the adult body model; "
                                f"got {self.person_height:g}")
        if not math.isfinite(self.min_parallax) or self.min_parallax < 0:
            raise UserError(f"--min-parallax must be >= 0, got {self.min_parallax:g}")
        self.person_prompt()
        positives, negatives = self.object_prompts()
        if self.object_masks is not None and (positives or negatives):
            option = "--object-box" if positives else "--object-negative-box"
            raise UserError(f"give either {option} or --object-masks, not both (ready-made masks are not tracked)")
        from cogs.preprocess.frames import probe

        n, size = probe(src, self.stride, self.limit, self.start)  # where the header tells (checked again after decoding)
        if positives and n and size:
            from cogs.preprocess.prompts import check_against_frames

            check_against_frames(positives + negatives, size, n)
        if n and size:
            from cogs.preprocess.memory import check_fits

            check_fits(src, n, size, self.max_side, self.stride, self.limit)
        if self.object_masks is not None and not Path(self.object_masks).is_dir():
            raise UserError(f"--object-masks {self.object_masks} is not a folder")
        if self.sam2_checkpoint is not None and not Path(self.sam2_checkpoint).is_file():
            raise UserError(f"--sam2-checkpoint {self.sam2_checkpoint} does not exist")
        if self.body_model not in MODELS:
            raise UserError(f"--body-model {self.body_model!r} is unknown; known: {', '.join(sorted(MODELS))}")
        if self.body_model != "anny":  # the body fit's landmark map, feet, hands and forearms are Anny's bones
            raise UserError(f"--body-model {self.body_model}: preprocessing fits Anny only (the landmarks are mapped onto "
                            "Anny's bones); a run trained on its scene can still be driven by SMPL-family motions "
                            "(cogs render --motion)")
        if self.name is not None and not self.name.strip():
            raise UserError("--name must not be empty")
        out, inp = Path(self.out).resolve(), src.resolve()
        if out == inp or out.is_relative_to(inp) or inp.is_relative_to(out):
            raise UserError(f"--out {self.out} and the input {src} overlap; write the scene somewhere else")
        try:  # a folder holding nothing but a cache is what older versions left on failure: resumed
            only_cache = out.is_dir() and [p.name for p in out.iterdir()] == [".cache"]
        except OSError:
            only_cache = False
        if not only_cache:
            check_out_folder(Path(self.out), overwrite=self.overwrite, hint="its cached steps are reused")

    def run(self) -> int:
        from cogs.log import console
        from cogs.preprocess.pipeline import run_preprocess

        rep = run_preprocess(self)
        total = sum(rep.seconds.values())
        steps = ", ".join(f"{k} {v:.1f}s" for k, v in rep.seconds.items() if k not in rep.cached)
        console.print(
            f"[green]scene written[/green] {rep.scene} (preview {rep.preview}); {total:.1f} s"
            + (f" [{steps}]" if steps else "")
            + (f"; cached: {', '.join(rep.cached)}" if rep.cached else ""),
            highlight=False,
        )
        return 0
