"""Realistic errors on the synthetic scene's inputs (see `NoiseConfig` for the defaults).

Pose estimators and trackers drift slowly and jitter a little; segmenters get boundaries
wrong by a pixel or two and sometimes erode or dilate a whole mask; SfM cameras are off
by fractions of a degree and millimetres. Each function takes the exact values and a
numpy Generator and returns noisy copies; all are deterministic given the generator.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.ndimage import distance_transform_edt, gaussian_filter1d, zoom

from cogs.data.synth.config import NoiseConfig
from cogs.geometry.rotations import axis_angle_to_rotmat, rotmat_to_axis_angle

# Joints that get the smooth pose offset (the ones a pose estimator gets visibly wrong).
MAJOR_JOINTS = (
    "spine05", "spine03", "spine01", "neck01", "head",
    "upperleg01.L", "upperleg01.R", "lowerleg01.L", "lowerleg01.R", "foot.L", "foot.R",
    "upperarm01.L", "upperarm01.R", "lowerarm01.L", "lowerarm01.R", "wrist.L", "wrist.R",
)


def smooth_noise(rng: np.random.Generator, T: int, dims: int, sigma_frames: float) -> np.ndarray:
    """[T, dims] Gaussian-filtered white noise with unit standard deviation per sample."""
    if sigma_frames < 0.5:
        return rng.standard_normal((T, dims))
    pad = int(4 * sigma_frames) + 1
    white = rng.standard_normal((T + 2 * pad, dims))
    smooth = gaussian_filter1d(white, sigma_frames, axis=0, mode="constant", truncate=4.0)[pad:pad + T]
    k = np.exp(-0.5 * (np.arange(-pad + 1, pad) / sigma_frames) ** 2)
    k /= k.sum()
    return smooth / np.sqrt((k ** 2).sum())


def _rotvec_compose(delta: np.ndarray, rotvec: np.ndarray) -> np.ndarray:
    """exp(delta) exp(rotvec) as rotation vectors, batched over leading dims."""
    R = axis_angle_to_rotmat(torch.from_numpy(delta)) @ axis_angle_to_rotmat(torch.from_numpy(rotvec))
    return rotmat_to_axis_angle(R).numpy()


def _rot_offsets(rng, T, n, smooth_deg, jitter_deg, sigma_frames):
    """[T, n, 3] rotation-vector offsets (radians): smooth + per-frame jitter."""
    s = smooth_noise(rng, T, 3 * n, sigma_frames).reshape(T, n, 3) * np.deg2rad(smooth_deg)
    j = rng.standard_normal((T, n, 3)) * np.deg2rad(jitter_deg)
    return s + j


def noisy_body(pose: np.ndarray, transl: np.ndarray, shape: np.ndarray, bone_names: list[str],
               cfg: NoiseConfig, rng: np.random.Generator, sigma_frames: float):
    """Noisy (pose [T, J, 3], transl [T, 3], shape [S])."""
    T = len(pose)
    idx = [bone_names.index(n) for n in MAJOR_JOINTS]
    out = pose.astype(np.float64).copy()
    d = _rot_offsets(rng, T, len(idx), cfg.body_deg, cfg.body_jitter_deg, sigma_frames)
    out[:, idx] = _rotvec_compose(d, out[:, idx])
    root = bone_names.index("root")
    d_root = _rot_offsets(rng, T, 1, cfg.root_deg, 0.0, sigma_frames)[:, 0]
    out[:, root] = _rotvec_compose(d_root, out[:, root])
    tr = transl + smooth_noise(rng, T, 3, sigma_frames) * cfg.transl_m + rng.standard_normal((T, 3)) * cfg.transl_jitter_m
    sh = np.clip(shape + rng.standard_normal(shape.shape) * cfg.shape, 0.0, 1.0)
    return out, tr, sh


def noisy_rigid(R: np.ndarray, t: np.ndarray, smooth_m: float, jitter_m: float, smooth_deg: float,
                jitter_deg: float, rng: np.random.Generator, sigma_frames: float):
    """Noisy rigid trajectory: rotations [T, 3, 3] (left-multiplied) and positions [T, 3]."""
    T = len(R)
    dt = smooth_noise(rng, T, 3, sigma_frames) * smooth_m + rng.standard_normal((T, 3)) * jitter_m
    w = _rot_offsets(rng, T, 1, smooth_deg, jitter_deg, sigma_frames)[:, 0]
    dR = axis_angle_to_rotmat(torch.from_numpy(w)).numpy()
    return dR @ R, t + dt


def noisy_cameras(world_to_camera: np.ndarray, cfg: NoiseConfig, rng: np.random.Generator) -> np.ndarray:
    """Per-frame independent errors of camera orientation and position (world frame)."""
    T = len(world_to_camera)
    R_wc = np.swapaxes(world_to_camera[:, :3, :3], 1, 2)  # camera -> world
    C = -np.einsum("tij,tj->ti", R_wc, world_to_camera[:, :3, 3])
    w = rng.standard_normal((T, 3)) * np.deg2rad(cfg.camera_deg)
    R_wc = axis_angle_to_rotmat(torch.from_numpy(w)).numpy() @ R_wc
    C = C + rng.standard_normal((T, 3)) * cfg.camera_m
    out = np.zeros_like(world_to_camera)
    out[:, :3, :3] = np.swapaxes(R_wc, 1, 2)
    out[:, :3, 3] = -np.einsum("tij,tj->ti", out[:, :3, :3], C)
    out[:, 3, 3] = 1.0
    return out


def noisy_mask(mask: np.ndarray, cfg: NoiseConfig, rng: np.random.Generator) -> np.ndarray:
    """A segmenter's version of a binary mask [H, W]: a smooth boundary displacement
    (std `mask_px`, clipped at 2 px) plus, with probability `mask_morph_prob`, a 1-pixel
    erosion or dilation. Changes stay within 3 px of the true boundary."""
    H, W = mask.shape
    cell = 8
    coarse = rng.standard_normal((H // cell + 3, W // cell + 3))
    field = zoom(coarse, cell, order=3, mode="nearest")[:H, :W]
    field = np.clip(field / max(field.std(), 1e-6) * cfg.mask_px, -2.0, 2.0)
    morph = 0.0
    if rng.random() < cfg.mask_morph_prob:
        morph = 1.0 if rng.random() < 0.5 else -1.0
    if not mask.any():
        return mask.copy()
    # Signed distance (pixels, negative inside) between pixel centres and the boundary.
    inside = distance_transform_edt(mask)
    outside = distance_transform_edt(~mask)
    sdf = np.where(mask, 0.5 - inside, outside - 0.5)
    return sdf < field + morph
