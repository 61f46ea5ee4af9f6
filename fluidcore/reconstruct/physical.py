"""Physical particles of one frame: positions fitted to the images under the simulator's prior.

Algorithm S1, position step: starting from p_sim = Sim(p_{t-1}, u_{t-1}), Adam moves p_t to
minimise

    w_sim * mean(|p_t - p_sim|^2) / h^2          stay close to what physics predicts
  + w_incomp * L_incomp(p_t)                       no over-dense clumps now
  + w_next * L_incomp(Sim(p_t, u_t))               ... nor one step later (optional: costly)
  + w_flow * L_flow(p_t)                           keep up with the input video's optical flow in
                                                   the image plane (optional; reconstruct/flow.py)
  + the image loss of the visual Gaussians, which ride on the implied velocity
    u_t = (p_t - p_{t-1}) / dt: old Gaussians are advected by the kernel-interpolated u_t,
    Gaussians born this frame sit at their parent particle plus a fixed offset.

Squared distances are measured in kernel radii so the weight means the same in any scene unit.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from fluidcore.physics import PBFConfig, incompressibility_loss, sim_step
from fluidcore.physics.neighbours import neighbour_pairs
from fluidcore.physics.sph import poly6
from fluidcore.render import Gaussians
from fluidcore.smoke import Appearance
from fluidcore.spec.reconstruct import LossWeights


class FixedInterpolation:
    """`fluidcore.physics.interpolate_velocity` for query points and particles that stay put.

    During a frame's position fit the visual Gaussians at t-1 (queries) and the particles at
    t-1 (kernel centres) are fixed; only the velocities change. The normalised Poly6 weights
    are therefore computed once per frame and each iteration is a single scatter (same
    Shepard average, zero velocity where no particle is within the radius).
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
    """One frame's position fit; rows of the particle tensors are the frame's live particles."""

    p_prev: torch.Tensor  # (N, 3) positions at t-1 (particles born this frame: p_sim - dt * v_sim)
    p_sim: torch.Tensor  # (N, 3) the simulator's prediction for t
    v_sim: torch.Tensor  # (N, 3) the simulator's velocities for t
    visual_prev: torch.Tensor  # (G_old, 3) visual Gaussians at t-1, advected
    owner: torch.Tensor  # (G_new,) parent particle (row) of each Gaussian born this frame
    offsets: torch.Tensor  # (G_new, 3) its fixed offset from the parent
    velocity_radius: float  # kernel radius of the velocity interpolation (world units)

    def __post_init__(self) -> None:
        self.interpolate = FixedInterpolation(self.visual_prev, self.p_prev, self.velocity_radius)


def velocities(p: torch.Tensor, problem: PositionProblem, dt: float) -> torch.Tensor:
    """u_t = (p_t - p_{t-1}) / dt."""
    return (p - problem.p_prev) / dt


def visual_means(p: torch.Tensor, problem: PositionProblem, dt: float) -> torch.Tensor:
    """Where the visual Gaussians are at t, given physical positions p_t (differentiable in p).

    The interpolation radius is a few kernel radii rather than h itself, so that Gaussians
    between sparse physical particles (preview quality) still move with the flow."""
    parts = []
    if len(problem.visual_prev):
        parts.append(problem.visual_prev + dt * problem.interpolate(velocities(p, problem, dt)))
    parts.append(p[problem.owner] + problem.offsets)
    return torch.cat(parts)


def fit_positions(
    problem: PositionProblem,
    appearance: Appearance,
    image_loss: Callable[[Gaussians, int], torch.Tensor],
    config: PBFConfig,
    weights: LossWeights,
    iterations: int,
    learning_rate: float,
    next_step: bool,
    flow: Callable[[torch.Tensor], torch.Tensor] | None = None,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Adam on p_t (see the module docstring); `flow` is L_flow (a `FlowObservation`), None
    without one. Returns p_t and the last iteration's loss terms."""
    p = problem.p_sim.detach().clone().requires_grad_(True)
    optimiser = torch.optim.Adam([p], lr=learning_rate * config.h)
    frozen = appearance.detach()
    terms: dict[str, torch.Tensor] = {}
    for k in range(iterations):
        optimiser.zero_grad(set_to_none=True)
        terms = {
            "image": image_loss(frozen.gaussians(visual_means(p, problem, config.dt)), k),
            "sim": weights.sim * ((p - problem.p_sim) / config.h).pow(2).sum(-1).mean(),
            "incomp": weights.incomp * incompressibility_loss(p, config),
        }
        if next_step and weights.incomp_next > 0:
            p_next, _ = sim_step(p, velocities(p, problem, config.dt), config)
            terms["incomp_next"] = weights.incomp_next * incompressibility_loss(p_next, config)
        if flow is not None:
            terms["flow"] = weights.flow * flow(p)
        total = sum(terms.values())
        if not torch.isfinite(total):
            raise FloatingPointError(f"position fit: loss became {float(total.detach())} at iteration {k} ({_floats(terms)})")
        total.backward()
        optimiser.step()
    return p.detach(), _floats(terms)


def _floats(terms: dict[str, torch.Tensor]) -> dict[str, float]:
    return {k: float(v.detach()) for k, v in terms.items()}
