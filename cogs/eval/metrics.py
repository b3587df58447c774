"""Image metrics for evaluation: PSNR, SSIM, LPIPS-AlexNet, tight-bbox crops and mask IoU.

Conventions shared by every function here:

- Images are ``[H, W, C]`` floats in ``[0, 1]`` (data range 1), torch tensors or numpy
  arrays. Metric functions return Python floats (or ``None`` where a value cannot be
  computed); the differentiable building blocks (``ssim_torch``, ``LPIPSAlex``) return
  tensors.
- Masks are ``[H, W]`` (or ``[H, W, 1]``) booleans or {0, 1} numbers.

SSIM follows Wang et al. 2004 exactly as scikit-image computes it with
``gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1``: an 11x11
Gaussian window (sigma 1.5, truncated at 3.5 sigma and renormalised), statistics per
channel on the 2-D image, and the SSIM map averaged over the *valid* region only (5 pixels
are dropped on every border, where the window would leave the image). The test suite checks
it against scikit-image to 1e-4.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from cogs.eval.lpips import LPIPS_MIN_SIDE, LPIPSAlex, load_lpips_alex, lpips_alex, lpips_status
from cogs.ssim import SSIM_WINDOW_SIZE, gaussian_window_1d, ssim_torch

__all__ = [
    "psnr",
    "ssim",
    "ssim_torch",
    "gaussian_window_1d",
    "SSIM_WINDOW_SIZE",
    "lpips_alex",
    "lpips_status",
    "load_lpips_alex",
    "LPIPSAlex",
    "LPIPS_MIN_SIDE",
    "mask_bbox",
    "crop_to_mask",
    "iou",
    "image_metrics",
]

def _to_tensor(x: Any, dtype: torch.dtype | None = None) -> Tensor:
    t = x if isinstance(x, Tensor) else torch.as_tensor(np.asarray(x))
    if dtype is not None:
        t = t.to(dtype)
    elif not t.is_floating_point():
        t = t.float()
    return t


def _to_mask(mask: Any) -> Tensor:
    """[H, W] or [H, W, 1] mask -> [H, W] bool tensor on CPU."""
    m = mask.detach().cpu() if isinstance(mask, Tensor) else torch.as_tensor(np.asarray(mask))
    if m.ndim == 3 and m.shape[-1] == 1:
        m = m[..., 0]
    if m.ndim != 2:
        raise ValueError(f"mask must be [H, W] or [H, W, 1], got shape {tuple(m.shape)}")
    return m > 0.5 if m.is_floating_point() else m.bool()


def _check_pair(pred: Tensor, gt: Tensor) -> None:
    if pred.shape != gt.shape:
        raise ValueError(f"pred and gt differ in shape: {tuple(pred.shape)} vs {tuple(gt.shape)}")
    if pred.ndim != 3:
        raise ValueError(f"images must be [H, W, C], got shape {tuple(pred.shape)}")


# --------------------------------------------------------------------------------------
# PSNR


def psnr(pred: Any, gt: Any, mask: Any | None = None) -> float:
    """Peak signal-to-noise ratio in dB for data range 1.

    pred, gt: [H, W, C] in [0, 1]. mask: optional [H, W] selecting the pixels whose squared
    errors (all channels) enter the mean. Identical images give ``inf``; an empty mask is a
    ValueError (crop or skip the frame instead).
    """
    p = _to_tensor(pred, torch.float64).detach().cpu()
    g = _to_tensor(gt, torch.float64).detach().cpu()
    _check_pair(p, g)
    sq = (p - g) ** 2
    if mask is not None:
        m = _to_mask(mask)
        if m.shape != p.shape[:2]:
            raise ValueError(f"mask shape {tuple(m.shape)} does not match image {tuple(p.shape[:2])}")
        if not bool(m.any()):
            raise ValueError("psnr: mask is empty")
        sq = sq[m]
    mse = float(sq.mean())
    if mse == 0.0:
        return math.inf
    return -10.0 * math.log10(mse)


# --------------------------------------------------------------------------------------
# SSIM


def ssim(pred: Any, gt: Any) -> float:
    """SSIM of two [H, W, C] images in [0, 1] (float64, scikit-image conventions)."""
    p = _to_tensor(pred, torch.float64).detach()
    g = _to_tensor(gt, torch.float64).detach()
    _check_pair(p, g)
    with torch.no_grad():
        return float(ssim_torch(p, g.to(p.device)))


# --------------------------------------------------------------------------------------
# Crops and masks


def mask_bbox(mask: Any) -> tuple[int, int, int, int] | None:
    """Tight bounding box of a mask's true pixels as ``(y0, y1, x0, x1)``, end-exclusive

    (``image[y0:y1, x0:x1]`` is the crop); ``None`` for an empty mask.
    """
    m = _to_mask(mask)
    rows = torch.nonzero(m.any(dim=1)).flatten()
    if rows.numel() == 0:
        return None
    cols = torch.nonzero(m.any(dim=0)).flatten()
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def crop_to_mask(pred: Any, gt: Any, mask: Any, pad: int = 0) -> tuple[Any, Any] | None:
    """Crop the composite render and the ground truth to the mask's tight bounding box.

    pred, gt: [H, W, C]; mask: [H, W] (the ground-truth mask of the human or the object).
    ``pad`` pixels are added on every side, clamped to the image. Returns ``(pred_crop,
    gt_crop)`` of the input types, or ``None`` for an empty mask (report null with a note).
    Pixels outside the mask are kept: the protocols crop, they do not matte.
    """
    box = mask_bbox(mask)
    if box is None:
        return None
    h, w = pred.shape[:2]
    if tuple(gt.shape[:2]) != (h, w) or _to_mask(mask).shape != (h, w):
        raise ValueError("crop_to_mask: pred, gt and mask must share H and W")
    y0, y1, x0, x1 = box
    y0, x0 = max(0, y0 - pad), max(0, x0 - pad)
    y1, x1 = min(h, y1 + pad), min(w, x1 + pad)
    return pred[y0:y1, x0:x1], gt[y0:y1, x0:x1]


def iou(pred_mask: Any, gt_mask: Any, empty: float = 1.0) -> float:
    """Intersection over union of two boolean masks of the same shape.

    When both masks are empty the union is empty and ``empty`` is returned (1.0 by default:
    predicting nothing where there is nothing is a perfect decomposition; pass
    ``float("nan")`` to exclude such frames from an average with ``nanmean``).
    """
    a, b = _to_mask(pred_mask), _to_mask(gt_mask)
    if a.shape != b.shape:
        raise ValueError(f"mask shapes differ: {tuple(a.shape)} vs {tuple(b.shape)}")
    union = int((a | b).sum())
    if union == 0:
        return float(empty)
    return int((a & b).sum()) / union


# --------------------------------------------------------------------------------------
# All three


def image_metrics(
    pred: Any, gt: Any, *, with_lpips: bool = True, notes: list[str] | None = None
) -> dict[str, float | None]:
    """``{"psnr", "ssim", "lpips"}`` of one [H, W, 3] image pair in [0, 1].

    A value that cannot be computed is ``None`` and, when ``notes`` is given, a sentence
    saying why is appended to it: SSIM for images smaller than 11x11, LPIPS when its
    weights are unavailable (see ``lpips_status``) or the image is smaller than
    ``LPIPS_MIN_SIDE`` pixels on a side.
    """
    p = _to_tensor(pred, torch.float64).detach()
    g = _to_tensor(gt, torch.float64).detach().to(p.device)
    _check_pair(p, g)
    out: dict[str, float | None] = {"psnr": psnr(p, g), "ssim": None, "lpips": None}

    def note(msg: str) -> None:
        if notes is not None:
            notes.append(msg)

    h, w = p.shape[:2]
    if min(h, w) >= SSIM_WINDOW_SIZE:
        out["ssim"] = ssim(p, g)
    else:
        note(f"ssim is null: image {h}x{w} is smaller than the {SSIM_WINDOW_SIZE}x{SSIM_WINDOW_SIZE} window")
    if with_lpips:
        if min(h, w) < LPIPS_MIN_SIDE:
            note(
                f"lpips is null: image {h}x{w} is smaller than AlexNet's minimum "
                f"{LPIPS_MIN_SIDE}x{LPIPS_MIN_SIDE}"
            )
        else:
            value = lpips_alex(p, g)
            if value is None:
                note(f"lpips is null: {lpips_status()}")
            out["lpips"] = value
    return out
