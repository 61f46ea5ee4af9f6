"""System identification for Algorithm S2: the physics a prediction runs under, fitted to
the reconstruction's own last frames (the observed window only, never the future).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from fluidcore.physics import ParticleState
from fluidcore.physics.build import build_simulator
from fluidcore.runs import FrameState, Run
from fluidcore.smoke import SmokeState
from fluidcore.spec.scene import Scene

CALIBRATION_SECONDS = 1 / 3  # the last reconstructed stretch the buoyancy is identified on (10 frames at 30 fps)
# candidate multiples of the preset buoyancy; never 0: smoke the video showed rising keeps rising
BUOYANCY_SCALES = (0.25, 0.5, 0.75, 1.0, 1.5, 2.0)


def calibrate_buoyancy(
    parent: Run, scene: Scene, start_frame: int, device: str, scales: Sequence[float] = BUOYANCY_SCALES
) -> tuple[float, dict[str, float]]:
    """The multiple of the scene's buoyancy under which physics best replays the reconstruction's
    `CALIBRATION_SECONDS` (system identification on the observed window only).

    The preset alpha is a property of a dataset, not of this plume: a reconstruction whose column
    is denser than rest density feels no drag inside it (drag scales with 1 - rho/rho0), so with
    the preset buoyancy a free simulation accelerates the column well beyond the speed the video
    showed. Each candidate re-simulates the window from the reconstructed state at its start (the
    scene's air included, when it simulates one) and
    is scored by the mean squared distance, over every frame of the window, between simulated and
    reconstructed positions of the particles alive in both. Returns (scale, error per scale).
    """
    window = scene.physics.frames_in(CALIBRATION_SECONDS)
    frames = [t for t in parent.frames() if start_frame - window <= t <= start_frame]
    if len(frames) < 2 or frames != list(range(frames[0], start_frame + 1)):
        return 1.0, {}
    targets = [parent.read_frame(t) for t in frames[1:]]
    begin = SmokeState.from_frame(parent.read_frame(frames[0]), device).particles
    errors: dict[str, float] = {}
    for scale in scales:
        simulator = build_simulator(scene.with_buoyancy_scaled(scale), device=device)
        state, total = simulator.adopt_air(begin), 0.0
        for target in targets:
            state, _ = simulator.step(state)
            total += _tracking_error(state, begin.alive, target)
        errors[f"{scale:g}"] = total / len(targets)
    best = min(scales, key=lambda scale: errors[f"{scale:g}"])
    return float(best), errors


def _tracking_error(state: ParticleState, tracked: torch.Tensor, target: FrameState) -> float:
    """Mean squared distance between simulated and reconstructed positions of the particles that
    were alive at the window's start and still are in both."""
    n = min(len(tracked), len(target.alive), state.capacity)
    alive = torch.from_numpy(np.ascontiguousarray(target.alive[:n])).to(tracked.device)
    both = tracked[:n] & state.alive[:n] & alive
    if not bool(both.any()):
        return 0.0
    reference = torch.from_numpy(np.ascontiguousarray(target.positions[:n])).to(state.positions)
    return float(((state.positions[:n][both] - reference[both]).mean(dim=0) ** 2).sum())
