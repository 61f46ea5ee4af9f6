"""Position-based-fluid smoke (Macklin & Mueller 2013, as used by FluidNexus), torch in and out.

Units: world lengths, seconds; density is dimensionless (1 = 8 particles per h^3, so the
paper's rho0 values keep their meaning); gravity is scaled by `PBFConfig.length_scale`
(see `fluidcore.spec.physics`). The density constraint is one-sided (only rho > rho0 is corrected), and the
residual reported everywhere (StepStats, the benchmark) is max(0, rho/rho0 - 1).

Two motion models sit behind one seam (`motion`: `Controls`, `Integrator`, `StepStats`): the
paper's particles (`paper`) and buoyant air carrying them as markers (`carrier`); a `Simulator`
is a scene's box and source with one of them, built by `build.build_simulator` from a scene.

The paper's particles have two paths: a pure-torch reference (any device, differentiable:
`sim_step`, `density_residual`, `incompressibility_loss`) and a fused C++/OpenMP CPU kernel
(`fluidcore/kernels/pbf.cpp`) used on CPU when no gradient is needed. The air around them is
still unless the step's controls prescribe one (`Controls.air`, e.g. `wind_air`) or the scene
simulates it (`AirGrid`, `air`): incompressible air that the smoke's buoyancy and the wind drive
and that the particles drag towards.
"""

from fluidcore.lazy import lazy_exports
from fluidcore.spec.physics import PRESETS, Box, PBFConfig, PhysicsInputError, Source, Sphere, Vec3

# Everything below needs torch; it loads on first use, so torch-free callers (the API reading a
# preset or a scene) can import this package and `fluidcore.spec.physics`.
_LAZY = {
    "AirField": "forces",
    "AirGrid": "air",
    "AirState": "air",
    "Controls": "motion",
    "ForceField": "forces",
    "wind_air": "forces",
    "wind_force": "forces",
    "density": "functional",
    "density_residual": "functional",
    "incompressibility_loss": "functional",
    "interpolate_velocity": "functional",
    "sim_step": "functional",
    "Simulator": "simulator",
    "StepStats": "motion",
    "step_record": "motion",
    "ParticleState": "state",
    "NeighbourCache": "verlet",
}


__getattr__ = lazy_exports(__name__, _LAZY)

__all__ = [
    "PRESETS", "AirField", "AirGrid", "AirState", "Box", "Controls", "ForceField", "NeighbourCache", "PBFConfig", "ParticleState",
    "PhysicsInputError", "Simulator", "Source",
    "Sphere", "StepStats", "Vec3", "density", "density_residual", "incompressibility_loss", "interpolate_velocity",
    "sim_step", "step_record", "wind_air", "wind_force",
]
