"""Forces and velocity filters of the smoke model: buoyancy, drag, external fields (wind),
XSPH viscosity and vorticity confinement. Masses are 1, so a force is an acceleration."""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from fluidcore.physics.config import PBFConfig, PhysicsInputError, Vec3, _finite, _vec3
from fluidcore.physics.sph import differences, pair_geometry, poly6, spiky_gradient

ForceField = Callable[[Tensor, float], Tensor]  # (positions (N, 3), time s) -> force (N, 3)

MAX_EXPONENT = 60.0  # exp(60) ~ 1e26: far past physical, still finite in float32 after scaling


def wind_force(direction: Vec3, strength: float, growth: float = 0.0, base_height: float = 0.0,
               start_time: float = 0.0, end_time: float | None = None, up: Vec3 = (0.0, 1.0, 0.0)) -> ForceField:
    """Wind: strength * direction * exp(growth * (height - base_height)) between start and end time.

    Height is measured along `up`; the direction is normalised. Before `start_time` (and from
    `end_time` on) the field is zero. The exponent is capped at MAX_EXPONENT so a large growth
    far above the source stays finite; the simulator's speed limit bounds the result.
    """
    d, u = _vec3(direction, "direction"), _vec3(up, "up")
    strength = _finite(strength, "strength", non_negative=True)
    growth, base_height = _finite(growth, "growth"), _finite(base_height, "base_height")
    start_time = _finite(start_time, "start_time")
    if end_time is not None and _finite(end_time, "end_time") <= start_time:
        raise PhysicsInputError(f"end_time ({end_time}) must be after start_time ({start_time})")
    d_norm, u_norm = math.sqrt(sum(c * c for c in d)), math.sqrt(sum(c * c for c in u))
    if d_norm < 1e-12 or u_norm < 1e-12:
        raise PhysicsInputError("direction and up must be non-zero vectors")
    unit = tuple(c / d_norm for c in d)
    up_unit = tuple(c / u_norm for c in u)

    def force(positions: Tensor, time: float) -> Tensor:
        if time < start_time or (end_time is not None and time >= end_time):
            return torch.zeros_like(positions)
        height = positions @ positions.new_tensor(up_unit)
        gain = torch.exp(torch.clamp(growth * (height - base_height), max=MAX_EXPONENT))
        return (strength * gain)[:, None] * positions.new_tensor(unit)

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
