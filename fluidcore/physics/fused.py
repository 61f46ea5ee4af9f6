"""The fused C++/OpenMP CPU path (fluidcore/kernels/pbf.cpp) behind the same interfaces as the
torch reference: neighbour lists, the density solve and velocity interpolation. Not
differentiable; used without gradients on CPU, where it is several times faster than eager torch."""

from __future__ import annotations

import ctypes
from functools import lru_cache

import torch
from torch import Tensor

from fluidcore import kernels
from fluidcore.physics.neighbours import NeighbourList, cell_coords, cell_table, encode
from fluidcore.physics.solver import Solution
from fluidcore.spec.physics import PBFConfig

_i64, _f32, _int, _ptr = ctypes.c_int64, ctypes.c_float, ctypes.c_int, ctypes.c_void_p


@lru_cache(maxsize=None)
def library() -> ctypes.CDLL | None:
    """The compiled kernel with its signatures declared, or None when it cannot be built."""
    lib = kernels.load("pbf")
    if lib is None:
        return None
    lib.pbf_count_neighbours.argtypes = [_ptr, _f32, _ptr, _ptr, _i64, _ptr, _ptr, _int]
    lib.pbf_count_neighbours.restype = _i64
    lib.pbf_fill_neighbours.argtypes = [_ptr, _f32, _ptr, _ptr, _i64, _ptr, _ptr, _ptr, _int]
    lib.pbf_fill_neighbours.restype = None
    lib.pbf_density.argtypes = [_ptr, _i64, _f32, _ptr, _ptr, _ptr, _int]
    lib.pbf_density.restype = None
    lib.pbf_solve.argtypes = [_ptr, _i64, _ptr, _ptr, _f32, _f32, _f32, _f32, _int, _f32, _f32, _int, _f32, _ptr, _int]
    lib.pbf_solve.restype = _int
    lib.pbf_interpolate.argtypes = [_ptr, _ptr, _i64, _ptr, _ptr, _f32, _ptr, _ptr, _i64, _ptr, _int]
    lib.pbf_interpolate.restype = None
    return lib


def available() -> bool:
    """Whether the fused path can run here."""
    return library() is not None


def _lib() -> ctypes.CDLL:
    lib = library()
    if lib is None:
        raise RuntimeError("the fused PBF kernel is unavailable (no C++ compiler?); use backend='torch'")
    return lib


def _p(t: Tensor) -> ctypes.c_void_p:
    return kernels.pointer(t)


def neighbours_fused(positions: Tensor, h: float) -> NeighbourList:
    """Same list as `neighbours.neighbours_torch` (CPU float32 positions), built by the C++ kernel."""
    lib, threads = _lib(), torch.get_num_threads()
    pos = positions.detach().contiguous()
    table = cell_table(pos, h)
    n, n_cells = pos.shape[0], table.keys.shape[0]
    counts = torch.zeros(n, dtype=torch.long)
    in_cell_order = pos[table.order].contiguous()
    args = (_p(in_cell_order), h, _p(table.keys), _p(table.start), n_cells, _p(table.order))
    total = lib.pbf_count_neighbours(*args, _p(counts), threads)
    offsets = torch.zeros(n + 1, dtype=torch.long)
    torch.cumsum(counts, 0, out=offsets[1:])
    indices = torch.empty(total, dtype=torch.int32)
    lib.pbf_fill_neighbours(*args, _p(offsets), _p(indices), threads)
    return NeighbourList(offsets, indices)


def _csr(neighbours: NeighbourList) -> tuple[Tensor, Tensor]:
    return neighbours.offsets.contiguous(), neighbours.indices.to(torch.int32).contiguous()


def density_fused(positions: Tensor, neighbours: NeighbourList, h: float) -> Tensor:
    """Dimensionless density over a neighbour list, as `sph.density`."""
    pos = positions.detach().contiguous()
    offsets, indices = _csr(neighbours)
    out = torch.empty(pos.shape[0], dtype=torch.float32)
    _lib().pbf_density(_p(pos), pos.shape[0], h, _p(offsets), _p(indices), _p(out), torch.get_num_threads())
    return out


def solve_fused(positions: Tensor, neighbours: NeighbourList, config: PBFConfig) -> Solution:
    """Density solve in C++, same algorithm and stopping rule as `solver.solve_torch`."""
    pos = positions.detach().contiguous().clone()
    offsets, indices = _csr(neighbours)
    density = torch.empty(pos.shape[0], dtype=torch.float32)
    iterations = _lib().pbf_solve(
        _p(pos), pos.shape[0], _p(offsets), _p(indices), config.h, config.rho0, config.relaxation,
        config.s_corr_k, config.s_corr_n, config.s_corr_dq, config.max_correction * config.h,
        config.iteration_cap, config.tolerance or 0.0, _p(density), torch.get_num_threads(),
    )
    return Solution(pos, density, iterations)


def interpolate_fused(query: Tensor, points: Tensor, values: Tensor, h: float) -> Tensor:
    """Shepard Poly6 average of `values` (N, 3) at `query` (Q, 3), as `functional.interpolate_velocity`."""
    query, points = query.detach().contiguous(), points.detach().contiguous()
    out = torch.zeros_like(query)
    if query.shape[0] == 0 or points.shape[0] == 0:
        return out
    table = cell_table(points, h)
    query_keys = encode(cell_coords(query, table.origin, h)).contiguous()
    sorted_points = points.index_select(0, table.order).contiguous()
    sorted_values = values.detach().index_select(0, table.order).contiguous()
    _lib().pbf_interpolate(
        _p(query), _p(query_keys), query.shape[0], _p(sorted_points), _p(sorted_values), h, _p(table.keys),
        _p(table.start), table.keys.shape[0], _p(out), torch.get_num_threads(),
    )
    return out
