"""The simulator: a scene's box, source and solids with a motion model's integrator behind it,
stepped a frame at a time (a state in, a state out; fluidcore.physics.motion says how the two meet)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import torch

from fluidcore.physics import source as seeding
from fluidcore.physics.motion import NO_CONTROLS, Controls, Integrator, PartStats, StepStats
from fluidcore.physics.state import ParticleState
from fluidcore.spec.physics import PBFConfig, PhysicsInputError, Sphere, Vec3


class Simulator:
    """Smoke in an open box: the source seeds particles every frame, the integrator moves them
    (and the air it keeps), particles leaving the box are retired.

    Built by `fluidcore.physics.build.build_simulator` from a scene; `integrator` is the scene's
    motion model (`fluidcore.physics.paper.PositionBasedFluid`,
    `fluidcore.physics.carrier.BuoyantAirCarrier`), made for this simulator's config, box,
    source and device. `solids` are the scene's static balls (`fluidcore.spec.scene.Scene.solids`):
    part of the scene, not of a step's controls, so every step adds them to the balls its
    controls bring (`with_solids`) and no caller (the reconstruction's carry and stabilisation,
    the identification's rollouts, the calibration, a prediction, a what-if) can leave them out.
    """

    def __init__(self, integrator: Integrator, solids: Sequence[Sphere] = ()) -> None:
        if not isinstance(integrator, Integrator):
            raise PhysicsInputError(f"integrator must be an Integrator, got {type(integrator).__name__}")
        if not all(isinstance(solid, Sphere) for solid in solids):
            raise PhysicsInputError("solids must be Sphere instances")
        self.integrator = integrator
        self.solids = tuple(solids)

    @property
    def config(self) -> PBFConfig:
        return self.integrator.config

    @property
    def box(self):  # noqa: ANN201 - fluidcore.spec.physics.Box
        return self.integrator.box

    @property
    def source(self):  # noqa: ANN201 - fluidcore.spec.physics.Source | None
        return self.integrator.source

    @property
    def device(self) -> torch.device:
        return self.integrator.device

    @property
    def motion(self) -> str:
        """The motion model's name (`fluidcore.spec.scene.MOTION_MODELS`)."""
        return self.integrator.name

    def new_state(self) -> ParticleState:
        """An empty state on the simulator's device; the source fills it."""
        return ParticleState.empty(device=self.device)

    def step(self, state: ParticleState, controls: Controls = NO_CONTROLS) -> tuple[ParticleState, StepStats]:
        """One frame (config.dt) from `state` (left as it was) under `controls`: the new state and
        what the step did. The frame is stepped in the parts the integrator asks for, each
        seeding its share of the frame's particles."""
        if not isinstance(controls, Controls):
            raise PhysicsInputError(f"controls must be a Controls, got {type(controls).__name__}")
        controls = self.with_solids(controls)
        state = state.clone()
        start = state.time
        count = self.integrator.parts(state, self._inflow())
        config = self.config.substep(count)
        births = self._births(state, count)
        parts: list[PartStats] = []
        seeded = 0
        for part in range(count):
            if births[part].shape[0]:
                state.add(births[part], births[count + part])
                seeded += births[part].shape[0]
            parts.append(self.integrator.advance(state, controls, config))
            state.time += config.dt
        state.time, state.step = start + self.config.dt, state.step + 1
        return state, self.integrator.stats(parts, state.n_alive, seeded, state)

    def with_solids(self, controls: Controls) -> Controls:
        """`controls` with the scene's solids in the way as well as the balls they bring: what a
        step applies, and what a caller keeping other points out of the balls (a rollout's visual
        Gaussians) pushes them out of."""
        if not self.solids:
            return controls
        return replace(controls, spheres=(*self.solids, *controls.spheres))

    def stabilize(self, state: ParticleState, steps: int = 20) -> ParticleState:
        """`steps` steps ending at time 0 (the paper's N_stable = 20 before the first frame)."""
        if not isinstance(steps, int) or steps < 0:
            raise PhysicsInputError(f"steps must be an integer >= 0, got {steps!r}")
        state = state.clone()
        state.time = -steps * self.config.dt
        for _ in range(steps):
            state, _ = self.step(state)
        state.time = 0.0
        return state

    def velocity_at(self, state: ParticleState, points: torch.Tensor) -> torch.Tensor:
        """The smoke's velocity (world units / s) at `points` (Q, 3) in `state`, as the motion
        model reports it (`Integrator.velocity_at`)."""
        return self.integrator.velocity_at(state, points)

    def adopt_air(self, state: ParticleState) -> ParticleState:
        """`state` with the air it carries put onto this simulator's air grid (a state saved on
        another grid steps on from its own air); unchanged where there is nothing to adopt."""
        return self.integrator.adopt_air(state)

    def _births(self, state: ParticleState, count: int) -> tuple[torch.Tensor, ...]:
        """The frame's new particles (the source's draw for this frame, `seeding.emit`) in `count`
        equal shares, one per part of the frame: positions (count of them), then velocities."""
        if self.source is None or self.source.rate == 0:
            empty = torch.zeros(0, 3, device=self.device)
            return (empty,) * (2 * count)
        positions, velocities = seeding.emit(self.source, state.step, self.device, self.up)
        return (*torch.tensor_split(positions, count), *torch.tensor_split(velocities, count))

    def _inflow(self) -> torch.Tensor:
        """(1, 3) the velocity the source gives its particles ((0, 3) without a source)."""
        if self.source is None or self.source.rate == 0:
            return torch.zeros(0, 3, device=self.device)
        return torch.tensor([self.source.velocity], device=self.device)

    @property
    def up(self) -> Vec3:
        """The scene's up: against gravity, +y where there is none."""
        return up_of(self.config)


def up_of(config: PBFConfig) -> Vec3:
    """The unit vector against `config.gravity` (+y where there is none)."""
    g = config.gravity
    norm = math.sqrt(sum(c * c for c in g))
    return (0.0, 1.0, 0.0) if norm == 0.0 else (-g[0] / norm, -g[1] / norm, -g[2] / norm)
