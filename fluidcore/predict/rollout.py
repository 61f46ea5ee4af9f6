"""The rollout of Algorithm S2: a smoke state stepped forward by physics, one frame per call.

Every new frame costs one simulator step, carried exactly as during reconstruction
(`fluidcore.carry`: the visual Gaussians ride on the physical particles' displacement), so a
prediction continues the reconstruction without a visual jump; the step's controls (a wind, a
ball from its first frame) are passed with it (`fluidcore.predict.interventions`). Gaussians are born with every new physical particle and take the fitted
appearance of the reconstruction's Gaussians nearest the source (`source_template`), because
newborn smoke should look like the smoke the video showed coming out of it. With
`opacity_concentration` (the reconstruction's `ReconstructConfig.visual.opacity_concentration`) each Gaussian
follows the concentration of the smoke it carries from frame to frame, instead of keeping the
opacity and extent last fitted (`fluidcore.smoke.Appearance.diluted`: smoke that spreads
thins and widens, its mass kept). A ball (the what-if's, or one of the scene's solids) pushes the
visual Gaussians out of itself as it does the physical particles. All randomness is a function
of (seed, frame), so a resumed rollout computes what an uninterrupted one does.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import torch

from fluidcore.carry import carry, visual_means
from fluidcore.jobs import JobInputError
from fluidcore.physics import PBFConfig, Simulator, Source, StepStats
from fluidcore.physics.coupling import push_out
from fluidcore.predict.interventions import Interventions
from fluidcore.predict.priors import HeightProfile
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
        interventions: Interventions = Interventions(),
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
        self.interventions = interventions
        self.profile = profile
        self.opacity_concentration = opacity_concentration

    def advance(self, smoke: SmokeState, index: int, t: int) -> tuple[SmokeState, StepStats]:
        """New frame `index` (0 = the first new one; video frame `t`): `smoke` stepped one frame
        under that frame's controls, with the visual layer moved along with it, and what the step
        did (`fluidcore.physics.step_record` makes it a frame's record)."""
        sim, dt = self.simulator, self.simulator.config.dt
        controls = self.interventions.controls(index)
        carried = carry(smoke, sim, lambda rows: self._births(rows, t), self.velocity_radius, controls=controls)
        state, problem = carried.state, carried.problem
        means = visual_means(problem.p_sim, problem, dt)
        means, _ = push_out(means, sim.with_solids(controls).spheres, state.time)  # the scene's solids, the what-if's ball
        if not bool(torch.isfinite(means).all()):
            raise FloatingPointError(f"visual Gaussians became NaN or Inf at frame {t}")
        old = carried.old
        if self.opacity_concentration:
            n, radius, before = len(smoke.means), self.velocity_radius, smoke.particles
            then = concentration(smoke.means, before.positions[before.alive], radius, sim.config)
            old = old.diluted(then, concentration(means[:n], problem.p_sim, radius, sim.config))
        appearance = old.cat(carried.newborn)
        moved = SmokeState(state, means, appearance).cropped(sim.box.lo, sim.box.hi)
        assert carried.step is not None
        return (moved if self.profile is None else self.profile.hold(moved, dt)), carried.step

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
