"""Step 3: the handled object's mask in every frame, propagated from box prompts.

Two engines:

- **SAM2** (optional, when the ``sam2`` package is installed and a checkpoint is given): its
  video predictor propagates the box prompts forwards and backwards; negative boxes go in
  as negative clicks (``sam2_prompts``).
- **classical** (default, no weights): GrabCut inside the prompt box gives the object's
  first mask (``segment.grabcut_box``) on each prompted frame; ``tracking.propagate_masks``
  restarts from each and carries them through the video with motion (SIFT matches, DIS optical flow, the carrying hand, each fitted
  to a local colour model), a whole-frame colour search, and a search next to the hand
  that carried the object when it is lost, all told by a model of the static scene what
  cannot be the object and what moved. See ``tracking.py`` and ``background.py``.
  ``track`` runs it, on frames shrunk to ``--track-side`` when that is set.

The person's mask is a soft prior here, not a hard exclusion: MediaPipe's person mask often
swallows a held object. The returned object masks and the person masks are made disjoint
by the pipeline (object pixels win).

Masks can also be read ready-made from a folder (``read_mask_folder``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cogs.errors import UserError
from cogs.preprocess.segment import grabcut_box  # noqa: F401  (the step's entry points)
from cogs.preprocess.tracking import propagate_masks


def scale_box(box: tuple[float, float, float, float], source_size: tuple[int, int], size: tuple[int, int]) -> np.ndarray:
    """A box (x0, y0, x1, y1) in source-video pixels -> pixels of the resized frames."""
    sx, sy = size[0] / source_size[0], size[1] / source_size[1]
    x0, y0, x1, y1 = box
    return np.array([x0 * sx, y0 * sy, x1 * sx, y1 * sy], dtype=np.float64)


def read_mask_folder(folder: str | Path, n_frames: int, size: tuple[int, int], source_indices: np.ndarray | None = None) -> np.ndarray:
    """Ready-made object masks: one image per frame (sorted by name), resized -> [T, H, W] bool.

    The folder may hold one mask per *source* frame (then ``source_indices`` picks the kept
    ones) or exactly one per processed frame.
    """
    import cv2
    from PIL import Image

    from cogs.data.io import mask_from_values, mask_values

    folder = Path(folder)
    if not folder.is_dir():
        raise UserError(f"--object-masks {folder} is not a folder")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"))
    if len(files) == n_frames:
        chosen = files
    elif source_indices is not None and len(files) > int(source_indices.max()):
        chosen = [files[i] for i in source_indices]
    else:
        raise UserError(f"--object-masks {folder} holds {len(files)} masks; expected {n_frames} (one per processed frame) or one per input frame")
    out = np.zeros((n_frames, size[1], size[0]), bool)
    for t, f in enumerate(chosen):
        try:
            with Image.open(f) as im:
                m = mask_from_values(mask_values(im)).astype(np.uint8)  # 0/255 and 0/1 masks alike
        except (OSError, ValueError, SyntaxError) as e:
            raise UserError(f"cannot read mask {f}: {e}") from None
        out[t] = cv2.resize(m, size, interpolation=cv2.INTER_NEAREST) > 0
    return out


def sam2_prompts(positives: list[tuple[int, np.ndarray]], negatives: list[tuple[int, np.ndarray]] = ()) -> list[dict]:
    """The keyword arguments of one ``add_new_points_or_box`` call per prompted frame.

    A positive box goes in as SAM2's box prompt. SAM2 takes no negative box, only negative
    clicks (label 0): a negative box becomes five of them, its centre and the centres of
    its quarters. A frame with only negative boxes gets clicks alone; the pipeline also
    clears those boxes from SAM2's masks afterwards.
    """
    frames: dict[int, dict] = {}
    for k, box in positives:
        frames.setdefault(int(k), {})["box"] = np.asarray(box, np.float32)
    for k, box in negatives:
        x0, y0, x1, y1 = (float(v) for v in box)
        cx, cy, qx, qy = 0.5 * (x0 + x1), 0.5 * (y0 + y1), 0.25 * (x1 - x0), 0.25 * (y1 - y0)
        pts = np.array([[cx, cy], [cx - qx, cy - qy], [cx + qx, cy - qy], [cx - qx, cy + qy], [cx + qx, cy + qy]], np.float32)
        f = frames.setdefault(int(k), {})
        f["points"] = np.concatenate([f["points"], pts]) if "points" in f else pts
        f["labels"] = np.zeros(len(f["points"]), np.int32)
    return [{"frame_idx": k, "obj_id": 1, **frames[k]} for k in sorted(frames)]


def propagate_masks_sam2(images: np.ndarray, prompts: list[tuple[int, np.ndarray]], checkpoint: Path, config: str, work_dir: Path,
                         negatives: list[tuple[int, np.ndarray]] = (), on_frame=None) -> np.ndarray:
    """SAM2 video propagation from box prompts (optional engine) -> [T, H, W] bool.

    ``prompts``: (frame, box x0 y0 x1 y1 in processed pixels), one or more; ``negatives``
    likewise, regions that are not the object (``sam2_prompts``). SAM2 keeps every
    prompted frame in its memory, so one pass forwards from the first prompt and one
    backwards from it cover the clip, each frame seeing every prompt.
    """
    if not Path(checkpoint).exists():
        raise UserError(f"--sam2-checkpoint {checkpoint} does not exist")
    try:
        import torch
        from sam2.build_sam import build_sam2_video_predictor
    except ImportError as e:
        raise UserError(f"--sam2-checkpoint needs the `sam2` package ({e}); install it or drop the option") from None
    from PIL import Image

    frames_dir = Path(work_dir) / "sam2_frames"
    frames_dir.mkdir(parents=True, exist_ok=True)
    for t, rgb in enumerate(images):  # SAM2 reads a folder of JPEGs named by index
        Image.fromarray(rgb).save(frames_dir / f"{t:05d}.jpg", quality=95)
    predictor = build_sam2_video_predictor(config, str(checkpoint), device="cpu")
    T, H, W, _ = images.shape
    out = np.zeros((T, H, W), bool)
    first = min(int(k) for k, _ in prompts)
    done = 0
    with torch.inference_mode():
        state = predictor.init_state(video_path=str(frames_dir))
        for call in sam2_prompts(prompts, negatives):
            predictor.add_new_points_or_box(state, **call)
        for reverse in (False, True):
            for t, _, logits in predictor.propagate_in_video(state, start_frame_idx=first, reverse=reverse):
                out[t] = (logits[0, 0] > 0).cpu().numpy()
                done += 1
                if on_frame:
                    on_frame(min(done, T))
    return out


def track(images: np.ndarray, prompts: dict[int, np.ndarray], side: int = 0, human_probs: np.ndarray | None = None,
          kp2d: np.ndarray | None = None, negatives: dict[int, np.ndarray] | None = None, still: dict | None = None,
          **options) -> tuple[np.ndarray, np.ndarray]:
    """``tracking.propagate_masks`` from the prompt masks {frame: [H, W] bool}, run on the
    frames shrunk to a longer side of at most ``side`` pixels (0: the frames as they are)
    -> masks [T, H, W] bool at the frames' size, confidence [T].

    The frames, person probabilities, keypoints, prompts and negative regions are shrunk
    alike (pixels by their area); the masks come back by linear interpolation, kept at a
    half. ``still`` receives its pixel counts in pixels of the frames. Other keywords go
    to ``propagate_masks`` as they are.

    Shrinking is a trade (``--track-side``, off by default): on the synthetic video at
    1280x960 shrunk to 640 the objects step took 3.8x less time and the scene's object masks
    lost 0.03-0.04 IoU; on six real clips at 960 px the masks moved both ways
    (docs/experiments/2026-12-02-b-tracking-on-shrunk-frames.md)."""
    import cv2

    T, H, W, _ = images.shape
    frames = list(prompts)
    if not side or max(H, W) <= side:
        return propagate_masks(images, [prompts[k] for k in frames], frames, human_probs=human_probs, kp2d=kp2d,
                               negatives=negatives, still=still, **options)
    s = side / max(H, W)
    w, h = max(1, round(W * s)), max(1, round(H * s))

    def shrink(a: np.ndarray) -> np.ndarray:
        return cv2.resize(a, (w, h), interpolation=cv2.INTER_AREA)

    def shrink_mask(m: np.ndarray) -> np.ndarray:
        small = shrink(m.astype(np.float32))
        out = small >= 0.5
        return out if out.any() else small > 0  # an object thinner than a pixel of the small frame

    small_images = np.stack([shrink(f) for f in images])
    small_probs = None if human_probs is None else np.stack([shrink(p) for p in human_probs])
    small_kp = None
    if kp2d is not None:
        small_kp = np.array(kp2d, np.float64, copy=True)
        small_kp[..., 0] *= w / W
        small_kp[..., 1] *= h / H
    small_neg = None if negatives is None else {k: shrink_mask(m) for k, m in negatives.items()}
    counts: dict = {}
    masks, conf = propagate_masks(small_images, [shrink_mask(prompts[k]) for k in frames], frames, human_probs=small_probs,
                                  kp2d=small_kp, negatives=small_neg, still=counts if still is not None else None, **options)
    full = np.zeros((T, H, W), bool)
    for t in range(T):
        if masks[t].any():
            full[t] = cv2.resize(masks[t].astype(np.float32), (W, H), interpolation=cv2.INTER_LINEAR) >= 0.5
    for k, region in (negatives or {}).items():
        full[k] &= ~region
    if still is not None:
        still.update({k: int(round(v * (W * H) / (w * h))) for k, v in counts.items()})
    return full, conf
