"""Simulators for the physics tests, built the way `fluidcore.physics.build` builds them but from
a config, a box and a source directly (the tests' scenes are not reconstructions)."""

from __future__ import annotations

import torch

from fluidcore.physics import ParticleState, Simulator, StepStats
from fluidcore.physics.air import AirGrid
from fluidcore.physics.carrier import BuoyantAirCarrier
from fluidcore.physics.motion import NO_CONTROLS, Controls
from fluidcore.physics.paper import PositionBasedFluid
from fluidcore.spec.physics import Box, PBFConfig, Source


def paper(config: PBFConfig, box: Box, source: Source | None = None, *, air: AirGrid | None = None,
          backend: str = "auto", device: str = "cpu") -> Simulator:
    """The paper's particles in `box` (in `air` when given)."""
    return Simulator(PositionBasedFluid(config, box, source, torch.device(device), air, backend))


def carrier(config: PBFConfig, box: Box, source: Source | None = None, *, cells: int = 32, viscosity: float = 0.0,
            device: str = "cpu") -> Simulator:
    """The buoyant-air carrier in `box` on a grid of `cells` on its long side."""
    grid = AirGrid(box, cells, down=config.gravity)
    return Simulator(BuoyantAirCarrier(config, box, source, torch.device(device), grid, viscosity))


def run(sim: Simulator, state: ParticleState, steps: int,
        controls: Controls = NO_CONTROLS) -> tuple[ParticleState, list[StepStats]]:
    """`state` stepped `steps` frames under `controls`: the last state and every step's stats."""
    stats = []
    for _ in range(steps):
        state, step = sim.step(state, controls)
        stats.append(step)
    return state, stats
