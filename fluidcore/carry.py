"""The per-frame carry both algorithms share: one simulator step, and the visual layer moved
along with it.

Reconstruction (Algorithm S1, fluidcore.reconstruct.loop) fits the carried frame to the images
before it keeps it; prediction (Algorithm S2, fluidcore.predict.rollout) keeps it as it is. Both
start from `carry`: the physical state stepped by the scene's motion model under the step's
controls, the particles born in the step found (a state keeps each particle's slot for life),
the Gaussians born with them (the caller says how they look), and the `PositionProblem` that
moves the visual layer: old Gaussians ride on the kernel-interpolated velocity
u_t = (p_t - p_{t-1}) / dt of the physical particles (`visual_means`, forward Euler), new ones
sit at their parent particle plus a fixed offset. A prediction therefore continues a
reconstruction without a visual jump.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from fluidcore.physics import ParticleState, Simulator, StepStats
from fluidcore.physics.motion import NO_CONTROLS, Controls
from fluidcore.physics.neighbours import neighbour_pairs
from fluidcore.physics.sph import poly6
from fluidcore.smoke import Appearance, SmokeState

# (rows of the particles born this frame among the frame's live particles (B,)) ->
#   (owner row (G,), offset from the owner (G, 3), appearance of G new Gaussians)
Births = Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor, Appearance]]


class FixedInterpolation:
    """`fluidcore.physics.interpolate_velocity` for query points and particles that stay put.

    During a frame the visual Gaussians at t-1 (queries) and the particles at t-1 (kernel
    centres) are fixed; only the velocities change (the position fit moves them). The normalised
    Poly6 weights are therefore computed once per frame and each evaluation is a single scatter
    (same Shepard average, zero velocity where no particle is within the radius).
    """

    def __init__(self, query: torch.Tensor, positions: torch.Tensor, radius: float) -> None:
        self.n = query.shape[0]
        self.qi, self.pj = neighbour_pairs(query, positions, radius)
        r = query[self.qi] - positions[self.pj]
        w = poly6((r * r).sum(1) / (radius * radius))
        total = torch.zeros(self.n, dtype=query.dtype, device=query.device).index_add(0, self.qi, w)
        self.w = (w / total.clamp_min(1e-12)[self.qi])[:, None]

    def __call__(self, velocities: torch.Tensor) -> torch.Tensor:
        out = velocities.new_zeros((self.n, 3))
        return out.index_add(0, self.qi, self.w * velocities[self.pj])


@dataclass
class PositionProblem:
    """One frame's physical positions and the visual layer that rides on them; rows of the
    particle tensors are the frame's live particles."""

    p_prev: torch.Tensor  # (N, 3) positions at t-1 (particles born this frame: p_sim - dt * v_sim)
    p_sim: torch.Tensor  # (N, 3) the simulator's prediction for t
    v_sim: torch.Tensor  # (N, 3) the simulator's velocities for t
    visual_prev: torch.Tensor  # (G_old, 3) visual Gaussians at t-1
    owner: torch.Tensor  # (G_new,) parent particle (row) of each Gaussian born this frame
    offsets: torch.Tensor  # (G_new, 3) its fixed offset from the parent
    velocity_radius: float  # kernel radius of the velocity interpolation (world units)

    def __post_init__(self) -> None:
        self.interpolate = FixedInterpolation(self.visual_prev, self.p_prev, self.velocity_radius)


def visual_means(p: torch.Tensor, problem: PositionProblem, dt: float) -> torch.Tensor:
    """(G, 3) where the visual Gaussians are at t, given physical positions p_t (N, 3)
    (differentiable in p): the old ones moved by the interpolated u_t = (p_t - p_{t-1}) / dt,
    then the newborn ones at their parents.

    The interpolation radius is a few kernel radii rather than h itself, so that Gaussians
    between sparse physical particles (preview quality) still move with the flow."""
    parts = []
    if len(problem.visual_prev):
        parts.append(problem.visual_prev + dt * problem.interpolate((p - problem.p_prev) / dt))
    parts.append(p[problem.owner] + problem.offsets)
    return torch.cat(parts)


@dataclass(frozen=True)
class Carried:
    """A frame carried forward, before the visual layer is placed: the stepped physical `state`,
    its live `slots` (the rows of `problem`), the frame's `PositionProblem`, the appearance of the
    Gaussians carried over (`old`) and of those born this frame (`newborn`), and what the step
    did (None for the first frame, which is not stepped)."""

    state: ParticleState
    slots: torch.Tensor  # (N,) long
    problem: PositionProblem
    old: Appearance
    newborn: Appearance
    step: StepStats | None

    @property
    def appearance(self) -> Appearance:
        """Every Gaussian's appearance, in the order `visual_means` places them."""
        return self.old.cat(self.newborn)


def carry(smoke: SmokeState, simulator: Simulator, births: Births, velocity_radius: float, *,
          controls: Controls = NO_CONTROLS, first: bool = False) -> Carried:
    """Step `smoke` one frame under `controls` (module docstring); `births` makes the Gaussians of
    the particles born in the step. `first`: the frame is `smoke` itself, not stepped, every
    particle newborn (a reconstruction's first frame, from the stabilised source)."""
    before = smoke.particles
    state, step = (before.clone(), None) if first else simulator.step(before, controls)
    dt = simulator.config.dt
    previous = before.padded(state.capacity)
    newborn = state.alive.clone() if first else state.alive & ~previous.alive
    slots = torch.nonzero(state.alive).flatten()
    p_sim, v_sim = state.positions[slots], state.velocities[slots]
    born = newborn[slots]
    p_prev = torch.where(born[:, None], p_sim - dt * v_sim, previous.positions[slots])
    owner, offsets, appearance = births(torch.nonzero(born).flatten())
    problem = PositionProblem(p_prev, p_sim, v_sim, smoke.means, owner.to(state.device), offsets.to(state.device),
                              velocity_radius)
    return Carried(state, slots, problem, smoke.appearance, appearance, step)
