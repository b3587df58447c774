"""The image objectives a stage runs: each renders what it needs and returns its loss terms
as a named dict of weighted tensors, with the render (which feeds density control).

    human    the human alone on a random background, against the image with everything
             outside the human mask replaced by that background (CoGS' human-separated
             render): RGB, mask BCE, un-premultiplied colour, alpha L1 / Dice / edge
    object   human and object on a random background: RGB, silhouette BCE and Dice,
             edge and un-premultiplied colour, on a padded box round the object
    compose  every branch, the full frame: RGB and each branch's alpha against its mask

The object's mask supervises nothing on a frame whose object confidence is below
`ObjectConfig.min_confidence` (`Frame.object_trusted`): the object objective returns no
terms there, compose drops its object-mask term but keeps the full-frame RGB (the pixels
are the image whatever the masks say).

A term is computed only when the stage's weights name it (`StageSpec.weights`). Image
terms are pure functions in `losses.py`; the branches add their own regularisers
(`Branch.regularisers`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Mapping

import torch
from torch import Tensor

from cogs.branches.compositor import CompositeRender
from cogs.model import Model
from cogs.train import losses as L
from cogs.train.frames import Frame


@dataclass
class StepInputs:
    model: Model
    frame: Frame
    weights: Mapping[str, float]
    prepared: dict  # each branch's per-step shared work (Model.prepare)
    background: Callable[[], Tensor]  # a random [3] background (drawn from the run's generator)
    crop_human: bool  # human terms on a padded box round the person (TrainConfig.crop_human_losses)


Result = tuple[dict[str, Tensor], CompositeRender | None]
"""The terms, and the render (None when the objective had nothing to measure on the frame)."""


def _render(s: StepInputs, branches: tuple[str, ...] | None, background: Tensor) -> CompositeRender:
    f = s.frame
    return s.model.render(f.viewmat, f.K, int(f.image.shape[1]), int(f.image.shape[0]), f.t, branches=branches,
                          background=background, prepared=s.prepared)


def human(s: StepInputs) -> Result:
    w, f = s.weights, s.frame
    bg = s.background()
    out = _render(s, ("human",), bg)
    img, hm, om, band, rgb, alpha = f.image, f.human, f.object, f.human_band, out.rgb, out.alpha
    if s.crop_human:  # measured on a padded box round the person (mask or render), not the frame
        y0, y1, x0, x1 = L.crop_box(hm[..., 0] > 0.5, alpha[..., 0].detach() > 0.05)
        img, hm, om, band, rgb, alpha = (x[y0:y1, x0:x1] for x in (img, hm, om, band, rgb, alpha))
    valid = 1.0 - om  # the object hides the person there: no evidence either way
    target = L.composite_over(img, hm, bg)
    pred = torch.where(om > 0, target, rgb)
    terms = {"rgb": w["human_rgb"] * L.photometric(pred, target, w["l1"], w["dssim"])}
    if "human_mask" in w:
        terms["mask"] = w["human_mask"] * L.bce(alpha, hm, valid)
    if "human_unpremultiplied" in w:
        terms["unpremult"] = w["human_unpremultiplied"] * L.unpremultiplied(rgb, alpha, img, hm * valid, bg)
    if "human_alpha_refine" in w:
        terms["alpha"] = w["human_alpha_refine"] * L.l1(alpha, hm, valid)
        terms["dice"] = w["human_dice"] * L.dice(alpha * valid, hm * valid)
        terms["edge"] = w["human_edge"] * L.edge(alpha, hm, band * valid)
    return terms, out


def object_(s: StepInputs) -> Result:
    w, f = s.weights, s.frame
    if not f.object_trusted:  # the object was lost here: its mask would supervise the wrong pixels
        return {}, None
    bg = s.background()
    out = _render(s, ("human", "object"), bg)
    img, hm, om = f.image, f.human, f.object
    fg = torch.clamp(hm + om, max=1.0)
    target = L.composite_over(img, fg, bg)
    ao = out.branch_alpha["object"]
    # The object covers a few hundred pixels: its image terms are measured on a padded
    # box around it (mask or render), so that they are not diluted by the whole frame
    # and outweighed by the pose prior.
    y0, y1, x0, x1 = L.crop_box(om[..., 0] > 0.5, ao[..., 0].detach() > 0.05)
    c = lambda x: x[y0:y1, x0:x1]  # noqa: E731
    terms = {"rgb": w["object_rgb"] * L.photometric(c(out.rgb), c(target), w["l1"], w["dssim"])}
    # Dice is unstable on a nearly hidden object (a handful of mask pixels): fade it in.
    dice_w = min(1.0, f.object_px / 200.0)
    terms["silhouette"] = w["object_bce"] * L.bce(c(ao), c(om))
    terms["silhouette_dice"] = w["object_dice"] * dice_w * L.dice(ao, om)
    if "object_edge" in w:
        terms["edge"] = w["object_edge"] * L.edge(c(ao), c(om), c(f.object_band))
        terms["unpremult"] = w["object_unpremultiplied"] * L.unpremultiplied(c(out.rgb), c(out.alpha), c(img), c(om), bg)
    return terms, out


def compose(s: StepInputs) -> Result:
    w, f = s.weights, s.frame
    out = _render(s, None, f.image.new_zeros(3))
    terms = {"rgb": w["compose_rgb"] * L.photometric(out.rgb, f.image, w["l1"], w["dssim"])}
    # On a frame whose object mask is not trusted, the human's mask term still leaves the
    # object mask's pixels out: there the scene's human mask is the person minus that
    # object mask (preprocess gives each pixel one owner), so they carry no evidence.
    terms["decomp"] = w["compose_human_mask"] * L.bce(out.branch_alpha["human"], f.human, 1.0 - f.object)
    if s.model.object is not None and f.object_trusted:
        terms["decomp_object"] = w["compose_object_mask"] * L.bce(out.branch_alpha["object"], f.object)
    return terms, out


OBJECTIVES: dict[str, Callable[[StepInputs], Result]] = {"human": human, "object": object_, "compose": compose}
"""Objective name -> function; each names the branches it renders in `RENDERS`."""
RENDERS: dict[str, tuple[str, ...] | None] = {"human": ("human",), "object": ("human", "object"), "compose": None}
