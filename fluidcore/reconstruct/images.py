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
# The fraction of a pixel's frames, those least like smoke, that its background is taken from: a
# pixel the smoke leaves for a fifth of the clip shows its background (a per-pixel median needs
# half); fewer frames would average less of the noise away.
SMOKE_SIDE_FRACTION = 0.2
# Noise units (`axis_noise`) the least smoky frames of a pixel may spread along the smoke's axis
# before the pixel counts as covered in all of them: a clean pixel's lowest fifth (8 of 40 frames)
# spreads by 0.41 units at the median (0.45 for Gaussian noise), 0.86 at the 99th percentile, 1.12
# at most (2-code noise, 8-bit rounding; test_background's clip); a stem flickering between
# densities 0.2 and 0.8 by 2.4 at the median, 1.23 at the 5th percentile.
COVERED_SPREAD = 1.2
# A plate may look smokier than the clip's clearest frames on this fraction of the view (a light
# that flickers, a reflection); beyond it, it holds smoke.
PLATE_SMOKE_FRACTION = 0.01
MAX_AXIS_SAMPLES = 200_000  # visible changes the smoke's axis is fitted to (an SVD of (N, C); more adds nothing)
MAJORITY_WINDOW = 5  # pixels across the neighbourhood a covered pixel's vote is taken over
INPAINT_RADIUS = 5  # pixels around a covered region that its fill reads from (OpenCV's Telea)
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
    # (H, W) bool: pixels the smoke covered in (almost) every frame, whose background was filled from
    # their surroundings, or None: none (a flat background, a plate, or nothing covered)
    covered: np.ndarray | None = None

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
    half of the frames), and where smoke stays longer, the mean of the frames on the side of the
    pixel's values away from the smoke (`smoke_side`); not that everywhere, since it pulls a clean
    pixel's value away from the smoke by about one noise unit. Pixels the smoke covers in almost
    every frame (`covered`) show no background at all: they are filled from their surroundings.
    """
    import torch

    if frames.ndim != 4 or frames.shape[0] == 0:
        raise EstimationError(f"video: expected frames (T, H, W, C), got shape {frames.shape}")
    step = max(1, len(frames) // MAX_BACKGROUND_FRAMES)
    sample = frames[::step]
    noise = estimate_noise(sample)
    median = np.median(sample, axis=0)
    color = np.median(median.reshape(-1, median.shape[-1]), axis=0).astype(np.float32)
    median_t, noise_t = torch.from_numpy(median), torch.from_numpy(noise)
    if is_smoke(smoke_contrast(median_t, torch.from_numpy(color), noise_t)).mean() <= TEXTURED_FRACTION:
        return Background(color=color, image=None, noise=noise)
    side, covered = smoke_side(sample, smoke_axis(sample, median, color, noise), noise)
    smoky = is_smoke(smoke_contrast(median_t, torch.from_numpy(side), noise_t))[..., None]  # smoke there more often than not
    image = np.where(smoky, side, median).astype(np.float32)
    return Background(color=color, image=fill_covered(image, covered), noise=noise, covered=covered)


def plate_background(plate: np.ndarray, frames: np.ndarray) -> Background:
    """Background of one view from a plate: `plate` (P, H, W, C), frames the user says show no
    smoke, as float in [0, 1] like the clip's `frames` (T, H, W, C). The image is the plate's
    per-pixel median (kept even when flat: the user has told what is there); the noise is the
    clip's own (`estimate_noise`: a single-frame plate has none to measure). A plate that shows
    more smoke than the clip's own clearest frames somewhere (`smoke_side`) on more than
    PLATE_SMOKE_FRACTION of the view is refused: it holds smoke, and every mask would lose it."""
    if plate.ndim != 4 or plate.shape[0] == 0 or plate.shape[1:] != frames.shape[1:]:
        raise EstimationError(f"background plate: expected frames shaped like the clip's {frames.shape[1:]}, got {plate.shape}")
    step = max(1, len(frames) // MAX_BACKGROUND_FRAMES)
    sample = frames[::step]
    noise = estimate_noise(sample)
    image = np.median(plate, axis=0).astype(np.float32)
    color = np.median(image.reshape(-1, image.shape[-1]), axis=0).astype(np.float32)
    median = np.median(sample, axis=0)
    axis = smoke_axis(sample, median, color, noise)
    side, _ = smoke_side(sample, axis, noise)
    smokier = ((image - side) @ axis) / axis_noise(axis, noise) > SMOKE_SIGMAS
    if smokier.mean() > PLATE_SMOKE_FRACTION:
        raise EstimationError(
            f"background plate: {100 * smokier.mean():.1f}% of its pixels show more smoke than the clip's own clearest "
            "frames there; give frames from before the smoke starts (or after it has cleared)"
        )
    return Background(color=color, image=image, noise=noise)


def smoke_axis(sample: np.ndarray, median: np.ndarray, color: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """(C,) unit vector: the direction in colour space the smoke moves a pixel, pointing from the
    background towards the smoke. The leading direction of the visible changes about each pixel's
    median (a flickering stem's changes point along its colour, both ways), oriented towards the
    state, of the two each change joins, that lies farther from the view's background `color`. Grey (every channel alike) when
    nothing in the clip changes visibly."""
    channels = sample.shape[-1]
    change = (sample - median).reshape(-1, channels)
    visible = np.abs(change / noise).max(axis=-1) > SMOKE_SIGMAS
    if visible.sum() < channels:
        return np.full(channels, 1.0 / np.sqrt(channels), dtype=np.float32)
    stride = max(1, int(visible.sum()) // MAX_AXIS_SAMPLES)
    axis = np.linalg.svd(change[visible][::stride], full_matrices=False)[2][0]
    # Of the two states each visible change joins (the frame's value, the pixel's median), the
    # smoke is the one farther from the background colour: the median where smoke stays longest.
    values = (sample.reshape(-1, channels)[visible] - color)[::stride]
    medians = (np.broadcast_to(median, sample.shape).reshape(-1, channels)[visible] - color)[::stride]
    smoke = np.where((np.abs(values @ axis) > np.abs(medians @ axis))[:, None], values, medians)
    return (axis if float(smoke.mean(axis=0) @ axis) >= 0.0 else -axis).astype(np.float32)


def axis_noise(axis: np.ndarray, noise: np.ndarray) -> float:
    """The video's noise along a colour `axis` (C,): the noise of the channels taken as one, as a
    decoded video's mostly is (its luma noise), which projects at sum |a_c| sigma_c, not at the
    root of the squares that independent channels would give (sqrt(3) less on the grey axis)."""
    return float(np.abs(axis * noise).sum())


def smoke_side(sample: np.ndarray, axis: np.ndarray, noise: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each pixel's background from the side of its values away from the smoke, and where the
    smoke never left.

    Per pixel, the SMOKE_SIDE_FRACTION of the `sample` frames (T, H, W, C) least along the smoke's
    `axis` (`smoke_axis`)
    is averaged: the background wherever the smoke leaves the pixel in that many frames, however
    often it is there otherwise (a per-pixel median needs it gone half of the time). Those
    frames' values spread, along the axis, by about 0.45 noise units on a clean pixel (the lowest
    fifth of a Gaussian; 0.86 at the 99th percentile with 8 frames); a pixel still
    covered in them spreads by the smoke's own flicker, and where most pixels around it spread
    beyond COVERED_SPREAD noise units it is `covered`. Smoke that stays and never flickers is
    indistinguishable from a background here: only a background plate tells it.
    Returns the (H, W, C) background and the (H, W) bool covered mask.
    """
    along = sample @ axis  # (T, H, W)
    keep = max(2, round(SMOKE_SIDE_FRACTION * len(sample)))
    lowest = np.argsort(along, axis=0)[:keep]  # (keep, H, W)
    side = np.take_along_axis(sample, lowest[..., None], axis=0).mean(axis=0)
    spread = np.take_along_axis(along, lowest, axis=0).std(axis=0) > COVERED_SPREAD * axis_noise(axis, noise)
    return side.astype(np.float32), majority(spread)


def majority(mask: np.ndarray) -> np.ndarray:
    """(H, W) bool: where most of a pixel's MAJORITY_WINDOW-wide neighbourhood is in `mask`. One
    pixel's spread is read from a few frames: clean pixels pass COVERED_SPREAD here and there
    (1 in 1,000 on test_background's clip), a covered stem misses it here and there (1 in 20);
    smoke that stays covers regions, not single pixels."""
    import cv2

    return cv2.medianBlur(mask.astype(np.uint8) * 255, MAJORITY_WINDOW) > 127


def fill_covered(image: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """`image` (H, W, C) with its `covered` pixels (and a pixel around them, which smoke's soft edge
    still tints) filled from their surroundings (OpenCV's Telea inpainting)."""
    if not covered.any():
        return image
    import cv2

    grown = cv2.dilate(covered.astype(np.uint8), np.ones((3, 3), np.uint8))
    codes = np.round(np.clip(image, 0.0, 1.0) * 255.0).astype(np.uint8)
    filled = cv2.inpaint(codes, grown, INPAINT_RADIUS, cv2.INPAINT_TELEA).reshape(image.shape)
    return np.where(grown[..., None] > 0, filled.astype(np.float32) / 255.0, image).astype(np.float32)


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
