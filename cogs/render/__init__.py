"""Differentiable Gaussian-splatting rasterizer: ``rasterize`` and its backends.

``torch`` is the readable autograd reference, ``cpu`` the numba kernels (default off-GPU),
``gsplat`` the optional CUDA path. See docs/rendering.md.
"""

from cogs.render.api import count_pairs, rasterize, warmup
from cogs.render.output import RenderOutput

__all__ = ["rasterize", "RenderOutput", "count_pairs", "warmup"]
