"""What `cogs.render.rasterize` returns, whichever backend rendered it."""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor


@dataclass
class RenderOutput:
    """What :func:`rasterize` returns (H = height, W = width, N Gaussians, D channels)."""

    colors: Tensor  # [H, W, D] sum_i c_i alpha_i T_i + T_final * background
    alpha: Tensor  # [H, W, 1] 1 - T_final
    depth: Tensor  # [H, W, 1] expected camera z: sum_i w_i z_i / alpha; 0 where alpha == 0
    means2d: Tensor  # [N, 2] px; .grad holds dL/dmeans2d after backward (densification)
    radii: Tensor  # [N] int32 px, 0 = culled
    visible: Tensor  # [N] bool, radii > 0
