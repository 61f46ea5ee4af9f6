"""Entrainment: the turbulent spreading of a plume that neither the particles nor a coarse air
grid resolve.

A buoyant plume draws the still air around it into itself and widens as it rises: its radius
grows linearly with height, db/dz = 6/5 alpha_e (Morton, Taylor & Turner 1956), for an
entrainment coefficient alpha_e of about 0.1 in laboratory plumes with Gaussian profiles, so
about 0.12 (`PBFConfig.entrainment` holds db/dz). The smoke is a marker of the plume's fluid, so
it spreads with it. Without this the model's plume is a column: PBF's density constraint only
pushes particles apart where they are over-dense (at the source), buoyancy and drag only move
them up, and the air grid (`fluidcore.physics.air`), at a few cells across the plume, is a
narrow jet over it (docs/bench_generalise.md: its horizontal speeds are millimetres a second).

The closure, per step: the live particles are cut into horizontal slabs one kernel radius h
thick along up; each slab's centre (mean horizontal position), mean velocity (its rise speed w
the part along up, at least 0) and size b (rms offset from the centre across that velocity) are
taken, and every particle is moved outward by dt x rate x w x r / b, r its offset from the
slab's centre across the slab's mean flow (horizontal when the plume rises straight). Each
slab's rms radius then grows at rate x w, that is by `rate` per unit of height risen: MTT's
linear spreading, self-similar (the profile's shape is kept, only stretched). It is a
displacement, not a velocity: it does not accumulate in the particles' momentum (drag would
have to undo it every step), and the visual Gaussians, which ride on the particles'
displacement, spread with it.

The slabs are along up, not along a plume's own axis: a plume bent by a wind spreads by its
vertical speed only, an underestimate where it runs sideways.
"""

from __future__ import annotations

import torch
from torch import Tensor

from fluidcore.spec.physics import PBFConfig

MAX_SLABS = 4096  # a slab per kernel radius; a scene taller than 4096 h is cut into coarser slabs


def spread(positions: Tensor, velocities: Tensor, config: PBFConfig) -> Tensor:
    """`positions` (N, 3) moved outward by one step of entrainment at `config.entrainment`
    (db/dz), with `velocities` (N, 3) giving each slab's rise speed; unchanged when it is 0
    or there are fewer than two particles. Differentiable in both."""
    rate = config.entrainment
    if rate == 0.0 or positions.shape[0] < 2:
        return positions
    up = -positions.new_tensor(config.gravity)
    up = up / torch.linalg.vector_norm(up).clamp_min(1e-30)
    level = positions @ up
    height = level.detach()
    low, span = height.min(), float(height.max() - height.min())
    thickness = max(config.h, span / MAX_SLABS)
    slab = ((height - low) / thickness).long().clamp(0, MAX_SLABS - 1)
    count = torch.bincount(slab).to(positions.dtype).clamp_min(1.0)

    def slab_mean(values: Tensor) -> Tensor:
        """Mean over each slab of per-particle `values` (N,) or (N, 3)."""
        total = values.new_zeros((count.shape[0], *values.shape[1:])).index_add(0, slab, values)
        return total / count.view(-1, *([1] * (values.dim() - 1)))

    across = positions - level[:, None] * up  # the horizontal part
    flow = slab_mean(velocities)
    axis = flow / torch.linalg.vector_norm(flow, dim=1, keepdim=True).clamp_min(1e-12)
    offset = across - slab_mean(across)[slab]
    offset = offset - (offset * axis[slab]).sum(1, keepdim=True) * axis[slab]  # across the slab's flow only
    size = torch.sqrt(slab_mean((offset * offset).sum(1)) + (1e-6 * config.h) ** 2)
    rise = (flow @ up).clamp_min(0.0)
    return positions + (config.dt * rate) * (rise / size)[slab, None] * offset
