"""Edge cases render without NaN, bad input is refused with a message naming the tensor."""

from __future__ import annotations

import pytest
import torch

from cogs.render import rasterize, warmup
from cogs.render.scenes import random_scene, splat_scene

BACKENDS = ["torch", "cpu"]
K = torch.tensor([[40.0, 0.0, 20.0], [0.0, 40.0, 15.0], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="module", autouse=True)
def _compiled():
    warmup()


def _render_and_backward(means, quats, scales, opacities, colors, backend, **kw):
    params = [t.clone().requires_grad_(True) for t in (means, quats, scales, opacities, colors)]
    bg = kw.pop("background", None)
    if bg is not None:
        bg = bg.clone().requires_grad_(True)
    out = rasterize(*params, torch.eye(4), K, 40, 30, backend=backend, background=bg, **kw)
    loss = out.colors.sum() + out.alpha.sum() + 0.1 * out.depth.sum()
    loss.backward()
    return out, [p.grad for p in params], None if bg is None else bg.grad


def _assert_finite(out, grads):
    for name in ("colors", "alpha", "depth"):
        assert torch.isfinite(getattr(out, name)).all(), name
    for g in grads:
        assert g is not None and torch.isfinite(g).all()


def _gaussians(n, z=3.0, scale=0.1, seed=0):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([2.0, 1.5, 0.5])
    means[:, 2] += z
    return (means, torch.randn(n, 4, generator=g), torch.full((n, 3), scale),
            torch.rand(n, generator=g) * 0.9, torch.rand(n, 3, generator=g))


@pytest.mark.parametrize("backend", BACKENDS)
def test_zero_gaussians_render_the_background(backend):
    empty = (torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, 3))
    bg = torch.tensor([0.1, 0.2, 0.3])
    out, grads, g_bg = _render_and_backward(*empty, backend, background=bg)
    assert out.colors.shape == (30, 40, 3) and out.alpha.shape == (30, 40, 1)
    assert out.depth.shape == (30, 40, 1)
    assert torch.allclose(out.colors, bg.expand(30, 40, 3))
    assert (out.alpha == 0).all() and (out.depth == 0).all()
    assert out.means2d.shape == (0, 2) and out.radii.shape == (0,) and out.visible.shape == (0,)
    assert [tuple(g.shape) for g in grads] == [(0, 3), (0, 4), (0, 3), (0,), (0, 3)]
    assert torch.allclose(g_bg, torch.full((3,), 1200.0))


@pytest.mark.parametrize("backend", BACKENDS)
def test_gaussians_behind_the_camera_are_culled_with_zero_gradients(backend):
    means, quats, scales, opac, cols = _gaussians(30, z=-3.0)
    out, grads, _ = _render_and_backward(means, quats, scales, opac, cols, backend)
    _assert_finite(out, grads)
    assert (out.radii == 0).all() and not out.visible.any()
    assert (out.alpha == 0).all()
    for g in grads:
        assert (g == 0).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_gaussians_straddling_the_near_plane_are_kept_or_culled_by_their_centre(backend):
    means = torch.tensor([[0.0, 0.0, 0.02], [0.1, 0.0, 0.005], [0.0, 0.1, -0.01], [0.2, 0.1, 2.0]])
    quats = torch.tensor([[1.0, 0, 0, 0]] * 4)
    scales = torch.tensor([[0.3, 0.3, 0.3], [1.0, 1.0, 1.0], [1.0, 1.0, 1.0], [0.1, 0.1, 0.1]])
    opac = torch.tensor([0.3, 0.9, 0.9, 0.9])
    cols = torch.rand(4, 3, generator=torch.Generator().manual_seed(0))
    out, grads, _ = _render_and_backward(means, quats, scales, opac, cols, backend)
    _assert_finite(out, grads)
    assert out.visible.tolist() == [True, False, False, True]
    assert out.alpha.min() > 0.25  # the splat just in front of the near plane covers everything
    assert (grads[0][1:3] == 0).all()


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("scale", [1e-8, 1e3, 1e6])
def test_extreme_scales_render_without_nan(backend, scale):
    out, grads, _ = _render_and_backward(*_gaussians(20, scale=scale), backend)
    _assert_finite(out, grads)
    assert out.visible.any()


@pytest.mark.parametrize("backend", BACKENDS)
def test_zero_quaternion_renders_like_the_identity_rotation(backend):
    means, quats, scales, opac, cols = _gaussians(10, seed=3)
    scales = torch.rand(10, 3, generator=torch.Generator().manual_seed(4)) * 0.2 + 0.02
    zero = torch.zeros(10, 4)
    identity = torch.tensor([[1.0, 0, 0, 0]]).expand(10, 4)
    out0, grads, _ = _render_and_backward(means, zero, scales, opac, cols, backend)
    _assert_finite(out0, grads)
    with torch.no_grad():
        out1 = rasterize(means, identity, scales, opac, cols, torch.eye(4), K, 40, 30, backend=backend)
    torch.testing.assert_close(out0.colors, out1.colors)


@pytest.mark.parametrize("backend", BACKENDS)
def test_means2d_grad_is_available_after_backward(backend):
    means, quats, scales, opac, cols = _gaussians(25)
    out, _, _ = _render_and_backward(means, quats, scales, opac, cols, backend)
    assert out.means2d.shape == (25, 2)
    assert out.means2d.grad is not None and out.means2d.grad.shape == (25, 2)
    assert out.means2d.grad[out.visible].abs().sum() > 0
    assert out.radii.dtype == torch.int32 and out.visible.dtype == torch.bool


@pytest.mark.parametrize("backend", BACKENDS)
def test_background_fills_the_remaining_transmittance(backend):
    scene = random_scene(50, 33, 21, seed=5)
    bg = torch.tensor([0.3, 0.6, 0.9])
    with torch.no_grad():
        plain = rasterize(*scene.gaussians(), *scene.camera(), backend=backend)
        with_bg = rasterize(*scene.gaussians(), *scene.camera(), background=bg, backend=backend)
    torch.testing.assert_close(with_bg.colors, plain.colors + (1 - plain.alpha) * bg)


@pytest.mark.parametrize("backend", BACKENDS)
def test_depth_of_a_lone_gaussian_is_its_camera_depth_and_zero_elsewhere(backend):
    means = torch.tensor([[0.0, 0.0, 2.5]])
    with torch.no_grad():
        out = rasterize(means, torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), 0.05),
                        torch.tensor([0.8]), torch.ones(1, 1), torch.eye(4), K, 40, 30,
                        backend=backend)
    covered = out.alpha[..., 0] > 0
    assert 0 < covered.sum() < 40 * 30
    torch.testing.assert_close(out.depth[covered], torch.full_like(out.depth[covered], 2.5))
    assert (out.depth[~covered] == 0).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_any_channel_count_renders(backend):
    scene = random_scene(40, 24, 20, channels=13, seed=2)
    with torch.no_grad():
        out = rasterize(*scene.gaussians(), *scene.camera(), backend=backend)
    assert out.colors.shape == (20, 24, 13)


def test_cpu_backend_accepts_float64_and_returns_float64():
    scene = random_scene(40, 24, 20, seed=2, dtype=torch.float64)
    params = [t.clone().requires_grad_(True) for t in scene.gaussians()]
    out = rasterize(*params, *scene.camera(), backend="cpu")
    out.colors.sum().backward()
    assert out.colors.dtype == torch.float64 and params[0].grad.dtype == torch.float64


@pytest.mark.parametrize("name", ["means", "quats", "scales", "opacities", "colors", "viewmat", "K", "background"])
@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_input_raises_naming_the_tensor(name, bad):
    scene = splat_scene(10, 20, 16)
    args = dict(means=scene.means, quats=scene.quats, scales=scene.scales,
                opacities=scene.opacities, colors=scene.colors, viewmat=scene.viewmat, K=scene.K,
                background=torch.zeros(3))
    t = args[name].clone()
    t.view(-1)[:2] = bad
    args[name] = t
    with pytest.raises(ValueError, match=rf"`{name}` contains 2 non-finite values"):
        rasterize(args["means"], args["quats"], args["scales"], args["opacities"], args["colors"],
                  args["viewmat"], args["K"], 20, 16, background=args["background"], backend="cpu")


@pytest.mark.parametrize(
    "name, shape, expected",
    [("quats", (10, 3), r"\[10, 4\]"), ("scales", (9, 3), r"\[10, 3\]"),
     ("opacities", (10, 1), r"\[10\]"), ("viewmat", (3, 4), r"\[4, 4\]"), ("K", (3,), r"\[3, 3\]"),
     ("colors", (11, 3), r"\[N=10, D>=1\]"), ("means", (10, 2), r"\[N, 3\]")],
)
def test_shape_mismatch_raises_naming_the_tensor_and_the_expected_shape(name, shape, expected):
    scene = splat_scene(10, 20, 16)
    args = dict(means=scene.means, quats=scene.quats, scales=scene.scales,
                opacities=scene.opacities, colors=scene.colors, viewmat=scene.viewmat, K=scene.K)
    args[name] = torch.zeros(shape)
    with pytest.raises(ValueError, match=rf"`{name}` must have shape {expected}"):
        rasterize(*args.values(), 20, 16)


def test_wrong_background_and_sh_shapes_are_refused():
    scene = splat_scene(10, 20, 16)
    with pytest.raises(ValueError, match=r"`background` must have shape \[3\]"):
        rasterize(*scene.gaussians(), *scene.camera(), background=torch.zeros(4))
    with pytest.raises(ValueError, match=r"`colors` must have shape \[N=10, K>=9, 3\]"):
        rasterize(*scene.gaussians()[:4], torch.zeros(10, 4, 3), *scene.camera(), sh_degree=2)


def test_unknown_backend_is_refused():
    scene = splat_scene(5, 20, 16)
    with pytest.raises(ValueError, match="unknown backend"):
        rasterize(*scene.gaussians(), *scene.camera(), backend="vulkan")


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the error raised without CUDA")
def test_gsplat_backend_without_cuda_says_what_is_missing():
    scene = splat_scene(5, 20, 16)
    with pytest.raises(RuntimeError, match="needs CUDA tensors"):
        rasterize(*scene.gaussians(), *scene.camera(), backend="gsplat")


def test_auto_backend_on_cpu_tensors_is_the_cpu_backend():
    scene = splat_scene(200, 40, 30, seed=1)
    with torch.no_grad():
        a = rasterize(*scene.gaussians(), *scene.camera(), backend="auto")
        b = rasterize(*scene.gaussians(), *scene.camera(), backend="cpu")
    assert torch.equal(a.colors, b.colors)


def test_cpu_backend_renders_in_a_forked_child_after_rendering_in_the_parent():
    """DataLoader-style fork: the child must not wait on the parent's pool threads."""
    import multiprocessing as mp

    scene = splat_scene(20000, 64, 48, seed=3)  # large enough to use the thread pool
    with torch.no_grad():
        parent = rasterize(*scene.gaussians(), *scene.camera(), backend="cpu").colors
    ctx = mp.get_context("fork")
    with ctx.Pool(1) as pool:
        child = pool.apply_async(_render_colors_sum, (scene,)).get(timeout=60)
    assert abs(child - float(parent.sum())) < 1e-3


def _render_colors_sum(scene):
    with torch.no_grad():
        return float(rasterize(*scene.gaussians(), *scene.camera(), backend="cpu").colors.sum())
