"""CUDA backend: a thin wrapper of ``gsplat.rasterization`` (optional ``[cuda]`` extra).

gsplat is imported lazily, only when this backend is used. Known differences from the
reference (all below the parity tolerance for ordinary scenes, see docs/rendering.md):
gsplat clamps alpha at 0.999 instead of 0.99, stops a pixel when T <= 1e-4 rather than
< 1e-4, and bins Gaussians with a per-axis, opacity-aware box instead of the 3-sigma square.
"""

from __future__ import annotations

import torch

from cogs.render.output import RenderOutput


def gsplat_available() -> bool:
    try:
        import gsplat  # noqa: F401
    except Exception:
        return False
    return True


def _import_gsplat():
    try:
        import gsplat
    except Exception as exc:  # ImportError, or a broken CUDA extension
        raise RuntimeError(
            "rasterize(backend='gsplat') needs the optional gsplat package: install a CUDA "
            "build of torch, then `pip install -e \".[cuda]\"` "
            f"(import failed: {exc!r})"
        ) from exc
    return gsplat


def _require_cuda(means) -> None:
    if means.device.type != "cuda":
        raise RuntimeError(
            "rasterize(backend='gsplat') needs CUDA tensors; got tensors on "
            f"{means.device}. Use backend='cpu' (or 'auto') on this machine."
        )


def rasterize(means, quats, scales, opacities, colors, viewmat, K, width, height, *,
              near, far, background, sh_degree):
    _require_cuda(means)
    gsplat = _import_gsplat()
    D = 3 if sh_degree is not None else colors.shape[-1]
    # gsplat pads unsupported channel counts internally; the depth channel is appended by
    # render_mode "RGB+ED" (with a zero background).
    render, alpha, meta = gsplat.rasterization(
        means, quats, scales, opacities, colors, viewmat[None], K[None], width, height,
        near_plane=near, far_plane=far, eps2d=0.3, sh_degree=sh_degree, packed=False,
        tile_size=16, backgrounds=None if background is None else background[None],
        render_mode="RGB+ED", rasterize_mode="classic",
    )
    means2d_full = meta["means2d"]  # [1, N, 2], the tensor gsplat's kernels differentiate
    means2d = means2d_full.detach()[0].clone()
    if means2d_full.requires_grad:
        # The [1, N, 2] tensor is what enters the graph; expose its gradient on the [N, 2]
        # tensor callers read (gsplat's own trainer calls retain_grad on the [1, N, 2] one).
        means2d.requires_grad_(True)

        def _copy_grad(grad):
            g = grad[0].detach()
            means2d.grad = g.clone() if means2d.grad is None else means2d.grad + g

        means2d_full.register_hook(_copy_grad)
    radii = meta["radii"][0]
    if radii.dim() == 2:  # gsplat >= 1.5 returns per-axis radii
        radii = radii.amax(dim=-1)
    radii = radii.to(dtype=torch.int32)
    return RenderOutput(
        colors=render[0, ..., :D],
        alpha=alpha[0],
        depth=render[0, ..., D:D + 1],
        means2d=means2d,
        radii=radii,
        visible=radii > 0,
    )
