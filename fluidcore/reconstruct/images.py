"""The input videos as images: resizing, the background and the video's noise, and the one smoke mask.

* the background: a colour for empty space (what every novel view shows where there is no
  smoke), only when a view's background is textured a static image for that view, and the
  video's own noise per channel;
* the smoke mask of a frame: where some channel differs from the background by more than
  SMOKE_SIGMAS of that channel's noise.

Only the videos handed in are used (never a held-out view), and nothing here is tuned to a
particular clip: thresholds are in units of the image's own noise.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from fluidcore.errors import InputError

if TYPE_CHECKING:
    import torch

MAX_BACKGROUND_FRAMES = 40  # frames sampled for the per-pixel background statistic
TEXTURED_FRACTION = 0.2  # a background image is kept when this much of the view is not flat
# A pixel differs from the background (smoke, or a textured background) where some channel lies
# more than SMOKE_SIGMAS of that channel's noise away. Set from the noise statistics, not from a
# scene: Gaussian noise exceeds 5 sigma with probability 5.7e-7, so a preview frame (480 x 270
# pixels, 3 channels) shows 0.2 false smoke pixels on average.
SMOKE_SIGMAS = 5.0
# The least noise a video is taken to have, per channel: one 8-bit code value. An 8-bit video
# rounds every value to steps of 1/255 (and an mp4 codec moves values by about a step around
# anything that changes), so noise below a step is not taken at its word (the dev scenes and
# ScalarFlow have perfectly still backgrounds: 0 measured) and a difference of a step or two is
# no evidence of smoke.
NOISE_FLOOR = 1.0 / 255.0


class EstimationError(InputError):
    """The videos do not show what an estimate needs (e.g. no smoke in the first frames)."""


@dataclass(frozen=True)
class Background:
    """A view's background: a colour, plus a static image when the view's background is textured,
    and the video's noise: how far a pixel strays from it while nothing is there."""

    color: np.ndarray  # (C,) float32 in [0, 1]
    image: np.ndarray | None  # (H, W, C) float32, or None: the colour everywhere
    noise: np.ndarray  # (C,) float32: each channel's noise (standard deviation), at least NOISE_FLOOR

    def as_image(self, height: int, width: int) -> np.ndarray:
        """(H, W, C) float32 at the requested size (area-resampled from the stored image)."""
        if self.image is None:
            return np.broadcast_to(self.color, (height, width, len(self.color))).astype(np.float32)
        return resize_image(self.image, width, height)


def to_float(frames: np.ndarray, channels: int) -> np.ndarray:
    """uint8 (T, H, W, 3) -> float32 (T, H, W, channels) in [0, 1] (grey = channel mean)."""
    data = frames.astype(np.float32) / 255.0
    return data.mean(axis=-1, keepdims=True) if channels == 1 else data


def resize_image(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """Area-style resize of an (H, W, C) float image (torch's antialiased bilinear)."""
    if image.shape[:2] == (height, width):
        return image.astype(np.float32)
    import torch
    import torch.nn.functional as F

    tensor = torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32)).permute(2, 0, 1)[None]
    out = F.interpolate(tensor, size=(height, width), mode="bilinear", antialias=True, align_corners=False)
    return out[0].permute(1, 2, 0).numpy()


def estimate_noise(frames: np.ndarray) -> np.ndarray:
    """(C,) float32: each channel's noise in `frames` (T, H, W, C), at least NOISE_FLOOR.

    Per pixel, the standard deviation over time; then the median over pixels, which are those
    the smoke never crosses as long as it crosses fewer than half of them (36% of dev scene D's
    input view over its 90 frames, 14% of ScalarFlow's): the temporal spread of the background,
    blind to a textured background's spatial pattern. Not the median absolute deviation, though
    it is robust within a pixel: on 8-bit values it moves in half steps (Gaussian noise of 2 codes
    reads 1.48, of 1 code 1.48 or 0), where the median of standard deviations reads 2.01 and 1.03.
    """
    spread = frames.std(axis=0)  # (H, W, C)
    sigma = np.median(spread.reshape(-1, spread.shape[-1]), axis=0)
    return np.maximum(sigma, NOISE_FLOOR).astype(np.float32)


def estimate_background(frames: np.ndarray) -> Background:
    """Background of one view from its frames (float (T, H, W, C) in [0, 1]).

    The colour is the median over the frame of the per-pixel temporal median: smoke covers
    well under half of a typical frame. The background is textured when that per-pixel median
    differs from the colour beyond the noise (as smoke would) on more than TEXTURED_FRACTION of
    the view; only then is an image returned, because a flat background is better described by
    its colour than by an image that still holds the smoke that never leaves (e.g. right above
    the source). The image is the per-pixel temporal median (smoke covers a pixel in fewer than
    half of the frames), and where smoke stays longer, the value over time closest to the colour
    ("the least smoky moment"), the true background wherever the smoke ever leaves; not that
    everywhere, since the noise pulls it towards the colour by two or three of its units.
    """
    import torch

    if frames.ndim != 4 or frames.shape[0] == 0:
        raise EstimationError(f"video: expected frames (T, H, W, C), got shape {frames.shape}")
    step = max(1, len(frames) // MAX_BACKGROUND_FRAMES)
    sample = frames[::step]
    noise = estimate_noise(sample)
    median = np.median(sample, axis=0)
    color = np.median(median.reshape(-1, median.shape[-1]), axis=0).astype(np.float32)
    least_smoky = np.take_along_axis(sample, np.abs(sample - color).mean(axis=-1).argmin(axis=0)[None, ..., None], axis=0)[0]
    median_t, noise_t = torch.from_numpy(median), torch.from_numpy(noise)
    if is_smoke(smoke_contrast(median_t, torch.from_numpy(color), noise_t)).mean() <= TEXTURED_FRACTION:
        return Background(color=color, image=None, noise=noise)
    smoky = is_smoke(smoke_contrast(median_t, torch.from_numpy(least_smoky), noise_t))[..., None]  # smoke there more often than not
    return Background(color=color, image=np.where(smoky, least_smoky, median).astype(np.float32), noise=noise)


def smoke_contrast(frames: torch.Tensor, background: torch.Tensor, noise: torch.Tensor) -> np.ndarray:
    """(..., H, W) float32: how far `frames` (..., H, W, C) lie from the `background` ((H, W, C)
    or (C,)) in units of the video's `noise` ((C,), `Background.noise`), in the channel where they
    lie farthest; the measure every smoke mask thresholds.

    The farthest channel, not the mean over channels: coloured smoke over a coloured background
    may change one channel only (the mean divides it by the channel count) or shift channels in
    opposite directions (a grey image does not change at all); nor the norm over channels, which
    counts a decoded video's noise, shared by its channels, sqrt(C) times over
    (tests/fluidcore/reconstruct/test_smoke_mask.py).
    """
    return ((frames - background).abs() / noise.to(frames)).amax(dim=-1).cpu().numpy()


def smoke_mask(frames: torch.Tensor, background: torch.Tensor, noise: torch.Tensor) -> np.ndarray:
    """(..., H, W) bool: where `frames` (..., H, W, C) differ visibly from the `background`
    ((H, W, C) or (C,)), beyond the video's `noise` ((C,)): the one smoke mask of the
    reconstruction (source estimate, physics identification, mirror agreement, optical flow
    confidence)."""
    return is_smoke(smoke_contrast(frames, background, noise))


def is_smoke(contrast: np.ndarray) -> np.ndarray:
    """Where a `smoke_contrast` is visible smoke (for a caller that needs the contrast too)."""
    return contrast > SMOKE_SIGMAS
