"""The branch protocol and the registry the model and the compositor iterate.

A branch is an `nn.Module` with one motion model over its own Gaussians. It provides:

* `splats(frame, campos, pose=None, prepared=None)`: its activated, world-space Gaussians
  for one frame (or an explicit pose), as `Splats`;
* `prepare()`: work shared by every render and loss of one step (the human decodes its
  field once; others return None);
* `param_groups(lr, extent)`: its named optimizer groups with their base learning rates;
* `density_adapter()`: the per-Gaussian tensors density control edits together
  (`cogs.branches.surgery`);
* `guard(extent)`: numerical repairs after an optimizer step;
* `regularisers(weights, frames)`: its own loss terms (anchoring, motion priors, planes),
  weighted, as a named dict;
* `extent(scene_extent)`: the length density control and the guards measure it by;
* `export(folder, n_frames)`: its files in a finished run;
* `from_state(state, cfg, body)`: the branch rebuilt from its state dict alone (no scene
  images), for `Model.load`.

A new branch registers its class with `@register`; the registry's order is the order of
the branch one-hot channels the compositor renders, and of `Model.branches`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Mapping

import torch
from torch import Tensor


@dataclass
class Splats:
    """Activated, world-space Gaussians of one branch for one frame."""

    means: Tensor  # [N, 3] world, metres
    quats: Tensor  # [N, 4] wxyz, unit
    scales: Tensor  # [N, 3] standard deviations, metres
    opacities: Tensor  # [N] in [0, 1]
    rgb: Tensor  # [N, 3] colour, view-dependent part already evaluated

    def __len__(self) -> int:
        return int(self.means.shape[0])

    def subset(self, keep: Tensor) -> "Splats":
        return Splats(self.means[keep], self.quats[keep], self.scales[keep], self.opacities[keep], self.rgb[keep])


class Branch(torch.nn.Module):
    """What every branch provides (see the module docstring)."""

    name: ClassVar[str]

    def __len__(self) -> int:
        raise NotImplementedError

    @property
    def device(self) -> torch.device:
        return next(self.buffers()).device

    def prepare(self) -> Any:
        return None

    def splats(self, frame: int, campos: Tensor, pose: Any = None, prepared: Any = None) -> Splats:
        raise NotImplementedError

    def param_groups(self, lr, extent: float) -> list[dict]:
        raise NotImplementedError

    def density_adapter(self):
        raise NotImplementedError

    def guard(self, extent: float) -> None:
        pass

    def regularisers(self, weights: Mapping[str, float], frames: Tensor, prepared: Any = None) -> dict[str, Tensor]:
        return {}

    def extent(self, scene_extent: float) -> float:
        return scene_extent

    def export(self, folder: Path, n_frames: int) -> list[Path]:
        return []

    @classmethod
    def from_state(cls, state: dict[str, Tensor], cfg, body=None) -> "Branch":
        raise NotImplementedError


REGISTRY: dict[str, type[Branch]] = {}


def register(cls: type[Branch]) -> type[Branch]:
    assert cls.name not in REGISTRY, cls.name
    REGISTRY[cls.name] = cls
    return cls

