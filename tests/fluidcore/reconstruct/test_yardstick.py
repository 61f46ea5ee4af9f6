"""fluidcore.reconstruct.yardstick: what each frame's input-view fit is recorded against (issue 48):
the background's own score, the share of the smoke's image energy explained, and where the
observed smoke sits along the image's up."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fluidcore.cameras.single import single_camera
from fluidcore.reconstruct.yardstick import input_fit, smoke_position

H, W = 40, 30
NOISE = torch.full((1,), 0.01)


def _frames() -> tuple[torch.Tensor, torch.Tensor]:
    """A grey background and a frame with a bright blob in its upper half (rows 5-14, columns 10-19)."""
    background = torch.full((H, W, 1), 0.2)
    target = background.clone()
    target[5:15, 10:20] = 0.8
    return target, background


def test_a_perfect_render_explains_all_the_smoke_and_an_empty_one_none() -> None:
    target, background = _frames()
    camera, _ = single_camera("cam", W, H, 40.0)
    perfect = input_fit(target, target, background, NOISE, camera, (0.0, 0.0, 0.0), (0.0, 1.0, 0.0))
    empty = input_fit(background, target, background, NOISE, camera, (0.0, 0.0, 0.0), (0.0, 1.0, 0.0))
    mse = 100 / (H * W) * 0.6**2  # 100 smoke pixels 0.6 off the background
    assert empty["background_psnr"] == pytest.approx(10 * np.log10(1 / mse), rel=1e-5)
    assert perfect["background_psnr"] == empty["background_psnr"] == pytest.approx(empty["input_psnr"], rel=1e-6)
    assert perfect["explained"] == pytest.approx(1.0) and empty["explained"] == pytest.approx(0.0, abs=1e-6)
    half = target.clone()
    half[5:15, 10:20] = 0.5  # half the contrast: a quarter of the energy left
    assert input_fit(half, target, background, NOISE, camera, (0.0, 0.0, 0.0), (0.0, 1.0, 0.0))["explained"] == pytest.approx(0.75, rel=1e-5)
    no_smoke = input_fit(background, background, background, NOISE, camera, (0.0, 0.0, 0.0), (0.0, 1.0, 0.0))
    assert "explained" not in no_smoke and "smoke_up" not in no_smoke  # nothing to explain, nowhere to place


@pytest.mark.parametrize(("image_up", "world_up", "along", "across"), [
    ("up", (0.0, 1.0, 0.0), 1.0, 0.0),     # upright: the blob above the centre is up
    ("up", (0.0, -1.0, 0.0), -1.0, 0.0),   # up given the wrong way round: the blob is down
    ("left", (0.0, 1.0, 0.0), 0.0, 1.0),   # world up said to point left in the image: the blob is across it, on its right
])
def test_the_smoke_is_placed_along_the_images_up(image_up: str, world_up: tuple, along: float, across: float) -> None:
    target, background = _frames()
    camera, _ = single_camera("cam", W, H, 40.0, up=image_up)
    mask = (target - background).abs()[..., 0].numpy() > 0.1
    place = smoke_position(mask, camera, (0.0, 0.0, 0.0), world_up)
    above = (H / 2 - 10.0) / max(W, H)  # the blob's centre is 10 px above the image's centre, on its vertical
    assert place["smoke_up"] == pytest.approx(along * above, abs=1e-6)
    assert place["smoke_across"] == pytest.approx(across * above, abs=1e-6)
    assert smoke_position(np.zeros((H, W), bool), camera, (0.0, 0.0, 0.0), world_up) == {}
