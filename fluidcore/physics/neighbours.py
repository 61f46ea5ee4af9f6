"""Fixed-radius neighbour search on a uniform grid built by sorting cell keys.

Cells have the size of the kernel radius h, so every neighbour of a particle lies in the
3 x 3 x 3 block of cells around its own. Cells are identified by a 63-bit key (21 bits per
axis, counted from the particles' lower corner) and only occupied cells exist: the table is
the sorted list of distinct keys with, for each, the range of the particles in it. A
particle farther than 2^21 cells from the others is clamped into the border cell, which only
adds candidates; the exact distance test keeps the result correct. Never O(N^2).

Two builders give the same CSR list (row i: the neighbours j != i with |x_i - x_j| < h):
the torch one (any device) and the fused C++/OpenMP one (CPU); both share the cell table.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import product

import torch
from torch import Tensor

AXIS_BITS = 21
AXIS_CELLS = 1 << AXIS_BITS
OFFSETS = tuple(product((-1, 0, 1), repeat=3))


@dataclass(frozen=True)
class CellTable:
    """Particles sorted by cell: cell m holds order[start[m]:start[m+1]] and has key keys[m]."""

    origin: Tensor  # (3,) lower corner of the grid
    h: float
    keys: Tensor  # (M,) int64, ascending
    start: Tensor  # (M + 1,) int64
    order: Tensor  # (N,) int64, particle indices sorted by cell


@dataclass(frozen=True)
class NeighbourList:
    """Neighbours of n particles in CSR form: row i is indices[offsets[i]:offsets[i+1]]."""

    offsets: Tensor  # (n + 1,) int64
    indices: Tensor  # (P,) int32 or int64

    @property
    def n(self) -> int:
        return self.offsets.shape[0] - 1

    @property
    def n_pairs(self) -> int:
        return self.indices.shape[0]

    def pairs(self) -> tuple[Tensor, Tensor]:
        """Pair index tensors (i, j), int64, grouped by i."""
        counts = self.offsets[1:] - self.offsets[:-1]
        i = torch.repeat_interleave(torch.arange(self.n, device=self.offsets.device), counts)
        return i, self.indices.long()


def cell_coords(points: Tensor, origin: Tensor, h: float) -> Tensor:
    """Integer cell coordinates (N, 3), clamped into the 21-bit grid."""
    return torch.floor((points.detach() - origin) / h).long().clamp_(0, AXIS_CELLS - 1)


def encode(coords: Tensor) -> Tensor:
    """Cell key of integer coordinates (..., 3)."""
    return (coords[..., 0] << (2 * AXIS_BITS)) | (coords[..., 1] << AXIS_BITS) | coords[..., 2]


def cell_table(points: Tensor, h: float) -> CellTable:
    """Sort points by cell; the grid starts at their lower corner and covers occupied cells only."""
    device = points.device
    if points.shape[0] == 0:
        empty = torch.zeros(0, dtype=torch.long, device=device)
        return CellTable(torch.zeros(3, device=device), h, empty, torch.zeros(1, dtype=torch.long, device=device), empty)
    origin = points.detach().min(dim=0).values
    keys, order = torch.sort(encode(cell_coords(points, origin, h)))
    cell_keys, counts = torch.unique_consecutive(keys, return_counts=True)
    start = torch.zeros(cell_keys.shape[0] + 1, dtype=torch.long, device=device)
    torch.cumsum(counts, 0, out=start[1:])
    return CellTable(origin, h, cell_keys, start, order)


def candidate_ranges(table: CellTable, coords: Tensor) -> tuple[Tensor, Tensor]:
    """For each query cell (Q, 3): start and length of the particle ranges of its 27 neighbour cells."""
    offsets = torch.tensor(OFFSETS, dtype=torch.long, device=coords.device)
    neighbour = coords[:, None, :] + offsets[None]  # (Q, 27, 3)
    inside = ((neighbour >= 0) & (neighbour < AXIS_CELLS)).all(dim=2)
    keys = encode(neighbour.clamp(0, AXIS_CELLS - 1))
    slot = torch.searchsorted(table.keys, keys).clamp_(max=max(table.keys.shape[0] - 1, 0))
    found = inside & (table.keys[slot] == keys)
    start = table.start[slot]
    length = torch.where(found, table.start[slot + 1] - start, torch.zeros_like(start))
    return start, length


def neighbour_pairs(queries: Tensor, points: Tensor, h: float, exclude_self: bool = False) -> tuple[Tensor, Tensor]:
    """All (query q, point p) with |queries[q] - points[p]| < h, grouped by q (torch, any device)."""
    device = queries.device
    if queries.shape[0] == 0 or points.shape[0] == 0:
        empty = torch.zeros(0, dtype=torch.long, device=device)
        return empty, empty
    table = cell_table(points, h)
    start, length = candidate_ranges(table, cell_coords(queries, table.origin, h))
    length = length.reshape(-1)
    total = int(length.sum())
    q = torch.repeat_interleave(torch.arange(queries.shape[0], device=device), length.reshape(queries.shape[0], -1).sum(1))
    first = torch.cumsum(length, 0) - length
    local = torch.arange(total, device=device) - torch.repeat_interleave(first, length)
    p = table.order.index_select(0, torch.repeat_interleave(start.reshape(-1), length) + local)
    d = queries.detach().index_select(0, q) - points.detach().index_select(0, p)
    keep = (d * d).sum(dim=1) < h * h
    if exclude_self:
        keep &= q != p
    return q[keep], p[keep]


def neighbours_torch(positions: Tensor, h: float) -> NeighbourList:
    """Neighbour list of particles among themselves, built with torch ops (reference, any device)."""
    i, j = neighbour_pairs(positions, positions, h, exclude_self=True)
    counts = torch.bincount(i, minlength=positions.shape[0])
    offsets = torch.zeros(positions.shape[0] + 1, dtype=torch.long, device=positions.device)
    torch.cumsum(counts, 0, out=offsets[1:])
    return NeighbourList(offsets, j)
