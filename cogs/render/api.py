"""The one public entry point of the renderer: :func:`rasterize`."""

from __future__ import annotations

import time

import numpy as np
import torch
from torch import Tensor

from cogs.render import cpu_backend, gsplat_backend, torch_backend
from cogs.render.output import RenderOutput
from cogs.render.projection import project_gaussians, tile_ranges
from cogs.render.sh import MAX_SH_DEGREE, num_sh_bases, sh_to_color

BACKENDS = ("auto", "torch", "cpu", "gsplat")


def rasterize(
    means: Tensor,  # [N, 3] world
    quats: Tensor,  # [N, 4] wxyz, any norm (zero -> identity)
    scales: Tensor,  # [N, 3] activated, > 0
    opacities: Tensor,  # [N] activated, in [0, 1]
    colors: Tensor,  # [N, D] (any D >= 1), or [N, K, 3] SH coefficients when sh_degree is set
    viewmat: Tensor,  # [4, 4] world -> camera, OpenCV (x right, y down, z forward)
    K: Tensor,  # [3, 3] intrinsics in pixels
    width: int,
    height: int,
    *,
    near: float = 0.01,
    far: float = 1e10,
    background: Tensor | None = None,  # [D]; None = zeros
    backend: str = "auto",
    sh_degree: int | None = None,
) -> RenderOutput:
    """Render N 3D Gaussians into one camera with classic 3DGS semantics.

    EWA projection (perspective Jacobian with gsplat's 1.3 x tan(fov/2) clamp, +0.3 px^2
    low-pass), 16x16 tiles, 3-sigma square bounds, front-to-back compositing with
    ``alpha = min(0.99, o exp(-0.5 d^T conic d))``, pairs with alpha < 1/255 skipped, a
    pixel stops before its transmittance would drop below 1e-4. With ``sh_degree`` the
    colours are SH coefficients [N, K, 3], K >= (sh_degree+1)^2, evaluated towards each
    Gaussian from the camera centre, then ``clamp_min(. + 0.5, 0)``.

    backend: "torch" (autograd reference), "cpu" (numba kernels), "gsplat" (CUDA), or
    "auto" = gsplat for CUDA tensors when gsplat imports, else cpu. All differentiable with
    respect to means, quats, scales, opacities, colors and background.

    Raises ValueError naming the tensor on a wrong shape, mixed devices/dtypes, or
    non-finite values.
    """
    D = _validate(means, quats, scales, opacities, colors, viewmat, K, width, height,
                  near, far, background, sh_degree)
    backend = _resolve_backend(backend, means)
    if backend == "gsplat":
        return gsplat_backend.rasterize(
            means, quats, scales, opacities, colors, viewmat, K, width, height,
            near=near, far=far, background=background, sh_degree=sh_degree,
        )

    project = project_gaussians if backend == "torch" else cpu_backend.project
    proj = project(means, quats, scales, viewmat, K, width, height, near, far)
    if sh_degree is not None:
        R, t = viewmat[:3, :3], viewmat[:3, 3]
        campos = -(R.T @ t)
        colors = sh_to_color(sh_degree, means - campos, colors)
    if backend == "torch":
        # depth rides along as one more channel, then the per-pixel finish
        features = torch.cat([colors, proj.depths[:, None]], dim=-1)
        feat, alpha = torch_backend.rasterize_pixels(proj.means2d, proj.conics, opacities,
                                                     features, proj.radii, proj.depths,
                                                     width, height)
        out_colors, depth = torch_backend.finish(feat, alpha, D, background)
    else:
        out_colors, alpha, depth = cpu_backend.rasterize_image(
            proj.means2d, proj.conics, opacities, colors, proj.depths, background, proj.radii,
            width, height)
    means2d = proj.means2d
    if means2d.requires_grad:
        means2d.retain_grad()
    return RenderOutput(colors=out_colors, alpha=alpha, depth=depth, means2d=means2d,
                        radii=proj.radii, visible=proj.radii > 0)


def _resolve_backend(backend: str, means: Tensor) -> str:
    if backend not in BACKENDS:
        raise ValueError(f"rasterize: unknown backend {backend!r}; expected one of {BACKENDS}")
    if backend == "auto":
        if means.device.type == "cuda" and gsplat_backend.gsplat_available():
            return "gsplat"
        return "cpu"
    return backend


def _all_finite(t: Tensor) -> bool:
    if t.device.type == "cpu" and t.dtype in (torch.float32, torch.float64):
        # single-threaded numpy: no torch thread-pool wake-up for a tiny check
        return bool(np.isfinite(t.detach().numpy()).all())
    return bool(torch.isfinite(t.detach()).all())


def _validate(means, quats, scales, opacities, colors, viewmat, K, width, height, near, far,
              background, sh_degree) -> int:
    """Boundary checks a caller can trip; returns the output channel count D."""
    named = {"means": means, "quats": quats, "scales": scales, "opacities": opacities,
             "colors": colors, "viewmat": viewmat, "K": K}
    if background is not None:
        named["background"] = background
    for name, t in named.items():
        if not isinstance(t, Tensor):
            raise ValueError(f"rasterize: `{name}` must be a torch.Tensor, got {type(t).__name__}")
        if not t.is_floating_point():
            raise ValueError(f"rasterize: `{name}` must be a floating-point tensor, got {t.dtype}")
    for name, t in named.items():
        if t.device != means.device:
            raise ValueError(f"rasterize: `{name}` is on {t.device} but `means` is on {means.device}")
        if t.dtype != means.dtype:
            raise ValueError(f"rasterize: `{name}` has dtype {t.dtype} but `means` has {means.dtype}")
    if not (isinstance(width, int) and isinstance(height, int)) or width <= 0 or height <= 0:
        raise ValueError(f"rasterize: width and height must be positive ints, got {width!r}, {height!r}")
    if not (0.0 <= near < far):
        raise ValueError(f"rasterize: need 0 <= near < far, got near={near}, far={far}")

    if means.dim() != 2 or means.shape[1] != 3:
        raise ValueError(f"rasterize: `means` must have shape [N, 3], got {list(means.shape)}")
    N = means.shape[0]
    expected = {"quats": (N, 4), "scales": (N, 3), "opacities": (N,), "viewmat": (4, 4), "K": (3, 3)}
    for name, shape in expected.items():
        if tuple(named[name].shape) != shape:
            raise ValueError(
                f"rasterize: `{name}` must have shape {list(shape)}, got {list(named[name].shape)}"
            )
    if sh_degree is None:
        if colors.dim() != 2 or colors.shape[0] != N or colors.shape[1] < 1:
            raise ValueError(
                f"rasterize: `colors` must have shape [N={N}, D>=1], got {list(colors.shape)}"
                " (pass sh_degree for [N, K, 3] SH coefficients)"
            )
        D = colors.shape[1]
    else:
        if not (isinstance(sh_degree, int) and 0 <= sh_degree <= MAX_SH_DEGREE):
            raise ValueError(f"rasterize: sh_degree must be an int in 0..{MAX_SH_DEGREE}, got {sh_degree!r}")
        k = num_sh_bases(sh_degree)
        if colors.dim() != 3 or colors.shape[0] != N or colors.shape[1] < k or colors.shape[2] != 3:
            raise ValueError(
                f"rasterize: `colors` must have shape [N={N}, K>={k}, 3] for sh_degree={sh_degree}, "
                f"got {list(colors.shape)}"
            )
        D = 3
    if background is not None and tuple(background.shape) != (D,):
        raise ValueError(f"rasterize: `background` must have shape [{D}], got {list(background.shape)}")

    for name, t in named.items():
        if not _all_finite(t):
            bad = int((~torch.isfinite(t.detach())).sum().item())
            raise ValueError(f"rasterize: `{name}` contains {bad} non-finite values")
    return D


@torch.no_grad()
def count_pairs(means: Tensor, quats: Tensor, scales: Tensor, viewmat: Tensor, K: Tensor,
                width: int, height: int, *, near: float = 0.01, far: float = 1e10) -> int:
    """Gaussian-pixel pairs the torch reference evaluates for this camera (the benchmark's
    work unit): sum over tiles of Gaussians-in-tile x pixels-in-tile."""
    proj = project_gaussians(means, quats, scales, viewmat, K, width, height, near, far)
    return torch_backend.pair_count(tile_ranges(proj.means2d, proj.radii, width, height),
                                    width, height)


def warmup() -> float:
    """Compile (or load from numba's on-disk cache) every CPU kernel by rendering a tiny
    scene forward and backward. Returns the seconds it took. Call it once at start-up so
    that JIT time never lands inside a training loop."""
    t0 = time.perf_counter()
    cpu = torch.device("cpu")  # the kernels are host code: warm them on host tensors
    g = torch.Generator(device=cpu).manual_seed(0)
    n = 8
    means = (torch.rand(n, 3, generator=g, device=cpu) - 0.5) * 0.5 + torch.tensor([0.0, 0.0, 2.0], device=cpu)
    means.requires_grad_(True)
    quats = torch.randn(n, 4, generator=g, device=cpu)
    scales = torch.full((n, 3), 0.05, device=cpu)
    opac = torch.full((n,), 0.7, device=cpu)
    colors = torch.rand(n, 3, generator=g, device=cpu)
    K = torch.tensor([[20.0, 0.0, 10.0], [0.0, 20.0, 10.0], [0.0, 0.0, 1.0]], device=cpu)
    out = rasterize(means, quats, scales, opac, colors, torch.eye(4, device=cpu), K, 20, 20, backend="cpu")
    (out.colors.sum() + out.alpha.sum() + out.depth.sum()).backward()
    return time.perf_counter() - t0
