"""Forces and velocity filters of the smoke model: buoyancy, drag, external fields (wind),
XSPH viscosity and vorticity confinement. Masses are 1, so a force is an acceleration."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from fluidcore.physics.sph import differences, pair_geometry, poly6, spiky_gradient
from fluidcore.spec.physics import PBFConfig, Vec3

if TYPE_CHECKING:  # the edge type is only read here; physics imports nothing from the edge
    from fluidcore.spec.controls import WindParams

ForceField = Callable[[Tensor, float], Tensor]  # (positions (N, 3), time s) -> force (N, 3)
AirField = Callable[[Tensor, float], Tensor]  # (positions (N, 3), time s) -> air velocity (N, 3), world units / s


def wind_force(
    wind: WindParams, blowing: Callable[[float], bool], base_height: float = 0.0, up: Vec3 = (0.0, 1.0, 0.0)
) -> ForceField:
    """The force field of `wind`: strength * direction * gain(z), z = height above `base_height`
    along `up`, in every step whose start time `blowing(time)` accepts (gain: `wind_acceleration`).

    `wind` is the validated edge type (fluidcore.spec.controls.WindParams: unit direction, finite
    bounded strength and growth, a known profile), so nothing is checked again here; when it
    blows is the caller's clock (`fluidcore.predict.interventions` derives it from the wind's
    frame window). The simulator's speed limit bounds the result.
    """

    def force(positions: Tensor, time: float) -> Tensor:
        if not blowing(time):
            return torch.zeros_like(positions)
        return wind_acceleration(wind, positions, base_height, up)

    return force


def wind_air(
    wind: WindParams, seconds_blown: Callable[[float], float], base_height: float = 0.0, up: Vec3 = (0.0, 1.0, 0.0)
) -> AirField:
    """The velocity the wind has given the air around the smoke by `time`.

    A wind is a body force on all the air, not on the smoke alone: the air it pushes carries the
    smoke, and drag relaxes the smoke towards that moving air. With drag towards still air a
    wind of acceleration a could only ever move sparse smoke at a / k (a few cm/s here), however
    long it blew. The air's velocity is the force integrated over the time it has blown,
    `seconds_blown(time)`, up to the wind's terminal speed (`WindParams.air_speed`), and it keeps
    that velocity after the wind stops.
    """

    def air(positions: Tensor, time: float) -> Tensor:
        speed = wind.air_speed(seconds_blown(time))
        if speed == 0.0:
            return torch.zeros_like(positions)
        return (speed / wind.strength) * wind_acceleration(wind, positions, base_height, up)

    return air


def wind_acceleration(wind: WindParams, positions: Tensor, base_height: float, up: Vec3) -> Tensor:
    """strength * direction * gain(z) at `positions` (N, 3), z their height above `base_height`
    (`WindParams.gain`, the one definition of each profile)."""
    norm = math.sqrt(sum(c * c for c in up))
    z = positions @ positions.new_tensor([c / norm for c in up]) - base_height
    return (wind.strength * wind.gain(z))[:, None] * positions.new_tensor(wind.direction)


def drag(velocities: Tensor, density: Tensor, config: PBFConfig, air: Tensor | None = None) -> Tensor:
    """Apply f = -k (v - v_env) max(0, 1 - rho/rho0) over one step; v_env is `config.env_velocity`
    plus `air` (N, 3), the velocity an external field gave the air (`wind_air`), when given.

    Integrated exactly (v_env + (v - v_env) exp(-k s dt)) rather than by Euler, so no dt or k
    can overshoot the environment velocity.
    """
    if config.drag == 0.0:
        return velocities
    env = velocities.new_tensor(config.env_velocity)
    if air is not None:
        env = env + air
    sparse = torch.clamp(1.0 - density / config.rho0, min=0.0)
    decay = torch.exp(-config.drag * config.dt * sparse)[:, None]
    return env + (velocities - env) * decay


def xsph(velocities: Tensor, positions: Tensor, i: Tensor, j: Tensor, config: PBFConfig) -> Tensor:
    """XSPH viscosity: v_i += c sum_j (v_j - v_i) W_ij (smooths the velocity field)."""
    r = differences(positions, i, j)
    w = poly6((r * r).sum(1) / (config.h * config.h))
    blend = torch.zeros_like(velocities).index_add(0, i, w[:, None] * differences(velocities, j, i))
    return velocities + config.xsph * blend


def vorticity_confinement(velocities: Tensor, positions: Tensor, i: Tensor, j: Tensor, config: PBFConfig) -> Tensor:
    """Vorticity confinement (Macklin & Mueller 2013, eq. 15-16): re-inject the swirl that
    numerical damping removes, f_i = epsilon (N_i x omega_i), N = grad|omega| / |grad|omega||."""
    q, direction, _ = pair_geometry(positions, i, j, config.h)
    grad = spiky_gradient(q, direction, config.h)  # grad_i W_ij; grad_j W_ij = -grad
    omega = torch.zeros_like(velocities).index_add(0, i, torch.cross(differences(velocities, j, i), -grad, dim=1))
    magnitude = torch.linalg.vector_norm(omega, dim=1)
    eta = torch.zeros_like(velocities).index_add(0, i, differences(magnitude, j, i)[:, None] * grad)
    normal = eta / torch.linalg.vector_norm(eta, dim=1, keepdim=True).clamp_min(1e-12)
    return velocities + config.dt * config.vorticity * torch.cross(normal, omega, dim=1)
