"""The two-layer smoke state: physical particles (with the air around them, when the run
simulates it: `ParticleState.air`) and the visual Gaussians that ride on them, with
`Appearance`, the visual layer's per-Gaussian parameters.

Reconstruction (Algorithm S1) and prediction (S2) carry a `SmokeState` from frame to frame; a
run folder stores it as a numpy `fluidcore.runs.FrameState` (torch-free, so the API and the
exporter read runs without torch). `from_frame` / `to_frame` are the one conversion between
the two: both algorithms resume from and write the same files through it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from fluidcore.physics import AirState, ParticleState
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

    def cropped(self, lo: Sequence[float], hi: Sequence[float]) -> SmokeState:
        """Without the Gaussians outside the box [lo, hi]: the simulator retires particles that
        leave it, and a Gaussian out there would float on with nothing to carry it."""
        inside = ((self.means >= self.means.new_tensor(lo)) & (self.means <= self.means.new_tensor(hi))).all(dim=1)
        return SmokeState(self.particles, self.means[inside], self.appearance.select(inside))


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
