"""The background of a view whose smoke never leaves some pixels (fluidcore.reconstruct.images.
estimate_background): a textured background drawn here, with a flickering stem of smoke in every
frame, and smoke that covers a patch in most frames but not all. A per-pixel median takes such
smoke into the background, and the smoke then disappears from every mask and every fit."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fluidcore.reconstruct import images

T, H, W = 40, 64, 96
NOISE = 2.0 / 255.0
STEM = (slice(16, H), slice(44, 52))  # rows, columns of the smoke's stem


def _textured(seed: int = 0) -> np.ndarray:
    """(H, W, 3): a smooth two-way gradient, bluish, with blobs of texture far from the stem."""
    v, u = np.mgrid[0:H, 0:W] / np.array([H, W])[:, None, None]
    base = 0.15 + 0.35 * u + 0.1 * v
    image = np.stack([base, base * 1.05, base * 1.2], axis=-1)
    rng = np.random.default_rng(seed)
    for _ in range(6):  # texture in the left and right thirds only
        cx = rng.choice([rng.uniform(5, 25), rng.uniform(70, 90)])
        cy, r = rng.uniform(5, H - 5), rng.uniform(3, 6)
        image[(np.mgrid[0:H, 0:W][1] - cx) ** 2 + (np.mgrid[0:H, 0:W][0] - cy) ** 2 < r**2] += 0.15
    return image.astype(np.float32)


def _film(background: np.ndarray, density: np.ndarray, seed: int = 1) -> np.ndarray:
    """float (T, H, W, 3) 8-bit video: white smoke of `density` (T, H, W) in [0, 1] over
    `background`, with Gaussian noise."""
    rng = np.random.default_rng(seed)
    frames = background[None] + density[..., None] * (0.95 - background[None])
    frames = frames + NOISE * rng.normal(size=frames.shape[:-1] + (1,))
    return (np.round(np.clip(frames, 0.0, 1.0) * 255.0) / 255.0).astype(np.float32)


def _flickering_stem(seed: int = 2) -> np.ndarray:
    """(T, H, W) density: the stem in every frame, between 0.2 and 0.8 (turbulent flicker)."""
    density = np.zeros((T, H, W), np.float32)
    density[(slice(None),) + STEM] = np.random.default_rng(seed).uniform(0.2, 0.8, size=(T, H - 16, 8))
    return density


def _error(background: images.Background, truth: np.ndarray, where: np.ndarray) -> float:
    """The estimate's largest error over `where`, in noise units."""
    return float(np.abs(background.as_image(H, W) - truth)[where].max() / NOISE)


def test_a_stem_in_every_frame_is_found_covered_and_filled_from_its_surroundings() -> None:
    truth = _textured()
    frames = _film(truth, _flickering_stem())
    background = images.estimate_background(frames)
    stem = np.zeros((H, W), bool)
    stem[STEM] = True
    assert background.image is not None and background.covered is not None
    assert background.covered[stem].mean() > 0.9  # the stem is covered in every frame
    assert background.covered[~stem].mean() < 0.01  # and the rest never is
    # filled from the gradient around it: within 4 noise units (the median is 10+ off)
    assert _error(background, truth, stem) < 4.0
    assert np.abs(np.median(frames, axis=0) - truth)[stem].max() / NOISE > 10.0
    # so the stem stays smoke in every frame's mask, and the background elsewhere does not
    mask = images.smoke_mask(torch.from_numpy(frames), torch.from_numpy(background.as_image(H, W)),
                             torch.from_numpy(background.noise))
    assert mask[:, stem].mean() > 0.95 and mask[:, ~stem].mean() < 0.01


def test_smoke_that_leaves_a_patch_for_a_fifth_of_the_clip_reveals_its_background() -> None:
    """Smoke over a textured patch in 70% of the frames: the median is smoke there; the frames on
    the side away from the smoke are the background itself (nothing is filled)."""
    truth = _textured(seed=3)
    density = np.zeros((T, H, W), np.float32)
    present = np.random.default_rng(4).permutation(T) < int(0.7 * T)
    density[present, 8:40, 10:30] = 0.6  # over the textured left third
    frames = _film(truth, density)
    background = images.estimate_background(frames)
    patch = np.zeros((H, W), bool)
    patch[8:40, 10:30] = True
    assert background.image is not None
    assert background.covered is None or not background.covered.any()
    assert _error(background, truth, patch) < 3.0
    assert np.abs(np.median(frames, axis=0) - truth)[patch].max() / NOISE > 10.0


def test_dark_smoke_over_a_bright_background_is_on_the_other_side() -> None:
    """The smoke's side is read from the clip, not assumed bright: dark smoke over a bright
    textured background, present in 70% of the frames, is still left out."""
    truth = 1.0 - _textured(seed=5)
    density = np.zeros((T, H, W), np.float32)
    present = np.random.default_rng(6).permutation(T) < int(0.7 * T)
    density[present, 20:50, 60:80] = 0.5
    rng = np.random.default_rng(7)
    frames = truth[None] + density[..., None] * (0.05 - truth[None]) + NOISE * rng.normal(size=(T, H, W, 1))
    frames = (np.round(np.clip(frames, 0.0, 1.0) * 255.0) / 255.0).astype(np.float32)
    background = images.estimate_background(frames)
    patch = np.zeros((H, W), bool)
    patch[20:50, 60:80] = True
    assert background.image is not None
    assert _error(background, truth, patch) < 3.0


def test_a_plate_gives_the_background_that_steady_smoke_hides() -> None:
    """Smoke that stays and never flickers looks like background to any estimate from the clip
    alone; a plate (frames without smoke) tells it, and the smoke is then seen in every frame."""
    truth = _textured(seed=8)
    density = np.zeros((T, H, W), np.float32)
    density[(slice(None),) + STEM] = 0.5  # steady: the same in every frame
    frames = _film(truth, density)
    stem = np.zeros((H, W), bool)
    stem[STEM] = True
    assert _error(images.estimate_background(frames), truth, stem) > 10.0  # the clip alone cannot tell
    plate = _film(truth, np.zeros((3, H, W), np.float32), seed=9)
    background = images.plate_background(plate, frames)
    assert background.image is not None and _error(background, truth, stem) < 3.0
    mask = images.smoke_mask(torch.from_numpy(frames), torch.from_numpy(background.image), torch.from_numpy(background.noise))
    assert mask[:, stem].mean() > 0.99 and mask[:, ~stem].mean() < 0.01


def test_a_plate_that_holds_smoke_is_refused() -> None:
    """Frames picked while the (flickering) stem was there are no plate: the message says so."""
    frames = _film(_textured(), _flickering_stem())
    with pytest.raises(images.EstimationError, match="show more smoke than the clip"):
        images.plate_background(frames[:3], frames)
    with pytest.raises(images.EstimationError, match="shaped like the clip"):
        images.plate_background(frames[:3, :10], frames)
