"""The body-model interface every implementation (Anny, SMPL, ...) provides.

A body model maps a pose (per-bone axis-angle rotations + a world translation) and a
shape vector to per-bone skinning transforms. Its *canonical space* is the model's zero
pose (all rotations zero, translation zero) for a given shape: the human branch stores
its Gaussians there and poses them with `lbs_points` / `lbs_gaussians` and the transforms
returned by `bone_transforms`, so the zero pose returns the canonical set exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from cogs.body.lbs import lbs_points


@dataclass
class Canonical:
    """A body model's canonical (zero-pose) geometry for one shape (all float32)."""

    vertices: Tensor  # [V, 3] metres, model frame (z up)
    joints: Tensor  # [J, 3] bone heads
    faces: Tensor  # [F, 3] int64 triangles
    weights: Tensor  # [V, J] skinning weights, rows sum to 1


class BodyModel(torch.nn.Module):
    """Abstract body model. Subclasses set the label attributes and implement `_fk`.

    Attributes (data, not code, so callers never hard-code indices):
        name: registry name ("anny", "smpl", ...).
        bone_names: J labels; bone_parents: J parent indices (-1 for the root).
        shape_names: S labels of the shape vector; default_shape: [S].
        major_bones: the bones whose rotations a pose estimator recovers (the SMPL-24
            articulation); pose refinement acts on these only (default: every bone).
    """

    name: str
    bone_names: list[str]
    bone_parents: list[int]
    shape_names: list[str]
    default_shape: Tensor

    @property
    def major_bones(self) -> list[str]:
        return list(self.bone_names)

    @property
    def n_bones(self) -> int:
        return len(self.bone_names)

    @property
    def device(self) -> torch.device:
        """Where its constants live (`.to(device)` moves them); outputs follow the inputs'."""
        buf = next(self.buffers(), None)
        return buf.device if buf is not None else torch.device("cpu")

    def bone_index(self, name: str) -> int:
        try:
            return self.bone_names.index(name)
        except ValueError:
            raise KeyError(f"{self.name} has no bone named {name!r}") from None

    # -- implemented by subclasses -------------------------------------------------
    def canonical(self, shape: Tensor | None = None) -> Canonical:
        raise NotImplementedError

    def bone_transforms(
        self, pose: Tensor, transl: Tensor, shape: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """pose [B, J, 3] axis-angle, transl [B, 3] -> (skinning transforms [B, J, 4, 4]
        mapping canonical to world, posed joints [B, J, 3]). Differentiable in pose and
        transl."""
        raise NotImplementedError

    # -- shared --------------------------------------------------------------------
    def zero_pose(self, batch: int = 1) -> tuple[Tensor, Tensor]:
        return torch.zeros(batch, self.n_bones, 3, device=self.device), torch.zeros(batch, 3, device=self.device)

    def posed_vertices(self, pose: Tensor, transl: Tensor, shape: Tensor | None = None) -> Tensor:
        """[B, V, 3] skinned mesh vertices (the same LBS the human branch applies)."""
        can = self.canonical(shape)
        T, _ = self.bone_transforms(pose, transl, shape)
        return torch.stack([lbs_points(can.vertices, can.weights, t) for t in T])
