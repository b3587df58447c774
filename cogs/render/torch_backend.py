"""Tile-based PyTorch reference of the pixel pass: the specification the fast backends are
tested against. Readable first, fast never; fully differentiable by autograd.

For every 16x16 tile: take the Gaussians whose 3-sigma square overlaps the tile, front to
back; evaluate alpha for every (Gaussian, pixel of the tile) pair densely; compose with a
cumulative product, expressing the three 3DGS rules as masks:

* ``alpha = min(0.99, o exp(-0.5 d^T conic d))``; a pair with ``alpha < 1/255`` (or a
  numerically non-positive-definite exponent > 0) contributes nothing;
* a pixel stops *before* the Gaussian that would take its transmittance below ``1e-4``;
* ``colour = sum_i f_i alpha_i T_i``, ``alpha_pixel = 1 - T_final``.

The number of pairs this pass evaluates, ``sum_tiles n_gaussians_in_tile * pixels_in_tile``,
is the work unit of the rasterizer benchmark (:func:`pair_count`).
"""

from __future__ import annotations

import torch
from torch import Tensor

from cogs.render.projection import TILE_SIZE, depth_order, tile_grid, tile_ranges

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4


def _axis_pixels(n_tiles: int, size: int, device) -> Tensor:
    """Pixels per tile along one axis (the last tile may be partial)."""
    starts = torch.arange(n_tiles, device=device) * TILE_SIZE
    return (torch.clamp(size - starts, max=TILE_SIZE)).to(torch.int64)


@torch.no_grad()
def pair_count(ranges: Tensor, width: int, height: int) -> int:
    """Gaussian-pixel pairs the reference evaluates: sum over Gaussians of the pixels of the
    tiles its square touches. ``ranges`` is :func:`cogs.render.projection.tile_ranges`."""
    tiles_x, tiles_y = tile_grid(width, height)
    device = ranges.device
    cx = torch.cat([torch.zeros(1, dtype=torch.int64, device=device),
                    torch.cumsum(_axis_pixels(tiles_x, width, device), 0)])
    cy = torch.cat([torch.zeros(1, dtype=torch.int64, device=device),
                    torch.cumsum(_axis_pixels(tiles_y, height, device), 0)])
    r = ranges.to(torch.int64)
    px = cx[r[:, 1]] - cx[r[:, 0]]
    py = cy[r[:, 3]] - cy[r[:, 2]]
    return int((px * py).sum().item())


def composite_tile(
    means2d: Tensor,  # [G, 2] front to back
    conics: Tensor,  # [G, 3]
    opacities: Tensor,  # [G]
    features: Tensor,  # [G, F]
    px: Tensor,  # [P] pixel-centre x
    py: Tensor,  # [P] pixel-centre y
) -> tuple[Tensor, Tensor]:
    """Dense front-to-back compositing of G Gaussians over P pixels -> ([P, F], [P] alpha)."""
    dx = means2d[:, 0:1] - px[None, :]  # [G, P]
    dy = means2d[:, 1:2] - py[None, :]
    a, b, c = conics[:, 0:1], conics[:, 1:2], conics[:, 2:3]
    power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
    alpha = torch.clamp(opacities[:, None] * torch.exp(power), max=ALPHA_MAX)
    counts = (alpha >= ALPHA_MIN) & (power <= 0.0)
    alpha = torch.where(counts, alpha, torch.zeros_like(alpha))
    one_minus = 1.0 - alpha
    T_incl = torch.cumprod(one_minus, dim=0)  # transmittance after each Gaussian
    # A pixel stops before the Gaussian that would take T below T_MIN; T_incl is
    # non-increasing, so everything after that Gaussian is excluded as well.
    keep = T_incl >= T_MIN
    T_excl = torch.cat([torch.ones_like(T_incl[:1]), T_incl[:-1]], dim=0)
    weights = torch.where(keep, alpha * T_excl, torch.zeros_like(alpha))  # [G, P]
    feat = weights.T @ features  # [P, F]
    T_final = torch.cumprod(torch.where(keep, one_minus, torch.ones_like(one_minus)), dim=0)[-1]
    return feat, 1.0 - T_final


def rasterize_pixels(
    means2d: Tensor,  # [N, 2]
    conics: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    features: Tensor,  # [N, F]
    radii: Tensor,  # [N] int, 0 = culled
    depths: Tensor,  # [N] sort key, front to back
    width: int,
    height: int,
) -> tuple[Tensor, Tensor]:
    """Composite features -> ([H, W, F] sum_i f_i w_i, [H, W, 1] alpha)."""
    ranges = tile_ranges(means2d, radii, width, height)
    order = depth_order(depths)
    F = features.shape[1]
    tiles_x, tiles_y = tile_grid(width, height)
    device, dtype = means2d.device, means2d.dtype
    # Zero that still depends on every input, so backward works (and yields zeros) even
    # when no Gaussian reaches the image.
    zero = 0.0 * (means2d.sum() + conics.sum() + opacities.sum() + features.sum())
    r = ranges[order]
    m2, co, op, fe = means2d[order], conics[order], opacities[order], features[order]
    rows = []
    for ty in range(tiles_y):
        y0, y1 = ty * TILE_SIZE, min((ty + 1) * TILE_SIZE, height)
        in_row = (r[:, 2] <= ty) & (ty < r[:, 3])
        cols_f, cols_a = [], []
        for tx in range(tiles_x):
            x0, x1 = tx * TILE_SIZE, min((tx + 1) * TILE_SIZE, width)
            idx = torch.nonzero(in_row & (r[:, 0] <= tx) & (tx < r[:, 1])).squeeze(1)
            h, w = y1 - y0, x1 - x0
            if idx.numel() == 0:
                cols_f.append(features.new_zeros(h, w, F))
                cols_a.append(features.new_zeros(h, w, 1))
                continue
            yy, xx = torch.meshgrid(
                torch.arange(y0, y1, device=device, dtype=dtype),
                torch.arange(x0, x1, device=device, dtype=dtype),
                indexing="ij",
            )
            feat, alpha = composite_tile(
                m2[idx], co[idx], op[idx], fe[idx], xx.reshape(-1) + 0.5, yy.reshape(-1) + 0.5
            )
            cols_f.append(feat.reshape(h, w, F))
            cols_a.append(alpha.reshape(h, w, 1))
        rows.append((torch.cat(cols_f, dim=1), torch.cat(cols_a, dim=1)))
    out_feat = torch.cat([f for f, _ in rows], dim=0) + zero
    out_alpha = torch.cat([a for _, a in rows], dim=0) + zero
    return out_feat, out_alpha


def finish(feat: Tensor, alpha: Tensor, D: int, background: Tensor | None) -> tuple[Tensor, Tensor]:
    """[H, W, D+1] composited colour + depth channel, [H, W, 1] alpha -> colour with the
    background behind (T_final = 1 - alpha), expected depth (0 where alpha == 0)."""
    colors = feat[..., :D]
    if background is not None:
        colors = colors + (1.0 - alpha) * background
    has = alpha > 0
    depth = torch.where(has, feat[..., D:] / torch.where(has, alpha, torch.ones_like(alpha)),
                        torch.zeros_like(alpha))
    return colors, depth
