"""Differentiable Gaussian splatting: Gaussians + camera -> image, alpha and (on request) depth.

The pipeline is split the way gsplat splits it, so each stage can be read and tested alone:
`projection` (3D Gaussians -> screen-space conics, differentiable torch), `tiles` (which
Gaussians touch which 16x16 tile, front to back), `rasterize` (alpha compositing: a torch
reference and a fused C++/OpenMP kernel), and `gsplat_backend` (gsplat's CUDA rasterizer).

Backends:
* "torch": projection and binning in torch, compositing in the fused kernel for float32 CPU
  tensors, in the torch reference otherwise (float64, CUDA, or a machine where the kernel
  could not be compiled, which `fluidcore.kernels.load` warns about);
* "torch-reference": the torch reference compositor always (slow; for checking);
* "gsplat": gsplat's CUDA rasterizer (CUDA tensors only);
* "auto": "gsplat" for CUDA tensors, "torch" otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from fluidcore.render.gaussians import Gaussians, RenderError
from fluidcore.render.gsplat_backend import rasterize_gsplat
from fluidcore.render.projection import covariance_3d, project
from fluidcore.render.rasterize import composite, fused_available
from fluidcore.render.tiles import bin_gaussians

__all__ = ["BACKENDS", "Gaussians", "RenderError", "RenderResult", "render"]

BACKENDS = ("auto", "torch", "torch-reference", "gsplat")
MIN_ALPHA_FOR_DEPTH = 1e-10  # depth is sum(w z) / alpha; 0 where nothing was drawn (as gsplat)


@dataclass
class RenderResult:
    image: torch.Tensor  # (H, W, C) composited over the background
    alpha: torch.Tensor  # (H, W) coverage, 1 - final transmittance
    depth: torch.Tensor | None  # (H, W) alpha-weighted camera-space z, 0 where alpha is 0; None unless asked


def render(
    g: Gaussians, camera: Any, background: float | torch.Tensor = 0.0, backend: str = "auto", depth: bool = True
) -> RenderResult:
    """Render Gaussians seen by a `fluidcore.cameras.Camera` (anything with intrinsics(),
    viewmat(), width and height).

    `background` is a float, a (C,) colour or an (H, W, C) image (a tensor may require grad).
    `depth=False` skips the depth map (RenderResult.depth is None): depth is one more composited
    channel, which a grey image loss would pay for on every iteration without using it.
    Raises RenderError (a ValueError) naming the bad field; never returns NaN.
    """
    g.validate()
    backend = _resolve_backend(backend, g.device)
    width, height = int(camera.width), int(camera.height)
    intrinsics = camera.intrinsics(g.device).to(g.dtype)
    viewmat = camera.viewmat(g.device).to(g.dtype)
    bg = _background(background, g.channels, height, width, g.device, g.dtype)

    if backend == "gsplat":
        color, alpha, depth_map = rasterize_gsplat(g, intrinsics, viewmat, width, height, depth)
    else:
        color, alpha, depth_map = _rasterize_torch(g, intrinsics, viewmat, width, height, backend == "torch", depth)
    image = color + (1.0 - alpha)[..., None] * bg
    _check_finite(image=image, alpha=alpha, depth=depth_map)
    return RenderResult(image=image, alpha=alpha, depth=depth_map)


def _rasterize_torch(
    g: Gaussians,
    intrinsics: torch.Tensor,
    viewmat: torch.Tensor,
    width: int,
    height: int,
    allow_fused: bool,
    with_depth: bool,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """(H, W, C) colour over black, (H, W) alpha, (H, W) depth or None through the torch pipeline.

    Depth rides along as one more composited feature, so the compositor returns sum(w z).
    """
    covariances = covariance_3d(g.scales(), g.unit_quats())
    projected = project(g.means, covariances, g.opacities(), viewmat, intrinsics, width, height)
    bins = bin_gaussians(projected.bboxes, projected.depths, projected.visible, width, height)
    features = torch.cat([g.colors, projected.depths[:, None]], dim=1) if with_depth else g.colors
    composited, transmittance = composite(projected, features, bins, allow_fused and fused_available(features))
    alpha = 1.0 - transmittance
    depth = composited[..., g.channels] / alpha.clamp(min=MIN_ALPHA_FOR_DEPTH) if with_depth else None
    return composited[..., : g.channels], alpha, depth


def _resolve_backend(backend: str, device: torch.device) -> str:
    if backend not in BACKENDS:
        raise RenderError(f"backend must be one of {', '.join(BACKENDS)}; got {backend!r}")
    if backend == "auto":
        return "gsplat" if device.type == "cuda" else "torch"
    return backend


def _background(
    background: float | torch.Tensor, channels: int, height: int, width: int, device: torch.device, dtype: torch.dtype
) -> torch.Tensor:
    """The background as a tensor broadcastable against (H, W, C)."""
    if isinstance(background, (int, float)):
        bg = torch.full((channels,), float(background), device=device, dtype=dtype)
    elif isinstance(background, torch.Tensor):
        if tuple(background.shape) not in ((channels,), (height, width, channels)):
            raise RenderError(
                f"background must be a float, a ({channels},) colour or a ({height}, {width}, {channels}) "
                f"image, got shape {tuple(background.shape)}"
            )
        bg = background.to(device=device, dtype=dtype)
    else:
        raise RenderError(f"background must be a float or a tensor, got {type(background).__name__}")
    if not bool(torch.isfinite(bg).all()):
        raise RenderError("background is not finite (NaN or inf)")
    return bg


def _check_finite(**outputs: torch.Tensor | None) -> None:
    for name, value in outputs.items():
        if value is not None and not bool(torch.isfinite(value).all()):
            raise RenderError(f"render produced a non-finite {name}; the Gaussians are numerically degenerate")
