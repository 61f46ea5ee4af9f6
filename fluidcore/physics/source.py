"""Particle seeding: a source ball emits `rate` particles per step, uniformly inside it.

The draw for step k depends only on (seed, k), through a CPU torch.Generator, so a run is
reproducible on any device and a resumed or re-simulated run seeds exactly the same particles.
The draw is made in a frame whose +y is the scene's up and turned into the world, so a world
turned to another up axis (a +z-up Blender file of the same capture) seeds the same particles,
turned: the reconstruction of a turned scene is the original's, turned, not a re-draw.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from fluidcore.spec.physics import Source, Vec3

_STEP_STRIDE = 1_000_003  # a prime: (seed, step) -> distinct generator seeds for any realistic run


def emit(source: Source, step: int, device: torch.device | str, up: Vec3 = (0.0, 1.0, 0.0)) -> tuple[Tensor, Tensor]:
    """Positions and velocities (rate, 3) of the particles born at `step`; `up` (3,), the scene's."""
    generator = torch.Generator().manual_seed(source.seed * _STEP_STRIDE + step)
    direction = torch.randn(source.rate, 3, generator=generator) @ from_y(up).T
    direction = direction / torch.linalg.vector_norm(direction, dim=1, keepdim=True).clamp_min(1e-12)
    radius = source.radius * torch.rand(source.rate, 1, generator=generator) ** (1.0 / 3.0)
    positions = torch.tensor(source.center) + direction * radius
    velocities = torch.tensor(source.velocity).expand(source.rate, 3).clone()
    return positions.to(device), velocities.to(device)


def from_y(up: Vec3) -> Tensor:
    """The rotation (3, 3) taking +y onto the unit `up`, about the axis perpendicular to both
    (the identity for +y, so y-up scenes draw exactly as before; half a turn about x for -y)."""
    u = torch.tensor(up, dtype=torch.float32)
    u = u / torch.linalg.vector_norm(u)
    y = torch.tensor((0.0, 1.0, 0.0))
    cos = float(u @ y)
    if cos > 1.0 - 1e-7:
        return torch.eye(3)
    if cos < -1.0 + 1e-7:
        return torch.diag(torch.tensor((1.0, -1.0, -1.0)))
    axis = torch.linalg.cross(y, u)
    axis = axis / torch.linalg.vector_norm(axis)
    k = torch.tensor([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    sin = math.sqrt(max(0.0, 1.0 - cos * cos))
    return torch.eye(3) + sin * k + (1.0 - cos) * (k @ k)
