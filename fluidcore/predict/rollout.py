"""The rollout of Algorithm S2: a smoke state stepped forward by physics, one frame per call.

Every new frame costs one simulator step. The visual Gaussians ride on the physical velocity
field exactly as during reconstruction (`fluidcore.reconstruct.physical.visual_means`:
kernel-interpolated displacement, forward Euler), so a prediction continues the reconstruction
without a visual jump; Gaussians are born with every new physical particle and take the fitted
appearance of the reconstruction's Gaussians nearest the source (`source_template`), because
newborn smoke should look like the smoke the video showed coming out of it. With
`opacity_concentration` (the reconstruction's `ReconstructConfig.visual.opacity_concentration`) each Gaussian
follows the concentration of the smoke it carries from frame to frame, instead of keeping the
opacity and extent last fitted (`fluidcore.smoke.Appearance.diluted`: smoke that spreads
thins and widens, its mass kept). A ball pushes the
visual Gaussians out of itself as it does the physical particles. All randomness is a function
of (seed, frame), so a resumed rollout computes what an uninterrupted one does.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import torch

from fluidcore.jobs import JobInputError
from fluidcore.physics import PBFConfig, Simulator, Source, Sphere, StepStats
from fluidcore.physics.coupling import push_out
from fluidcore.predict.interventions import Ball
from fluidcore.predict.priors import HeightProfile
from fluidcore.reconstruct.physical import PositionProblem, visual_means
from fluidcore.smoke import Appearance, SmokeState, concentration
from fluidcore.spec.scene import Scene

TEMPLATE_SIZE = 64  # fitted Gaussians nearest the source whose appearance newborn Gaussians copy
BIRTH_SPREAD = 0.25  # jitter of a newborn Gaussian around its physical particle, in kernel radii (as in S1)


class Rollout:
    """Steps a physical state and its visual Gaussians forward together, one frame per call.

    `template` is the appearance newborn Gaussians copy (one row picked at random per birth);
    `velocity_radius` (world units) is the kernel radius of the velocity interpolation that
    carries the Gaussians (and of the concentration their opacity follows with
    `opacity_concentration`), `per_physical` how many are born per new physical particle.
    """

    def __init__(
        self,
        simulator: Simulator,
        template: Appearance,
        *,
        velocity_radius: float,
        per_physical: int,
        seed: int,
        ball: Ball | None = None,
        profile: HeightProfile | None = None,
        opacity_concentration: bool = False,
    ) -> None:
        if len(template) == 0 and per_physical > 0:
            raise JobInputError("template: no Gaussians to copy the appearance of newborn smoke from")
        self.simulator = simulator
        self.template = template
        self.velocity_radius = velocity_radius
        self.per_physical = per_physical
        self.seed = seed
        self.ball = ball
        self.profile = profile
        self.opacity_concentration = opacity_concentration
        self._static_spheres = tuple(simulator.spheres)

    def advance(self, smoke: SmokeState, index: int, t: int) -> tuple[SmokeState, StepStats]:
        """New frame `index` (0 = the first new one; video frame `t`): step `smoke.particles` in
        place and return the state with the visual layer moved along with it, and what the step
        did (`fluidcore.physics.step_record` makes it a frame's record)."""
        sim, dt, state = self.simulator, self.simulator.config.dt, smoke.particles
        sim.spheres = self._spheres(index)
        before = state.clone()
        step = sim.step(state)
        before = before.padded(state.capacity)
        slots = torch.nonzero(state.alive).flatten()
        p, v = state.positions[slots], state.velocities[slots]
        was_alive = before.alive[slots]
        p_prev = torch.where(was_alive[:, None], before.positions[slots], p - dt * v)
        owner, offsets, born = self._births(torch.nonzero(~was_alive).flatten(), t)
        problem = PositionProblem(p_prev, p, v, smoke.means, owner, offsets, self.velocity_radius)
        means = visual_means(p, problem, dt)
        if sim.spheres:
            means, _ = push_out(means, sim.spheres, state.time)
        if not bool(torch.isfinite(means).all()):
            raise FloatingPointError(f"visual Gaussians became NaN or Inf at frame {t}")
        appearance = smoke.appearance
        if self.opacity_concentration:
            n, radius = len(smoke.means), self.velocity_radius
            then = concentration(smoke.means, before.positions[before.alive], radius, sim.config)
            appearance = appearance.diluted(then, concentration(means[:n], p, radius, sim.config))
        moved = SmokeState(state, means, appearance.cat(born)).cropped(sim.box.lo, sim.box.hi)
        return (moved if self.profile is None else self.profile.hold(moved, dt)), step

    def _spheres(self, index: int) -> tuple[Sphere, ...]:
        if self.ball is None or index < self.ball.first_frame:
            return self._static_spheres
        return (*self._static_spheres, self.ball.sphere)

    def _births(self, rows: torch.Tensor, t: int) -> tuple[torch.Tensor, torch.Tensor, Appearance]:
        """Gaussians for the physical particles born this frame (`rows` of the live particles):
        owner row, offset from it, and an appearance copied from the template."""
        generator = torch.Generator().manual_seed(self.seed * 1_000_003 + t)
        owner = rows.repeat_interleave(self.per_physical)
        spread = BIRTH_SPREAD * self.simulator.config.h
        offsets = (torch.randn(len(owner), 3, generator=generator) * spread).to(rows.device)
        pick = torch.randint(max(len(self.template), 1), (len(owner),), generator=generator).to(rows.device)
        return owner, offsets, self.template.select(pick)


def source_template(visual: SmokeState, center: Sequence[float], size: int = TEMPLATE_SIZE) -> Appearance:
    """The appearance of the `size` Gaussians nearest the source centre: what newborn smoke looks like."""
    distance = torch.linalg.vector_norm(visual.means - visual.means.new_tensor(center), dim=1)
    nearest = torch.argsort(distance)[:size]
    return visual.appearance.select(nearest)


def inlet_source(source: Source, config: PBFConfig) -> Source:
    """The source, seeding no faster than its inlet carries particles away at rest density.

    A source ball of radius r whose particles leave at speed v stays at rest density when it
    seeds n0 pi r^2 v dt particles per step, n0 = 8 rho0 / h^3 being the number density at rest
    (fluidcore.physics: density 1 = 8 particles per h^3). Seeding faster piles particles up at
    the inlet: during reconstruction the image fit absorbs the excess, but a free simulation
    pushes it sideways and the plume's base widens and darkens frame after frame. The inlet
    speed is the source's velocity, or the buoyancy-drag terminal speed when that is larger.
    """
    speed = math.hypot(*source.velocity)
    if config.drag > 0:
        speed = max(speed, config.terminal_speed)
    capacity = config.inlet_capacity(source.radius, speed)
    if speed == 0.0 or source.rate <= capacity:
        return source
    return replace(source, rate=max(1, round(capacity)))


def continued_scene(scene: Scene) -> Scene:
    """The parent's scene, its source seeding at most what the inlet carries at rest density."""
    return replace(scene, source=inlet_source(scene.source, scene.physics))
