"""Priors of Algorithm S2: what a prediction assumes beyond the physics.

    HeightProfile      the appearance height profile: smoke at a given height keeps looking the
                       way the reconstruction's last frame showed it (a stationarity prior)
    refine_future      Algorithm S2's generative prior: the rough simulated frames, rendered from
                       the input camera, refined by the video model (`fluidcore.generative`) and
                       reconstructed again (Algorithm S1) from the first predicted state; without
                       video weights the manifest records why it was skipped

A new prior goes here, and `fluidcore.predict.job` applies it (see docs/architecture.md).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import torch

from fluidcore.jobs import JobContext, JobInputError
from fluidcore.runs import REFINED_RUN, AppearanceProfile, Run
from fluidcore.smoke import Appearance, SmokeState
from fluidcore.spec.scene import SourcePlace

if TYPE_CHECKING:
    from fluidcore.generative.stages import GenerativeSettings

PROFILE_BANDS = 12  # height bands of the appearance profile newborn and rising smoke is held to
HOLD_RATE = 0.25  # fraction of a band's departure from the profile undone per 1/30 s (a frame at 30 fps)
# Held attributes are shifted in the space they are drawn in and kept valid there: a mean of
# opacity logits is dominated by the few (nearly) opaque Gaussians of a band.
HELD_RANGE = {"colors": (0.0, 1.0), "opacities": (1e-4, 1.0 - 1e-4)}


class HeightProfile(AppearanceProfile):
    """The mean appearance of the smoke by height in the last reconstructed frame.

    Smoke thins as it rises, and the reconstruction's image fit keeps each height looking the way
    the video does: Gaussians born dark and large at the source were lightened and shrunk by the
    fit as they climbed. A simulation alone carries them up unchanged, so the plume darkens and
    widens above the source frame after frame. `hold`, once per frame, undoes HOLD_RATE per 1/30 s of each
    band's departure from the profile's mean colour and opacity (a stationarity prior over the
    short horizons a prediction covers, relaxed so the handover is gradual), keeping each
    Gaussian's difference from its band's mean. Scales are left to the Gaussians: holding them
    too made the ScalarFlow prediction worse (docs/bench_predict.md). Its data is the run
    record's `AppearanceProfile`, which a prediction records as it is.
    """

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
        return cls(edges=tuple(edges.tolist()), up=(float(up[0]), float(up[1]), float(up[2])), means=rows, counts=counts)

    @classmethod
    def of(cls, recorded: AppearanceProfile) -> HeightProfile:
        """The profile a run recorded (a chained prediction holds its parent's)."""
        return cls(**dict(recorded))

    def hold(self, visual: SmokeState, dt: float) -> SmokeState:
        """`visual` a frame of `dt` s later, each band's mean appearance moved towards the profile's:
        HOLD_RATE of the way per 1/30 s, compounded over the frame (the same hold in seconds at any
        frame rate)."""
        if len(visual.means) == 0:
            return visual
        bands = len(self.edges) - 1
        band = _band(visual.means @ visual.means.new_tensor(self.up), torch.tensor(self.edges, dtype=torch.float64))
        present = visual.means.new_tensor(self.counts)[band] > 0
        held = {}
        for name, value in _profiled(visual.appearance).items():
            target = value.new_tensor(self.means[name])
            shift = hold_fraction(dt) * (target - _band_means(value, band, bands))[band]
            held[name] = (value + torch.where(present[:, None], shift, torch.zeros_like(shift))).clamp(*HELD_RANGE[name])
        a = visual.appearance
        opacity_logits = torch.logit(held["opacities"][:, 0])
        return visual.with_visual(visual.means, Appearance(a.log_scales, a.quats, opacity_logits, held["colors"]))


def hold_fraction(dt: float) -> float:
    """The fraction of a band's departure undone over a frame of `dt` seconds."""
    return 1.0 - (1.0 - HOLD_RATE) ** (30.0 * dt)


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


def refine_future(run: Run, generative: GenerativeSettings | None, context: JobContext) -> str:
    """Refine the new frames of a finished prediction `run` and reconstruct on them into
    `run.path / REFINED_RUN`; returns the manifest's "refinement" line (what ran, or why not).

    The refined reconstruction fits at the quality and physics preset of the reconstruction the
    prediction started from, seeing only the input camera(s), and starts from the prediction's
    first frame. Stages: "refine futures" (per window batch), "reconstruct refined" (per frame).
    """
    from fluidcore.cameras import render_size
    from fluidcore.generative import models
    from fluidcore.generative.stages import GenerativeSettings, refine_frames
    from fluidcore.reconstruct.pipeline import Footage, reconstruct
    from fluidcore.run_frames import render_frames

    settings = generative or GenerativeSettings()
    skipped = models.skip_reason(models.VIDEO, settings.models_root)
    if skipped is not None:
        return skipped
    origin = run.reconstruction()
    if origin is None:
        return "skipped: no reconstruction among the run's parents to take the quality and physics from"
    origin_settings = origin.settings
    quality = origin_settings.quality
    cameras = run.cameras()
    rough = {}
    for name in run.input_views:
        camera = cameras[name].scaled(*render_size(cameras[name].width, cameras[name].height, quality.fit.long_side))
        rough[name] = torch.from_numpy(render_frames(run, camera, run.frames(), context.device)).float() / 255.0
    refined, status = refine_frames(rough, settings, context.device, context.batch_progress(f"refinement of {run.path}"))
    scene = run.scene
    videos = {name: _as_video(frames, run.channels) for name, frames in refined.items()}
    footage = Footage(cameras, videos, run.frame_range, run.fps, (np.asarray(scene.box_lo), np.asarray(scene.box_hi)),
                      scene.up, SourcePlace.of(scene.source), solids=scene.solids)
    first = run.frames()[0]
    reconstruct(  # the refined input views alone are the targets
        footage, quality, run.path / REFINED_RUN, physics=origin_settings.physics.mode, pseudo_views=False,
        first_state=run.read_frame(first), status={"refinement": status}, stage="reconstruct refined", context=context,
    )
    return f"{status}; reconstructed on them from frame {first} in {REFINED_RUN}/"


def _as_video(frames: torch.Tensor, channels: int) -> np.ndarray:
    """Refined (T, H, W, C) floats as the uint8 RGB video `prepare` reads; grey runs stay grey
    (the model's output can drift apart per channel)."""
    if channels == 1:
        frames = frames.mean(dim=-1, keepdim=True)
    rgb = frames.expand(-1, -1, -1, 3) if frames.shape[-1] == 1 else frames
    return (rgb.clamp(0.0, 1.0) * 255.0 + 0.5).to(torch.uint8).numpy()
