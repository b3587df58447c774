"""Fitting one frame's body pose to its image, everything else frozen.

Two callers:

* the training's last step, `refit` (after stage VI): every *training* frame's pose is
  fitted again against the finished model. Held-out frames interpolate these fits
  (`HumanBranch.held_out_pose`), so they inherit poses consistent with the appearance
  the model ended with, instead of the poses stage II fitted against an appearance that
  V-VI went on to change.
* `cogs eval`'s test-time fit (the Anim-NeRF / InstantAvatar protocol, reported apart
  from the strict numbers): the same fit on each held-out frame's own image.

Only the major bones' rotations and the body translation move, pulled by the image
alone: an L1 between the composite render and the frame. The input masks are left out on
purpose: they are a segmenter's, a pixel or two off along the outline, and a pose fitted
to them follows that noise (measured on the demo scene:
docs/experiments/2026-11-25-curriculum-levers.md).

The fit is exact and cheap at once: it renders only a padded box around the person and
only the frozen Gaussians that touch it (the rest cannot change a pixel of the box), and
it normalises the L1 by the whole frame's pixel count, so the loss, its gradient and the
fitted pose are those of the whole-frame fit.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from cogs.config import PoseRefit
from cogs.train import losses as L


class PoseFit(NamedTuple):
    dpose: Tensor  # [1, B, 3] axis-angle added to the refined bones' rotations
    dtransl: Tensor  # [1, 3] added to the body translation
    loss_first: float  # the image L1 (whole-frame mean) before and after the fit
    loss_last: float


def fit_frame_pose(model, image: Tensor, viewmat: Tensor, K: Tensor, t: int, opts: PoseRefit,
                   pose: tuple[Tensor, Tensor] | None = None) -> PoseFit:
    """The correction to frame t's body pose that fits `image` ([H, W, 3] in [0, 1]),
    starting from `pose` (default: the pose the human branch gives frame t)."""
    human = model.human
    H, W = int(image.shape[0]), int(image.shape[1])
    zero = (image.new_zeros(1, len(human.refined_bones), 3), image.new_zeros(1, 3))
    black = image.new_zeros(3)
    campos = -(viewmat[:3, :3].T @ viewmat[:3, 3])
    with torch.no_grad():
        state = human.decode()
        base_pose, base_transl = pose if pose is not None else human.frame_pose(t)
        alone = model.render(viewmat, K, W, H, t, branches=("human",), background=black,
                             poses={"human": (base_pose, base_transl)}, prepared={"human": state})
        foot = alone.alpha[..., 0] > 0.01
        if not bool(foot.any()):  # the person is off screen: no pixel depends on the pose
            r = model.render(viewmat, K, W, H, t, background=black, poses={"human": (base_pose, base_transl)})
            l1 = float(L.l1(r.rgb, image))
            return PoseFit(*zero, l1, l1)
        y0, y1, x0, x1 = L.crop_box(foot, foot, pad=opts.pad)
        Kc = K.clone()
        Kc[0, 2] -= x0
        Kc[1, 2] -= y0
        h, w = y1 - y0, x1 - x0
        others = model.splats(t, viewmat, tuple(b for b in model.available() if b != "human"))
        if others:
            seen = model.render(viewmat, Kc, w, h, t, background=black, splats=others)
            others = {b: s.subset(seen.raw.radii[seen.slices[b]] > 0) for b, s in others.items()}
    target = image[y0:y1, x0:x1]
    scale = 1.0 / (H * W * 3)  # the whole frame's L1 mean: pixels outside the box do not change

    def image_l1(dp: Tensor, dt: Tensor) -> Tensor:
        p = base_pose.index_add(1, human.refined_bones, dp)
        splats = {"human": human.splats(t, campos, (p, base_transl + dt), state), **others}
        r = model.render(viewmat, Kc, w, h, t, background=black, splats=splats)
        return (r.rgb - target).abs().sum() * scale

    dp, dt = (z.clone().requires_grad_(True) for z in zero)
    opt = torch.optim.Adam([{"params": [dp], "lr": opts.lr}, {"params": [dt], "lr": opts.lr * 0.5}])
    seen_l1 = []
    for _ in range(opts.steps):
        opt.zero_grad()
        data = image_l1(dp, dt)
        seen_l1.append(data.detach())
        loss = data + opts.reg * (dp.square().sum() + dt.square().sum())
        loss.backward()
        opt.step()
    with torch.no_grad():
        last = float(image_l1(dp, dt))
    if not (all(bool(torch.isfinite(v)) for v in seen_l1) and torch.isfinite(dp).all() and torch.isfinite(dt).all()):
        raise FloatingPointError(f"pose fit of frame {t}: a non-finite loss or correction")
    return PoseFit(dp.detach(), dt.detach(), float(seen_l1[0]) if seen_l1 else last, last)


def posed(human, t: int, fit: PoseFit, pose: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor]:
    """Frame t's pose with a fitted correction applied (from `pose`, default the branch's)."""
    base_pose, base_transl = pose if pose is not None else human.frame_pose(t)
    return base_pose.index_add(1, human.refined_bones, fit.dpose), base_transl + fit.dtransl
