"""The one way from a scene spec to a simulator.

Every simulation of a scene (the reconstruction's fit, the identification's rollouts, the
buoyancy calibration, the continuations, the synthetic plume, the benchmark) builds its
`Simulator` here from a `fluidcore.spec.scene.Scene`, so none of them can leave out a part of
the scene's physics: the motion model the scene names (`Scene.motion`, its integrator), the
air it keeps and its static solids (`Scene.solids`, which the simulator adds to every step). What
acts on the scene from outside (a wind, a what-if's ball) is not part of it: it comes with each
step (`fluidcore.physics.motion.Controls`).
"""

from __future__ import annotations

import torch

from fluidcore.physics.air import AirGrid
from fluidcore.physics.carrier import BuoyantAirCarrier
from fluidcore.physics.motion import Integrator
from fluidcore.physics.paper import PositionBasedFluid
from fluidcore.physics.simulator import Simulator
from fluidcore.spec.scene import Scene


def build_simulator(scene: Scene, *, device: torch.device | str = "cpu", backend: str = "auto") -> Simulator:
    """The simulator of `scene`: its physics, box and source, moved by its motion model.

    "paper": the position-based particles, in the scene's air grid when `scene.air.simulated`
    (still air otherwise); `backend` picks their kernel (`PositionBasedFluid`). "carrier": the
    scene's air grid is the motion (`BuoyantAirCarrier`, with the scene's eddy viscosity and diffusivity).
    Either way the scene's solids are in the way of every step.
    """
    return Simulator(integrator(scene, torch.device(device), backend), tuple(solid.sphere for solid in scene.solids))


def integrator(scene: Scene, device: torch.device, backend: str = "auto") -> Integrator:
    """The integrator of the scene's motion model (`build_simulator`)."""
    grid = None
    if scene.air.simulated:
        grid = AirGrid(scene.box, scene.air.cells, down=scene.physics.gravity, vorticity=scene.air.vorticity)
    if scene.motion == "carrier":
        assert grid is not None  # a carrier scene always has its air (`Scene` checks it)
        return BuoyantAirCarrier(scene.physics, scene.box, scene.source, device, grid, scene.air.viscosity,
                                 scene.air.diffusivity)
    return PositionBasedFluid(scene.physics, scene.box, scene.source, device, grid, backend)
