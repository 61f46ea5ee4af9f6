"""Parameters of the position-based-fluid (PBF) smoke model, the scene primitives, and the paper's presets:
the physics half of the scene spec (`fluidcore.spec.scene`), torch-free.

Units. Lengths, velocities and forces are in *world units* (the scene's, e.g. the cameras'
frame), time in seconds. The paper's constants (|g| = 9.8 with alpha = -3 or -6, drag
k = 3) were tuned in the official release's units, where positions are world x 100; so
gravity is given in those "simulation" units and divided by `length_scale` (simulation
units per world unit): the body acceleration in world units is
``alpha * gravity / length_scale``. Everything else (density, drag rate, relaxation,
s_corr) is dimensionless or per second, so it does not depend on the length unit.

Density. Mass is 1 per particle and the Poly6 kernel is scaled so that density 1 is the
number density of a cubic lattice with spacing h/2 (8 particles per h^3, the usual SPH
resolution of two spacings per kernel radius): rho_i = (h/2)^3 * sum_j W_poly6(x_i - x_j, h).
With the official kernel radius (0.02 world = 2 simulation units) this is exactly the
density the official release computes, so its rest densities (rho0 = 2 for ScalarFlow,
1.5 for the FluidNexus scenes) mean the same here, for any h.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

from fluidcore.errors import InputError

Vec3 = tuple[float, float, float]


class PhysicsInputError(InputError):
    """Bad input to the simulator: the message names the offending field or argument."""


def vec3(value: object, name: str) -> Vec3:
    """`value` as three finite floats; `name` is the field a bad value is blamed on."""
    try:
        vec = tuple(float(c) for c in value)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise PhysicsInputError(f"{name} must be three numbers, got {value!r}") from None
    if len(vec) != 3:
        raise PhysicsInputError(f"{name} must have 3 components, got {len(vec)}")
    if not all(math.isfinite(c) for c in vec):
        raise PhysicsInputError(f"{name} must be finite, got {list(vec)}")
    return vec  # type: ignore[return-value]


def _finite(value: float, name: str, *, positive: bool = False, non_negative: bool = False) -> float:
    value = float(value)
    if not math.isfinite(value):
        raise PhysicsInputError(f"{name} must be finite, got {value}")
    if positive and value <= 0:
        raise PhysicsInputError(f"{name} must be > 0, got {value}")
    if non_negative and value < 0:
        raise PhysicsInputError(f"{name} must be >= 0, got {value}")
    return value


@dataclass(frozen=True)
class PBFConfig:
    """Constants of one simulated scene (see the module docstring for units).

    The density constraint is one-sided, as suits a gas: only over-dense particles
    (rho > rho0) are pushed apart, and the residual the solver drives to zero is
    max(0, rho/rho0 - 1).
    """

    rho0: float = 2.0
    alpha: float = -3.0  # buoyancy: acceleration alpha * gravity (alpha < 0 lifts)
    gravity: Vec3 = (0.0, -9.8, 0.0)  # simulation units / s^2 (see length_scale)
    length_scale: float = 100.0  # simulation length units per world unit (gravity only)
    drag: float = 3.0  # k in f = -k (v - v_env) max(0, 1 - rho/rho0), 1/s
    env_velocity: Vec3 = (0.0, 0.0, 0.0)  # world units / s
    dt: float = 1.0 / 30.0  # s, one frame of the clip; each step runs substeps of it (fluidcore.physics.step.substeps)
    h: float = 0.02  # kernel radius, world units
    iterations: int = 10  # fixed solver iterations (used when tolerance is None)
    tolerance: float | None = None  # stop when the mean residual is below this
    max_iterations: int = 50  # cap when a tolerance is set
    relaxation: float = 0.1  # CFM epsilon, in units of 1/h^2
    # Tensile-instability term (artificial pressure, Macklin's k = 0.1). Off by default: with the
    # one-sided constraint lambda <= 0, particles never attract, so the clumping it cures cannot occur.
    s_corr_k: float = 0.0
    s_corr_n: int = 4
    s_corr_dq: float = 0.2  # reference distance, fraction of h
    xsph: float = 0.0  # XSPH viscosity c (0 = off)
    vorticity: float = 0.0  # vorticity-confinement epsilon, world units / s^2 per unit curl (0 = off)
    max_speed: float | None = None  # world units / s; None = h / dt (one kernel radius per step)
    max_correction: float = 0.5  # largest solver correction per iteration, fraction of h
    entrainment: float = 0.0  # the plume's spreading rate db/dz (fluidcore.physics.entrainment; 0 = off)

    def __post_init__(self) -> None:
        for name in ("rho0", "dt", "h", "length_scale", "max_correction"):
            _finite(getattr(self, name), name, positive=True)
        for name in ("drag", "relaxation", "s_corr_k", "s_corr_dq", "xsph", "vorticity", "entrainment"):
            _finite(getattr(self, name), name, non_negative=True)
        _finite(self.alpha, "alpha")
        object.__setattr__(self, "gravity", vec3(self.gravity, "gravity"))
        object.__setattr__(self, "env_velocity", vec3(self.env_velocity, "env_velocity"))
        if self.s_corr_dq >= 1.0:
            raise PhysicsInputError(f"s_corr_dq must be < 1 (a fraction of h), got {self.s_corr_dq}")
        if not isinstance(self.iterations, int) or self.iterations < 0:
            raise PhysicsInputError(f"iterations must be an integer >= 0, got {self.iterations!r}")
        if not isinstance(self.max_iterations, int) or self.max_iterations < 1:
            raise PhysicsInputError(f"max_iterations must be an integer >= 1, got {self.max_iterations!r}")
        if not isinstance(self.s_corr_n, int) or not 1 <= self.s_corr_n <= 15:
            raise PhysicsInputError(f"s_corr_n must be an integer in 1..15, got {self.s_corr_n!r}")
        if self.tolerance is not None:
            _finite(self.tolerance, "tolerance", positive=True)
        if self.max_speed is not None:
            _finite(self.max_speed, "max_speed", positive=True)

    @property
    def body_acceleration(self) -> Vec3:
        """Buoyancy in world units / s^2: alpha * gravity / length_scale."""
        s = self.alpha / self.length_scale
        return (self.gravity[0] * s, self.gravity[1] * s, self.gravity[2] * s)

    @property
    def terminal_speed(self) -> float:
        """Speed (world units / s) at which drag balances buoyancy in sparse smoke: |alpha g| / k.
        What a source's particles are launched at, so they leave the inlet as they would rise.
        Infinite without drag."""
        if self.drag == 0.0:
            return math.inf
        return math.hypot(*self.body_acceleration) / self.drag

    def inlet_capacity(self, radius: float, speed: float) -> float:
        """Particles per step a source ball of `radius` carries away at `speed` at rest density:
        n0 pi r^2 v dt, n0 = 8 rho0 / h^3 the number density at rest (density 1 = 8 per h^3)."""
        return 8.0 * self.rho0 / self.h**3 * math.pi * radius**2 * speed * self.dt

    @property
    def speed_limit(self) -> float:
        """Largest particle speed (world units / s): a particle never moves more than this * dt per step."""
        return self.max_speed if self.max_speed is not None else self.h / self.dt

    def frames_in(self, seconds: float) -> int:
        """Frames of dt in `seconds` (at least 1): a window stated in seconds, at this clip's rate."""
        return max(1, round(seconds / self.dt))

    def substep(self, count: int) -> PBFConfig:
        """This physics stepped `count` times per frame: dt / count, and with it the speed limit
        h / (dt / count) (`fluidcore.physics.step.substeps` chooses the count)."""
        return self if count == 1 else replace(self, dt=self.dt / count)

    @property
    def iteration_cap(self) -> int:
        """Most solver iterations a step may use."""
        return self.max_iterations if self.tolerance is not None else self.iterations


PRESETS: dict[str, PBFConfig] = {
    "scalarflow": PBFConfig(rho0=2.0, alpha=-3.0),
    "fluidnexus_smoke": PBFConfig(rho0=1.5, alpha=-6.0),
    "fluidnexus_ball": PBFConfig(rho0=1.5, alpha=-6.0),
}


@dataclass(frozen=True)
class Box:
    """Axis-aligned scene box (world units); particles that leave it are retired."""

    lo: Vec3
    hi: Vec3

    def __post_init__(self) -> None:
        lo, hi = vec3(self.lo, "box.lo"), vec3(self.hi, "box.hi")
        if not all(l < u for l, u in zip(lo, hi)):
            raise PhysicsInputError(f"box.lo must be below box.hi on every axis, got {list(lo)} and {list(hi)}")
        object.__setattr__(self, "lo", lo)
        object.__setattr__(self, "hi", hi)


@dataclass(frozen=True)
class Source:
    """A ball that seeds `rate` particles per step, uniformly inside it, with one velocity."""

    center: Vec3
    radius: float
    rate: int
    velocity: Vec3 = (0.0, 0.0, 0.0)
    seed: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", vec3(self.center, "source.center"))
        object.__setattr__(self, "velocity", vec3(self.velocity, "source.velocity"))
        _finite(self.radius, "source.radius", positive=True)
        if not isinstance(self.rate, int) or self.rate < 0:
            raise PhysicsInputError(f"source.rate must be an integer >= 0, got {self.rate!r}")
        if not isinstance(self.seed, int):
            raise PhysicsInputError(f"source.seed must be an integer, got {self.seed!r}")


@dataclass(frozen=True)
class Sphere:
    """A rigid ball with one-way coupling, moving at a constant velocity from `center` at time 0."""

    center: Vec3
    radius: float
    velocity: Vec3 = field(default=(0.0, 0.0, 0.0))

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", vec3(self.center, "sphere.center"))
        object.__setattr__(self, "velocity", vec3(self.velocity, "sphere.velocity"))
        _finite(self.radius, "sphere.radius", positive=True)

    def center_at(self, time: float) -> Vec3:
        """Where the centre is at `time` seconds."""
        return tuple(c + v * time for c, v in zip(self.center, self.velocity))  # type: ignore[return-value]
