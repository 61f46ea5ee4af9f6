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
  opacity is the scene's shared opacity, one value or a coarse profile along the height
  (`OpacityTie.knots`), each Gaussian allowed `OpacityTie.spread` logits from it (0 by default);
* a Gaussian's extent stays between the spread of the SPH kernel that carries its particle's
  smoke and the kernel's support (`ScaleBounds`): neither a paint stroke thinner than the
  particles resolve nor a sheet wider than the particle it rides on.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

from fluidcore.reconstruct.presets import LossWeights
from fluidcore.render import Gaussians
from fluidcore.smoke import Appearance


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
    """How the Gaussians' opacities are tied to the scene's shared opacity.

    The shared opacity is `knots` logits evenly spaced in height along `up`, from `base` (the
    source) to `top` (the box's top), linearly interpolated at each Gaussian's height and held
    beyond the ends; one knot is one opacity for the scene. A height profile lets the fit say that
    smoke thins as it rises and mixes with air, and it is a function of height alone, so it
    shades the plume alike from every camera and cannot paint the input view. Each Gaussian may
    stray `spread` logits from the profile (0: none; None: free per Gaussian).
    """

    spread: float | None  # 0: the profile alone; None: free per Gaussian
    knots: int = 1
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)  # unit vector, world
    base: float = 0.0  # height along `up` of the first knot, world units
    top: float = 1.0  # height of the last knot

    def __post_init__(self) -> None:
        if self.knots < 1 or not self.top > self.base:
            raise ValueError(f"opacity profile: knots >= 1 and top > base, got {self.knots}, {self.base}, {self.top}")

    def weights(self, means: torch.Tensor) -> torch.Tensor:
        """(G, knots) linear-interpolation weights of each Gaussian's height (means (G, 3))."""
        if self.knots == 1:
            return means.new_ones((len(means), 1))
        height = means @ means.new_tensor(self.up)
        position = ((height - self.base) / (self.top - self.base)).clamp(0.0, 1.0) * (self.knots - 1)
        lower = position.floor().clamp(max=self.knots - 2).long()
        upper_weight = position - lower
        w = means.new_zeros((len(means), self.knots))
        w.scatter_(1, lower[:, None], (1.0 - upper_weight)[:, None])
        w.scatter_add_(1, (lower + 1)[:, None], upper_weight[:, None])
        return w

    def start(self, logits: torch.Tensor, means: torch.Tensor) -> torch.Tensor:
        """(knots,) profile to start a fit from: each knot the interpolation-weighted mean of the
        `logits` (G,) of Gaussians at `means` (G, 3); a knot none reaches takes their plain mean.
        One knot is that mean as a 0-dim tensor (the scene's one opacity, as before profiles)."""
        mean = logits.mean() if len(logits) else logits.new_zeros(())
        if self.knots == 1:
            return mean
        w = self.weights(means)
        total = w.sum(0)
        return torch.where(total > 1e-6, (w * logits[:, None]).sum(0) / total.clamp_min(1e-6), mean)

    def logits(self, shared: torch.Tensor, free: torch.Tensor, means: torch.Tensor) -> torch.Tensor:
        """(G,) the Gaussians' opacity logits from the profile `shared` (knots,) and their free
        parameters (G,) at `means` (G, 3)."""
        if self.spread is None:
            return free
        return self._at(shared, means) + self.spread * torch.tanh(free)

    def free(self, logits: torch.Tensor, shared: torch.Tensor, means: torch.Tensor) -> torch.Tensor:
        """Inverse of `logits` (deviations beyond the spread start just inside it)."""
        if self.spread is None:
            return logits.clone()
        return torch.atanh(((logits - self._at(shared, means)) / max(self.spread, 1e-6)).clamp(-0.99, 0.99))

    def _at(self, shared: torch.Tensor, means: torch.Tensor) -> torch.Tensor:
        """The profile `shared` (knots,) at `means` (G, 3): (G,), or the 0-dim one opacity as it is."""
        return shared if self.knots == 1 else self.weights(means) @ shared


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
    """Adam on the shared smoke colour and opacity profile, and on the Gaussians' scale (within
    `bounds`), opacity (within `opacity` of the profile) and rotation, positions (`means` (G, 3)) fixed.

    `image_loss(gaussians, iteration)` renders one (randomly chosen) view and returns its
    weighted photometric loss. The shared colour and opacity start from the previous frame's
    Gaussians (the first len(previous) rows of `appearance`; all of them on the first frame).
    Returns the fitted appearance (per Gaussian, as the renderer and the run folder take it)
    and the last total loss.
    """
    n = len(previous) if len(previous) else len(appearance)
    color = appearance.colors[:n].detach().mean(0).clone().requires_grad_(True)
    free_scales = bounds.free(appearance.log_scales.detach()).requires_grad_(True)
    shared_opacity = opacity.start(appearance.opacity_logits[:n].detach(), means[:n]).clone().requires_grad_(True)
    free_opacity = opacity.free(appearance.opacity_logits.detach(), shared_opacity.detach(), means).requires_grad_(True)
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
        logits = opacity.logits(shared_opacity, free_opacity, means)
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
