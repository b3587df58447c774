"""CPU backend: numba pixel pass (see :mod:`cogs.render._kernels`) behind an autograd.Function.

Projection, SH and culling stay in differentiable torch (shared with the reference, O(N));
only binning, compositing and its backward run in numba. The kernels work in float32 on
host memory; inputs of another dtype or device are converted and the gradients converted
back, so the backend also serves float64 or CUDA tensors (slowly, through the host).
"""

from __future__ import annotations

import time

import numpy as np
import torch
from torch import Tensor

from cogs.render import _kernels
from cogs.render.projection import tile_grid


def _np32(t: Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().to(device="cpu", dtype=torch.float32).numpy())


def _tile_order(tiles_x: int, tiles_y: int) -> np.ndarray:
    """Tiles interleaved so that the contiguous chunks numba hands to each thread are spread
    over the whole image (neighbouring tiles cost alike; halves of an image do not)."""
    n = tiles_x * tiles_y
    return np.concatenate([np.arange(s, n, 2, dtype=np.int64) for s in (0, 1)])


def bin_tiles(ranges: Tensor, order: Tensor, width: int, height: int):
    """(offsets [T+1] int64, ids [M] int32) of the depth-sorted tile lists."""
    tiles_x, tiles_y = tile_grid(width, height)
    r = np.ascontiguousarray(ranges.detach().cpu().numpy().astype(np.int32, copy=False))
    o = np.ascontiguousarray(order.detach().cpu().numpy().astype(np.int64, copy=False))
    return _kernels.bin_gaussians(r, o, tiles_x, tiles_x * tiles_y)


class _PixelPass(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, ranges, order, width, height):
        tiles_x, tiles_y = tile_grid(width, height)
        offsets, ids = bin_tiles(ranges, order, width, height)
        tile_order = _tile_order(tiles_x, tiles_y)
        m2, co, op, fe = _np32(means2d), _np32(conics), _np32(opacities), _np32(features)
        feat, T_final, last = _kernels.forward(
            offsets, ids, m2, co, op, fe, width, height, tiles_x, tile_order
        )
        ctx.kernel_state = (offsets, ids, m2, co, op, fe, tile_order, T_final, last)
        ctx.geometry = (width, height, tiles_x)
        ctx.like = (means2d, conics, opacities, features)
        alpha = (1.0 - T_final)[..., None]
        out_feat = torch.from_numpy(feat).to(device=features.device, dtype=features.dtype)
        out_alpha = torch.from_numpy(alpha).to(device=features.device, dtype=features.dtype)
        return out_feat, out_alpha

    @staticmethod
    def backward(ctx, grad_feat, grad_alpha):
        offsets, ids, m2, co, op, fe, tile_order, T_final, last = ctx.kernel_state
        width, height, tiles_x = ctx.geometry
        n = m2.shape[0]
        slots = _kernels.backward(
            offsets, ids, m2, co, op, fe, width, height, tiles_x, tile_order, T_final, last,
            _np32(grad_feat), _np32(grad_alpha[..., 0]),
        )
        grads = _kernels.reduce_slots(ids, n, *slots)
        out = []
        for g, like in zip(grads, ctx.like):
            out.append(torch.from_numpy(g).to(device=like.device, dtype=like.dtype))
        return (*out, None, None, None, None)


def rasterize_pixels(
    means2d: Tensor,  # [N, 2]
    conics: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    features: Tensor,  # [N, F]
    ranges: Tensor,  # [N, 4] int32
    order: Tensor,  # [N] front to back
    width: int,
    height: int,
) -> tuple[Tensor, Tensor]:
    """Same contract as :func:`cogs.render.torch_backend.rasterize_pixels`."""
    return _PixelPass.apply(means2d, conics, opacities, features, ranges, order, width, height)


def warmup() -> float:
    """Compile (or load from numba's on-disk cache) every CPU kernel by rendering a tiny
    scene forward and backward once. Returns the seconds it took. Call it once at start-up
    so that JIT time never lands inside a training loop."""
    from cogs.render.api import rasterize

    t0 = time.perf_counter()
    g = torch.Generator().manual_seed(0)
    n = 8
    means = (torch.rand(n, 3, generator=g) - 0.5) * 0.5 + torch.tensor([0.0, 0.0, 2.0])
    means.requires_grad_(True)
    quats = torch.randn(n, 4, generator=g)
    scales = torch.full((n, 3), 0.05)
    opac = torch.full((n,), 0.7)
    colors = torch.rand(n, 3, generator=g)
    K = torch.tensor([[20.0, 0.0, 10.0], [0.0, 20.0, 10.0], [0.0, 0.0, 1.0]])
    out = rasterize(means, quats, scales, opac, colors, torch.eye(4), K, 20, 20, backend="cpu")
    (out.colors.sum() + out.alpha.sum() + out.depth.sum()).backward()
    return time.perf_counter() - t0
