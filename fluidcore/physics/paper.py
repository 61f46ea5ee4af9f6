"""The paper's motion model as an integrator: position-based-fluid particles with their own
buoyancy and density-gated drag (Macklin & Mueller 2013 as FluidNexus uses them;
fluidcore.physics.step is one part of a frame).

The particles carry their velocities from step to step. Around them the air is still, or a
prescribed velocity (`Controls.air`, the wind's air), or, with the scene's air grid
(`fluidcore.physics.air.AirGrid`, `Scene.air.cells` > 0), an incompressible air that the
smoke's buoyancy and the wind drive and that the particles drag towards: each part then first
advances the state's air (`ParticleState.air`) from the particles. Drag only acts where the smoke
is sparser than its rest density (max(0, 1 - rho/rho0)), so a dense core rises on its own
buoyancy whatever the air does: why `fluidcore.physics.carrier` exists
(../shared/notes/motion_ceiling.md measured both).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from fluidcore.physics import checks
from fluidcore.physics.air import AirGrid, floor_face
from fluidcore.physics.functional import incompressibility_loss, sim_step
from fluidcore.physics.motion import Controls, Integrator, PartStats, StepStats, common_stats
from fluidcore.physics.solver import residual
from fluidcore.physics.state import ParticleState
from fluidcore.physics.step import BACKENDS, advance, substeps, use_fused
from fluidcore.spec.physics import Box, PBFConfig, PhysicsInputError, Source
from fluidcore.spec.reconstruct import LossWeights


@dataclass(frozen=True)
class PaperStepStats(StepStats):
    """`StepStats` with the density solve's figures: the Jacobi iterations of the frame's parts,
    and the one-sided residual max(0, rho/rho0 - 1) of the particles alive after the step,
    measured on their final positions."""

    iterations: int = 0
    mean_density_error: float = 0.0
    max_density_error: float = 0.0


class PositionBasedFluid(Integrator):
    """The paper's particles (module docstring). backend: "auto" (the fused C++ kernel on CPU
    when it builds and no gradient is needed, torch otherwise), "torch" (the reference, any
    device) or "fused" (CPU only). air: the scene's air grid, or None for still (or
    prescribed, `Controls.air`) air."""

    name = "paper"

    def __init__(self, config: PBFConfig, box: Box, source: Source | None, device: torch.device,
                 air: AirGrid | None = None, backend: str = "auto") -> None:
        if backend not in BACKENDS:
            raise PhysicsInputError(f"backend must be one of {BACKENDS}, got {backend!r}")
        if air is not None and air.floor != floor_face(config.gravity):
            raise PhysicsInputError(f"air.down must point through the box face gravity {list(config.gravity)} points "
                                    f"through (axis {floor_face(config.gravity)[0]})")
        super().__init__(config, box, source, device)
        self.air, self.backend = air, backend

    def parts(self, state: ParticleState, inflow: Tensor) -> int:
        """The CFL bound on the fastest particle (`fluidcore.physics.step.substeps`)."""
        alive = torch.nonzero(state.alive).flatten()
        return substeps(torch.cat([state.velocities[alive], inflow]), self.config)

    def advance(self, state: ParticleState, controls: Controls, config: PBFConfig) -> PartStats:
        slots = torch.nonzero(state.alive).flatten()
        x = checks.points(state.positions[slots], "state.positions")
        v = checks.points(state.velocities[slots], "state.velocities")
        converged, divergence = True, 0.0
        with torch.no_grad():
            air = controls.air
            if self.air is not None:
                if state.air is None:
                    state.air = self.air.still(state.device)
                grid, air_state = self.air, state.air
                projected = grid.step(air_state, x, config, state.time, controls.spheres, controls.force,
                                      controls.terminal_time)
                converged, divergence = projected.converged, projected.divergence_after
                air = lambda positions, _time: grid.velocity_at(air_state, positions)  # noqa: E731
            out = advance(x, v, config, time=state.time, force=controls.force, air=air, spheres=controls.spheres,
                          fast=use_fused(self.backend, x))
        state.positions[slots] = checks.finite_result(out.positions, "particle positions")
        state.velocities[slots] = checks.finite_result(out.velocities, "particle velocities")
        retired = self.retire(state, slots)
        inside = state.alive[slots]
        errors = residual(out.density[inside], config.rho0)
        return PartStats(retired, converged, divergence, {
            "iterations": float(out.iterations), "mean_density_error": float(errors.mean()) if errors.numel() else 0.0,
            "max_density_error": float(errors.max()) if errors.numel() else 0.0})

    def stats(self, parts: Sequence[PartStats], n_alive: int, seeded: int, state: ParticleState) -> PaperStepStats:
        last = parts[-1].extra if parts else {}
        return PaperStepStats(**common_stats(parts, n_alive, seeded),
                              iterations=int(sum(p.extra.get("iterations", 0.0) for p in parts)),
                              mean_density_error=last.get("mean_density_error", 0.0) if n_alive else 0.0,
                              max_density_error=last.get("max_density_error", 0.0) if n_alive else 0.0)

    def velocity_at(self, state: ParticleState, points: Tensor) -> Tensor:
        """The air's velocity where the scene simulates it, else the particles' own velocities
        averaged within 2 kernel radii (zero where no particle is near): in still air the
        particles' velocity is how the smoke moves."""
        from fluidcore.physics.functional import interpolate_velocity

        if self.air is not None and state.air is not None:
            return self.air.velocity_at(state.air, points)
        alive = state.alive
        return interpolate_velocity(points, state.positions[alive], state.velocities[alive], REPORT_RADIUS * self.config.h)

    def fit_terms(self, p: Tensor, p_sim: Tensor, p_prev: Tensor, weights: LossWeights,
                  next_step: bool) -> dict[str, Tensor]:
        """The paper's: "sim", "incomp" (L_incomp now) and, when asked, "incomp_next" (L_incomp
        one simulated step later, from u = (p - p_prev) / dt)."""
        terms = super().fit_terms(p, p_sim, p_prev, weights, next_step)
        terms["incomp"] = weights.incomp * incompressibility_loss(p, self.config)
        if next_step and weights.incomp_next > 0:
            p_next, _ = sim_step(p, (p - p_prev) / self.config.dt, self.config)
            terms["incomp_next"] = weights.incomp_next * incompressibility_loss(p_next, self.config)
        return terms

    def adopt_air(self, state: ParticleState) -> ParticleState:
        """The state's air resampled onto this model's grid (`AirGrid.resample`)."""
        if self.air is None or state.air is None:
            return state
        adopted = state.clone()
        adopted.air = self.air.resample(state.air)
        return adopted


REPORT_RADIUS = 2.0  # kernel radii: the visual Gaussians' default velocity radius (`VisualConfig.velocity_radius`)
