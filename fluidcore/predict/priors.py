"""Priors of Algorithm S2: what a prediction assumes beyond the physics.

    HeightProfile      the appearance height profile: smoke at a given height keeps looking the
                       way the reconstruction's last frame showed it (a stationarity prior)
    refinement_status  the seam for generative priors (`fluidcore.generative`): Algorithm S2
                       refines the rough simulated frames with a video diffusion model; until
                       that stage exists the manifest records why it was skipped

A new prior goes here, and `fluidcore.predict.job` applies it (see docs/architecture.md).
"""

from __future__ import annotations

import importlib.util
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch

from fluidcore.jobs import JobInputError
from fluidcore.smoke import Appearance, SmokeState

NO_REFINER = "skipped: no video model weights"
PROFILE_BANDS = 12  # height bands of the appearance profile newborn and rising smoke is held to
HOLD_RATE = 0.25  # fraction of a band's departure from the profile undone per frame
# Held attributes are shifted in the space they are drawn in and kept valid there: a mean of
# opacity logits is dominated by the few (nearly) opaque Gaussians of a band.
HELD_RANGE = {"colors": (0.0, 1.0), "opacities": (1e-4, 1.0 - 1e-4)}


@dataclass(frozen=True)
class HeightProfile:
    """The mean appearance of the smoke by height in the last reconstructed frame.

    Smoke thins as it rises, and the reconstruction's image fit keeps each height looking the way
    the video does: Gaussians born dark and large at the source were lightened and shrunk by the
    fit as they climbed. A simulation alone carries them up unchanged, so the plume darkens and
    widens above the source frame after frame. `hold`, once per frame, undoes HOLD_RATE of each
    band's departure from the profile's mean colour and opacity (a stationarity prior over the
    short horizons a prediction covers, relaxed so the handover is gradual), keeping each
    Gaussian's difference from its band's mean. Scales are left to the Gaussians: holding them
    too made the ScalarFlow prediction worse (docs/bench_predict.md).
    """

    edges: tuple[float, ...]  # band boundaries along `up`; heights outside go to the end bands
    up: tuple[float, float, float]
    means: dict[str, tuple[tuple[float, ...], ...]]  # attribute -> per band, per channel
    counts: tuple[int, ...]  # Gaussians per band; an empty band holds nothing

    @classmethod
    def observe(cls, visual: SmokeState, up: Sequence[float], bands: int = PROFILE_BANDS) -> HeightProfile:
        if len(visual.means) == 0:
            raise JobInputError("state: the frame to continue has no visual Gaussians to take the look of the smoke from")
        height = visual.means @ visual.means.new_tensor(up)
        edges = torch.linspace(float(height.min()), float(height.max()), bands + 1, dtype=torch.float64)
        band = _band(height, edges)
        means = {name: _band_means(value, band, bands).tolist() for name, value in _profiled(visual.appearance).items()}
        if any(not math.isfinite(x) for rows in means.values() for row in rows for x in row):
            raise FloatingPointError("appearance profile: a band mean is NaN or Inf")
        counts = tuple(torch.bincount(band, minlength=bands).tolist())
        rows = {name: tuple(tuple(row) for row in value) for name, value in means.items()}
        return cls(tuple(edges.tolist()), (float(up[0]), float(up[1]), float(up[2])), rows, counts)

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> HeightProfile:
        means = {k: tuple(map(tuple, v)) for k, v in data["means"].items()}
        return cls(tuple(data["edges"]), tuple(data["up"]), means, tuple(data["counts"]))

    def to_json(self) -> dict[str, Any]:
        means = {k: [list(row) for row in v] for k, v in self.means.items()}
        return {"edges": list(self.edges), "up": list(self.up), "means": means, "counts": list(self.counts)}

    def hold(self, visual: SmokeState) -> SmokeState:
        """`visual` with each band's mean appearance moved HOLD_RATE of the way to the profile's."""
        if len(visual.means) == 0:
            return visual
        bands = len(self.edges) - 1
        band = _band(visual.means @ visual.means.new_tensor(self.up), torch.tensor(self.edges, dtype=torch.float64))
        present = visual.means.new_tensor(self.counts)[band] > 0
        held = {}
        for name, value in _profiled(visual.appearance).items():
            target = value.new_tensor(self.means[name])
            shift = HOLD_RATE * (target - _band_means(value, band, bands))[band]
            held[name] = (value + torch.where(present[:, None], shift, torch.zeros_like(shift))).clamp(*HELD_RANGE[name])
        a = visual.appearance
        opacity_logits = torch.logit(held["opacities"][:, 0])
        return visual.with_visual(visual.means, Appearance(a.log_scales, a.quats, opacity_logits, held["colors"]))


def _profiled(appearance: Appearance) -> dict[str, torch.Tensor]:
    """The attributes a height profile holds, each as (G, channels)."""
    return {"colors": appearance.colors, "opacities": torch.sigmoid(appearance.opacity_logits)[:, None]}


def _band(height: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    inner = edges[1:-1].to(height)
    return torch.bucketize(height, inner)


def _band_means(value: torch.Tensor, band: torch.Tensor, bands: int) -> torch.Tensor:
    """Mean of `value` (G, C) per band; an empty band's mean is 0 (callers never use it)."""
    sums = value.new_zeros(bands, value.shape[1]).index_add_(0, band, value)
    counts = torch.bincount(band, minlength=bands).clamp(min=1).to(value)
    return sums / counts[:, None]


def refinement_status() -> str:
    """What became of Algorithm S2's refinement step for a run written now.

    The seam for `fluidcore.generative`: once that stage provides a video model with weights,
    this is where the rough renders of the new frames are refined and reconstructed again.
    """
    if importlib.util.find_spec("fluidcore.generative") is None:
        return NO_REFINER
    return "skipped: fluidcore.generative has no video refinement step yet"
