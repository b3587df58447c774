"""The reference is right: an independent per-pixel brute force, finite differences, gsplat's
own projection and SH code, and the orthonormality of the SH basis."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from cogs.render import rasterize, warmup
from cogs.render.projection import project_gaussians
from cogs.render.scenes import random_scene
from cogs.render.sh import eval_sh, sh_basis


@pytest.fixture(scope="module", autouse=True)
def _compiled():
    warmup()


def brute_force(scene, near=0.01, far=1e10, background=None):
    """Plain float64 numpy restatement of the semantics, one pixel at a time."""
    m = scene.means.double().numpy()
    q = scene.quats.double().numpy()
    s = scene.scales.double().numpy()
    o = scene.opacities.double().numpy()
    col = scene.colors.double().numpy()
    V = scene.viewmat.double().numpy()
    Kd = scene.K.double().numpy()
    W, H = scene.width, scene.height
    fx, fy, cx, cy = Kd[0, 0], Kd[1, 1], Kd[0, 2], Kd[1, 2]
    splats = []
    for i in range(len(m)):
        pc = V[:3, :3] @ m[i] + V[:3, 3]
        z = pc[2]
        if not (near < z < far):
            continue
        n = np.linalg.norm(q[i])
        w, x, y, zq = q[i] / n if n > 1e-12 else np.array([1.0, 0.0, 0.0, 0.0])
        Rq = np.array([
            [1 - 2 * (y * y + zq * zq), 2 * (x * y - w * zq), 2 * (x * zq + w * y)],
            [2 * (x * y + w * zq), 1 - 2 * (x * x + zq * zq), 2 * (y * zq - w * x)],
            [2 * (x * zq - w * y), 2 * (y * zq + w * x), 1 - 2 * (x * x + y * y)],
        ])
        Mq = Rq * s[i][None, :]
        cov_c = V[:3, :3] @ (Mq @ Mq.T) @ V[:3, :3].T
        tanx, tany = 0.5 * W / fx, 0.5 * H / fy
        u = np.clip(pc[0] / z, -(cx / fx + 0.3 * tanx), (W - cx) / fx + 0.3 * tanx)
        v = np.clip(pc[1] / z, -(cy / fy + 0.3 * tany), (H - cy) / fy + 0.3 * tany)
        J = np.array([[fx / z, 0.0, -fx * u / z], [0.0, fy / z, -fy * v / z]])
        cov2 = J @ cov_c @ J.T + 0.3 * np.eye(2)
        conic = np.linalg.inv(cov2)
        r = math.ceil(3.0 * math.sqrt(np.linalg.eigvalsh(cov2).max()))
        mean2 = np.array([fx * pc[0] / z + cx, fy * pc[1] / z + cy])
        if mean2[0] + r <= 0 or mean2[0] - r >= W or mean2[1] + r <= 0 or mean2[1] - r >= H:
            continue
        tiles = (math.floor((mean2[0] - r) / 16), math.ceil((mean2[0] + r) / 16),
                 math.floor((mean2[1] - r) / 16), math.ceil((mean2[1] + r) / 16))
        splats.append((z, i, mean2, conic, tiles))
    splats.sort(key=lambda sp: (sp[0], sp[1]))
    D = col.shape[1]
    bg = np.zeros(D) if background is None else background.double().numpy()
    colors = np.zeros((H, W, D))
    alpha = np.zeros((H, W, 1))
    depth = np.zeros((H, W, 1))
    for py in range(H):
        for px in range(W):
            T, c, dz = 1.0, np.zeros(D), 0.0
            for z, i, mean2, conic, (tx0, tx1, ty0, ty1) in splats:
                if not (tx0 <= px // 16 < tx1 and ty0 <= py // 16 < ty1):
                    continue
                d = mean2 - np.array([px + 0.5, py + 0.5])
                power = -0.5 * d @ conic @ d
                if power > 0:
                    continue
                a = min(0.99, o[i] * math.exp(power))
                if a < 1.0 / 255.0:
                    continue
                if T * (1.0 - a) < 1e-4:
                    break
                c += col[i] * a * T
                dz += z * a * T
                T *= 1.0 - a
            colors[py, px] = c + T * bg
            alpha[py, px] = 1.0 - T
            depth[py, px] = dz / (1.0 - T) if T < 1.0 else 0.0
    return colors, alpha, depth


@pytest.mark.parametrize("backend", ["torch", "cpu"])
@pytest.mark.parametrize("n, width, height, channels", [(12, 21, 19, 3), (40, 35, 18, 2)])
def test_backend_matches_independent_per_pixel_brute_force(backend, n, width, height, channels):
    scene = random_scene(n, width, height, channels=channels, seed=100 + n)
    bg = torch.linspace(0.1, 0.9, channels)
    with torch.no_grad():
        out = rasterize(*scene.gaussians(), *scene.camera(), background=bg, backend=backend)
    colors, alpha, depth = brute_force(scene, background=bg)
    assert alpha.max() > 0.5
    np.testing.assert_allclose(out.colors.numpy(), colors, atol=1e-4, rtol=0)
    np.testing.assert_allclose(out.alpha.numpy(), alpha, atol=1e-4, rtol=0)
    np.testing.assert_allclose(out.depth.numpy(), depth, atol=1e-4 * np.abs(depth).max(), rtol=0)


def test_reference_gradients_match_finite_differences_in_float64():
    scene = random_scene(6, 24, 20, channels=2, seed=7, dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    w_c = torch.randn(20, 24, 2, generator=g, dtype=torch.float64)
    w_a = torch.randn(20, 24, 1, generator=g, dtype=torch.float64)
    w_d = torch.randn(20, 24, 1, generator=g, dtype=torch.float64)
    base = [t.clone() for t in scene.gaussians()]

    def loss(params):
        out = rasterize(*params, *scene.camera(), background=torch.tensor([0.2, 0.7], dtype=torch.float64),
                        backend="torch")
        return (out.colors * w_c).sum() + (out.alpha * w_a).sum() + (out.depth * w_d).sum()

    params = [t.clone().requires_grad_(True) for t in base]
    loss(params).backward()
    h = 1e-6
    for k, name in enumerate(["means", "quats", "scales", "opacities", "colors"]):
        v = torch.randn(base[k].shape, generator=g, dtype=torch.float64)
        if name == "scales":
            v = v * base[k]  # relative steps: scales span orders of magnitude
        plus = [t.clone() for t in base]
        minus = [t.clone() for t in base]
        plus[k] = plus[k] + h * v
        minus[k] = minus[k] - h * v
        with torch.no_grad():
            fd = (loss(plus) - loss(minus)).item() / (2 * h)
        analytic = (params[k].grad * v).sum().item()
        assert abs(analytic) > 1e-6, name
        assert abs(fd - analytic) <= 1e-5 * max(1.0, abs(fd)), f"{name}: fd {fd} vs autograd {analytic}"


def test_projection_matches_gsplat_pure_torch_projection():
    torch_impl = pytest.importorskip("gsplat.cuda._torch_impl", reason="gsplat is not importable")
    scene = random_scene(400, 64, 48, seed=3)
    covars, _ = torch_impl._quat_scale_to_covar_preci(scene.quats, scene.scales, True, False)
    radii_g, means2d_g, depths_g, conics_g, _ = torch_impl._fully_fused_projection(
        scene.means, covars, scene.viewmat[None], scene.K[None], 64, 48, eps2d=0.3,
        near_plane=0.01, far_plane=1e10,
    )
    proj = project_gaussians(scene.means, scene.quats, scene.scales, scene.viewmat, scene.K, 64, 48)
    torch.testing.assert_close(proj.depths, depths_g[0], rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(proj.means2d, means2d_g[0], rtol=1e-5, atol=1e-4)
    torch.testing.assert_close(proj.conics, conics_g[0], rtol=1e-4, atol=1e-7)
    # gsplat bounds each axis by 3.33 sigma, the contract by 3 sqrt(lambda_max): compare the
    # culled set only where the two agree on depth culling.
    assert torch.equal(proj.depths > 0.01, depths_g[0] > 0.01)


def test_projection_matches_gsplat_for_gaussians_far_off_screen():
    torch_impl = pytest.importorskip("gsplat.cuda._torch_impl", reason="gsplat is not importable")
    g = torch.Generator().manual_seed(0)
    means = torch.randn(200, 3, generator=g) * torch.tensor([6.0, 6.0, 1.0]) + torch.tensor([0.0, 0.0, 3.0])
    quats = torch.randn(200, 4, generator=g)
    scales = torch.rand(200, 3, generator=g) * 0.5 + 0.01
    K = torch.tensor([[50.0, 0.0, 30.0], [0.0, 50.0, 20.0], [0.0, 0.0, 1.0]])
    covars, _ = torch_impl._quat_scale_to_covar_preci(quats, scales, True, False)
    _, _, depths_g, conics_g, _ = torch_impl._fully_fused_projection(
        means, covars, torch.eye(4)[None], K[None], 60, 40)
    proj = project_gaussians(means, quats, scales, torch.eye(4), K, 60, 40)
    ok = depths_g[0] > 0.01
    assert ok.sum() > 100
    torch.testing.assert_close(proj.conics[ok], conics_g[0][ok], rtol=1e-4, atol=1e-7)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_matches_gsplat(degree):
    torch_impl = pytest.importorskip("gsplat.cuda._torch_impl", reason="gsplat is not importable")
    g = torch.Generator().manual_seed(degree)
    dirs = torch.randn(300, 3, generator=g)
    coeffs = torch.randn(300, 16, 3, generator=g)
    ours = eval_sh(degree, dirs, coeffs)
    theirs = torch_impl._spherical_harmonics(degree, dirs, coeffs)
    torch.testing.assert_close(ours, theirs, rtol=1e-5, atol=1e-5)


def test_sh_basis_is_orthonormal_on_the_sphere():
    g = torch.Generator().manual_seed(0)
    dirs = torch.nn.functional.normalize(torch.randn(400_000, 3, generator=g, dtype=torch.float64), dim=-1)
    Y = sh_basis(3, dirs)  # [M, 16]
    gram = (Y.T @ Y) * (4 * math.pi / dirs.shape[0])
    assert (gram - torch.eye(16, dtype=torch.float64)).abs().max() < 0.03


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_sh_rendering_uses_view_directions_from_the_camera_centre(backend):
    scene = random_scene(60, 30, 22, seed=9)
    g = torch.Generator().manual_seed(1)
    sh = torch.randn(60, 16, 3, generator=g) * 0.3
    R, t = scene.viewmat[:3, :3], scene.viewmat[:3, 3]
    campos = -(R.T @ t)
    rgb = torch.clamp_min(eval_sh(3, scene.means - campos, sh) + 0.5, 0.0)
    with torch.no_grad():
        a = rasterize(scene.means, scene.quats, scene.scales, scene.opacities, sh,
                      *scene.camera(), sh_degree=3, backend=backend)
        b = rasterize(scene.means, scene.quats, scene.scales, scene.opacities, rgb,
                      *scene.camera(), backend=backend)
    torch.testing.assert_close(a.colors, b.colors, rtol=0, atol=1e-6)


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_sh_degree_zero_equals_the_plain_colour_path(backend):
    scene = random_scene(80, 30, 22, seed=11)
    sh0 = torch.randn(80, 1, 3, generator=torch.Generator().manual_seed(2))
    plain = torch.clamp_min(sh0[:, 0, :] * 0.28209479177387814 + 0.5, 0.0)
    with torch.no_grad():
        a = rasterize(scene.means, scene.quats, scene.scales, scene.opacities, sh0,
                      *scene.camera(), sh_degree=0, backend=backend)
        b = rasterize(scene.means, scene.quats, scene.scales, scene.opacities, plain,
                      *scene.camera(), backend=backend)
    torch.testing.assert_close(a.colors, b.colors, rtol=0, atol=1e-7)
    torch.testing.assert_close(a.depth, b.depth, rtol=0, atol=0)
