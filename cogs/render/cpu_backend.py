"""CPU backend: numba kernels behind autograd.Functions.

* projection: :mod:`cogs.render.cpu_projection` (fused EWA projection with a hand-written
  backward; the torch version when a camera tensor needs gradients);
* pixel pass: :mod:`cogs.render._kernels` (binning, forward compositing, backward).

SH evaluation and the final colour/depth arithmetic stay in torch (O(N) or O(pixels)).
The kernels work in float32 on host memory; inputs of another dtype or device are converted
and the gradients converted back, so the backend also serves float64 or CUDA tensors
(slowly, through the host).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from cogs.render import _kernels
from cogs.render.cpu_projection import project_gaussians_fused
from cogs.render.projection import Projected, project_gaussians, tile_grid


def _np32(t: Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().to(device="cpu", dtype=torch.float32).numpy())


def _pad4(a: np.ndarray) -> np.ndarray:
    """Zero-pad the last (channel) axis to a multiple of 4: the kernels handle channels in
    blocks of four, one vectorised loop per block."""
    pad = (-a.shape[-1]) % 4
    if pad == 0:
        return a
    return np.ascontiguousarray(np.concatenate([a, np.zeros(a.shape[:-1] + (pad,), a.dtype)], axis=-1))


def _tile_order(tiles_x: int, tiles_y: int) -> np.ndarray:
    """Tiles interleaved so that the contiguous chunks numba hands to each thread are spread
    over the whole image (neighbouring tiles cost alike; halves of an image do not)."""
    n = tiles_x * tiles_y
    return np.concatenate([np.arange(s, n, 2, dtype=np.int64) for s in (0, 1)])


def project(means, quats, scales, viewmat, K, width, height, near, far) -> Projected:
    """EWA projection for the CPU backend: fused numba unless camera gradients are needed."""
    if viewmat.requires_grad or K.requires_grad:
        return project_gaussians(means, quats, scales, viewmat, K, width, height, near, far)
    return project_gaussians_fused(means, quats, scales, viewmat, K, width, height, near, far)


def bin_tiles(means2d: np.ndarray, radii: np.ndarray, depths: np.ndarray, width: int, height: int):
    """(offsets [T+1] int64, ids [M] int32): per-tile lists of Gaussian ids, front to back."""
    tiles_x, tiles_y = tile_grid(width, height)
    order = _kernels.depth_order(depths)
    return _kernels.bin_gaussians(means2d, radii, order, tiles_x, tiles_y)


_NO_BG = np.zeros(0, np.float32)


class _Rasterize(torch.autograd.Function):
    """Pixel pass plus the per-pixel finish (background, expected depth) in one node.

    The finish runs in two small serial numba kernels (``_kernels.finish_forward`` and
    ``start_backward``) rather than torch or numpy expressions: after a numba parallel
    region, every multi-threaded torch op on an image-sized tensor can stall on a thread of
    the other pool (on a loaded machine each stall costs a time slice), and the numpy
    version's dozen image-sized temporaries cost ~1 ms per step at 256x192.
    """

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, depths, background, radii, width,
                height):
        tiles_x, tiles_y = tile_grid(width, height)
        m2, co, op = _np32(means2d), _np32(conics), _np32(opacities)
        z = _np32(depths)
        r = np.ascontiguousarray(radii.detach().cpu().numpy().astype(np.int32, copy=False))
        offsets, ids = bin_tiles(m2, r, z, width, height)
        tile_order = _tile_order(tiles_x, tiles_y)
        D = colors.shape[1]
        fe = _pad4(np.concatenate([_np32(colors), z[:, None]], axis=1))
        spans = _kernels.support_spans(m2, co, op)
        geometry = (offsets, ids, m2, co, op, fe, spans, width, height, tiles_x, tile_order)
        feat, T_final, last = _kernels.forward(*geometry)
        bg = _NO_BG if background is None else _np32(background)
        img, alpha, depth = _kernels.finish_forward(feat, T_final, D, bg)
        ctx.kernel_state = (geometry, T_final, last, feat, bg)
        ctx.like = (means2d, conics, opacities, colors, depths, background)
        to = dict(device=colors.device, dtype=colors.dtype)
        return (torch.from_numpy(img).to(**to), torch.from_numpy(alpha).to(**to),
                torch.from_numpy(depth).to(**to))

    @staticmethod
    def backward(ctx, g_img, g_alpha, g_depth):
        geometry, T_final, last, feat, bg = ctx.kernel_state
        grad_feat, g_a, g_bg = _kernels.start_backward(_np32(g_img), _np32(g_alpha), _np32(g_depth),
                                                       T_final, feat, bg)
        D = g_img.shape[-1]
        g_bg = None if ctx.like[5] is None else g_bg.astype(np.float32)
        ids, n = geometry[1], geometry[2].shape[0]
        slots = _kernels.backward(*geometry, T_final, last, grad_feat, g_a)
        g = _kernels.reduce_slots(ids, n, slots)
        f = _kernels.SLOT_FEAT
        grads = (g[:, 0:2], g[:, 2:5], g[:, 5], g[:, f:f + D], g[:, f + D], g_bg)
        out = []
        for g, like in zip(grads, ctx.like):
            out.append(None if g is None or like is None
                       else torch.from_numpy(g).to(device=like.device, dtype=like.dtype))
        return (*out, None, None, None)


def rasterize_image(
    means2d: Tensor,  # [N, 2]
    conics: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    colors: Tensor,  # [N, D]
    depths: Tensor,  # [N] camera z: sort key and depth channel
    background: Tensor | None,  # [D]
    radii: Tensor,  # [N] int, 0 = culled
    width: int,
    height: int,
) -> tuple[Tensor, Tensor, Tensor]:
    """-> colours [H, W, D] (with background), alpha [H, W, 1], expected depth [H, W, 1]."""
    return _Rasterize.apply(means2d, conics, opacities, colors, depths, background, radii,
                            width, height)
