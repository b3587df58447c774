"""Density control edits every per-Gaussian tensor and the optimizer moments together."""

from __future__ import annotations

import torch

from cogs.branches.gaussians import GaussianSet
from cogs.branches.scene import SceneBranch, SceneConfig
from cogs.config import Density
from cogs.train import density as dens


def _branch(n=40, seed=0):
    g = torch.Generator().manual_seed(seed)
    xyz = torch.randn(n, 3, generator=g)
    gs = GaussianSet.from_points(xyz, torch.rand(n, 3, generator=g), torch.full((n,), 0.02), opacity=0.5)
    return SceneBranch(gs, [], SceneConfig())


def _optimizer(branch):
    opt = torch.optim.Adam([{"params": [p]} for p in branch.gaussians.params.values()], lr=1e-3)
    loss = sum(p.square().sum() for p in branch.gaussians.params.values())
    loss.backward()
    opt.step()
    return opt


def _state_for(branch, high: torch.Tensor):
    st = dens.new_state(len(branch))
    st["grad2d"][high] = 1.0
    st["count"][:] = 1
    return st


def test_clone_and_split_follow_gradient_and_size_and_keep_moments_aligned():
    b = _branch()
    with torch.no_grad():
        b.gaussians.params["scales"][:10] = torch.log(torch.tensor(0.5))  # large: split
    opt = _optimizer(b)
    ad = b.density_adapter()
    old_means = b.gaussians.means.detach().clone()
    old_scales = b.gaussians.scales.detach().clone()
    old_m = opt.state[b.gaussians.params["means"]]["exp_avg"].clone()
    high = torch.zeros(40, dtype=torch.bool)
    high[5:15] = True  # 5 large (split) and 5 small (clone)
    ev = dens.refine(ad, _state_for(b, high), Density(prune_opacity=0.0, prune_scale=100.0), 10.0, [opt], torch.Generator().manual_seed(0))
    assert ev["cloned"] == 5 and ev["split"] == 5 and ev["pruned"] == 0
    assert len(b) == 40 + 5 + 5  # clones add one each; a split replaces one by two
    p = b.gaussians.params["means"]
    st = opt.state[p]
    assert st["exp_avg"].shape == p.shape and st["exp_avg_sq"].shape == p.shape
    assert any(q is p for g in opt.param_groups for q in g["params"])  # the optimizer holds the new Parameter
    # Survivors keep their rows and moments in order; the 5 clones (appended next) copy
    # their parents with zero moments; the 10 split children come last.
    keep = torch.cat([torch.arange(5), torch.arange(10, 40)])
    torch.testing.assert_close(st["exp_avg"][:35], old_m[keep])
    torch.testing.assert_close(p[:35], old_means[keep])
    torch.testing.assert_close(p[35:40], old_means[10:15])
    assert st["exp_avg"][35:].abs().sum() == 0
    # Children of splits are smaller than their parents by 1.6.
    torch.testing.assert_close(b.gaussians.scales[-10:], old_scales[5:10].repeat(2, 1) / 1.6)
    # A step after the edit works (autograd sees the new shapes).
    loss = sum(q.square().sum() for q in b.gaussians.params.values())
    loss.backward()
    opt.step()


def test_prune_removes_transparent_and_huge_gaussians():
    b = _branch()
    with torch.no_grad():
        b.gaussians.params["opacities"][:3] = -10.0
        b.gaussians.params["scales"][3:5] = torch.log(torch.tensor(5.0))
    opt = _optimizer(b)
    ev = dens.refine(b.density_adapter(), dens.new_state(40), Density(), 1.0, [opt], torch.Generator())
    assert ev["pruned"] == 5 and len(b) == 35
    assert opt.state[b.gaussians.params["opacities"]]["exp_avg"].shape == (35,)


def test_cap_limits_growth_to_the_highest_gradients():
    b = _branch()
    opt = _optimizer(b)
    means = b.gaussians.means.detach().clone()
    st = dens.new_state(40)
    st["grad2d"] = torch.linspace(0.0, 1.0, 40)
    st["count"][:] = 1
    ev = dens.refine(b.density_adapter(), st, Density(grad_threshold=0.1, max_gaussians=45, prune_opacity=0.0, prune_scale=100.0),
                     10.0, [opt], torch.Generator())
    assert len(b) == 45 and ev["cloned"] == 5
    torch.testing.assert_close(b.gaussians.means[40:], means[35:40])


def test_accumulate_converts_pixel_gradients_to_ndc_for_visible_gaussians():
    st = dens.new_state(3)
    grad = torch.tensor([[1.0, 0.0], [0.0, 1.0], [5.0, 5.0]])
    radii = torch.tensor([2, 3, 0])
    dens.accumulate(st, grad, radii, width=100, height=50)
    torch.testing.assert_close(st["grad2d"], torch.tensor([50.0, 25.0, 0.0]))
    assert st["count"].tolist() == [1.0, 1.0, 0.0]
