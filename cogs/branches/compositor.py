"""The compositor: splat every branch's Gaussians for one camera in one pass.

The branches' world-space splats (`Branch.splats`) are concatenated and rasterized once.
Beside RGB, each Gaussian carries a one-hot channel of its branch (registry order), so the
same pass returns each branch's alpha map (they sum to the total alpha, since the one-hots
of every Gaussian sum to one). Branch-only renders are the same call with a subset.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from cogs.branches.base import REGISTRY, Splats
from cogs.render import RenderOutput, rasterize


@dataclass
class CompositeRender:
    rgb: Tensor  # [H, W, 3]
    alpha: Tensor  # [H, W, 1]
    depth: Tensor  # [H, W, 1]
    branch_alpha: dict[str, Tensor]  # name -> [H, W, 1], every registered branch
    raw: RenderOutput  # the rasterizer's output (means2d, radii, visibility of all Gaussians)
    slices: dict[str, slice]  # where each rendered branch's Gaussians sit in raw.means2d / radii


def composite(
    splats: dict[str, Splats],
    viewmat: Tensor,  # [4, 4] world -> camera
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
    background: Tensor | None = None,  # [3]
    backend: str = "auto",
    near: float = 0.05,
    far: float = 100.0,
) -> CompositeRender:
    """Render the given branches' splats together, with per-branch alpha maps."""
    names = tuple(REGISTRY)
    nb = len(names)
    parts, slices, start = [], {}, 0
    for b, s in splats.items():
        onehot = s.means.new_zeros(len(s), nb)
        onehot[:, names.index(b)] = 1.0
        parts.append((s, onehot))
        slices[b] = slice(start, start + len(s))
        start += len(s)
    if start == 0:
        z = viewmat.new_zeros(height, width, 1)
        bg = viewmat.new_zeros(3) if background is None else background
        empty = RenderOutput(z, z, z, viewmat.new_zeros(0, 2), torch.zeros(0, dtype=torch.int32, device=z.device),
                             torch.zeros(0, dtype=torch.bool, device=z.device))
        return CompositeRender(bg.expand(height, width, 3).clone(), z, z, {b: z for b in names}, empty, {})
    cat = lambda f: torch.cat([f(s) for s, _ in parts])  # noqa: E731
    colors = torch.cat([torch.cat([s.rgb, oh], dim=1) for s, oh in parts])
    bg = None
    if background is not None:
        bg = torch.cat([background, background.new_zeros(nb)])
    out = rasterize(
        cat(lambda s: s.means), cat(lambda s: s.quats), cat(lambda s: s.scales), cat(lambda s: s.opacities),
        colors, viewmat, K, width, height, near=near, far=far, background=bg, backend=backend,
    )
    branch_alpha = {b: out.colors[..., 3 + i : 4 + i] for i, b in enumerate(names)}
    return CompositeRender(out.colors[..., :3], out.alpha, out.depth, branch_alpha, out, slices)
