"""Stateless, differentiable entry points used inside the reconstruction's optimiser.

Sim(p, u) = `sim_step`, L_incomp = `incompressibility_loss`, and the velocity field that
advects the visual particles = `interpolate_velocity`. Gradients flow to positions (and
velocities); neighbour lists are rebuilt from detached positions, as they are piecewise
constant in them.
"""

from __future__ import annotations

import torch
from torch import Tensor

from fluidcore.physics import checks, fused, sph
from fluidcore.physics.forces import ForceField
from fluidcore.physics.neighbours import neighbour_pairs
from fluidcore.physics.solver import residual
from fluidcore.physics.sph import poly6
from fluidcore.physics.step import advance, neighbour_list, substeps, use_fused
from fluidcore.physics.verlet import NeighbourCache
from fluidcore.spec.physics import PBFConfig, PhysicsInputError


def sim_step(positions: Tensor, velocities: Tensor, config: PBFConfig, force: ForceField | None = None,
             time: float = 0.0, backend: str = "auto",
             neighbour_cache: NeighbourCache | None = None) -> tuple[Tensor, Tensor]:
    """One frame (config.dt) of the given particles (no source, no box, no spheres), in the
    substeps the CFL bound asks for (`fluidcore.physics.step.substeps`): new (positions, velocities).

    Differentiable w.r.t. positions and velocities; with backend="auto" the fused CPU kernel
    is used only when no gradient is needed. An optimiser calling this many times on slowly
    moving particles may pass `neighbour_cache=NeighbourCache(config.h)` (one per sequence of
    calls, see `verlet`): the neighbour list of the predicted positions is then reused while
    it stays valid, with the same pairs, so results agree with a fresh list up to float rounding.
    """
    _check_config(config)
    positions = checks.points(positions, "positions")
    velocities = checks.points(velocities, "velocities", positions.shape[0])
    count = substeps(velocities, config)
    part = config.substep(count)
    fast = use_fused(backend, positions, velocities)
    for k in range(count):
        out = advance(positions, velocities, part, time=float(time) + k * part.dt, force=force, fast=fast,
                      cache=neighbour_cache)
        positions, velocities = out.positions, out.velocities
    return checks.finite_result(positions, "sim_step positions"), checks.finite_result(velocities, "sim_step velocities")


def density(positions: Tensor, h: float) -> Tensor:
    """Dimensionless density (8 particles per h^3 = 1) of each particle, differentiable."""
    positions = checks.points(positions, "positions")
    return sph.density(positions, *neighbour_pairs(positions, positions, h, exclude_self=True), h)


def density_residual(positions: Tensor, config: PBFConfig, neighbour_cache: NeighbourCache | None = None) -> Tensor:
    """Per-particle one-sided residual max(0, rho/rho0 - 1), differentiable w.r.t. positions.

    `neighbour_cache` (optional, for repeated calls on slowly moving positions): see `sim_step`."""
    _check_config(config)
    if neighbour_cache is None:
        return residual(density(positions, config.h), config.rho0)
    positions = checks.points(positions, "positions")
    pairs = neighbour_list(positions, config.h, False, neighbour_cache).pairs()
    return residual(sph.density(positions, *pairs, config.h), config.rho0)


def incompressibility_loss(positions: Tensor, config: PBFConfig,
                           neighbour_cache: NeighbourCache | None = None) -> Tensor:
    """L_incomp: mean squared one-sided density residual (0 for no particles), a scalar."""
    r = density_residual(positions, config, neighbour_cache)
    return (r * r).mean() if r.numel() else r.sum()


def interpolate_velocity(query: Tensor, positions: Tensor, velocities: Tensor, h: float,
                         backend: str = "auto") -> Tensor:
    """Velocity at query points (Q, 3): Poly6-weighted average of particle velocities within h.

    A Shepard (normalised) average, so a uniform flow is reproduced exactly; a query with no
    particle within h gets zero velocity. backend="auto" uses the fused CPU kernel when no
    gradient is needed (it never materialises the query-particle pairs), the torch reference
    (differentiable, any device) otherwise.
    """
    query = checks.points(query, "query")
    positions = checks.points(positions, "positions")
    velocities = checks.points(velocities, "velocities", positions.shape[0])
    if not (isinstance(h, (int, float)) and h > 0 and h < float("inf")):
        raise PhysicsInputError(f"h must be a positive finite number, got {h!r}")
    if use_fused(backend, query, positions, velocities):
        return checks.finite_result(fused.interpolate_fused(query, positions, velocities, float(h)), "interpolated velocity")
    qi, pj = neighbour_pairs(query, positions, float(h))
    r = query.index_select(0, qi) - positions.index_select(0, pj)
    w = poly6((r * r).sum(1) / (h * h))
    total = torch.zeros(query.shape[0], dtype=query.dtype, device=query.device).index_add(0, qi, w)
    weighted = torch.zeros_like(query).index_add(0, qi, w[:, None] * velocities.index_select(0, pj))
    return weighted / total.clamp_min(1e-12)[:, None]


def _check_config(config: object) -> None:
    if not isinstance(config, PBFConfig):
        raise PhysicsInputError(f"config must be a PBFConfig, got {type(config).__name__}")
