"""Per-Gaussian image statistics through the rasterizer's own backward pass.

For a rendered channel C(p) = sum_i c_i w_i(p), the gradient of sum_p m(p) g(p) C(p)
with respect to c_i is sum_p m(p) g(p) w_i(p): the Gaussian's compositing weight, summed
over the pixels of a mask, optionally weighted by an image. One render + backward thus
gives, for every Gaussian at once, how much it is seen inside a mask and the
weight-averaged colour it covers. Used to colour freshly initialised Gaussians and to
compute the human visibility scores.
"""

from __future__ import annotations

import torch
from torch import Tensor

from cogs.render import rasterize


def splat_statistics(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    weight: Tensor,  # [H, W] pixel weights (e.g. a mask)
    image: Tensor | None = None,  # [H, W, 3]: also return the weighted colour sums
    backend: str = "auto",
) -> tuple[Tensor, Tensor | None, Tensor]:
    """Returns (visible weight [N], weighted colour sum [N, 3] or None, means2d [N, 2])."""
    n = means.shape[0]
    D = 1 if image is None else 4
    ones = torch.ones(n, D, device=means.device, requires_grad=True)
    with torch.enable_grad():
        out = rasterize(
            means.detach(), quats.detach(), scales.detach(), opacities.detach(), ones,
            viewmat, K, width, height, backend=backend,
        )
        target = weight[..., None].expand(height, width, D).clone()
        if image is not None:
            target[..., :3] = target[..., :3] * image
            target = target[..., [3, 0, 1, 2]]
        (out.colors * target).sum().backward()
    g = ones.grad
    vis = g[:, 0]
    col = g[:, 1:] if image is not None else None
    return vis, col, out.means2d.detach()
