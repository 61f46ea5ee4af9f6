"""Visual particles: the 3D Gaussians that carry the smoke's appearance.

They are born with the physical particles (a few per new physical particle, jittered around
it), move with the physical velocity field (kernel-interpolated from the physical particles,
forward Euler), and after each frame's positions are settled their scale, opacity and rotation
are fitted to the images with temporal regularisation (paper: lambda_c 10, lambda_s 0,
lambda_o 8, lambda_r 0.1, plus an anisotropy penalty that keeps splats from degenerating into
needles that only look right from the input view).

The fit is tied to the physics so that it cannot paint the input view over a wrong 3D state
(a free per-Gaussian fit was 21 dB better on the dev scene's input view than on its novel views,
docs/bench_generalise.md):
* smoke of one kind under one light has one colour: all Gaussians share the scene's smoke
  colour, one fitted parameter;
* the particles carry equal masses of smoke, so density shows through where they are: the
  opacity is the scene's one shared opacity, each Gaussian allowed `OpacityTie.spread` logits
  from it (0 by default);
* a Gaussian's extent stays between the spread of the SPH kernel that carries its particle's
  smoke and the kernel's support (`ScaleBounds`): neither a paint stroke thinner than the
  particles resolve nor a sheet wider than the particle it rides on.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

from fluidcore.render import Gaussians
from fluidcore.smoke import Appearance
from fluidcore.spec.reconstruct import LossWeights


def spawn(
    parent_rows: torch.Tensor,
    per_parent: int,
    spread: float,
    scale: float,
    opacity: float,
    color: torch.Tensor,
    generator: torch.Generator,
) -> tuple[torch.Tensor, torch.Tensor, Appearance]:
    """Visual Gaussians for newly born physical particles (rows `parent_rows` of the frame's particles).

    Returns (owner row (G,), offset from the owner (G, 3), appearance): `per_parent` round
    Gaussians per new particle, jittered by `spread` (drawn on the CPU generator, so the result
    does not depend on the device).
    """
    device = parent_rows.device
    owner = parent_rows.repeat_interleave(per_parent)
    g = len(owner)
    offsets = (torch.randn((g, 3), generator=generator) * spread).to(device)
    appearance = Appearance(
        log_scales=torch.full((g, 3), math.log(scale), device=device),
        quats=torch.tensor([1.0, 0.0, 0.0, 0.0], device=device).repeat(g, 1),
        opacity_logits=torch.full((g,), math.log(opacity / (1.0 - opacity)), device=device),
        colors=color.to(device).expand(g, -1).clone(),
    )
    return owner, offsets, appearance


def regularisation(current: Appearance, previous: Appearance, weights: LossWeights) -> torch.Tensor:
    """Temporal regularisation of the Gaussians that existed last frame (the first
    len(previous) rows of `current`), plus the anisotropy penalty on all of them."""
    n = len(previous)
    loss = current.log_scales.new_zeros(())
    if n:
        loss = loss + weights.color * (current.colors[:n] - previous.colors).pow(2).mean()
        loss = loss + weights.scale * (current.log_scales[:n] - previous.log_scales).pow(2).mean()
        loss = loss + weights.opacity * (
            torch.sigmoid(current.opacity_logits[:n]) - torch.sigmoid(previous.opacity_logits)
        ).pow(2).mean()
        q = current.quats[:n] / current.quats[:n].norm(dim=-1, keepdim=True)
        q0 = previous.quats / previous.quats.norm(dim=-1, keepdim=True)
        loss = loss + weights.rotation * (1.0 - (q * q0).sum(-1).pow(2)).mean()
    return loss + weights.anisotropy * anisotropy(current.log_scales, weights.max_anisotropy)


def anisotropy(log_scales: torch.Tensor, max_ratio: float) -> torch.Tensor:
    """Mean excess of a Gaussian's largest-to-smallest scale ratio over `max_ratio` (0 when all are rounder)."""
    if len(log_scales) == 0:
        return log_scales.new_zeros(())
    ratio = torch.exp(log_scales.max(dim=-1).values - log_scales.min(dim=-1).values)
    return torch.relu(ratio - max_ratio).mean()


@dataclass(frozen=True)
class ScaleBounds:
    """The range (world units) a visual Gaussian's standard deviation is kept in, on every axis."""

    low: float
    high: float

    def __post_init__(self) -> None:
        if not 0.0 < self.low < self.high:
            raise ValueError(f"scale bounds must satisfy 0 < low < high, got {self.low}, {self.high}")

    def log_scales(self, free: torch.Tensor) -> torch.Tensor:
        """Log-scales inside the bounds from unconstrained values (a sigmoid between the log bounds)."""
        lo, hi = math.log(self.low), math.log(self.high)
        return lo + (hi - lo) * torch.sigmoid(free)

    def free(self, log_scales: torch.Tensor) -> torch.Tensor:
        """Inverse of `log_scales`; scales at or beyond a bound start just inside it, where the
        sigmoid still passes a gradient."""
        lo, hi = math.log(self.low), math.log(self.high)
        return torch.logit(((log_scales - lo) / (hi - lo)).clamp(0.01, 0.99))


@dataclass(frozen=True)
class OpacityTie:
    """How far (in logits) a Gaussian's opacity may stray from the scene's shared opacity."""

    spread: float | None  # 0: one opacity for all; None: free per Gaussian

    def logits(self, shared: torch.Tensor, free: torch.Tensor) -> torch.Tensor:
        if self.spread is None:
            return free
        return shared + self.spread * torch.tanh(free)

    def free(self, logits: torch.Tensor, shared: torch.Tensor) -> torch.Tensor:
        """Inverse of `logits` (deviations beyond the spread start just inside it)."""
        if self.spread is None:
            return logits.clone()
        return torch.atanh(((logits - shared) / max(self.spread, 1e-6)).clamp(-0.99, 0.99))


def fit_appearance(
    means: torch.Tensor,
    appearance: Appearance,
    previous: Appearance,
    image_loss: Callable[[Gaussians, int], torch.Tensor],
    iterations: int,
    learning_rates: dict[str, float],
    weights: LossWeights,
    bounds: ScaleBounds,
    opacity: OpacityTie,
) -> tuple[Appearance, float]:
    """Adam on the shared smoke colour and opacity, and on the Gaussians' scale (within
    `bounds`), opacity (within `opacity` of the shared one) and rotation, positions fixed.

    `image_loss(gaussians, iteration)` renders one (randomly chosen) view and returns its
    weighted photometric loss. The shared colour and opacity start from the previous frame's
    means (`appearance`'s on the first frame). Returns the fitted appearance (per Gaussian, as
    the renderer and the run folder take it) and the last total loss.
    """
    start = previous if len(previous) else appearance
    color = start.colors.detach().mean(0).clone().requires_grad_(True)
    free_scales = bounds.free(appearance.log_scales.detach()).requires_grad_(True)
    shared_opacity = start.opacity_logits.detach().mean().clone().requires_grad_(True)
    free_opacity = opacity.free(appearance.opacity_logits.detach(), shared_opacity.detach()).requires_grad_(True)
    quats = appearance.quats.detach().clone().requires_grad_(True)
    optimiser = torch.optim.Adam(
        [
            {"params": [color], "lr": learning_rates["color"]},
            {"params": [free_scales], "lr": learning_rates["scale"]},
            {"params": [shared_opacity, free_opacity], "lr": learning_rates["opacity"]},
            {"params": [quats], "lr": learning_rates["rotation"]},
        ]
    )

    def current() -> Appearance:
        logits = opacity.logits(shared_opacity, free_opacity)
        return Appearance(bounds.log_scales(free_scales), quats, logits, color.expand(len(appearance), -1))

    last = float("nan")
    for k in range(iterations):
        optimiser.zero_grad(set_to_none=True)
        params = current()
        loss = image_loss(params.gaussians(means), k) + regularisation(params, previous, weights)
        loss.backward()
        optimiser.step()
        last = float(loss.detach())
    return current().detach(), last
