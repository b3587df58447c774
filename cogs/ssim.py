"""SSIM (Wang et al. 2004) exactly as scikit-image computes it, differentiable: the metric
evaluation reports (`cogs.eval.metrics.ssim`) and the D-SSIM loss training minimises
(`cogs.train.losses.dssim`) share it.

``gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1``: an 11x11
Gaussian window (sigma 1.5, truncated at 3.5 sigma and renormalised), statistics per
channel on the 2-D image, and the SSIM map averaged over the *valid* region only (5 pixels
are dropped on every border, where the window would leave the image). The test suite checks
it against scikit-image to 1e-4.

`ssim` is what the training's D-SSIM loss calls: on CPU float32 images whose second
argument needs no gradient it runs the fused numba kernels of `cogs.ssim_cpu` (the same
value and gradient, several times faster at training sizes), elsewhere `ssim_torch`.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

SSIM_SIGMA = 1.5
SSIM_TRUNCATE = 3.5  # scikit-image / scipy.ndimage default
SSIM_WINDOW_SIZE = 2 * int(SSIM_TRUNCATE * SSIM_SIGMA + 0.5) + 1  # 11
SSIM_K1 = 0.01
SSIM_K2 = 0.03


def gaussian_window_1d(
    sigma: float = SSIM_SIGMA, truncate: float = SSIM_TRUNCATE, dtype=torch.float64, device=None
) -> Tensor:
    """Normalised 1-D Gaussian taps, the same as scipy.ndimage's for (sigma, truncate)."""
    radius = int(truncate * sigma + 0.5)
    x = torch.arange(-radius, radius + 1, dtype=dtype, device=device)
    w = torch.exp(-0.5 * (x / sigma) ** 2)
    return w / w.sum()


def _blur_valid(x: Tensor, w: Tensor) -> Tensor:
    """Separable depthwise Gaussian blur of [B, C, H, W], keeping only the valid region."""
    c = x.shape[1]
    k = w.numel()
    x = F.conv2d(x, w.view(1, 1, 1, k).expand(c, 1, 1, k), groups=c)
    return F.conv2d(x, w.view(1, 1, k, 1).expand(c, 1, k, 1), groups=c)


def ssim_torch(pred: Tensor, gt: Tensor, data_range: float = 1.0) -> Tensor:
    """Differentiable SSIM (mean over the valid region, then over channels).

    pred, gt: [H, W, C] (returns a 0-dim tensor) or [B, C, H, W] (returns [B]). Both sides
    must be at least 11 pixels high and wide (ValueError otherwise, as in scikit-image).
    Gradients flow to both inputs; ``1 - ssim_torch(render, image)`` is the D-SSIM loss.
    Note that border pixels (5 on each side) only influence the value through windows
    centred inside the valid region, as in the metric.
    """
    if pred.shape != gt.shape:
        raise ValueError(f"pred and gt differ in shape: {tuple(pred.shape)} vs {tuple(gt.shape)}")
    single = pred.ndim == 3
    if single:
        x, y = pred.permute(2, 0, 1)[None], gt.permute(2, 0, 1)[None]
    elif pred.ndim == 4:
        x, y = pred, gt
    else:
        raise ValueError(f"expected [H, W, C] or [B, C, H, W], got shape {tuple(pred.shape)}")
    h, w = x.shape[-2:]
    if min(h, w) < SSIM_WINDOW_SIZE:
        raise ValueError(
            f"ssim needs images at least {SSIM_WINDOW_SIZE}x{SSIM_WINDOW_SIZE}, got {h}x{w}"
        )
    dtype = torch.promote_types(x.dtype, torch.float32)
    x, y = x.to(dtype), y.to(dtype)
    win = gaussian_window_1d(dtype=dtype, device=x.device)

    mu_x = _blur_valid(x, win)
    mu_y = _blur_valid(y, win)
    # Population (not sample) covariance: use_sample_covariance=False in scikit-image.
    var_x = _blur_valid(x * x, win) - mu_x * mu_x
    var_y = _blur_valid(y * y, win) - mu_y * mu_y
    cov_xy = _blur_valid(x * y, win) - mu_x * mu_y
    c1 = (SSIM_K1 * data_range) ** 2
    c2 = (SSIM_K2 * data_range) ** 2
    s_map = ((2 * mu_x * mu_y + c1) * (2 * cov_xy + c2)) / (
        (mu_x * mu_x + mu_y * mu_y + c1) * (var_x + var_y + c2)
    )
    # Every channel has the same number of valid pixels, so the mean over (C, H, W) equals
    # the per-channel means averaged.
    value = s_map.mean(dim=(1, 2, 3))
    return value[0] if single else value


def ssim(pred: Tensor, gt: Tensor) -> Tensor:
    """Differentiable mean SSIM of two [H, W, C] images (gradient to `pred`), as
    `ssim_torch`: fused CPU kernels for float32 host tensors with a constant `gt`."""
    fused = (pred.ndim == 3 and pred.shape == gt.shape and pred.device.type == "cpu" and gt.device.type == "cpu"
             and pred.dtype == torch.float32 and gt.dtype == torch.float32 and not gt.requires_grad
             and min(pred.shape[0], pred.shape[1]) >= SSIM_WINDOW_SIZE)
    if not fused:
        return ssim_torch(pred, gt)
    from cogs.ssim_cpu import FusedSSIM

    return FusedSSIM.apply(pred, gt, _window32(), SSIM_K1**2, SSIM_K2**2)


_WINDOW32 = None


def _window32():
    global _WINDOW32
    if _WINDOW32 is None:
        _WINDOW32 = gaussian_window_1d(dtype=torch.float64, device=torch.device("cpu")).float().numpy()
    return _WINDOW32


def warmup() -> float:
    """Compile (or load from numba's cache) the fused SSIM kernels on a tiny image, forward
    and backward, so that JIT time never lands inside a training loop. Returns seconds."""
    import time

    t0 = time.perf_counter()
    cpu = torch.device("cpu")
    g = torch.Generator(device=cpu).manual_seed(0)
    pred = torch.rand(SSIM_WINDOW_SIZE + 1, SSIM_WINDOW_SIZE + 2, 3, generator=g, device=cpu).requires_grad_(True)
    ssim(pred, torch.rand(pred.shape, generator=g, device=cpu)).backward()
    return time.perf_counter() - t0
