"""Differentiable Gaussian-splatting rasterizer: ``rasterize`` and its backends.

``torch`` is the readable autograd reference, ``cpu`` the numba kernels (default off-GPU),
``gsplat`` the optional CUDA path. See docs/rendering.md.
"""

from cogs.render.api import RenderOutput, count_pairs, rasterize
from cogs.render.cpu_backend import warmup

__all__ = ["rasterize", "RenderOutput", "count_pairs", "warmup"]
