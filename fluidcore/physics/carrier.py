"""The buoyant-air carrier: the smoke's motion is the air's, on a grid; the particles are markers
of the smoke it carries.

Why: the paper's particles (`fluidcore.physics.paper`) carry their own buoyancy, and their drag
acts only where they are sparser than the rest density, so their dense core rises on its own
whatever the air does; no setting of their constants fits the images and the velocities
together. Run forward from the true source of dev scenes D and F, buoyant air carrying marker
particles put the plume's head within 1 cm where the particles were 6-9 cm off, halved the
velocity error at frame 45 and moved the change a ball makes twice as much the right way
(../shared/notes/motion_ceiling.md). This is the Boussinesq smoke model of grid solvers
(Fedkiw, Stam & Jensen 2001; PhiFlow, which made the dev scenes, and ScalarFlow's
reconstructions use it), with the density carried by particles instead of a grid.

One part of a frame (dt), from time t:

  1. the smoke's concentration c on the cells: the live particles splatted trilinearly, each
     carrying the smoke volume its share of the inlet's flux brings in (`concentration`: c = 1
     is smoke as dense as it leaves the source);
  2. the air (`fluidcore.physics.air.AirGrid`): self-advection; buoyancy b c along up (b the
     scene's `PBFConfig.body_acceleration`, world units / s^2 at c = 1, identified from the
     video), the wind (`Controls.force`, on the air only: the particles are markers) and the
     optional vorticity confinement; the inflow (`_inflow`: the air inside the source ball
     blended towards the source's velocity, the momentum the inlet puts in); the eddy
     viscosity (`Air.viscosity`, world units^2 / s); the projection, with the floor and the
     balls (`Controls.spheres`) as walls, so the flow goes around a ball before the smoke
     arrives;
  3. the markers move with the new air by the midpoint rule (second order), then down the
     smoke's concentration gradient by its turbulent diffusivity (`Air.diffusivity`: the mixing
     the grid does not resolve, `_diffused`), are pushed out of the balls, and take the air's
     velocity where they end; those outside the box retire.

No PBF density solve runs: markers in a divergence-free flow keep their spacing up to the
interpolation's error, and the fit keeps PBF's spacing as a position-only term (`fit_terms`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from fluidcore.physics import checks
import torch.nn.functional as F

from fluidcore.physics.air import AirGrid, AirState, floor_face, sample, splat
from fluidcore.physics.coupling import push_out
from fluidcore.physics.functional import incompressibility_loss
from fluidcore.physics.motion import Controls, Integrator, PartStats
from fluidcore.physics.simulator import up_of
from fluidcore.physics.step import cap_length
from fluidcore.physics.state import ParticleState
from fluidcore.spec.physics import Box, PBFConfig, PhysicsInputError, Source
from fluidcore.spec.reconstruct import LossWeights

# Parts a frame is stepped in: the fastest air moves at most CFL_CELLS cells a part. Semi-Lagrangian
# advection is stable at any step; the bound keeps the markers' midpoint rule and the inflow's
# blending accurate. Two cells: one part per frame at 30 fps on the dev scenes (air up to 0.6 m/s,
# cells of 1.6 cm), three at 10 fps.
CFL_CELLS = 2.0
MAX_PARTS = 16  # bounds a frame's work, as the paper model's MAX_SUBSTEPS
# The air's speed is capped at this many cells a part (the parts keep it within CFL_CELLS): a runaway
# force stays finite and a semi-Lagrangian trace stays near its face. In cells per part, not the
# particles' speed limit (a kernel radius per part), so the cap scales with the parts and a clip's
# frame rate does not change the physics: with the kernel radius's limit the same plume rose 0.67x
# as high at 15 fps as at 30 (tests/fluidcore/physics/test_carrier.py).
SPEED_CAP_CELLS = 2.0 * CFL_CELLS
# The eddy viscosity a scene's air is given, a declared prior (the grid resolves neither the plume's
# turbulence nor the mixing it causes): nu = EDDY_COEFFICIENT x the inflow's speed x the source's
# radius, a mixing-length closure on the plume's own scales (so it means the same in any unit and
# at any frame rate). Forward from the true source of dev scene D (b 0.7, 48 cells), the velocity
# error at frames 45 / 89 went from 0.51 / 0.76 without it to 0.50 / 0.70 at 0.06 (nu = 6e-4 m^2/s).
EDDY_COEFFICIENT = 0.06
# The smoke's turbulent diffusivity against that viscosity: D = nu / TURBULENT_SCHMIDT. Forward from
# the true sources of D and F, without it the markers' plume was 0.3-0.6 as wide as the truth's smoke
# (rms radius per height band, frames 45 and 89); at Schmidt 2 (D = 3e-4 m^2/s) 0.5-1.0, the velocity
# error the same (D 0.50 / 0.73, F 0.54 / 0.63 at frames 45 / 89); at 1, 0.9-1.2 wide, the velocity
# and the head worse (D 0.52 / 0.76, head 9 cm low at frame 89).
TURBULENT_SCHMIDT = 2.0
DIFFUSION_FLOOR = 0.05  # concentration (of the inlet's) below which the diffusion velocity stops growing


def eddy_viscosity(inflow_speed: float, source_radius: float) -> float:
    """The air's eddy viscosity (world units^2 / s) for a source of this inflow speed and radius."""
    return EDDY_COEFFICIENT * abs(inflow_speed) * source_radius


def eddy_diffusivity(viscosity: float) -> float:
    """The smoke's turbulent diffusivity (world units^2 / s) in air of this eddy viscosity."""
    return viscosity / TURBULENT_SCHMIDT


class BuoyantAirCarrier(Integrator):
    """Buoyant air carrying the smoke (module docstring) on `air`, with the eddy viscosity
    `viscosity` (world units^2 / s). Its source must blow (a velocity > 0): the smoke's
    concentration is what the inlet's flux brings in."""

    name = "carrier"

    def __init__(self, config: PBFConfig, box: Box, source: Source | None, device: torch.device, air: AirGrid,
                 viscosity: float = 0.0, diffusivity: float = 0.0) -> None:
        if not isinstance(air, AirGrid):
            raise PhysicsInputError(f"air must be an AirGrid (the carrier is the air), got {type(air).__name__}")
        if air.floor != floor_face(config.gravity):
            raise PhysicsInputError(f"air.down must point through the box face gravity {list(config.gravity)} points "
                                    f"through (axis {floor_face(config.gravity)[0]})")
        for value, name in ((viscosity, "viscosity"), (diffusivity, "diffusivity")):
            if not (isinstance(value, (int, float)) and 0.0 <= value < math.inf):
                raise PhysicsInputError(f"{name} must be a finite number >= 0, got {value!r}")
        if source is not None and source.rate > 0 and math.hypot(*source.velocity) == 0.0:
            raise PhysicsInputError("source.velocity must not be 0 for the carrier: the smoke it seeds is the air its inlet blows in")
        super().__init__(config, box, source, device)
        self.air, self.viscosity, self.diffusivity = air, float(viscosity), float(diffusivity)
        self.up = torch.tensor(up_of(config), device=device)
        self._inlet = None if source is None or source.rate == 0 else self._inlet_mask(source)

    def parts(self, state: ParticleState, inflow: Tensor) -> int:
        fastest = float(inflow.norm(dim=1).max()) if inflow.shape[0] else 0.0
        if state.air is not None:
            fastest = max(fastest, max(float(f.abs().max()) for f in state.air.faces))
        fastest += math.hypot(*self.config.body_acceleration) * self.config.dt
        if not math.isfinite(fastest):
            raise PhysicsInputError(f"the air's speed must be finite, got {fastest}")
        return int(min(max(math.ceil(fastest * self.config.dt / (CFL_CELLS * self.air.spacing)), 1), MAX_PARTS))

    def advance(self, state: ParticleState, controls: Controls, config: PBFConfig) -> PartStats:
        grid, dt = self.air, config.dt
        if state.air is None:
            state.air = grid.still(state.device)
        air = grid.check(state.air)
        slots = torch.nonzero(state.alive).flatten()
        x = checks.points(state.positions[slots], "state.positions")
        with torch.no_grad():
            lift = self.concentration(x)[None] * (self.buoyancy * self.up)[:, None, None, None]
            grid.advect(air, dt)
            grid.accelerate(air, dt, SPEED_CAP_CELLS * grid.spacing / dt, cells=lift, force=controls.force,
                            terminal_time=controls.terminal_time, time=state.time)
            self._inflow(air)
            grid.diffuse(air, self.viscosity, dt)
            projected = grid.project(air, controls.spheres, state.time + dt)
            moved = x + dt * grid.velocity_at(air, x + 0.5 * dt * grid.velocity_at(air, x))
            moved = self._diffused(moved, dt)
            if controls.spheres:
                moved, _ = push_out(moved, controls.spheres, state.time + dt)
        state.positions[slots] = checks.finite_result(moved, "marker positions")
        state.velocities[slots] = grid.velocity_at(air, moved)
        return PartStats(self.retire(state, slots), projected.converged, projected.divergence_after)

    @property
    def buoyancy(self) -> float:
        """b: the air's acceleration along up where the smoke is as dense as at the inlet."""
        return float(torch.dot(self.up.cpu(), torch.tensor(self.config.body_acceleration)))

    def concentration(self, markers: Tensor) -> Tensor:
        """(nx, ny, nz) the smoke's concentration on the cells from the markers (M, 3): each
        carries the smoke volume pi r^2 v dt / rate that its share of the inlet's flux brings in
        (1 = as dense as it leaves the source), splatted trilinearly."""
        grid = self.air
        if markers.shape[0] == 0 or self.source is None or self.source.rate == 0:
            return torch.zeros(grid.shape, device=markers.device)
        counts = splat(grid.grid_coords(markers) - 0.5, grid.shape)
        return counts * (self.marker_volume / grid.spacing**3)

    @property
    def marker_volume(self) -> float:
        """The smoke volume one marker carries at concentration 1 (world units^3)."""
        source = self.source
        assert source is not None
        flux = math.pi * source.radius**2 * math.hypot(*source.velocity)  # volume per second
        return flux * self.config.dt / source.rate

    def _diffused(self, markers: Tensor, dt: float) -> Tensor:
        """The markers (M, 3) moved over `dt` by the smoke's turbulent diffusion: the diffusion
        velocity -D grad(c) / (c + DIFFUSION_FLOOR) of the concentration c (smoothed over a cell's
        neighbours), capped at half a cell a part. Deterministic, so the markers, and the visual
        Gaussians riding on them, spread as the smoke does without jittering."""
        if self.diffusivity == 0.0 or markers.shape[0] == 0:
            return markers
        grid = self.air
        c = F.avg_pool3d(self.concentration(markers)[None, None], 3, 1, 1, count_include_pad=False)[0, 0]
        gradient = torch.stack(torch.gradient(c, spacing=grid.spacing))
        drift = -self.diffusivity * gradient / (c + DIFFUSION_FLOOR)[None]
        at = grid.grid_coords(markers) - 0.5
        velocity = torch.stack([sample(drift[k], at) for k in range(3)], dim=1)
        return markers + dt * cap_length(velocity, 0.5 * grid.spacing / dt)

    def _inflow(self, air: AirState) -> None:
        """Blend the faces inside the source ball towards the source's velocity, in place (weight
        1 a cell inside its surface, falling to 0 a cell outside: the inlet's momentum)."""
        if self._inlet is None:
            return
        target = self.source.velocity  # type: ignore[union-attr]
        air.faces = tuple(f * (1.0 - m) + m * float(v)  # type: ignore[assignment]
                          for f, m, v in zip(air.faces, self._inlet, target, strict=True))

    def _inlet_mask(self, source: Source) -> tuple[Tensor, Tensor, Tensor]:
        """Per face component, the weight of the inlet at each face (`_inflow`)."""
        grid, centre = self.air, torch.tensor(source.center, device=self.device)
        masks = []
        for a in range(3):
            distance = torch.linalg.vector_norm(grid.face_positions(a, self.device) - centre, dim=1)
            shape = [n + (b == a) for b, n in enumerate(grid.shape)]
            masks.append((1.0 - (distance - source.radius) / grid.spacing).clamp(0.0, 1.0).view(shape))
        return tuple(masks)  # type: ignore[return-value]

    def velocity_at(self, state: ParticleState, points: Tensor) -> Tensor:
        """The air's velocity at `points` (zero before the air has moved)."""
        if state.air is None:
            return torch.zeros_like(points)
        return self.air.velocity_at(state.air, points)

    def fit_terms(self, p: Tensor, p_sim: Tensor, p_prev: Tensor, weights: LossWeights,
                  next_step: bool) -> dict[str, Tensor]:
        """"sim" and, as a position-only term, PBF's spacing ("incomp": no marker piles up over
        the rest density). Nothing one step ahead: the markers have no momentum of their own."""
        terms = super().fit_terms(p, p_sim, p_prev, weights, next_step)
        terms["incomp"] = weights.incomp * incompressibility_loss(p, self.config)
        return terms

    def adopt_air(self, state: ParticleState) -> ParticleState:
        """The state's air on this grid (`AirGrid.resample`); still air where it holds none (a
        frame of the paper model)."""
        adopted = state.clone()
        adopted.air = self.air.still(state.device) if state.air is None else self.air.resample(state.air)
        return adopted

