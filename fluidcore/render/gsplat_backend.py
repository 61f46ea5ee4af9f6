"""The CUDA backend: gsplat's fused rasterizer (gsplat 1.5.3, classic 3DGS mode).

gsplat JIT-builds its CUDA extension on first use and has no CPU path, so this backend refuses
anything but CUDA tensors with a clear error instead of failing deep inside gsplat. The torch
backend uses gsplat's rules (near plane, eps2d, 1/255 alpha cut, 0.999 alpha cap, 1e-4
transmittance stop), so the two draw the same picture; tests/fluidcore/render/test_gpu.py checks that.
"""

from __future__ import annotations

import torch

from fluidcore.render.gaussians import Gaussians, RenderError
from fluidcore.render.projection import EPS2D, NEAR_PLANE


def rasterize_gsplat(
    g: Gaussians, intrinsics: torch.Tensor, viewmat: torch.Tensor, width: int, height: int, with_depth: bool
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """(H, W, C) colour composited over black, (H, W) alpha and (H, W) alpha-normalised depth
    (None without `with_depth`)."""
    if g.device.type != "cuda":
        raise RenderError(f"backend 'gsplat' needs CUDA tensors, the Gaussians are on {g.device}")
    if g.dtype != torch.float32:
        raise RenderError(f"backend 'gsplat' needs float32 Gaussians, got {g.dtype}")
    from gsplat import rasterization

    colors, alphas, _ = rasterization(
        means=g.means,
        quats=g.unit_quats(),
        scales=g.scales(),
        opacities=g.opacities(),
        colors=g.colors,
        viewmats=viewmat[None],
        Ks=intrinsics[None],
        width=width,
        height=height,
        near_plane=NEAR_PLANE,
        eps2d=EPS2D,
        render_mode="RGB+ED" if with_depth else "RGB",  # "ED": expected depth sum(w z) / sum(w)
        rasterize_mode="classic",
    )
    channels = g.channels
    depth = colors[0, ..., channels] if with_depth else None
    return colors[0, ..., :channels], alphas[0, ..., 0], depth
