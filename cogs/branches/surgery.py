"""Tensor surgery on a branch's per-Gaussian tensors, shared by density control and
checkpoint loading (gsplat's `strategy/ops.py` pattern).

A branch is seen through a small adapter (`BranchGaussians`) that names its per-Gaussian
parameters and buffers and tells its current geometry; `gather` (keep / duplicate rows)
and `append` (new rows) edit all of them and the matching Adam moments together.

A resized parameter is a new `Parameter` object swapped into its module and into every
optimizer (with its moments): autograd caches a leaf's shape in its gradient
accumulator, so changing `.data` in place would break the next backward pass.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

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

    @property
    def device(self) -> torch.device:
        return self.param(next(iter(self.params))).device

    def geometry(self) -> Geometry:
        raise NotImplementedError

    def split_children(self, sel: Tensor, offsets: Tensor) -> dict[str, Tensor]:
        """Per-Gaussian values of the children of `sel` (two per parent, `offsets` [2M, 3])."""
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
            return torch.cat([t, t.new_zeros((m,) + t.shape[1:])])

        for name, (owner, key) in self.params.items():
            old = self.param(name)
            replace_parameter(owner, key, torch.cat([old.detach(), values[name].to(old.dtype)]), optimizers, pad)
        for name in self.buffers:
            buf = getattr(self.module, name)
            setattr(self.module, name, torch.cat([buf, values[name].to(buf.dtype)]))
        assert len(self) == n + m


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
        out["scales"] = out["scales"] - torch.log(torch.tensor(SPLIT_SHRINK, device=offsets.device))
        return out

