"""Shading of the moving branches under light that stays fixed in the world.

A person who turns, or an object twisted in the hand, shows each surface point under a
different angle to the room's light, so its observed colour changes although its albedo
does not. The human and object branches therefore store albedo and multiply it by an
irradiance E(n) of the posed world-space normal n: a second-order spherical-harmonic
irradiance (9 coefficients, grey), which represents Lambertian shading from any distant
lighting to within a few percent (Ramamoorthi & Hanrahan 2001). It starts at E = 1
(unshaded); the static scene needs none (its shading is baked into its colours).
"""

from __future__ import annotations

import torch
from torch import Tensor

from cogs.render.sh import SH_C0, sh_basis


class Irradiance(torch.nn.Module):
    def __init__(self, device: torch.device | str | None = None) -> None:
        super().__init__()
        coeffs = torch.zeros(9, device=device)
        coeffs[0] = 1.0 / SH_C0
        self.coeffs = torch.nn.Parameter(coeffs)

    def forward(self, normals: Tensor) -> Tensor:
        """[N, 3] world normals (any length) -> [N, 1] irradiance, >= 0."""
        n = torch.nn.functional.normalize(normals, dim=-1)
        return (sh_basis(2, n) @ self.coeffs).clamp_min(0.0)[:, None]
