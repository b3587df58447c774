"""The compositor: pose every branch for one frame and splat them together in one pass.

For a camera and a frame (or any body pose and object pose), the human is skinned, the
object moved along its trajectory, both concatenated with the static scene, and
rasterized once. Beside RGB, each Gaussian carries a one-hot channel of its branch, so
the same pass returns each branch's alpha map (they sum to the total alpha, since the
one-hots of every Gaussian sum to one). Branch-only renders are the same call with a
subset of branches.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from cogs.branches.gaussians import GaussianSet
from cogs.branches.human import HumanBranch, HumanState
from cogs.branches.object import ObjectBranch
from cogs.branches.scene import SceneBranch
from cogs.geometry.rotations import quat_to_rotmat
from cogs.render import RenderOutput, rasterize
from cogs.render.sh import sh_to_color

BRANCHES = ("human", "object", "scene")


@dataclass
class Splats:
    """Activated, world-space Gaussians of one branch for one frame."""

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    rgb: Tensor  # [N, 3] view-dependent colour already evaluated

    def __len__(self) -> int:
        return int(self.means.shape[0])


@dataclass
class CompositeRender:
    rgb: Tensor  # [H, W, 3]
    alpha: Tensor  # [H, W, 1]
    depth: Tensor  # [H, W, 1]
    branch_alpha: dict[str, Tensor]  # name -> [H, W, 1]
    raw: RenderOutput  # the rasterizer's output (means2d, radii, visibility of all Gaussians)
    slices: dict[str, slice]  # where each branch's Gaussians sit in raw.means2d / radii


def _set_colors(g: GaussianSet, means: Tensor, campos: Tensor) -> Tensor:
    if g.sh_degree == 0:
        return g.rgb
    return sh_to_color(g.sh_degree, means - campos, g.sh)


class Compositor:
    """Renders any subset of the three branches for a frame and camera."""

    def __init__(
        self,
        human: HumanBranch | None,
        object: ObjectBranch | None,
        scene: SceneBranch | None,
        backend: str = "auto",
        near: float = 0.05,
        far: float = 100.0,
    ):
        self.human, self.object, self.scene = human, object, scene
        self.backend, self.near, self.far = backend, near, far

    def available(self) -> tuple[str, ...]:
        return tuple(b for b in BRANCHES if getattr(self, b) is not None and len(getattr(self, b)) > 0)

    # -- per-branch world-space splats -----------------------------------------------------
    def human_splats(self, frame: int, pose: tuple[Tensor, Tensor] | None = None, state: HumanState | None = None) -> Splats:
        h = self.human
        posed = h.posed(*pose, state) if pose is not None else h.posed_frame(frame, state)
        return Splats(posed.means, posed.quats, posed.scales, posed.opacities, posed.colors)

    def object_splats(self, frame: int, campos: Tensor, pose: tuple[Tensor, Tensor] | None = None) -> Splats:
        o = self.object
        translation, quat = pose if pose is not None else o.frame_pose(frame)
        means, quats = o.posed(translation, quat)
        g = o.gaussians
        # View-dependent colour is defined in the object's own frame: rotate the view ray back.
        if g.sh_degree > 0:
            rgb = sh_to_color(g.sh_degree, (means - campos) @ quat_to_rotmat(quat), g.sh)
        else:
            rgb = g.rgb
        if o.cfg.shading:
            rgb = rgb * o.shading(quat_to_rotmat(quats)[:, :, 2])
        return Splats(means, quats, g.scales, g.opacities, rgb)

    def scene_splats(self, campos: Tensor) -> Splats:
        g = self.scene.gaussians
        return Splats(g.means, g.quats, g.scales, g.opacities, _set_colors(g, g.means, campos))

    def splats(
        self,
        frame: int,
        viewmat: Tensor,
        branches: tuple[str, ...] | None = None,
        human_pose: tuple[Tensor, Tensor] | None = None,
        object_pose: tuple[Tensor, Tensor] | None = None,
        human_state: HumanState | None = None,
    ) -> dict[str, Splats]:
        branches = self.available() if branches is None else tuple(b for b in branches if b in self.available())
        campos = -(viewmat[:3, :3].T @ viewmat[:3, 3])
        out: dict[str, Splats] = {}
        for b in branches:
            if b == "human":
                out[b] = self.human_splats(frame, human_pose, human_state)
            elif b == "object":
                out[b] = self.object_splats(frame, campos, object_pose)
            else:
                out[b] = self.scene_splats(campos)
        return out

    # -- rendering --------------------------------------------------------------------------
    def render(
        self,
        viewmat: Tensor,
        K: Tensor,
        width: int,
        height: int,
        frame: int,
        branches: tuple[str, ...] | None = None,
        background: Tensor | None = None,  # [3]
        human_pose: tuple[Tensor, Tensor] | None = None,
        object_pose: tuple[Tensor, Tensor] | None = None,
        human_state: HumanState | None = None,
        splats: dict[str, Splats] | None = None,
    ) -> CompositeRender:
        if splats is None:
            splats = self.splats(frame, viewmat, branches, human_pose, object_pose, human_state)
        names = list(splats)
        nb = len(BRANCHES)
        parts, slices, start = [], {}, 0
        for b in names:
            s = splats[b]
            onehot = torch.zeros(len(s), nb)
            onehot[:, BRANCHES.index(b)] = 1.0
            parts.append((s, onehot))
            slices[b] = slice(start, start + len(s))
            start += len(s)
        if start == 0:
            z = torch.zeros(height, width, 1)
            bg = torch.zeros(3) if background is None else background
            return CompositeRender(bg.expand(height, width, 3).clone(), z, z, {b: z for b in BRANCHES},
                                   RenderOutput(z, z, z, torch.zeros(0, 2), torch.zeros(0, dtype=torch.int32), torch.zeros(0, dtype=torch.bool)), {})
        cat = lambda f: torch.cat([f(s) for s, _ in parts])  # noqa: E731
        colors = torch.cat([torch.cat([s.rgb, oh], dim=1) for s, oh in parts])
        bg = None
        if background is not None:
            bg = torch.cat([background, torch.zeros(nb)])
        out = rasterize(
            cat(lambda s: s.means), cat(lambda s: s.quats), cat(lambda s: s.scales), cat(lambda s: s.opacities),
            colors, viewmat, K, width, height, near=self.near, far=self.far, background=bg, backend=self.backend,
        )
        branch_alpha = {b: out.colors[..., 3 + i : 4 + i] for i, b in enumerate(BRANCHES)}
        return CompositeRender(out.colors[..., :3], out.alpha, out.depth, branch_alpha, out, slices)
