"""SPH kernels in the dimensionless density units of `config` (torch reference, differentiable).

Density uses Poly6 and constraint gradients use the Spiky gradient (Macklin & Mueller 2013),
both multiplied by (h/2)^3 so that density 1 means 8 particles per h^3 (see `fluidcore.spec.physics`).
Pairs are given as index tensors (i, j), i != j; the self term W(0) is added separately.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

POLY6 = 315.0 / (512.0 * math.pi)  # (h/2)^3 * 315 / (64 pi h^9) * h^6: W(r) = POLY6 (1 - q^2)^3
SPIKY_GRAD = 45.0 / (8.0 * math.pi)  # |grad W| = SPIKY_GRAD (1 - q)^2 / h
SELF_DENSITY = POLY6  # W(0): a lone particle's own contribution
COINCIDENT = 1.0e-6  # pairs closer than this fraction of h get a fixed separating direction

# Irrational steps of the R3 low-discrepancy sequence: frac(k * STEPS) gives each particle index
# a distinct pseudo-random point, and the difference of two such points a direction that is
# antisymmetric in (i, j). It separates exactly coincident particles, for which r/|r| is undefined.
R3_STEPS = (0.8191725133961645, 0.6710436067037893, 0.5497004779019703)


def differences(values: Tensor, i: Tensor, j: Tensor) -> Tensor:
    """values[i] - values[j] per pair (index_select: much faster than advanced indexing on CPU)."""
    return values.index_select(0, i) - values.index_select(0, j)


def poly6(r2_over_h2: Tensor) -> Tensor:
    """Dimensionless Poly6 weight from q^2 = |r|^2 / h^2 (zero beyond the kernel radius)."""
    return POLY6 * torch.clamp(1.0 - r2_over_h2, min=0.0) ** 3


def index_directions(i: Tensor, j: Tensor) -> Tensor:
    """Unit vectors, antisymmetric in (i, j), used as r/|r| for coincident particles."""
    steps = torch.tensor(R3_STEPS, dtype=torch.float64, device=i.device)
    pi = torch.frac(i.to(torch.float64)[:, None] * steps)
    pj = torch.frac(j.to(torch.float64)[:, None] * steps)
    d = (pi - pj).to(torch.float32)
    return d / torch.linalg.vector_norm(d, dim=1, keepdim=True).clamp_min(1e-12)


def pair_geometry(positions: Tensor, i: Tensor, j: Tensor, h: float) -> tuple[Tensor, Tensor, Tensor]:
    """For each pair: q = |x_i - x_j| / h, the unit direction from j to i, and q^2."""
    r = differences(positions, i, j) / h
    q2 = (r * r).sum(dim=1)
    coincident = q2 < COINCIDENT * COINCIDENT
    # sqrt has an infinite derivative at 0: evaluate it only where q is safely positive.
    q = torch.sqrt(torch.where(coincident, torch.ones_like(q2), q2)).masked_fill(coincident, 0.0)
    direction = r / q.clamp_min(COINCIDENT)[:, None]
    if bool(coincident.any()):  # rare: only then pay for the fixed directions
        direction = torch.where(coincident[:, None], index_directions(i, j), direction)
    return q, direction, q2


def spiky_gradient(q: Tensor, direction: Tensor, h: float) -> Tensor:
    """Dimensionless Spiky gradient grad_i W(x_i - x_j) for each pair, shape (P, 3)."""
    magnitude = -SPIKY_GRAD / h * torch.clamp(1.0 - q, min=0.0) ** 2
    return magnitude[:, None] * direction


def density(positions: Tensor, i: Tensor, j: Tensor, h: float) -> Tensor:
    """Dimensionless density of every particle: W(0) plus the Poly6 sum over its pairs."""
    r = differences(positions, i, j)
    w = poly6((r * r).sum(dim=1) / (h * h))
    rho = torch.full((positions.shape[0],), SELF_DENSITY, dtype=positions.dtype, device=positions.device)
    return rho.index_add(0, i, w)
