"""What a frame's fit of the input view is measured against (issue 48), recorded with the frame.

A PSNR alone does not say how much of the smoke a reconstruction reproduces: where the smoke
covers a small part of the frame, the background alone (an empty reconstruction) already
scores within a few dB of a good fit (FluidNexus-Smoke, frames 0-29 at preview: 25.6 dB
against a 29.7 dB fit). So each frame also records the background's own score on the same
frame, the share of the smoke's image energy the render explains, and where the observed smoke
sits along the scene's up as the input view sees it: the health report (`fluidcore.health`)
pools these over the clip, and checks from the last that the smoke rises along the up the
reconstruction was given. Computed where the reconstruction already renders the input view
(`fluidcore.reconstruct.loop.Reconstructor`), at its working resolution.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from fluidcore.cameras import Camera
from fluidcore.reconstruct.images import EstimationError, smoke_mask
from fluidcore.reconstruct.rays import image_up

# A frame whose smoke mask covers fewer pixels has no smoke to place (its position is left out).
MIN_SMOKE_PIXELS = 4


def psnr_db(image: torch.Tensor, target: torch.Tensor) -> float:
    """PSNR (dB, images in [0, 1]) of `image` against `target`, capped where they agree exactly."""
    mse = float((image - target).pow(2).mean())
    return 10.0 * math.log10(1.0 / max(mse, 1e-12))


def input_fit(
    image: torch.Tensor, target: torch.Tensor, background: torch.Tensor, noise: torch.Tensor, camera: Camera,
    source: Sequence[float], up: Sequence[float],
) -> dict[str, float]:
    """One frame's record of the input view: "input_psnr" (the render `image` against the
    footage `target`), "background_psnr" (the `background` alone against it: what an empty
    reconstruction scores), "explained" (1 - |image - target|^2 / |background - target|^2, the
    share of the smoke's image energy the render accounts for; left out of a frame without any),
    and "smoke_up", "smoke_across" (`smoke_position`; left out of a frame without smoke)."""
    residual = float((image - target).pow(2).sum())
    smoke_energy = float((background - target).pow(2).sum())
    record = {"input_psnr": psnr_db(image, target), "background_psnr": psnr_db(background.expand_as(target), target)}
    if smoke_energy > 0.0:
        record["explained"] = 1.0 - residual / smoke_energy
    return {**record, **smoke_position(smoke_mask(target, background, noise), camera, source, up)}


def smoke_position(mask: np.ndarray, camera: Camera, source: Sequence[float], up: Sequence[float]) -> dict[str, float]:
    """{"smoke_up", "smoke_across"}: the centroid of the smoke `mask` (H, W) from the image's
    centre, along the direction in which `up` points in the image at the `source` and across it
    (to its right), in image long sides; empty when the mask holds too little smoke or the camera
    looks along up. Over the frames, smoke that rises along `up` moves to larger "smoke_up"."""
    rows, cols = np.nonzero(mask)
    if len(rows) < MIN_SMOKE_PIXELS:
        return {}
    try:
        direction = image_up(camera, np.asarray(source, dtype=np.float64), np.asarray(up, dtype=np.float64))
    except EstimationError:
        return {}
    height, width = mask.shape
    offset = np.array([cols.mean() + 0.5 - width / 2, rows.mean() + 0.5 - height / 2]) / max(width, height)
    across = np.array([-direction[1], direction[0]])
    return {"smoke_up": float(offset @ direction), "smoke_across": float(offset @ across)}
