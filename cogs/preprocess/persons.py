"""Step 2: the person in every frame: a mask, 33 2D keypoints and 33 metric 3D keypoints.

MediaPipe Pose (BlazePose GHUM, ``model_complexity=1``, the only variant whose model ships in
the 0.10.14 wheel, so nothing is downloaded) runs in video mode (landmarks tracked from frame
to frame) with segmentation on. Its outputs, per frame:

- ``kp2d [33, 3]``: pixel x, y and a visibility score in [0, 1];
- ``kp3d [33, 3]``: "world" landmarks in metres, origin between the hips, axes roughly
  aligned with the camera's (x right, y down, z away from the camera);
- a soft person mask, thresholded at 0.5 and cleaned to the components that touch the
  detected pose.

Landmark order is MediaPipe's (``LANDMARK_NAMES``). Frames where no person is found get an
empty mask and NaN keypoints; later steps interpolate over them.

When the optional ``sam2`` package is installed and a checkpoint is given, SAM2 re-segments
the person from a box prompt around MediaPipe's mask (sharper boundaries); it is imported
only then.
"""

from __future__ import annotations

import contextlib
import logging
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cogs.errors import UserError

log = logging.getLogger(__name__)

LANDMARK_NAMES = [
    "nose", "left_eye_inner", "left_eye", "left_eye_outer", "right_eye_inner", "right_eye",
    "right_eye_outer", "left_ear", "right_ear", "mouth_left", "mouth_right", "left_shoulder",
    "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_pinky",
    "right_pinky", "left_index", "right_index", "left_thumb", "right_thumb", "left_hip",
    "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle", "left_heel",
    "right_heel", "left_foot_index", "right_foot_index",
]  # fmt: skip
N_LANDMARKS = 33
# Skeleton edges for drawing (indices into LANDMARK_NAMES).
EDGES = [
    (11, 12), (11, 13), (13, 15), (12, 14), (14, 16), (11, 23), (12, 24), (23, 24), (23, 25),
    (25, 27), (27, 29), (29, 31), (27, 31), (24, 26), (26, 28), (28, 30), (30, 32), (28, 32),
    (0, 2), (0, 5), (2, 7), (5, 8),
]  # fmt: skip


@dataclass
class PersonTrack:
    masks: np.ndarray  # [T, H, W] bool
    probs: np.ndarray  # [T, H, W] uint8, soft mask * 255
    kp2d: np.ndarray  # [T, 33, 3] pixels x, y and visibility; NaN where undetected
    kp3d: np.ndarray  # [T, 33, 3] metres, hip-centred, camera-aligned axes; NaN where undetected
    detected: np.ndarray  # [T] bool

    def arrays(self) -> dict[str, np.ndarray]:
        return {"masks": self.masks, "probs": self.probs, "kp2d": self.kp2d, "kp3d": self.kp3d, "detected": self.detected}

    @classmethod
    def from_arrays(cls, a: dict) -> "PersonTrack":
        return cls(a["masks"].astype(bool), a["probs"], a["kp2d"], a["kp3d"], a["detected"].astype(bool))


@contextlib.contextmanager
def _quiet_native_logs():
    """MediaPipe's C++ side (absl, TFLite) writes INFO/WARNING lines straight to fd 2."""
    os.environ.setdefault("GLOG_minloglevel", "2")
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")
    try:
        fd = 2
        saved = os.dup(fd)
    except OSError:
        yield
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, fd)
    try:
        yield
    finally:
        os.dup2(saved, fd)
        os.close(saved)
        os.close(devnull)


def import_mediapipe():
    """The mediapipe module, or a UserError saying how to install it."""
    import cv2  # noqa: F401  (FACTS: cv2 before mediapipe/pycolmap keeps native libs sane)

    try:
        with _quiet_native_logs():
            import mediapipe as mp
    except ImportError as e:
        raise UserError(
            f"mediapipe is not installed ({e}); install the preprocessing extra: "
            'pip install -e ".[preprocess]" (see docs/preprocess.md)'
        ) from None
    return mp


def clean_person_mask(mask: np.ndarray, kp2d: np.ndarray | None) -> np.ndarray:
    """Keep the connected components that hold a confident keypoint (or the largest)."""
    import cv2

    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 2:
        return mask
    keep = set()
    if kp2d is not None and np.isfinite(kp2d).all():
        H, W = mask.shape
        for x, y, v in kp2d:
            xi, yi = int(round(x)), int(round(y))
            if v > 0.5 and 0 <= xi < W and 0 <= yi < H and labels[yi, xi] > 0:
                keep.add(int(labels[yi, xi]))
    if not keep:
        keep = {int(np.argmax(stats[1:, cv2.CC_STAT_AREA])) + 1}
    # Components larger than a fifth of the kept area stay too (an arm split off by a held object).
    kept_area = sum(stats[k, cv2.CC_STAT_AREA] for k in keep)
    for k in range(1, n):
        if stats[k, cv2.CC_STAT_AREA] > 0.2 * kept_area:
            keep.add(k)
    return np.isin(labels, sorted(keep))


def detect_persons(images: np.ndarray, on_frame=None, mask_threshold: float = 0.5) -> PersonTrack:
    """Run MediaPipe Pose over frames [T, H, W, 3] uint8 RGB (video mode)."""
    mp = import_mediapipe()
    T, H, W, _ = images.shape
    masks = np.zeros((T, H, W), dtype=bool)
    probs = np.zeros((T, H, W), dtype=np.uint8)
    kp2d = np.full((T, N_LANDMARKS, 3), np.nan, dtype=np.float32)
    kp3d = np.full((T, N_LANDMARKS, 3), np.nan, dtype=np.float32)
    detected = np.zeros(T, dtype=bool)
    with _quiet_native_logs():
        pose = mp.solutions.pose.Pose(
            static_image_mode=False,
            model_complexity=1,  # 0 and 2 download their models at first use
            smooth_landmarks=True,
            enable_segmentation=True,
            smooth_segmentation=True,
            min_detection_confidence=0.5,
            min_tracking_confidence=0.5,
        )
    try:
        for t in range(T):
            with _quiet_native_logs(), warnings.catch_warnings():
                # protobuf 4.25 warns about an API mediapipe 0.10.14 still uses.
                warnings.filterwarnings("ignore", message=".*GetPrototype.*", category=UserWarning)
                res = pose.process(np.ascontiguousarray(images[t]))
            if res.pose_landmarks is not None:
                detected[t] = True
                lm = res.pose_landmarks.landmark
                kp2d[t] = [(p.x * W, p.y * H, p.visibility) for p in lm]
                if res.pose_world_landmarks is not None:
                    kp3d[t] = [(p.x, p.y, p.z) for p in res.pose_world_landmarks.landmark]
                if res.segmentation_mask is not None:
                    soft = np.clip(res.segmentation_mask, 0.0, 1.0)
                    probs[t] = (soft * 255 + 0.5).astype(np.uint8)
                    masks[t] = clean_person_mask(soft > mask_threshold, kp2d[t])
            if on_frame:
                on_frame(t + 1)
    finally:
        pose.close()
    return PersonTrack(masks, probs, kp2d, kp3d, detected)


def refine_masks_sam2(images: np.ndarray, track: PersonTrack, checkpoint: Path, config: str, on_frame=None) -> np.ndarray:
    """Re-segment the person with SAM2 (box prompt from each frame's MediaPipe mask) -> [T, H, W] bool.

    Needs the optional ``sam2`` package and a checkpoint file; frames without a detection keep
    their (empty) mask.
    """
    if not Path(checkpoint).exists():
        raise UserError(f"--sam2-checkpoint {checkpoint} does not exist")
    try:
        import torch
        from sam2.build_sam import build_sam2
        from sam2.sam2_image_predictor import SAM2ImagePredictor
    except ImportError as e:
        raise UserError(f"--sam2-checkpoint needs the `sam2` package ({e}); install it or drop the option") from None
    predictor = SAM2ImagePredictor(build_sam2(config, str(checkpoint), device="cpu"))
    out = track.masks.copy()
    with torch.inference_mode():
        for t in range(len(images)):
            m = track.masks[t]
            if m.any():
                ys, xs = np.nonzero(m)
                box = np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], dtype=np.float32)
                predictor.set_image(images[t])
                pred, _, _ = predictor.predict(box=box, multimask_output=False)
                out[t] = pred[0] > 0.5
            if on_frame:
                on_frame(t + 1)
    return out


def refine_mask_boundary(rgb: np.ndarray, prob: np.ndarray, threshold: float = 0.5, band_frac: float = 0.03, iterations: int = 3) -> np.ndarray:
    """Sharpen a soft person mask's boundary with GrabCut inside a narrow band -> [H, W] bool.

    MediaPipe's mask is predicted at low resolution and upsampled, so it bleeds a few
    pixels over the background. Pixels deeper than the band inside the mask are kept as
    person, pixels beyond the band outside it as background; only the band (``band_frac``
    of the person's height on each side) is relabelled, by GrabCut colour models learnt
    from this frame, so a wrong colour model can move the boundary by at most the band.
    """
    import cv2

    mask = prob >= threshold * 255 if prob.dtype == np.uint8 else prob >= threshold
    if mask.sum() < 50:
        return mask
    ys, xs = np.nonzero(mask)
    band = max(2, int(round(band_frac * (ys.max() - ys.min() + 1))))
    H, W = mask.shape
    y0, y1 = max(0, ys.min() - 2 * band), min(H, ys.max() + 2 * band + 1)
    x0, x1 = max(0, xs.min() - 2 * band), min(W, xs.max() + 2 * band + 1)
    m = mask[y0:y1, x0:x1].astype(np.uint8)
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * band + 1, 2 * band + 1))
    inner = cv2.erode(m, k) > 0
    outer = cv2.dilate(m, k) > 0
    gc = np.full(m.shape, cv2.GC_BGD, np.uint8)
    gc[outer] = cv2.GC_PR_BGD
    gc[m > 0] = cv2.GC_PR_FGD
    gc[inner] = cv2.GC_FGD
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    crop = np.ascontiguousarray(rgb[y0:y1, x0:x1, ::-1])
    try:
        cv2.grabCut(crop, gc, None, bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK)
    except cv2.error:
        return mask
    out = np.zeros_like(mask)
    out[y0:y1, x0:x1] = (gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD)
    return out
