"""Adaptive density control per branch: clone, split, prune.

Semantics follow 3DGS (and gsplat's DefaultStrategy): the mean norm of each Gaussian's
screen-space positional gradient (NDC units) is accumulated over the views it was visible
in (`step_post_backward`, fed by the step's renders); every `refine_every` steps inside
the stage's [start_fraction, stop_fraction) window, Gaussians above `grad_threshold` are
cloned when small or split in two (children sampled from the parent, scales / 1.6) when
large; then Gaussians that became transparent or huge are pruned (`step_refine`).

The running state is an explicit dict of tensors passed in and out, so it checkpoints
with the run; every edit goes through the branch's density adapter
(`cogs.branches.surgery`), which keeps all per-Gaussian tensors and the matching Adam
moments together. No opacity reset: CoGS' final stage avoids aggressive resets and the
quick and paper schedules never used one.
"""

from __future__ import annotations

import torch
from torch import Tensor

from cogs.branches.compositor import CompositeRender
from cogs.branches.surgery import BranchGaussians, Geometry
from cogs.config import Density
from cogs.geometry.rotations import quat_to_rotmat


class DensityStrategy:
    """Density control of one branch: its hyper-parameters and schedule (`Density`); the
    state lives outside, in the dict `initialize_state` returns."""

    def __init__(self, branch: str, cfg: Density):
        self.branch, self.cfg = branch, cfg

    def initialize_state(self, n: int, device: torch.device) -> dict[str, Tensor]:
        return new_state(n, device)

    def step_post_backward(self, state: dict[str, Tensor], render: CompositeRender, width: int, height: int) -> None:
        """Add this render's screen-space gradients of the branch's Gaussians."""
        raw, sl = render.raw, render.slices.get(self.branch)
        if sl is None or raw.means2d.grad is None:
            return
        accumulate(state, raw.means2d.grad[sl], raw.radii[sl], width, height)

    def due(self, step: int, n_steps: int) -> bool:
        """Whether step `step` of a stage of `n_steps` ends with a refinement."""
        c = self.cfg
        start, stop = int(c.start_fraction * n_steps), int(c.stop_fraction * n_steps)
        return start <= step < stop and step != 0 and (step + 1) % c.refine_every == 0

    def step_refine(self, state: dict[str, Tensor], adapter: BranchGaussians, extent: float, optimizers,
                    generator: torch.Generator) -> dict[str, int]:
        return refine(adapter, state, self.cfg, extent, optimizers, generator)


def new_state(n: int, device: torch.device | str = "cpu") -> dict[str, Tensor]:
    return {"grad2d": torch.zeros(n, device=device), "count": torch.zeros(n, device=device)}


def accumulate(state: dict[str, Tensor], means2d_grad: Tensor, radii: Tensor, width: int, height: int) -> None:
    """Add one view's screen-space gradient norms (NDC units) for the visible Gaussians."""
    vis = radii > 0
    g = means2d_grad.detach().clone()
    g[:, 0] *= 0.5 * width
    g[:, 1] *= 0.5 * height
    # Masked adds without boolean indexing (which serialises on a nonzero): adding exact
    # zeros elsewhere changes nothing.
    state["grad2d"] += torch.where(vis, g.norm(dim=-1), 0.0)
    state["count"] += vis


def refine(
    adapter: BranchGaussians,
    state: dict[str, Tensor],
    cfg: Density,
    extent: float,
    optimizers,
    generator: torch.Generator,
    prune: bool = True,
) -> dict[str, int]:
    """One densify-and-prune round; returns counts of what changed. Resets `state`.
    Random draws (the split children's offsets) come from `generator`, on its device."""
    n = len(adapter)
    dev = adapter.device
    geo = adapter.geometry()
    avg = state["grad2d"] / state["count"].clamp_min(1)
    high = avg > cfg.grad_threshold
    max_scale = geo.scales.max(dim=1).values
    small = max_scale <= cfg.split_scale * extent
    dup = high & (small | torch.tensor(cfg.clone_only, device=dev))
    split = high & ~dup
    room = max(cfg.max_gaussians - n, 0)
    # Respect the cap: keep the highest-gradient candidates (splits add one net Gaussian each).
    cand = torch.nonzero(dup | split).flatten()
    if len(cand) > room:
        keep = cand[torch.argsort(avg[cand], descending=True)[:room]]
        mask = torch.zeros(n, dtype=torch.bool, device=dev)
        mask[keep] = True
        dup &= mask
        split &= mask
    n_dup, n_split = int(dup.sum()), int(split.sum())
    if n_dup:
        idx = torch.cat([torch.arange(n, device=dev), torch.nonzero(dup).flatten()])
        fresh = torch.zeros(len(idx), dtype=torch.bool, device=dev)
        fresh[n:] = True
        adapter.gather(idx, fresh, optimizers)
        split = torch.cat([split, torch.zeros(n_dup, dtype=torch.bool, device=dev)])
        geo = Geometry(*(torch.cat([t, t[dup]]) for t in (geo.means, geo.scales, geo.quats, geo.opacities)))
    if n_split:
        sel = torch.nonzero(split).flatten()
        R = quat_to_rotmat(geo.quats[sel])
        eps = torch.randn(2 * len(sel), 3, generator=generator, device=generator.device).to(dev)
        local = geo.scales[sel].repeat(2, 1) * eps
        offsets = (R.repeat(2, 1, 1) @ local[..., None])[..., 0]
        children = adapter.split_children(sel, offsets)
        adapter.append(children, optimizers)
        keep = torch.ones(len(adapter), dtype=torch.bool, device=dev)
        keep[sel] = False
        idx = torch.nonzero(keep).flatten()
        adapter.gather(idx, torch.zeros(len(idx), dtype=torch.bool, device=dev), optimizers)
    n_pruned = 0
    if prune:
        geo = adapter.geometry()
        bad = (geo.opacities < cfg.prune_opacity) | (geo.scales.max(dim=1).values > cfg.prune_scale * extent)
        if bool(bad.all()):
            bad[:] = False  # never prune a branch away entirely
        n_pruned = int(bad.sum())
        if n_pruned:
            idx = torch.nonzero(~bad).flatten()
            adapter.gather(idx, torch.zeros(len(idx), dtype=torch.bool, device=dev), optimizers)
    state.update(new_state(len(adapter), dev))
    return {"cloned": n_dup, "split": n_split, "pruned": n_pruned, "total": len(adapter)}
