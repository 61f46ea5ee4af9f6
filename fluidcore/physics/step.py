"""One PBF step on a compact set of particles: the core shared by `Simulator` and `sim_step`.

Order (Macklin & Mueller 2013, Algorithm 1, with the smoke model's forces):
  1. v* = v + dt (alpha g + f_ext(x, t)), capped at the speed limit;  p = x + dt v*
  2. spheres push p out
  3. neighbours of p (built once, reused by every solver iteration and the filters below)
  4. density-constraint iterations on p (they spread what a sphere piled onto its surface)
  5. spheres push particles out again (exact contact)
  6. v = (p - x) / dt, then drag (needs the density just solved), XSPH, vorticity,
     sliding along spheres, and the speed limit;
  7. entrainment moves p outward (`fluidcore.physics.entrainment`; a displacement, v keeps step 6's).
Drag is applied after the solve, as a velocity filter, because it needs the density of the
new positions, which the solver has just computed: no extra neighbour pass. The speed limit
bounds velocities; a particle's displacement per step is then at most the limit x dt plus
the solver's capped corrections (max_correction x h per iteration).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from fluidcore.physics import coupling, entrainment, forces, fused
from fluidcore.physics.checks import points
from fluidcore.physics.forces import AirField, ForceField
from fluidcore.physics.neighbours import NeighbourList, cell_table, neighbours_torch
from fluidcore.physics.solver import solve_torch
from fluidcore.physics.sph import density as sph_density
from fluidcore.physics.verlet import NeighbourCache
from fluidcore.spec.physics import PBFConfig, PhysicsInputError, Sphere

BACKENDS = ("auto", "torch", "fused")
# Substeps (a CFL bound): a frame of dt is stepped in n equal parts so that the fastest particle,
# its speed at the frame's start plus what buoyancy adds over the frame, moves at most CFL kernel
# radii per part. The speed limit, one kernel radius per part, is then at least 1 / CFL times that
# speed and binds only on particles the solver flings. With one step per frame the same physics
# rose at 0.507 m/s at 30 fps, 0.271 at 15 and 0.182 at 10, the limit binding (issue 33);
# docs/bench_physics.md, "Frame rates", has the rise and the binding with these substeps.
CFL = 1.0
MAX_SUBSTEPS = 16  # bounds a frame's work: a 10 fps clip with smoke at 6 kernel radii per frame


@dataclass(frozen=True)
class Advanced:
    """Result of one step: new positions and velocities, their density, solver iterations used."""

    positions: Tensor
    velocities: Tensor
    density: Tensor
    iterations: int


def use_fused(backend: str, *tensors: Tensor) -> bool:
    """Resolve a backend name for these inputs: the fused kernel runs on CPU when none of them
    needs a gradient, torch everywhere."""
    if backend not in BACKENDS:
        raise PhysicsInputError(f"backend must be one of {BACKENDS}, got {backend!r}")
    differentiable = torch.is_grad_enabled() and any(t.requires_grad for t in tensors)
    on_cpu = all(t.device.type == "cpu" for t in tensors)
    if backend == "fused":
        if not on_cpu or differentiable or not fused.available():
            raise PhysicsInputError("backend='fused' needs CPU tensors without gradients and a C++ compiler")
        return True
    return backend == "auto" and on_cpu and not differentiable and fused.available()


def substeps(velocities: Tensor, config: PBFConfig) -> int:
    """Parts a frame of `config.dt` is stepped in (see CFL), from the velocities (N, 3) at its start."""
    if velocities.shape[0] == 0:
        return 1
    fastest = float(torch.linalg.vector_norm(velocities.detach(), dim=1).max())
    fastest += math.hypot(*config.body_acceleration) * config.dt
    if not math.isfinite(fastest):
        raise PhysicsInputError(f"velocities must be finite, the fastest is {fastest}")
    return int(min(max(math.ceil(fastest * config.dt / (CFL * config.h)), 1), MAX_SUBSTEPS))


def external_force(force: ForceField, positions: Tensor, time: float) -> Tensor:
    """Evaluate a user force field, checking what it returns."""
    value = force(positions, time)
    if not isinstance(value, Tensor) or value.shape != positions.shape:
        shape = tuple(value.shape) if isinstance(value, Tensor) else type(value).__name__
        raise PhysicsInputError(f"force must return a tensor of shape {tuple(positions.shape)}, got {shape}")
    return points(value, "force(positions, time)")


def advance(x: Tensor, v: Tensor, config: PBFConfig, *, time: float, force: ForceField | None = None,
            air: AirField | None = None, spheres: Sequence[Sphere] = (), fast: bool = False,
            cache: NeighbourCache | None = None) -> Advanced:
    """Advance particles x, v (N, 3) by one step of config.dt (differentiable when fast=False).
    `force` is an external acceleration field, `air` the velocity it gave the surrounding air
    (drag relaxes the smoke towards it; fluidcore.physics.forces.wind_air).

    The fused path works on the particles sorted by grid cell: neighbours are then close in
    memory, which makes every solver pass cache-friendly (callers' particle order is arbitrary,
    e.g. a state's slot order). The external force is evaluated before sorting, in the caller's
    order, so a field may index its particles. Everything after is independent of the order up to
    float rounding, except the fixed separating directions of exactly coincident particles
    (any antisymmetric choice is as valid; see sph.index_directions). With a neighbour `cache`
    (whose lists are in the caller's order) nothing is sorted.
    """
    p = x + config.dt * cap_length(v + config.dt * acceleration(x, config, time, force), config.speed_limit)
    if not fast or cache is not None:
        out = correct(x, p, config, time=time, air=air, spheres=spheres, fast=fast, cache=cache)
    else:
        order = cell_table(p, config.h).order
        out = correct(x[order], p[order], config, time=time, air=air, spheres=spheres, fast=True)
        inverse = torch.empty_like(order)
        inverse[order] = torch.arange(order.shape[0], device=order.device)
        out = Advanced(out.positions[inverse], out.velocities[inverse], out.density[inverse], out.iterations)
    return replace(out, positions=entrainment.spread(out.positions, out.velocities, config))


def acceleration(x: Tensor, config: PBFConfig, time: float, force: ForceField | None) -> Tensor:
    """Buoyancy plus the external force field, if any: (3,) or (N, 3), world units / s^2."""
    body = x.new_tensor(config.body_acceleration)
    return body if force is None else body + external_force(force, x, time)


def correct(x: Tensor, p: Tensor, config: PBFConfig, *, time: float, air: AirField | None, spheres: Sequence[Sphere],
            fast: bool, cache: NeighbourCache | None = None) -> Advanced:
    """Steps 2-6 of the module docstring: from predicted positions p to the step's result."""
    dt = config.dt
    contacts: list[coupling.Contact] = []
    if spheres:
        p, contacts = coupling.push_out(p, spheres, time + dt)
    neighbours = neighbour_list(p, config.h, fast, cache)
    solution = (fused.solve_fused if fast else solve_torch)(p, neighbours, config)
    p, density = solution.positions, solution.density

    if spheres:
        p, after_solve = coupling.push_out(p, spheres, time + dt)
        contacts = coupling.merge(contacts, after_solve)
        density = fused.density_fused(p, neighbours, config.h) if fast else sph_density(p, *neighbours.pairs(), config.h)

    air_velocity = None if air is None else points(air(p, time + dt), "air(positions, time)")
    velocities = forces.drag((p - x) / dt, density, config, air_velocity)
    if config.xsph > 0.0 or config.vorticity > 0.0:
        i, j = neighbours.pairs()
        if config.xsph > 0.0:
            velocities = forces.xsph(velocities, p, i, j, config)
        if config.vorticity > 0.0:
            velocities = forces.vorticity_confinement(velocities, p, i, j, config)
    if contacts:
        velocities = coupling.slide(velocities, contacts)
    velocities = cap_length(velocities, config.speed_limit)
    return Advanced(p, velocities, density, solution.iterations)


def neighbour_list(p: Tensor, h: float, fast: bool, cache: NeighbourCache | None) -> NeighbourList:
    """Pairs of p closer than h: from the cache when one is given, else built (fused or torch)."""
    if cache is not None:
        if cache.h != h:
            raise PhysicsInputError(f"neighbour_cache was made for h={cache.h}, the config has h={h}")
        return cache.neighbours(p)
    return fused.neighbours_fused(p, h) if fast else neighbours_torch(p, h)


def cap_length(vectors: Tensor, limit: float) -> Tensor:
    """Scale rows longer than `limit` down to it (differentiable, safe at zero)."""
    norm = torch.linalg.vector_norm(vectors, dim=1, keepdim=True)
    return vectors * torch.clamp(limit / norm.clamp_min(1e-30), max=1.0)
