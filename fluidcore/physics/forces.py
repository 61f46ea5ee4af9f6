"""Forces and velocity filters of the smoke model: buoyancy, drag, external fields (wind),
XSPH viscosity and vorticity confinement. Masses are 1, so a force is an acceleration."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from fluidcore.physics.config import PBFConfig, Vec3
from fluidcore.physics.sph import differences, pair_geometry, poly6, spiky_gradient

if TYPE_CHECKING:  # the edge type is only read here; physics imports nothing from the edge
    from fluidcore.interaction import WindParams

ForceField = Callable[[Tensor, float], Tensor]  # (positions (N, 3), time s) -> force (N, 3)

MAX_EXPONENT = 60.0  # exp(60) ~ 1e26: far past physical, still finite in float32 after scaling


def wind_force(
    wind: WindParams, start_time: float, dt: float, base_height: float = 0.0, up: Vec3 = (0.0, 1.0, 0.0)
) -> ForceField:
    """The force field of `wind` (strength * direction * exp(growth * height above `base_height`,
    height along `up`), whose frame 0 is the step starting at `start_time`.

    `wind` is the validated edge type (fluidcore.interaction.WindParams: unit direction, finite
    bounded strength and growth, a frame window), so nothing is checked again here. The step
    starting at time `s` belongs to frame round((s - start_time) / dt), and the wind blows in
    it when `wind.active(frame)`: the one definition of its window, and rounding keeps a step
    in its frame despite accumulated float error in the simulator's time. The exponent is
    capped at MAX_EXPONENT so a large growth far above the source stays finite; the
    simulator's speed limit bounds the result.
    """
    norm = math.sqrt(sum(c * c for c in up))
    up_unit = tuple(c / norm for c in up)

    def force(positions: Tensor, time: float) -> Tensor:
        if not wind.active(math.floor((time - start_time) / dt + 0.5)):
            return torch.zeros_like(positions)
        height = positions @ positions.new_tensor(up_unit)
        gain = torch.exp(torch.clamp(wind.growth * (height - base_height), max=MAX_EXPONENT))
        return (wind.strength * gain)[:, None] * positions.new_tensor(wind.direction)

    return force


def drag(velocities: Tensor, density: Tensor, config: PBFConfig) -> Tensor:
    """Apply f = -k (v - v_env) max(0, 1 - rho/rho0) over one step.

    Integrated exactly (v_env + (v - v_env) exp(-k s dt)) rather than by Euler, so no dt or k
    can overshoot the environment velocity.
    """
    if config.drag == 0.0:
        return velocities
    env = velocities.new_tensor(config.env_velocity)
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
