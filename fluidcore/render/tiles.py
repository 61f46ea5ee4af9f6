"""Tile binning: which Gaussians touch which 16x16 pixel tile, front to back (no gradients).

A compositor that visits every Gaussian for every pixel costs N x H x W; binning cuts that to the
Gaussians whose screen box overlaps a pixel's tile. The list is built with vectorised torch ops
on whatever device the inputs live: Gaussians are sorted by depth once, expanded into one
(tile, Gaussian) pair per overlapped tile, and stably sorted by tile, which keeps the depth order
inside each tile.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from fluidcore.render.gaussians import RenderError

TILE_SIZE = 16  # the fused kernel (fluidcore/kernels/splat.cpp) is compiled for this size


@dataclass
class TileBins:
    """Per-tile Gaussian lists in CSR form: tile t draws ids[offsets[t]:offsets[t + 1]], nearest first."""

    width: int
    height: int
    tile_size: int
    tiles_x: int
    tiles_y: int
    offsets: torch.Tensor  # (tiles_y * tiles_x + 1,) int32
    ids: torch.Tensor  # (pairs,) int32 Gaussian indices

    @property
    def n_tiles(self) -> int:
        return self.tiles_x * self.tiles_y

    def counts(self) -> torch.Tensor:
        """(n_tiles,) number of Gaussians in each tile."""
        return (self.offsets[1:] - self.offsets[:-1]).long()


@torch.no_grad()
def bin_gaussians(
    bboxes: torch.Tensor,
    depths: torch.Tensor,
    visible: torch.Tensor,
    width: int,
    height: int,
    tile_size: int = TILE_SIZE,
) -> TileBins:
    """Bin visible Gaussians by the tiles their (N, 4) int pixel boxes x0, x1, y0, y1 overlap."""
    device = bboxes.device
    tiles_x, tiles_y = -(-width // tile_size), -(-height // tile_size)
    candidates = torch.nonzero(visible).squeeze(1)
    order = candidates[torch.argsort(depths.detach()[candidates], stable=True)]
    box = bboxes[order].long()
    tx0, tx1 = box[:, 0] // tile_size, (box[:, 1] - 1) // tile_size + 1
    ty0, ty1 = box[:, 2] // tile_size, (box[:, 3] - 1) // tile_size + 1
    span_x = tx1 - tx0
    per_gaussian = span_x * (ty1 - ty0)

    gaussian = torch.repeat_interleave(order, per_gaussian)
    first = torch.cumsum(per_gaussian, 0) - per_gaussian
    local = torch.arange(gaussian.shape[0], device=device) - torch.repeat_interleave(first, per_gaussian)
    span_x = torch.repeat_interleave(span_x, per_gaussian)
    tile_x = torch.repeat_interleave(tx0, per_gaussian) + local % span_x
    tile_y = torch.repeat_interleave(ty0, per_gaussian) + local // span_x
    tile = tile_y * tiles_x + tile_x

    if tile.shape[0] > torch.iinfo(torch.int32).max:
        raise RenderError(f"{tile.shape[0]} (tile, Gaussian) pairs overflow int32; render at a lower resolution")
    tile, by_tile = torch.sort(tile, stable=True)
    counts = torch.bincount(tile, minlength=tiles_x * tiles_y)
    offsets = torch.zeros(tiles_x * tiles_y + 1, dtype=torch.int64, device=device)
    offsets[1:] = torch.cumsum(counts, 0)
    return TileBins(
        width=width,
        height=height,
        tile_size=tile_size,
        tiles_x=tiles_x,
        tiles_y=tiles_y,
        offsets=offsets.to(torch.int32),
        ids=gaussian[by_tile].to(torch.int32),
    )
