"""The two-layer smoke state: physical particles (with the air around them, when the run
simulates it: `ParticleState.air`) and the visual Gaussians that ride on them, with
`Appearance`, the visual layer's per-Gaussian parameters.

Reconstruction (Algorithm S1) and prediction (S2) carry a `SmokeState` from frame to frame; a
run folder stores it as a numpy `fluidcore.runs.FrameState` (torch-free, so the API and the
exporter read runs without torch). `from_frame` / `to_frame` are the one conversion between
the two: both algorithms resume from and write the same files through it.

`concentration` is the smoke concentration the physical particles give at any point, and
`Appearance.diluted` the one rule by which a visual Gaussian follows it: a parcel of fixed smoke
mass that expands as its smoke thins (prediction, `ReconstructConfig.visual.opacity_concentration`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from fluidcore.physics import AirState, PBFConfig, ParticleState
from fluidcore.physics.neighbours import neighbour_pairs
from fluidcore.render import Gaussians
from fluidcore.runs import FrameState, RunError, SavedAir


@dataclass
class Appearance:
    """Per-Gaussian appearance parameters in the renderer's unconstrained form."""

    log_scales: torch.Tensor  # (G, 3)
    quats: torch.Tensor  # (G, 4)
    opacity_logits: torch.Tensor  # (G,)
    colors: torch.Tensor  # (G, C), clamped to [0, 1] when drawn

    def __len__(self) -> int:
        return int(self.log_scales.shape[0])

    def detach(self) -> Appearance:
        return Appearance(*(t.detach().clone() for t in (self.log_scales, self.quats, self.opacity_logits, self.colors)))

    def cat(self, other: Appearance) -> Appearance:
        return Appearance(
            torch.cat([self.log_scales, other.log_scales]),
            torch.cat([self.quats, other.quats]),
            torch.cat([self.opacity_logits, other.opacity_logits]),
            torch.cat([self.colors, other.colors]),
        )

    def diluted(self, before: torch.Tensor, after: torch.Tensor) -> Appearance:
        """The Gaussians after the smoke they carry went from concentration `before` to `after`
        (per Gaussian), each a parcel of fixed smoke mass: its volume grows as 1/c, so its extent
        by (before / after)^(1/3) on every axis, and its optical depth -log(1 - opacity) through
        the centre (concentration x path length) by (after / before)^(2/3)."""
        ratio = (after / before).clamp(1.0 / MAX_RATIO, MAX_RATIO)
        log_scales = self.log_scales - torch.log(ratio)[:, None] / 3.0
        depth = F.softplus(self.opacity_logits) * ratio.pow(2.0 / 3.0)
        return Appearance(log_scales, self.quats, depth_logits(depth), self.colors)

    def select(self, rows: torch.Tensor) -> Appearance:
        """The Gaussians picked by `rows` (a boolean mask or indices, repeats allowed)."""
        return Appearance(self.log_scales[rows], self.quats[rows], self.opacity_logits[rows], self.colors[rows])

    def gaussians(self, means: torch.Tensor) -> Gaussians:
        return Gaussians(means, self.log_scales, self.quats, self.opacity_logits, self.colors.clamp(0.0, 1.0))


@dataclass
class SmokeState:
    """One frame of smoke: `particles` (physical layer), `means` (G, 3) world units and
    `appearance` (the visual layer's Gaussians, one row per mean)."""

    particles: ParticleState
    means: torch.Tensor
    appearance: Appearance

    @classmethod
    def start(cls, particles: ParticleState, channels: int) -> SmokeState:
        """Particles with no visual Gaussians yet (before frame 0 is fitted)."""
        device = particles.device
        empty = lambda *shape: torch.empty(*shape, device=device)  # noqa: E731
        return cls(particles, empty(0, 3), Appearance(empty(0, 3), empty(0, 4), empty(0), empty(0, channels)))

    @classmethod
    def from_frame(cls, saved: FrameState, device: str | torch.device) -> SmokeState:
        """The state a run folder holds for one frame, on `device`, ready to continue."""
        if "step" not in saved.extra:
            raise RunError("state: no extra_step (the simulator step count) to continue from")
        particles = ParticleState(
            _tensor(saved.positions, device),
            _tensor(saved.velocities, device),
            _tensor(saved.alive, device),
            saved.time,
            int(saved.extra["step"]),
            None if saved.air is None else _air_state(saved.air, device),
        )
        return cls(particles, *visual_layer(saved, device))

    def to_frame(self) -> FrameState:
        """The numpy FrameState a run stores for this frame (the inverse of `from_frame`)."""
        numpy = lambda x: x.detach().cpu().numpy()  # noqa: E731
        a = self.appearance
        return FrameState(
            positions=numpy(self.particles.positions),
            velocities=numpy(self.particles.velocities),
            alive=numpy(self.particles.alive),
            time=self.particles.time,
            gaussians={
                "means": numpy(self.means),
                "log_scales": numpy(a.log_scales),
                "quats": numpy(a.quats),
                "opacity_logits": numpy(a.opacity_logits),
                "colors": numpy(a.colors),
            },
            extra={"step": np.asarray(self.particles.step, dtype=np.int64)},
            air=None if self.particles.air is None else _saved_air(self.particles.air),
        )

    def with_visual(self, means: torch.Tensor, appearance: Appearance) -> SmokeState:
        return SmokeState(self.particles, means, appearance)

    def with_particles(self, particles: ParticleState) -> SmokeState:
        return SmokeState(particles, self.means, self.appearance)

    def cropped(self, lo: Sequence[float], hi: Sequence[float]) -> SmokeState:
        """Without the Gaussians outside the box [lo, hi]: the simulator retires particles that
        leave it, and a Gaussian out there would float on with nothing to carry it."""
        inside = ((self.means >= self.means.new_tensor(lo)) & (self.means <= self.means.new_tensor(hi))).all(dim=1)
        return SmokeState(self.particles, self.means[inside], self.appearance.select(inside))


# Optical depths are kept within [MIN_DEPTH, MAX_DEPTH]: opacity within [1e-4, 1 - 3e-7], which
# float32 still tells from 0 and 1, however far the smoke is diluted or piled up.
MIN_DEPTH = 1.0e-4
MAX_DEPTH = 15.0
# A concentration changes at most this many times over: more than the particles resolve (1 down to
# the floor of one particle's share, 0.012 for the 2 h neighbourhood at rho0 = 2, is 80 times), so
# the clamp only keeps extents and depths finite.
MAX_RATIO = 1.0e4


def depth_logits(depth: torch.Tensor) -> torch.Tensor:
    """Opacity logits of optical depths (opacity = 1 - exp(-depth)): the inverse of softplus,
    log(e^d - 1), in the form that does not overflow."""
    d = depth.clamp(MIN_DEPTH, MAX_DEPTH)
    return d + torch.log(-torch.expm1(-d))


def concentration(points: torch.Tensor, positions: torch.Tensor, radius: float, config: PBFConfig) -> torch.Tensor:
    """Smoke concentration at `points` (Q, 3): the physical particles' number density there over
    the rest number density 8 rho0 / h^3 the inlet seeds them at (fluidcore.physics: density 1 =
    8 particles per h^3), 1 = smoke as dense as it leaves the source.

    The number density is a Poly6 average over `radius` (the neighbourhood a visual Gaussian
    moves with, `VisualConfig.velocity_radius`; the PBF kernel h alone sees a preview plume's sparse
    particles one at a time). It is at least one particle's share at the kernel's centre: less
    smoke than one particle carries is not resolved, and a Gaussian no particle reaches keeps a
    finite, positive concentration.
    """
    rest = 8.0 * config.rho0 / config.h**3
    peak = 315.0 / (64.0 * math.pi * radius**3)  # Poly6 of support `radius` at r = 0, integrating to 1
    qi, pj = neighbour_pairs(points, positions, radius)
    r2 = (points.index_select(0, qi) - positions.index_select(0, pj)).pow(2).sum(1) / radius**2
    n = points.new_zeros(points.shape[0]).index_add(0, qi, peak * (1.0 - r2).clamp(min=0.0).pow(3))
    return n.clamp(min=peak) / rest


def visual_layer(saved: FrameState, device: str | torch.device) -> tuple[torch.Tensor, Appearance]:
    """The Gaussian centres and appearance of a saved frame (all a renderer needs)."""
    g = saved.gaussians
    t = lambda name: _tensor(g[name], device)  # noqa: E731
    return t("means"), Appearance(t("log_scales"), t("quats"), t("opacity_logits"), t("colors"))


def _air_state(saved: SavedAir, device: str | torch.device) -> AirState:
    return AirState(tuple(_tensor(f, device) for f in saved.faces), tuple(map(float, saved.origin)), saved.spacing)  # type: ignore[arg-type]


def _saved_air(air: AirState) -> SavedAir:
    return SavedAir(tuple(f.detach().cpu().numpy() for f in air.faces), np.asarray(air.origin, dtype=np.float64), air.spacing)  # type: ignore[arg-type]


def _tensor(array: np.ndarray, device: str | torch.device) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(array)).to(device)
