"""Front-to-back alpha compositing of tile-binned screen-space Gaussians.

Two implementations of one function, `features, transmittance = composite(...)`:

* `composite_reference`: plain torch, differentiable by autograd, any device and dtype. It works
  on batches of tiles, each padded to its longest Gaussian list, so the largest tensor is
  (tiles in batch, 256 pixels, list length) and never N x H x W. Each batch runs under
  activation checkpointing, so the backward pass also holds one batch at a time.
* `composite_fused`: the C++/OpenMP kernel `fluidcore/kernels/splat.cpp` wrapped in an
  autograd Function (float32 on CPU). Same rules; about 60x faster on the benchmark plume.

For every pixel, with the Gaussians of its tile in front-to-back order and
alpha_i = min(0.999, opacity_i exp(-sigma_i)) (skipped when below 1/255):
    features = sum_i f_i alpha_i T_i,   T_i = prod_{j<i} (1 - alpha_j),
    transmittance = T after the last composited Gaussian,
stopping before the Gaussian that would take T to 1e-4 or below (gsplat's rules).
"""

from __future__ import annotations

import ctypes
from collections.abc import Iterator
from functools import lru_cache

import torch
from torch.utils.checkpoint import checkpoint

from fluidcore import kernels
from fluidcore.render.gaussians import RenderError
from fluidcore.render.projection import ALPHA_MIN, Projected
from fluidcore.render.tiles import TileBins

ALPHA_MAX = 0.999  # keeps 1 - alpha away from 0, so transmittance can be divided back out
TRANSMITTANCE_MIN = 1e-4  # a pixel this opaque ignores everything behind it
REFERENCE_BATCH_ELEMENTS = 1 << 20  # (tiles x pixels x list length) per reference batch
MAX_FEATURES = 4  # the fused kernel is compiled for 1..4 features (colour channels + depth)

_INT, _PTR = ctypes.c_int, ctypes.c_void_p


def composite(
    projected: Projected, features: torch.Tensor, bins: TileBins, fused: bool
) -> tuple[torch.Tensor, torch.Tensor]:
    """(H, W, F) composited features and (H, W) transmittance; `fused` picks the C++ kernel."""
    if fused:
        return composite_fused(projected, features, bins)
    return composite_reference(projected, features, bins)


def fused_available(features: torch.Tensor) -> bool:
    """Whether the fused kernel can take these inputs (float32 CPU, 1..4 features, library built)."""
    return (
        features.device.type == "cpu"
        and features.dtype == torch.float32
        and features.shape[1] <= MAX_FEATURES
        and kernels.load("splat") is not None
    )


# --- torch reference --------------------------------------------------------------------------


def composite_reference(
    projected: Projected, features: torch.Tensor, bins: TileBins, batch_elements: int = REFERENCE_BATCH_ELEMENTS
) -> tuple[torch.Tensor, torch.Tensor]:
    """Tile-batched torch compositor (see the module docstring); differentiable by autograd."""
    pixels = bins.tile_size * bins.tile_size
    counts = bins.counts()
    tile_features, tile_transmittance = [], []
    for first, last, longest in _tile_batches(counts.tolist(), batch_elements // pixels):
        tiles = torch.arange(first, last, device=features.device)
        if longest == 0:  # no Gaussian here; `attached` keeps the result in the autograd graph
            attached = 0.0 * features.sum()
            tile_features.append(attached + features.new_zeros(last - first, pixels, features.shape[1]))
            tile_transmittance.append(attached + features.new_ones(last - first, pixels))
            continue
        f, t = checkpoint(
            _composite_tiles,
            tiles,
            longest,
            bins,
            projected.means2d,
            projected.conics,
            projected.opacities,
            features,
            use_reentrant=False,
        )
        tile_features.append(f)
        tile_transmittance.append(t)
    order = _tile_major_pixel_order(bins, features.device)
    image = torch.cat(tile_features).reshape(-1, features.shape[1])[order]
    transmittance = torch.cat(tile_transmittance).reshape(-1)[order]
    return image.reshape(bins.height, bins.width, -1), transmittance.reshape(bins.height, bins.width)


def _tile_batches(counts: list[int], max_padded: int) -> Iterator[tuple[int, int, int]]:
    """Runs of consecutive tiles [first, last) whose padded size (tiles x longest list) fits."""
    first, longest = 0, 0
    for tile, count in enumerate(counts):
        grown = max(longest, count)
        if tile > first and (tile + 1 - first) * max(grown, 1) > max_padded:
            yield first, tile, longest
            first, grown = tile, count
        longest = grown
    if counts:
        yield first, len(counts), longest


def _composite_tiles(
    tiles: torch.Tensor,
    longest: int,
    bins: TileBins,
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    features: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite a batch of tiles: returns (tiles, pixels, F) features and (tiles, pixels) T."""
    size = bins.tile_size
    slot = torch.arange(longest, device=tiles.device)
    begin = bins.offsets[tiles].long()
    in_list = slot[None, :] < bins.counts()[tiles][:, None]  # (B, K)
    gaussian = bins.ids.long()[torch.where(in_list, begin[:, None] + slot, 0)]  # (B, K)

    local = torch.arange(size * size, device=tiles.device)
    px = ((tiles % bins.tiles_x) * size)[:, None] + local % size + 0.5  # (B, P) pixel centres
    py = ((tiles // bins.tiles_x) * size)[:, None] + local // size + 0.5
    dx = means2d[gaussian, 0][:, None, :] - px[:, :, None].to(means2d.dtype)  # (B, P, K)
    dy = means2d[gaussian, 1][:, None, :] - py[:, :, None].to(means2d.dtype)
    a, b, c = (conics[gaussian, i][:, None, :] for i in range(3))
    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    alpha = torch.clamp(opacities[gaussian][:, None, :] * torch.exp(-sigma), max=ALPHA_MAX)
    counted = in_list[:, None, :] & (sigma >= 0) & (alpha >= ALPHA_MIN)
    alpha = torch.where(counted, alpha, torch.zeros_like(alpha))
    with torch.no_grad():  # a prefix of each pixel's list: everything before T drops to 1e-4
        before_stop = torch.cumprod(1 - alpha, dim=-1) > TRANSMITTANCE_MIN
    alpha = torch.where(before_stop, alpha, torch.zeros_like(alpha))
    transmittance = torch.cumprod(1 - alpha, dim=-1)
    in_front = torch.cat([torch.ones_like(transmittance[..., :1]), transmittance[..., :-1]], dim=-1)
    weights = alpha * in_front
    composited = torch.einsum("bpk,bkf->bpf", weights, features[gaussian])
    return composited, transmittance[..., -1]


def _tile_major_pixel_order(bins: TileBins, device: torch.device) -> torch.Tensor:
    """For each image pixel (row-major), its position in the tile-major (tile, local pixel) layout."""
    y = torch.arange(bins.height, device=device)[:, None]
    x = torch.arange(bins.width, device=device)[None, :]
    size = bins.tile_size
    tile = (y // size) * bins.tiles_x + x // size
    return (tile * size * size + (y % size) * size + x % size).reshape(-1)


# --- fused C++ kernel -------------------------------------------------------------------------


def composite_fused(
    projected: Projected, features: torch.Tensor, bins: TileBins
) -> tuple[torch.Tensor, torch.Tensor]:
    """The C++/OpenMP compositor (float32, CPU), using torch's thread count."""
    if not fused_available(features):
        raise RenderError(
            "the fused compositor needs float32 CPU tensors with at most "
            f"{MAX_FEATURES} features and a built 'splat' kernel (got {features.dtype} on "
            f"{features.device}, {features.shape[1]} features)"
        )
    return _FusedComposite.apply(
        projected.means2d, projected.conics, projected.opacities, features, projected.bboxes, bins
    )


class _FusedComposite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, bboxes, bins):  # type: ignore[override]
        scene = _SceneBuffers(means2d, conics, opacities, features, bboxes, bins)
        height, width, n_features = bins.height, bins.width, features.shape[1]
        out_features = torch.empty(height, width, n_features, dtype=torch.float32)
        transmittance = torch.empty(height, width, dtype=torch.float32)
        stop = torch.empty(height, width, dtype=torch.int32)
        status = _library().splat_forward(
            *scene.arguments(),
            kernels.pointer(out_features),
            kernels.pointer(transmittance),
            kernels.pointer(stop),
            torch.get_num_threads(),
        )
        _check_status(status, "forward")
        ctx.scene = scene
        ctx.save_for_backward(transmittance, stop)
        return out_features, transmittance

    @staticmethod
    def backward(ctx, grad_features, grad_transmittance):  # type: ignore[override]
        scene: _SceneBuffers = ctx.scene
        transmittance, stop = ctx.saved_tensors
        n, n_features = scene.features.shape
        threads = torch.get_num_threads()
        buffers = torch.zeros(threads, n, 6 + n_features, dtype=torch.float32)
        # Bound to names: a pointer to a temporary tensor would dangle once Python frees it.
        grad_features = _dense(grad_features, transmittance.shape + (n_features,))
        grad_transmittance = _dense(grad_transmittance, transmittance.shape)
        status = _library().splat_backward(
            *scene.arguments(),
            n,
            kernels.pointer(transmittance),
            kernels.pointer(stop),
            kernels.pointer(grad_features),
            kernels.pointer(grad_transmittance),
            kernels.pointer(buffers),
            threads,
        )
        _check_status(status, "backward")
        grads = buffers.sum(dim=0)
        return grads[:, 0:2], grads[:, 2:5], grads[:, 5], grads[:, 6:], None, None


class _SceneBuffers:
    """Contiguous float32/int32 copies of the kernel inputs, kept alive for the backward pass."""

    def __init__(self, means2d, conics, opacities, features, bboxes, bins: TileBins) -> None:
        self.means2d = means2d.detach().contiguous()
        self.conics = conics.detach().contiguous()
        self.opacities = opacities.detach().contiguous()
        self.features = features.detach().contiguous()
        self.bboxes = bboxes.to(torch.int32).contiguous()
        self.offsets = bins.offsets.contiguous()
        self.ids = bins.ids.contiguous()
        self.bins = bins

    def arguments(self) -> tuple:
        b = self.bins
        return (
            b.width,
            b.height,
            b.tile_size,
            b.tiles_x,
            b.tiles_y,
            kernels.pointer(self.offsets),
            kernels.pointer(self.ids),
            kernels.pointer(self.means2d),
            kernels.pointer(self.conics),
            kernels.pointer(self.opacities),
            kernels.pointer(self.features),
            self.features.shape[1],
            kernels.pointer(self.bboxes),
        )


def _dense(grad: torch.Tensor | None, shape: tuple[int, ...]) -> torch.Tensor:
    """Autograd passes None for an output that did not reach the loss."""
    if grad is None:
        return torch.zeros(shape, dtype=torch.float32)
    return grad.to(torch.float32).contiguous()


@lru_cache(maxsize=1)
def _library() -> ctypes.CDLL:
    lib = kernels.load("splat")
    if lib is None:
        raise RenderError("the fused 'splat' kernel could not be built; see the warning above")
    scene = [_INT] * 5 + [_PTR] * 6 + [_INT, _PTR]
    lib.splat_forward.argtypes = scene + [_PTR, _PTR, _PTR, _INT]
    lib.splat_backward.argtypes = scene + [_INT, _PTR, _PTR, _PTR, _PTR, _PTR, _INT]
    lib.splat_forward.restype = lib.splat_backward.restype = _INT
    return lib


def _check_status(status: int, stage: str) -> None:
    if status != 0:
        raise RenderError(f"splat kernel {stage} rejected its inputs (status {status})")
