"""The one way from a scene spec to a simulator.

Every simulation of a scene (the reconstruction's fit, the identification's rollouts, the
buoyancy calibration, the continuations, the synthetic plume, the benchmark) builds its
`Simulator` here from a `fluidcore.spec.scene.Scene`, so none of them can leave out a part of
the scene's physics: when the scene simulates the air, each of them steps it.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from fluidcore.physics.air import AirGrid
from fluidcore.physics.forces import AirField, ForceField
from fluidcore.physics.simulator import Simulator
from fluidcore.spec.physics import Sphere
from fluidcore.spec.scene import Scene


def build_simulator(
    scene: Scene,
    *,
    device: torch.device | str = "cpu",
    force: ForceField | None = None,
    spheres: Sequence[Sphere] = (),
    backend: str = "auto",
    still_air: AirField | None = None,
) -> Simulator:
    """The simulator of `scene`: its physics, box and source, and its air.

    `force` (a wind) pushes the particles and, when the scene simulates the air, that air too;
    `spheres` are solid balls in the way. The air is the scene's `AirGrid` (floor where its
    gravity points, `scene.air` cells and vorticity) when `scene.air.simulated`; otherwise
    `still_air`, a prescribed air velocity (the wind's air, `fluidcore.physics.wind_air`), or
    still air when None.
    """
    air: AirField | AirGrid | None = still_air
    if scene.air.simulated:
        air = AirGrid(scene.box, scene.air.cells, down=scene.physics.gravity, force=force, vorticity=scene.air.vorticity)
    return Simulator(scene.physics, scene.box, scene.source, spheres=spheres, force=force, air=air, device=device,
                     backend=backend)
