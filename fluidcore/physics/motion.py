"""The seam between a scene and how its smoke moves: the step's controls, the integrator a
motion model implements, and what a step did.

A `Simulator` (fluidcore.physics.simulator) is a scene's box and source with one `Integrator`
behind it; `build_simulator` (fluidcore.physics.build) picks the integrator by the scene's
motion model (`fluidcore.spec.scene.MOTION_MODELS`). Every frame the simulator seeds the
source's particles, asks the integrator how many parts the frame needs (a CFL bound of its
own), lets it move the particles (and the air it keeps) part by part, retires the particles
that left the box, and returns a new state with the step's `StepStats`: a state in, a state
out, as in PhiFlow's steps and Warp's integrators. What acts on the scene from outside (a wind,
a what-if's ball) arrives as `Controls` with each step, never as settings of the simulator,
so one simulator serves the factual and the what-if frames alike; the scene's own static
solids reach the integrator the same way, as `Controls.spheres`, added by the simulator to
every step (`Simulator.with_solids`).

Two integrators exist: `fluidcore.physics.paper.PositionBasedFluid` (the paper's particles with
their own buoyancy and density-gated drag) and `fluidcore.physics.carrier.BuoyantAirCarrier`
(buoyant air on a grid carrying the particles as markers). docs/architecture.md, "How to add a
motion model", is the recipe for a third.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, ClassVar

import torch
from torch import Tensor

from fluidcore.physics.forces import AirField, ForceField
from fluidcore.spec.physics import Box, PBFConfig, PhysicsInputError, Source, Sphere
from fluidcore.spec.reconstruct import LossWeights

if TYPE_CHECKING:
    from fluidcore.physics.state import ParticleState


@dataclass(frozen=True)
class Controls:
    """What acts on a scene during one step from outside its own physics.

    force: a body force field (the wind), world units / s^2, evaluated at the step's start time;
    terminal_time: seconds: on an air grid the force drives the air at a point at most to
    terminal_time x the force there (a quadratic drag of the surroundings,
    `fluidcore.physics.air.AirGrid.accelerate`; None: without bound); air: a prescribed velocity
    of the surrounding air (the wind's air where the model keeps no air of its own), world
    units / s; spheres: solid balls in the way at the step's time."""

    force: ForceField | None = None
    air: AirField | None = None
    spheres: tuple[Sphere, ...] = ()
    terminal_time: float | None = None

    def __post_init__(self) -> None:
        if self.force is not None and not callable(self.force):
            raise PhysicsInputError("controls.force must be a callable (positions, time) -> (N, 3) tensor, or None")
        if self.air is not None and not callable(self.air):
            raise PhysicsInputError("controls.air must be a callable (positions, time) -> (N, 3) tensor, or None")
        object.__setattr__(self, "spheres", tuple(self.spheres))
        if not all(isinstance(s, Sphere) for s in self.spheres):
            raise PhysicsInputError("controls.spheres must be Sphere instances")
        if self.terminal_time is not None and not 0.0 < self.terminal_time < float("inf"):
            raise PhysicsInputError(f"controls.terminal_time must be a number of seconds > 0, got {self.terminal_time!r}")


NO_CONTROLS = Controls()


@dataclass(frozen=True)
class StepStats:
    """What one frame's step did, whatever the model: the particles alive after it, those the
    source seeded and those that left the box through its open faces (the smoke's outflow,
    counted, not lost silently), the parts the frame was stepped in, and, where the model keeps
    an air grid, the projections that stopped short of their tolerance and the largest
    |divergence| (1/s) the air kept. A model adds its own fields in a subclass (`record` says
    which reach a run's frame records)."""

    n_alive: int
    seeded: int
    retired: int
    substeps: int = 1
    air_unconverged: int = 0
    air_divergence: float = 0.0

    def record(self) -> dict[str, float]:
        """The frame's record in a run (the manifest's per-frame entries)."""
        record = {"left_box": float(self.retired)}
        if self.air_unconverged or self.air_divergence:
            record.update(air_unconverged=float(self.air_unconverged), air_divergence=self.air_divergence)
        return record


def step_record(stats: StepStats | None) -> dict[str, float]:
    """What a frame's step did, for its record in a run; empty for a frame that was not stepped."""
    return {} if stats is None else stats.record()


@dataclass(frozen=True)
class PartStats:
    """What an integrator did in one part of a frame: particles retired, and the air's
    projection when it keeps one (`converged`, the divergence it kept); `extra` holds the
    model's own per-part figures for its `StepStats`."""

    retired: int
    air_converged: bool = True
    air_divergence: float = 0.0
    extra: dict[str, float] = field(default_factory=dict)


class Integrator(ABC):
    """How a motion model moves a scene's smoke (module docstring). Built from the scene's
    physics constants, box and source (a Warp "model"); holds no per-step state: the particles
    and the air live in the `ParticleState` passed to `advance`."""

    name: ClassVar[str]

    def __init__(self, config: PBFConfig, box: Box, source: Source | None, device: torch.device) -> None:
        self.config, self.box, self.source, self.device = config, box, source, device

    @abstractmethod
    def parts(self, state: ParticleState, inflow: Tensor) -> int:
        """Parts a frame of `config.dt` is stepped in (the model's CFL bound), from the state at
        the frame's start and the (0 or 1, 3) velocity newborn particles get."""

    @abstractmethod
    def advance(self, state: ParticleState, controls: Controls, config: PBFConfig) -> PartStats:
        """Move the live particles of `state` (and the air it keeps) in place by one part of a
        frame (`config.dt` is the part's), starting at `state.time`; retire the particles that
        left the box (`retire`). The simulator advances `state.time` afterwards."""

    @abstractmethod
    def velocity_at(self, state: ParticleState, points: Tensor) -> Tensor:
        """The model's velocity (world units / s) at `points` (Q, 3) in `state`: what a run
        reports as the smoke's motion (exports, metrics, the API)."""

    def fit_terms(self, p: Tensor, p_sim: Tensor, p_prev: Tensor, weights: LossWeights,
                  next_step: bool) -> dict[str, Tensor]:
        """The model's own terms of a frame's position fit (fluidcore.reconstruct.physical), each
        weighted, at positions p (N, 3): here "sim", stay close to the model's prediction p_sim
        (N, 3), in kernel radii so the weight means the same in any unit. p_prev (N, 3): the
        positions one frame before; `next_step`: whether terms one step ahead are asked for
        (`PriorConfig.next_step_incompressibility`). A model adds its own."""
        return {"sim": weights.sim * ((p - p_sim) / self.config.h).pow(2).sum(-1).mean()}

    def adopt_air(self, state: ParticleState) -> ParticleState:
        """`state` with the air it carries put onto this model's air grid (a state saved on
        another grid, or by a model without one); `state` itself where the model keeps no air."""
        return state

    def stats(self, parts: Sequence[PartStats], n_alive: int, seeded: int, state: ParticleState) -> StepStats:
        """The frame's `StepStats` from its parts (a model with figures of its own overrides it)."""
        return StepStats(**common_stats(parts, n_alive, seeded))

    def retire(self, state: ParticleState, slots: Tensor) -> int:
        """Mark the particles in `slots` outside the box as dead; returns how many."""
        positions = state.positions[slots]
        lo, hi = positions.new_tensor(self.box.lo), positions.new_tensor(self.box.hi)
        outside = ~((positions >= lo) & (positions <= hi)).all(dim=1)
        state.alive[slots[outside]] = False
        return int(outside.sum())


def common_stats(parts: Sequence[PartStats], n_alive: int, seeded: int) -> dict[str, float | int]:
    """The fields of `StepStats` every model fills the same way from its parts."""
    return {
        "n_alive": n_alive,
        "seeded": seeded,
        "retired": sum(p.retired for p in parts),
        "substeps": len(parts),
        "air_unconverged": sum(not p.air_converged for p in parts),
        "air_divergence": max((p.air_divergence for p in parts), default=0.0),
    }
