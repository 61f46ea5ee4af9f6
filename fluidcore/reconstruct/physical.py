"""Physical particles of one frame: positions fitted to the images under the motion model's prior.

Algorithm S1, position step: starting from p_sim = Sim(p_{t-1}) (the carried frame,
`fluidcore.carry`), Adam moves p_t to minimise

    the motion model's own terms (`Integrator.fit_terms`): for both models
        w_sim * mean(|p_t - p_sim|^2) / h^2          stay close to what physics predicts
        w_incomp * L_incomp(p_t)                       no over-dense clumps now
      and for the paper's particles, optionally,
        w_next * L_incomp(Sim(p_t, u_t))               ... nor one step later (costly)
  + w_flow * L_flow(p_t)                           keep up with the input video's optical flow in
                                                   the image plane (optional; reconstruct/flow.py)
  + the image loss of the visual Gaussians, which ride on the implied velocity
    u_t = (p_t - p_{t-1}) / dt (`fluidcore.carry.visual_means`).
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from fluidcore.carry import PositionProblem, visual_means
from fluidcore.physics.motion import Integrator
from fluidcore.render import Gaussians
from fluidcore.smoke import Appearance
from fluidcore.spec.reconstruct import LossWeights


def fit_positions(
    problem: PositionProblem,
    appearance: Appearance,
    image_loss: Callable[[Gaussians, int], torch.Tensor],
    model: Integrator,
    weights: LossWeights,
    iterations: int,
    learning_rate: float,
    next_step: bool,
    flow: Callable[[torch.Tensor], torch.Tensor] | None = None,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Adam on p_t (see the module docstring); `model` is the scene's motion model, whose terms
    join the image's; `flow` is L_flow (a `FlowObservation`), None without one. Returns p_t and
    the last iteration's loss terms."""
    config = model.config
    p = problem.p_sim.detach().clone().requires_grad_(True)
    optimiser = torch.optim.Adam([p], lr=learning_rate * config.h)
    frozen = appearance.detach()
    terms: dict[str, torch.Tensor] = {}
    for k in range(iterations):
        optimiser.zero_grad(set_to_none=True)
        terms = {
            "image": image_loss(frozen.gaussians(visual_means(p, problem, config.dt)), k),
            **model.fit_terms(p, problem.p_sim, problem.p_prev, weights, next_step),
        }
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
