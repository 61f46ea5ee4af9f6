"""The stateful simulator: a scene (box, source, spheres, force) stepped forward in place."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from fluidcore.physics import checks, source as seeding
from fluidcore.physics.air import AirGrid, AirState, AirStats, floor_face
from fluidcore.physics.forces import AirField, ForceField
from fluidcore.physics.solver import residual
from fluidcore.physics.state import ParticleState
from fluidcore.physics.step import BACKENDS, Advanced, advance, substeps, use_fused
from fluidcore.spec.physics import Box, PBFConfig, PhysicsInputError, Source, Sphere, Vec3


@dataclass(frozen=True)
class StepStats:
    """What one step did. Density errors are the one-sided residual max(0, rho/rho0 - 1) of the
    particles alive after the step, measured on their final positions."""

    iterations: int
    mean_density_error: float
    max_density_error: float
    n_alive: int
    seeded: int
    retired: int  # particles that left the box through its open faces this step (the smoke's outflow)
    substeps: int = 1  # parts the frame was stepped in (fluidcore.physics.step.substeps)
    air_unconverged: int = 0  # parts whose air projection stopped short of its tolerance (AirStats.converged)
    air_divergence: float = 0.0  # the largest |divergence| (1/s) the air kept after its projections


def step_record(stats: StepStats | None) -> dict[str, float]:
    """What a frame's step did, for its record in a run (the manifest's per-frame entries): the
    particles that left through the box's open faces ("left_box": the smoke's outflow, counted,
    not lost silently) and, with an air grid, the projections that stopped short of their
    tolerance and the divergence the air kept. Empty for a frame that was not stepped."""
    if stats is None:
        return {}
    record = {"left_box": float(stats.retired)}
    if stats.air_unconverged or stats.air_divergence:
        record.update(air_unconverged=float(stats.air_unconverged), air_divergence=stats.air_divergence)
    return record


class Simulator:
    """PBF smoke in an open box: a source seeds particles, particles leaving the box are retired.

    backend: "auto" (the fused C++ kernel on CPU when it builds, torch otherwise), "torch"
    (reference, any device) or "fused" (CPU only). Spheres, the force field and the air it
    moves (`force`, `air`: fluidcore.physics.forces), XSPH and vorticity cost nothing when absent.

    air: None (still air, apart from `env_velocity`), an `AirField` (a prescribed air velocity,
    e.g. `wind_air`), or an `AirGrid` (fluidcore.physics.air): air that evolves with the smoke.
    With a grid, each step first advances the state's air (`ParticleState.air`, still air when
    it has none) from the particles, then the particles drag towards it; drag is computed in
    torch on both backends, so the fused kernel path needs nothing else.
    """

    def __init__(self, config: PBFConfig, box: Box, source: Source | None = None, spheres: Sequence[Sphere] = (),
                 force: ForceField | None = None, air: AirField | AirGrid | None = None, device: torch.device | str = "cpu",
                 backend: str = "auto") -> None:
        for value, kind, name in ((config, PBFConfig, "config"), (box, Box, "box")):
            if not isinstance(value, kind):
                raise PhysicsInputError(f"{name} must be a {kind.__name__}, got {type(value).__name__}")
        if source is not None and not isinstance(source, Source):
            raise PhysicsInputError(f"source must be a Source or None, got {type(source).__name__}")
        if not all(isinstance(s, Sphere) for s in spheres):
            raise PhysicsInputError("spheres must be Sphere instances")
        if force is not None and not callable(force):
            raise PhysicsInputError("force must be a callable (positions, time) -> (N, 3) tensor, or None")
        if air is not None and not callable(air) and not isinstance(air, AirGrid):
            raise PhysicsInputError("air must be an AirGrid, a callable (positions, time) -> (N, 3) tensor, or None")
        if isinstance(air, AirGrid) and air.floor != floor_face(config.gravity):
            raise PhysicsInputError(f"air.down must point through the box face gravity {list(config.gravity)} points "
                                    f"through (axis {floor_face(config.gravity)[0]})")
        if backend not in BACKENDS:
            raise PhysicsInputError(f"backend must be one of {BACKENDS}, got {backend!r}")
        self.config, self.box, self.source = config, box, source
        self.spheres, self.force, self.air = tuple(spheres), force, air
        self.device, self.backend = torch.device(device), backend

    def new_state(self) -> ParticleState:
        """An empty state on the simulator's device; the source fills it."""
        return ParticleState.empty(device=self.device)

    def step(self, state: ParticleState) -> StepStats:
        """Advance one frame (config.dt) in place: in `substeps` parts, each seeding its share of
        the frame's particles, advancing and retiring particles outside the box."""
        start, alive = state.time, torch.nonzero(state.alive).flatten()
        count = substeps(torch.cat([state.velocities[alive], self._inflow()]), self.config)
        config = self.config.substep(count)
        births = self._births(state, count)
        iterations, seeded, retired = 0, 0, 0
        airs: list[AirStats] = []
        density = torch.zeros(0, device=self.device)
        for part in range(count):
            if births[part].shape[0]:
                state.add(births[part], births[count + part])
                seeded += births[part].shape[0]
            out, inside, air = self._advance(state, config)
            iterations += out.iterations
            retired += int((~inside).sum())
            density = out.density[inside]
            airs += [air] if air is not None else []
        state.time, state.step = start + self.config.dt, state.step + 1
        error = residual(density, self.config.rho0)
        n_alive = int(density.shape[0])
        return StepStats(
            iterations=iterations,
            mean_density_error=float(error.mean()) if n_alive else 0.0,
            max_density_error=float(error.max()) if n_alive else 0.0,
            n_alive=n_alive,
            seeded=seeded,
            retired=retired,
            substeps=count,
            air_unconverged=sum(not air.converged for air in airs),
            air_divergence=max((air.divergence_after for air in airs), default=0.0),
        )

    def _advance(self, state: ParticleState, config: PBFConfig) -> tuple[Advanced, torch.Tensor, AirStats | None]:
        """One part of a frame (config.dt is the part's): advance the live particles, retire those
        that left the box; returns the step's result, which of them stayed inside and what the
        air grid's projection did (None without a grid)."""
        slots = torch.nonzero(state.alive).flatten()
        x = checks.points(state.positions[slots], "state.positions")
        v = checks.points(state.velocities[slots], "state.velocities")
        air_stats = None
        with torch.no_grad():
            air = self.air
            if isinstance(self.air, AirGrid):
                air, air_stats = self._advance_air(state, x, config)
            out = advance(x, v, config, time=state.time, force=self.force, air=air, spheres=self.spheres,
                          fast=use_fused(self.backend, x))
        checks.finite_result(out.positions, "particle positions")
        checks.finite_result(out.velocities, "particle velocities")
        state.positions[slots] = out.positions
        state.velocities[slots] = out.velocities
        inside = self._inside(out.positions)
        state.alive[slots[~inside]] = False
        state.time += config.dt
        return out, inside, air_stats

    def adopt_air(self, state: ParticleState) -> None:
        """Put the air `state` carries onto this simulator's air grid (`AirGrid.resample`), so a
        state saved on another grid (a continuation at other cells than its parent's) steps on
        from its own air; nothing to do without a grid or without saved air."""
        if isinstance(self.air, AirGrid) and state.air is not None:
            state.air = self.air.resample(state.air)

    def stabilize(self, state: ParticleState, steps: int = 20) -> None:
        """Run `steps` steps ending at time 0 (the paper's N_stable = 20 before the first frame)."""
        if not isinstance(steps, int) or steps < 0:
            raise PhysicsInputError(f"steps must be an integer >= 0, got {steps!r}")
        state.time = -steps * self.config.dt
        for _ in range(steps):
            self.step(state)
        state.time = 0.0

    def _advance_air(self, state: ParticleState, smoke: torch.Tensor, config: PBFConfig) -> tuple[AirField, AirStats]:
        """Step the state's air grid from the smoke (N, 3) at state.time (still air if it has none
        yet); the particles then drag towards it: its velocity at their positions. Also returns
        what the grid's projection did."""
        grid = self.air
        assert isinstance(grid, AirGrid)
        if state.air is None:
            state.air = grid.still(state.device)
        air: AirState = state.air
        stats = grid.step(air, smoke, config, state.time, self.spheres)
        return (lambda positions, _time: grid.velocity_at(air, positions)), stats

    def _births(self, state: ParticleState, count: int) -> tuple[torch.Tensor, ...]:
        """The frame's new particles (the source's draw for this frame, `seeding.emit`) in `count`
        equal shares, one per part of the frame: positions (count of them), then velocities."""
        if self.source is None or self.source.rate == 0:
            empty = torch.zeros(0, 3, device=self.device)
            return (empty,) * (2 * count)
        positions, velocities = seeding.emit(self.source, state.step, self.device, self._up())
        return (*torch.tensor_split(positions, count), *torch.tensor_split(velocities, count))

    def _inflow(self) -> torch.Tensor:
        """(1, 3) the velocity the source gives its particles ((0, 3) without a source)."""
        if self.source is None or self.source.rate == 0:
            return torch.zeros(0, 3, device=self.device)
        return torch.tensor([self.source.velocity], device=self.device)

    def _up(self) -> Vec3:
        """The scene's up: against gravity, +y where there is none."""
        g = self.config.gravity
        norm = math.sqrt(sum(c * c for c in g))
        return (0.0, 1.0, 0.0) if norm == 0.0 else (-g[0] / norm, -g[1] / norm, -g[2] / norm)

    def _inside(self, positions: torch.Tensor) -> torch.Tensor:
        lo, hi = positions.new_tensor(self.box.lo), positions.new_tensor(self.box.hi)
        return ((positions >= lo) & (positions <= hi)).all(dim=1)
