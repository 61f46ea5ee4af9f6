"""Particle seeding: a source ball emits `rate` particles per step, uniformly inside it.

The draw for step k depends only on (seed, k), through a CPU torch.Generator, so a run is
reproducible on any device and a resumed or re-simulated run seeds exactly the same particles.
"""

from __future__ import annotations

import torch
from torch import Tensor

from fluidcore.spec.physics import Source

_STEP_STRIDE = 1_000_003  # a prime: (seed, step) -> distinct generator seeds for any realistic run


def emit(source: Source, step: int, device: torch.device | str) -> tuple[Tensor, Tensor]:
    """Positions and velocities (rate, 3) of the particles born at `step`."""
    generator = torch.Generator().manual_seed(source.seed * _STEP_STRIDE + step)
    direction = torch.randn(source.rate, 3, generator=generator)
    direction = direction / torch.linalg.vector_norm(direction, dim=1, keepdim=True).clamp_min(1e-12)
    radius = source.radius * torch.rand(source.rate, 1, generator=generator) ** (1.0 / 3.0)
    positions = torch.tensor(source.center) + direction * radius
    velocities = torch.tensor(source.velocity).expand(source.rate, 3).clone()
    return positions.to(device), velocities.to(device)
