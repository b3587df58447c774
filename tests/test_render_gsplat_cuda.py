"""On a CUDA machine with gsplat, the gsplat backend agrees with the reference (and, on
any machine, the wrapper maps gsplat's outputs onto RenderOutput correctly).

The scene keeps opacities <= 0.3 so that every pair with alpha >= 1/255 lies within
sqrt(2 ln(255 * 0.3)) < 3 sigma: inside both the 3-sigma square the contract bins with
and gsplat's per-axis opacity-aware box, and far from gsplat's 0.999 alpha clamp. What
remains are float rounding differences.
"""

from __future__ import annotations

import pytest
import torch

from cogs.render import rasterize
from cogs.render.scenes import random_scene

needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


def _scene(device):
    scene = random_scene(800, 96, 72, channels=4, seed=1)
    opac = scene.opacities * 0.3
    return [t.to(device) for t in (scene.means, scene.quats, scene.scales, opac, scene.colors,
                                   scene.viewmat, scene.K)]


@needs_cuda
def test_gsplat_backend_matches_the_reference_forward_and_backward():
    pytest.importorskip("gsplat", reason="gsplat is not installed")
    device = torch.device("cuda")
    tensors = _scene(device)
    outs, grads = {}, {}
    for backend in ("gsplat", "torch"):
        params = [t.clone().requires_grad_(True) for t in tensors[:5]]
        out = rasterize(*params, *tensors[5:], 96, 72, backend=backend,
                        background=torch.full((4,), 0.25, device=device))
        g = torch.Generator(device="cpu").manual_seed(0)
        loss = sum((o * torch.randn(o.shape, generator=g).to(device)).sum()
                   for o in (out.colors, out.alpha, out.depth))
        loss.backward()
        outs[backend], grads[backend] = out, [p.grad for p in params]
    a, b = outs["gsplat"], outs["torch"]
    assert (a.colors - b.colors).abs().max() < 1e-4
    assert (a.alpha - b.alpha).abs().max() < 1e-4
    assert (a.depth - b.depth).abs().max() < 1e-4 * b.depth.abs().max()
    assert a.means2d.grad is not None
    for ga, gb in zip(grads["gsplat"], grads["torch"]):
        assert ((ga - gb).norm() / gb.norm()) < 1e-3
    assert ((a.means2d.grad - b.means2d.grad).norm() / b.means2d.grad.norm()) < 1e-3


def _compare(device, tensors, width, height, background, sh_degree=None):
    """Forward outputs and leaf gradients (incl. the background's) of gsplat vs torch."""
    outs, grads = {}, {}
    for backend in ("gsplat", "torch"):
        params = [t.clone().requires_grad_(True) for t in (*tensors[:5], background)]
        out = rasterize(*params[:5], *tensors[5:], width, height, backend=backend,
                        background=params[5], sh_degree=sh_degree)
        g = torch.Generator(device="cpu").manual_seed(0)
        loss = sum((o * torch.randn(o.shape, generator=g).to(device)).sum()
                   for o in (out.colors, out.alpha, out.depth))
        loss.backward()
        outs[backend], grads[backend] = out, [p.grad for p in params]
    return outs, grads


@needs_cuda
def test_gsplat_backend_matches_the_reference_with_sh_and_the_compositor_channels():
    """Degree-3 SH colour (gsplat evaluates SH itself) and D = 6, the compositor's RGB +
    three branch one-hot channels, which gsplat pads to its next supported width."""
    pytest.importorskip("gsplat", reason="gsplat is not installed")
    device = torch.device("cuda")
    base = _scene(device)
    g = torch.Generator().manual_seed(3)
    sh = (0.3 * torch.randn(800, 16, 3, generator=g)).to(device)
    six = torch.rand(800, 6, generator=g).to(device)
    for colors, sh_degree, bg in ((sh, 3, torch.full((3,), 0.2)),
                                  (six, None, torch.linspace(0.1, 0.6, 6))):
        tensors = [*base[:4], colors, *base[5:]]
        outs, grads = _compare(device, tensors, 96, 72, bg.to(device), sh_degree)
        a, b = outs["gsplat"], outs["torch"]
        assert a.colors.shape == b.colors.shape
        assert (a.colors - b.colors).abs().max() < 1e-4, sh_degree
        assert (a.alpha - b.alpha).abs().max() < 1e-4
        for name, ga, gb in zip(("means", "quats", "scales", "opacities", "colors", "background"),
                                grads["gsplat"], grads["torch"]):
            assert ga is not None, name
            assert ((ga - gb).norm() / gb.norm()) < 1e-3, (name, sh_degree)


@needs_cuda
def test_auto_backend_on_cuda_tensors_is_gsplat_when_available():
    pytest.importorskip("gsplat", reason="gsplat is not installed")
    tensors = _scene(torch.device("cuda"))
    with torch.no_grad():
        a = rasterize(*tensors, 96, 72, backend="auto")
        b = rasterize(*tensors, 96, 72, backend="gsplat")
    assert torch.equal(a.colors, b.colors)


@needs_cuda
def test_cpu_backend_serves_cuda_tensors_through_the_host():
    tensors = _scene(torch.device("cuda"))
    with torch.no_grad():
        a = rasterize(*tensors, 96, 72, backend="cpu")
        b = rasterize(*[t.cpu() for t in tensors], 96, 72, backend="cpu")
    assert a.colors.device.type == "cuda"
    assert torch.equal(a.colors.cpu(), b.colors)


def test_gsplat_wrapper_maps_outputs_and_exposes_the_means2d_gradient(monkeypatch):
    """Runs the wrapper on CPU against a stand-in for gsplat.rasterization built from the
    reference, with gsplat's return layout ([1, ...] batches, per-axis radii, "RGB+ED")."""
    gsplat = pytest.importorskip("gsplat", reason="gsplat is not importable")
    from cogs.render import gsplat_backend, torch_backend
    from cogs.render.projection import project_gaussians

    def fake_rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width, height,
                           *, near_plane, far_plane, eps2d, sh_degree, packed, tile_size,
                           backgrounds, render_mode, rasterize_mode):
        assert (eps2d, packed, tile_size, render_mode, rasterize_mode, sh_degree) == (
            0.3, False, 16, "RGB+ED", "classic", None)
        proj = project_gaussians(means, quats, scales, viewmats[0], Ks[0], width, height,
                                 near_plane, far_plane)
        means2d_full = proj.means2d[None]
        feats = torch.cat([colors, proj.depths[:, None]], dim=-1)
        feat, alpha = torch_backend.rasterize_pixels(
            means2d_full[0], proj.conics, opacities, feats, proj.radii, proj.depths, width, height)
        bg = torch.cat([backgrounds[0], torch.zeros(1)])
        D = colors.shape[-1]
        render = torch.cat([feat[..., :D] + (1 - alpha) * bg[:D],
                            feat[..., D:] / alpha.clamp_min(1e-10)], dim=-1)
        radii = torch.stack([proj.radii, proj.radii - 1], dim=-1).clamp_min(0)
        return render[None], alpha[None], {"means2d": means2d_full, "radii": radii[None]}

    monkeypatch.setattr(gsplat, "rasterization", fake_rasterization)
    monkeypatch.setattr(gsplat_backend, "_require_cuda", lambda means: None)
    scene = random_scene(120, 40, 30, channels=5, seed=2)
    bg = torch.full((5,), 0.4)
    outs = {}
    for backend in ("gsplat", "torch"):
        params = [t.clone().requires_grad_(True) for t in scene.gaussians()]
        out = rasterize(*params, *scene.camera(), background=bg, backend=backend)
        (out.colors.sum() + out.alpha.sum() + out.depth.sum()).backward()
        outs[backend] = out
    a, b = outs["gsplat"], outs["torch"]
    assert a.colors.shape == (30, 40, 5) and a.alpha.shape == (30, 40, 1) and a.depth.shape == (30, 40, 1)
    torch.testing.assert_close(a.colors, b.colors)
    torch.testing.assert_close(a.depth, b.depth)
    assert torch.equal(a.radii, b.radii) and a.radii.dtype == torch.int32
    assert a.means2d.shape == (120, 2)
    torch.testing.assert_close(a.means2d.grad, b.means2d.grad)
