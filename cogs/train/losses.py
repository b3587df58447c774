"""Loss terms as pure functions of rendered maps and targets.

Images are [H, W, 3] in [0, 1]; alpha maps and masks [H, W, 1] (masks float 0/1).
Branch-specific regularisers (anchoring, pose prior, smoothness, planes) live with their
branch; this module holds the image-space terms the stages combine.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from cogs.ssim import ssim

_EPS = 1e-6


def l1(pred: Tensor, target: Tensor, mask: Tensor | None = None) -> Tensor:
    if mask is None:
        return (pred - target).abs().mean()
    w = mask.expand_as(pred)
    return ((pred - target).abs() * w).sum() / w.sum().clamp_min(1.0)


def dssim(pred: Tensor, target: Tensor) -> Tensor:
    """D-SSIM as 3DGS uses it: 1 - SSIM (11x11 Gaussian window, sigma 1.5)."""
    return 1.0 - ssim(pred, target)


def photometric(pred: Tensor, target: Tensor, w_l1: float, w_dssim: float) -> Tensor:
    """3DGS image loss: w_l1 L1 + w_dssim (1 - SSIM)."""
    loss = w_l1 * l1(pred, target)
    if w_dssim > 0:
        loss = loss + w_dssim * dssim(pred, target)
    return loss


def bce(alpha: Tensor, mask: Tensor, weight: Tensor | None = None) -> Tensor:
    a = alpha.clamp(_EPS, 1 - _EPS)
    b = -(mask * torch.log(a) + (1 - mask) * torch.log(1 - a))
    if weight is None:
        return b.mean()
    return (b * weight).sum() / weight.sum().clamp_min(1.0)


def dice(alpha: Tensor, mask: Tensor) -> Tensor:
    """1 - soft Dice coefficient; 0 when both are empty."""
    inter = (alpha * mask).sum()
    denom = alpha.sum() + mask.sum()
    return 1.0 - (2 * inter + 1.0) / (denom + 1.0)


def boundary_band(mask: np.ndarray, width_px: int = 2) -> np.ndarray:
    """[H, W] bool band of +-width_px pixels around a mask's boundary."""
    import cv2

    m = mask.astype(np.uint8)
    k = np.ones((2 * width_px + 1, 2 * width_px + 1), np.uint8)
    return (cv2.dilate(m, k) > 0) & ~(cv2.erode(m, k) > 0)


def edge(alpha: Tensor, mask: Tensor, band: Tensor) -> Tensor:
    """Silhouette-boundary term: mean |alpha - mask| inside the boundary band, plus the
    mismatch of their spatial gradients there (sharp edges at the right place)."""
    # An empty band gives 0 (with a graph) through the clamped denominators, no branch.
    err = ((alpha - mask).abs() * band).sum() / band.sum().clamp_min(1)
    gx = lambda x: x[:, 1:] - x[:, :-1]  # noqa: E731
    gy = lambda x: x[1:] - x[:-1]  # noqa: E731
    bx, by = band[:, 1:] * band[:, :-1], band[1:] * band[:-1]
    grad = ((gx(alpha) - gx(mask)).abs() * bx).sum() / bx.sum().clamp_min(1) + ((gy(alpha) - gy(mask)).abs() * by).sum() / by.sum().clamp_min(1)
    return err + 0.5 * grad


def unpremultiplied(rgb: Tensor, alpha: Tensor, image: Tensor, mask: Tensor, background: Tensor | None = None) -> Tensor:
    """L1 between the un-premultiplied colour (C - (1 - alpha) bg) / alpha and the image,
    inside the mask where alpha is not tiny: appearance independent of coverage."""
    fg = rgb if background is None else rgb - (1 - alpha) * background
    valid = mask * (alpha.detach() > 0.05).float()
    c = fg / alpha.clamp_min(0.05)
    return l1(c, image, valid)


def composite_over(image: Tensor, mask: Tensor, background: Tensor) -> Tensor:
    """The image where mask is 1, the background elsewhere."""
    return image * mask + background * (1 - mask)


def crop_box(a: Tensor, b: Tensor, pad: int = 8, min_side: int = 16) -> tuple[int, int, int, int]:
    """(y0, y1, x0, x1) of the padded bounding box of two [H, W] bool masks' union, at
    least `min_side` on each side (SSIM's window fits); the whole frame when both are empty."""
    H, W = a.shape
    m = a | b
    if not bool(m.any()):
        return 0, H, 0, W
    ys = torch.nonzero(m.any(1)).flatten()
    xs = torch.nonzero(m.any(0)).flatten()
    y0, y1 = int(ys[0]) - pad, int(ys[-1]) + 1 + pad
    x0, x1 = int(xs[0]) - pad, int(xs[-1]) + 1 + pad
    if y1 - y0 < min_side:
        c = (y0 + y1) // 2
        y0, y1 = c - min_side // 2, c + min_side // 2
    if x1 - x0 < min_side:
        c = (x0 + x1) // 2
        x0, x1 = c - min_side // 2, c + min_side // 2
    y0, x0 = max(y0, 0), max(x0, 0)
    return y0, min(y1, H), x0, min(x1, W)
