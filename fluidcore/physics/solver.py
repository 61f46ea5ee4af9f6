"""Jacobi solve of the one-sided PBF density constraint (torch reference, differentiable).

C_i = max(0, rho_i / rho0 - 1): only over-dense particles push apart, as suits smoke, so
an expanding plume is left alone. lambda_i = -C_i / (sum_k |grad_k C_i|^2 + eps), with the
relaxation eps in units of 1/h^2 so it means the same at any kernel radius; the correction
dp_i = sum_j (lambda_i + lambda_j + s_corr_ij) grad W_ij / rho0 is capped per iteration
(`max_correction` x h) so no configuration can throw a particle across the domain.

Iteration k starts by measuring the density of the current positions; the loop stops there
after `iterations` corrections, or earlier with a tolerance once the mean residual is below
it. So the density returned is always that of the returned positions, for free.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from fluidcore.physics.neighbours import NeighbourList
from fluidcore.physics.sph import SELF_DENSITY, pair_geometry, poly6, spiky_gradient
from fluidcore.spec.physics import PBFConfig


@dataclass(frozen=True)
class Solution:
    """Solver output: corrected positions, their density, and the iterations used."""

    positions: Tensor
    density: Tensor
    iterations: int


def residual(density: Tensor, rho0: float) -> Tensor:
    """The one-sided constraint value max(0, rho / rho0 - 1) per particle."""
    return torch.clamp(density / rho0 - 1.0, min=0.0)


def solve_torch(positions: Tensor, neighbours: NeighbourList, config: PBFConfig) -> Solution:
    """Density solve with torch ops: differentiable w.r.t. positions, runs on any device."""
    i, j = neighbours.pairs()
    h, rho0, n = config.h, config.rho0, positions.shape[0]
    epsilon = config.relaxation / (h * h)
    s_corr_scale = config.s_corr_k * h * h
    w_dq = float(poly6(torch.tensor(config.s_corr_dq**2)))
    cap = config.iteration_cap
    p = positions
    iteration = 0
    while True:
        q, direction, q2 = pair_geometry(p, i, j, h)
        rho = torch.full((n,), SELF_DENSITY, dtype=p.dtype, device=p.device).index_add(0, i, poly6(q2))
        c = residual(rho, rho0)
        converged = config.tolerance is not None and n > 0 and float(c.mean()) < config.tolerance
        if iteration == cap or converged or n == 0:
            return Solution(p, rho, iteration)
        grad = spiky_gradient(q, direction, h) / rho0  # (P, 3): grad of C_i w.r.t. x_i, per pair
        grad_sum = torch.zeros_like(p).index_add(0, i, grad)
        denominator = (grad_sum * grad_sum).sum(1) + torch.zeros_like(rho).index_add(0, i, (grad * grad).sum(1))
        lam = -c / (denominator + epsilon)
        weight = lam.index_select(0, i) + lam.index_select(0, j)
        if s_corr_scale > 0.0:
            weight = weight - s_corr_scale * (poly6(q2) / w_dq) ** config.s_corr_n
        dp = torch.zeros_like(p).index_add(0, i, weight[:, None] * grad)
        norm = torch.linalg.vector_norm(dp, dim=1, keepdim=True)
        limit = config.max_correction * h
        p = p + dp * torch.clamp(limit / norm.clamp_min(1e-30), max=1.0)
        iteration += 1
