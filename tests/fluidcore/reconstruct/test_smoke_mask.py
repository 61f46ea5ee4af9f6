"""The one smoke mask (fluidcore.reconstruct.images.smoke_mask) in units of the video's own noise,
on videos drawn here: a bright background with darker smoke, coloured smoke on a coloured
background that a grey image cannot see, a noisy video, and a clean 8-bit one."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fluidcore.reconstruct import images

T, H, W = 24, 64, 80


def _disc(cx: float = 40.0, cy: float = 30.0, radius: float = 12.0) -> np.ndarray:
    v, u = np.mgrid[0:H, 0:W] + 0.5
    return (u - cx) ** 2 + (v - cy) ** 2 <= radius**2


def _video(background: tuple[float, ...], smoke: np.ndarray, shift: tuple[float, ...], noise: float = 0.0, shared: bool = True,
           seed: int = 0) -> np.ndarray:
    """float (T, H, W, C) 8-bit video: the `background` colour, `shift` added where `smoke` is
    (the disc in every frame but the first third, so the background's median stays clean), and
    Gaussian `noise` (std, [0, 1] units), the same in every channel when `shared` (as a decoded
    video's luma noise is) or independent per channel."""
    rng = np.random.default_rng(seed)
    channels = len(background)
    frames = np.broadcast_to(np.asarray(background, np.float32), (T, H, W, channels)).copy()
    frames[T // 3 :][:, smoke] += np.asarray(shift, np.float32)
    draw = rng.normal(size=(T, H, W, 1 if shared else channels)).astype(np.float32)
    frames += noise * draw
    return np.round(np.clip(frames, 0.0, 1.0) * 255.0) / 255.0


def _mask(frames: np.ndarray) -> tuple[np.ndarray, images.Background]:
    background = images.estimate_background(frames)
    mask = images.smoke_mask(torch.from_numpy(frames), torch.from_numpy(background.color), torch.from_numpy(background.noise))
    return mask, background


def test_smoke_darker_than_a_bright_background_is_the_disc_and_nothing_else() -> None:
    smoke = _disc()
    mask, background = _mask(_video((0.93, 0.93, 0.95), smoke, (-0.06, -0.06, -0.05), noise=2.0 / 255.0))
    assert background.image is None and np.allclose(background.color, (0.93, 0.93, 0.95), atol=1.5 / 255.0)
    assert mask[: T // 3].mean() < 1e-4  # the frames without smoke: the noise alone is (almost) never smoke
    late = mask[T // 3 :]
    assert late[:, smoke].mean() > 0.99 and late[:, ~smoke].mean() < 1e-4


def test_coloured_smoke_that_leaves_the_grey_level_unchanged_is_smoke() -> None:
    """Reddish smoke over a teal background: red up, green down by as much, so the channels' mean
    (a grey image) does not change at all; the change in each channel (1.3 x SMOKE_SIGMAS noise
    units) is below the threshold when averaged over the three channels (0.87 x), above it in
    the channel where it is largest: the mask takes the largest."""
    noise = 2.0 / 255.0
    step = 1.3 * images.SMOKE_SIGMAS * noise
    smoke = _disc()
    frames = _video((0.25, 0.55, 0.5), smoke, (step, -step, 0.0), noise=noise, shared=False)
    grey = frames.mean(axis=-1)
    assert abs(grey[-1][smoke].mean() - grey[0][smoke].mean()) < 0.3 * noise  # the grey image sees nothing
    mask, background = _mask(frames)
    assert background.noise == pytest.approx(noise, rel=0.15)
    assert mask[T // 3 :, smoke].mean() > 0.9
    assert mask[:, ~smoke].mean() < 1e-4


def test_noise_is_not_smoke_and_faint_smoke_above_it_is() -> None:
    """A noisy video (4 codes of noise shared by the channels, where the norm over channels
    would count it sqrt(3) times over): the measured noise is the drawn one, the noise alone gives
    (almost) no smoke pixel, smoke of 8 noise units is found, smoke of 2 is not."""
    noise = 4.0 / 255.0
    faint, too_faint = _disc(24.0, 30.0, 10.0), _disc(58.0, 30.0, 10.0)
    frames = _video((0.2, 0.22, 0.3), faint, (8.0 * noise,) * 3, noise=noise)
    frames[T // 3 :][:, too_faint] += 2.0 * noise
    mask, background = _mask(frames)
    assert background.noise == pytest.approx(np.full(3, noise), rel=0.1)
    clear = ~(faint | too_faint)
    assert mask[:, clear].mean() < 1e-4
    assert mask[T // 3 :, faint].mean() > 0.98
    assert mask[T // 3 :, too_faint].mean() < 0.05


def test_a_clean_8bit_video_has_the_floor_noise_and_one_step_is_not_smoke() -> None:
    """Without noise the temporal spread is 0: the noise is NOISE_FLOOR (one 8-bit step),
    so a difference of one step (a rounding) is no smoke, and one of SMOKE_SIGMAS + 1 steps is."""
    steps = images.SMOKE_SIGMAS + 1.0
    one_step, visible = _disc(24.0, 30.0, 8.0), _disc(58.0, 30.0, 8.0)
    frames = _video((0.4, 0.4, 0.4), one_step, (1.0 / 255.0,) * 3)
    frames[T // 3 :][:, visible] += steps / 255.0
    mask, background = _mask(frames)
    assert np.array_equal(background.noise, np.full(3, images.NOISE_FLOOR, np.float32))
    assert mask[:, one_step].sum() == 0 and mask[T // 3 :, visible].all()


def test_a_textured_background_is_kept_as_an_image_and_its_pattern_is_not_noise() -> None:
    """Stripes (10 steps apart) cover the view: the background is an image, the noise stays the
    temporal one (the stripes are no spread over time), and the stripes are no smoke."""
    v, u = np.mgrid[0:H, 0:W]
    frames = _video((0.5, 0.5, 0.5), _disc(), (0.1, 0.1, 0.1), noise=1.5 / 255.0)
    frames = frames + np.where((u // 4) % 2 == 0, 10.0 / 255.0, 0.0)[None, ..., None].astype(np.float32)
    background = images.estimate_background(frames)
    assert background.image is not None
    assert background.noise == pytest.approx(np.full(3, 1.5 / 255.0), rel=0.2)
    mask = images.smoke_mask(torch.from_numpy(frames), torch.from_numpy(background.image), torch.from_numpy(background.noise))
    assert mask[:, ~_disc()].mean() < 1e-3 and mask[T // 3 :, _disc()].mean() > 0.99
