"""Adaptive density control per branch: clone, split, prune, opacity reset.

Semantics follow 3DGS (and gsplat's DefaultStrategy): the mean norm of each Gaussian's
screen-space positional gradient (NDC units) is accumulated over the views it was visible
in; every `refine_every` steps, Gaussians above `grad_threshold` are cloned when small or
split in two (children sampled from the parent, scales / 1.6) when large; then Gaussians
that became transparent or huge are pruned. The running state is an explicit dict of
tensors passed in and out (so it checkpoints with the run), and every edit is applied to
all per-Gaussian tensors of the branch *and* to the matching Adam moments (new rows get
zero moments), keeping the Parameter objects the optimizers hold.

Each branch is seen through a small adapter telling which tensors are per-Gaussian and
what its Gaussians' current geometry is (the human's scales/rotations/opacities are
decoded from its field, so its adapter decodes them).

A resized parameter is a new `Parameter` object swapped into its module and into every
optimizer (with its moments): autograd caches a leaf's shape in its gradient
accumulator, so changing `.data` in place would break the next backward pass.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from cogs.branches.gaussians import inverse_sigmoid
from cogs.branches.human import HumanBranch
from cogs.branches.object import ObjectBranch
from cogs.branches.scene import SceneBranch
from cogs.config import Density
from cogs.geometry.rotations import quat_to_rotmat

SPLIT_SHRINK = 1.6  # 3DGS: children scales are the parent's / (0.8 * 2)


@dataclass
class Geometry:
    means: Tensor  # [N, 3] in the branch's own space
    scales: Tensor  # [N, 3] activated
    quats: Tensor  # [N, 4]
    opacities: Tensor  # [N]


def replace_parameter(owner: torch.nn.Module, key: str, value: Tensor, optimizers=(), moments=None) -> torch.nn.Parameter:
    """Swap `owner.<key>` (a module attribute or ParameterDict entry) for a new Parameter
    holding `value`; optimizers that held the old one hold the new one, with `moments(old
    state tensor) -> new state tensor` applied to its Adam moments."""
    old = owner[key] if isinstance(owner, torch.nn.ParameterDict) else getattr(owner, key)
    new = torch.nn.Parameter(value.detach().to(old.dtype).clone(), requires_grad=old.requires_grad)
    if isinstance(owner, torch.nn.ParameterDict):
        owner[key] = new
    else:
        setattr(owner, key, new)
    for opt in optimizers:
        for group in opt.param_groups:
            group["params"] = [new if p is old else p for p in group["params"]]
        if old in opt.state:
            st = opt.state.pop(old)
            if moments is not None:
                for k in ("exp_avg", "exp_avg_sq"):
                    if k in st:
                        st[k] = moments(st[k])
            opt.state[new] = st
    return new


class BranchGaussians:
    """Adapter: a branch's per-Gaussian parameters and buffers, and its geometry.

    `params` maps a name to (owner, key): the module or ParameterDict holding it."""

    def __init__(self, module: torch.nn.Module, params: dict[str, tuple], buffers: tuple[str, ...] = ()):
        self.module = module
        self.params = params
        self.buffers = buffers

    def param(self, name: str) -> torch.nn.Parameter:
        owner, key = self.params[name]
        return owner[key] if isinstance(owner, torch.nn.ParameterDict) else getattr(owner, key)

    def __len__(self) -> int:
        return int(self.param(next(iter(self.params))).shape[0])

    def geometry(self) -> Geometry:
        raise NotImplementedError

    def split_children(self, sel: Tensor, offsets: Tensor) -> dict[str, Tensor]:
        """Per-Gaussian values of the children of `sel` (two per parent, `offsets` [2M, 3])."""
        raise NotImplementedError

    def reset_opacity(self, value: float, optimizers) -> None:
        raise NotImplementedError

    # -- generic edits ----------------------------------------------------------------
    def gather(self, index: Tensor, fresh: Tensor, optimizers) -> None:
        """Rows `index` of every per-Gaussian tensor; moments zeroed where `fresh`."""

        def moments(m: Tensor) -> Tensor:
            out = m[index].clone()
            out[fresh] = 0
            return out

        for name, (owner, key) in self.params.items():
            replace_parameter(owner, key, self.param(name).detach()[index], optimizers, moments)
        for name in self.buffers:
            setattr(self.module, name, getattr(self.module, name)[index].clone())

    def append(self, values: dict[str, Tensor], optimizers) -> None:
        """Add new Gaussians (values for every per-Gaussian tensor, fresh moments)."""
        n = len(self)
        m = next(iter(values.values())).shape[0]

        def pad(t: Tensor) -> Tensor:
            return torch.cat([t, torch.zeros((m,) + t.shape[1:], dtype=t.dtype)])

        for name, (owner, key) in self.params.items():
            old = self.param(name)
            replace_parameter(owner, key, torch.cat([old.detach(), values[name].to(old.dtype)]), optimizers, pad)
        for name in self.buffers:
            buf = getattr(self.module, name)
            setattr(self.module, name, torch.cat([buf, values[name].to(buf.dtype)]))
        assert len(self) == n + m


def _optim_states(p, optimizers):
    for opt in optimizers:
        st = opt.state.get(p)
        if st:
            yield st


class SetGaussians(BranchGaussians):
    """A plain GaussianSet (scene, object)."""

    def __init__(self, gaussians):
        super().__init__(gaussians, {k: (gaussians.params, k) for k in gaussians.params})
        self.g = gaussians

    def geometry(self) -> Geometry:
        g = self.g
        return Geometry(g.means.detach(), g.scales.detach(), g.quats.detach(), g.opacities.detach())

    def split_children(self, sel: Tensor, offsets: Tensor) -> dict[str, Tensor]:
        rep = lambda t: t.detach()[sel].repeat(2, *([1] * (t.dim() - 1)))  # noqa: E731
        out = {k: rep(self.param(k)) for k in self.params}
        out["means"] = out["means"] + offsets
        out["scales"] = out["scales"] - torch.log(torch.tensor(SPLIT_SHRINK))
        return out

    def reset_opacity(self, value: float, optimizers) -> None:
        p = self.param("opacities")
        with torch.no_grad():
            p.clamp_(max=float(inverse_sigmoid(torch.tensor(value))))
        for st in _optim_states(p, optimizers):
            for k in ("exp_avg", "exp_avg_sq"):
                if k in st:
                    st[k].zero_()


class HumanGaussians(BranchGaussians):
    def __init__(self, human: HumanBranch):
        super().__init__(human, {k: (human, k) for k in HumanBranch.PER_GAUSSIAN_PARAMS}, HumanBranch.PER_GAUSSIAN_BUFFERS)
        self.human = human

    def geometry(self) -> Geometry:
        with torch.no_grad():
            st = self.human.decode()
        return Geometry(st.means.detach(), st.scales.detach(), st.quats.detach(), st.opacities.detach())

    def split_children(self, sel: Tensor, offsets: Tensor) -> dict[str, Tensor]:
        h = self.human
        rep = lambda t: t.detach()[sel].repeat(2, *([1] * (t.dim() - 1)))  # noqa: E731
        out = {"means": rep(h.means) + offsets, "color_residual": rep(h.color_residual)}
        for name in self.buffers:
            out[name] = rep(getattr(h, name))
        out["seed_means"] = out["seed_means"] + offsets  # the prior moves with the child
        out["seed_scales"] = out["seed_scales"] / SPLIT_SHRINK
        return out

    def reset_opacity(self, value: float, optimizers) -> None:
        pass  # the human's opacity is anchored to its seed; it is never reset


def adapter_for(branch) -> BranchGaussians:
    if isinstance(branch, HumanBranch):
        return HumanGaussians(branch)
    if isinstance(branch, (ObjectBranch, SceneBranch)):
        return SetGaussians(branch.gaussians)
    raise TypeError(type(branch))


def new_state(n: int) -> dict[str, Tensor]:
    return {"grad2d": torch.zeros(n), "count": torch.zeros(n), "radii": torch.zeros(n)}


def accumulate(state: dict[str, Tensor], means2d_grad: Tensor, radii: Tensor, width: int, height: int) -> None:
    """Add one view's screen-space gradient norms (NDC units) for the visible Gaussians."""
    vis = radii > 0
    g = means2d_grad.detach().clone()
    g[:, 0] *= 0.5 * width
    g[:, 1] *= 0.5 * height
    state["grad2d"][vis] += g[vis].norm(dim=-1)
    state["count"][vis] += 1
    r = radii.float() / max(width, height)
    state["radii"] = torch.maximum(state["radii"], torch.where(vis, r, torch.zeros_like(r)))


def refine(
    adapter: BranchGaussians,
    state: dict[str, Tensor],
    cfg: Density,
    extent: float,
    optimizers,
    generator: torch.Generator,
    prune: bool = True,
) -> dict[str, int]:
    """One densify-and-prune round; returns counts of what changed. Resets `state`."""
    n = len(adapter)
    geo = adapter.geometry()
    avg = state["grad2d"] / state["count"].clamp_min(1)
    high = avg > cfg.grad_threshold
    max_scale = geo.scales.max(dim=1).values
    small = max_scale <= cfg.split_scale * extent
    dup = high & (small | torch.tensor(cfg.clone_only))
    split = high & ~dup
    room = max(cfg.max_gaussians - n, 0)
    # Respect the cap: keep the highest-gradient candidates (splits add one net Gaussian each).
    cand = torch.nonzero(dup | split).flatten()
    if len(cand) > room:
        keep = cand[torch.argsort(avg[cand], descending=True)[:room]]
        mask = torch.zeros(n, dtype=torch.bool)
        mask[keep] = True
        dup &= mask
        split &= mask
    n_dup, n_split = int(dup.sum()), int(split.sum())
    if n_dup:
        idx = torch.cat([torch.arange(n), torch.nonzero(dup).flatten()])
        fresh = torch.zeros(len(idx), dtype=torch.bool)
        fresh[n:] = True
        adapter.gather(idx, fresh, optimizers)
        split = torch.cat([split, torch.zeros(n_dup, dtype=torch.bool)])
        geo = Geometry(*(torch.cat([t, t[dup]]) for t in (geo.means, geo.scales, geo.quats, geo.opacities)))
    if n_split:
        sel = torch.nonzero(split).flatten()
        R = quat_to_rotmat(geo.quats[sel])
        eps = torch.randn(2 * len(sel), 3, generator=generator)
        local = geo.scales[sel].repeat(2, 1) * eps
        offsets = (R.repeat(2, 1, 1) @ local[..., None])[..., 0]
        children = adapter.split_children(sel, offsets)
        adapter.append(children, optimizers)
        keep = torch.ones(len(adapter), dtype=torch.bool)
        keep[sel] = False
        idx = torch.nonzero(keep).flatten()
        adapter.gather(idx, torch.zeros(len(idx), dtype=torch.bool), optimizers)
    n_pruned = 0
    if prune:
        geo = adapter.geometry()
        bad = (geo.opacities < cfg.prune_opacity) | (geo.scales.max(dim=1).values > cfg.prune_scale * extent)
        if bool(bad.all()):
            bad[:] = False  # never prune a branch away entirely
        n_pruned = int(bad.sum())
        if n_pruned:
            idx = torch.nonzero(~bad).flatten()
            adapter.gather(idx, torch.zeros(len(idx), dtype=torch.bool), optimizers)
    state.update(new_state(len(adapter)))
    return {"cloned": n_dup, "split": n_split, "pruned": n_pruned, "total": len(adapter)}
