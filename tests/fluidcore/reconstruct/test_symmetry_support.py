"""The symmetry prior's weight follows how mirror-symmetric the input view's smoke is
(fluidcore.reconstruct.views.mirror_agreement / symmetry_support)."""

from __future__ import annotations

import numpy as np
import torch

from fluidcore.cameras import Camera, look_at
from fluidcore.reconstruct.images import NOISE_FLOOR
from fluidcore.reconstruct.views import ViewTarget, mirror_agreement, symmetry_support

UP = np.array([0.0, 1.0, 0.0])
CENTER = np.array([0.0, 0.1, 0.0])


def _view(frames: np.ndarray) -> ViewTarget:
    like = Camera("like", 40.0, 40.0, 16.0, 24.0, 32, 48, np.eye(4))
    camera = look_at(np.array([0.0, 0.1, 2.0]), CENTER, (0.0, 1.0, 0.0), like, "v")
    return ViewTarget(camera, torch.from_numpy(frames), torch.zeros(1), torch.full((1,), NOISE_FLOOR))


def test_a_symmetric_column_agrees_with_its_mirror_and_a_bent_one_does_not() -> None:
    frames = np.zeros((3, 48, 32, 1), np.float32)
    frames[:, 5:30, 12:20] = 0.5  # centred on the image column of the source (cx = 16)
    assert mirror_agreement(_view(frames), CENTER, UP) > 0.9
    bent = np.zeros((3, 48, 32, 1), np.float32)
    bent[:, 5:30, 17:28] = 0.5  # all of it right of the axis
    assert mirror_agreement(_view(bent), CENTER, UP) < 0.1


def test_support_is_off_below_the_low_mark_and_full_above_the_high_one() -> None:
    assert symmetry_support(0.1) == 0.0
    assert symmetry_support(0.95) == 1.0
    assert 0.0 < symmetry_support(0.45) < 1.0
    assert symmetry_support(0.4) < symmetry_support(0.5)
