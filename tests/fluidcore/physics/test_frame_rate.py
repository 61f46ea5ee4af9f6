"""Time in seconds: a frame is stepped in the substeps a CFL bound asks for, so the same smoke
rises the same whatever the clip's frame rate (issue 33, item 3)."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from fluidcore.physics import Box, PBFConfig, Source, sim_step
from fluidcore.physics.step import CFL, MAX_SUBSTEPS, substeps
from tests.support.simulators import paper

# Dev scene D's identified plume (docs/bench_generalise_results/i32_after_D_s0.json, as bench/frame_rate.py)
PHYSICS = PBFConfig(alpha=-3.589, drag=3.0, rho0=2.0, h=0.02, length_scale=100.0)
PER_SECOND = 900  # particles the source seeds per second
BOX = Box((-0.3, 0.0, -0.3), (0.3, 1.0, 0.3))


def test_substeps_keep_the_fastest_particle_within_the_cfl_bound() -> None:
    still = PHYSICS.substep(1)
    assert substeps(torch.zeros(0, 3), still) == 1
    assert substeps(torch.zeros(5, 3), still) == 1
    for speed in (0.3, 0.9, 2.5):
        count = substeps(torch.tensor([[0.0, speed, 0.0], [0.01, 0.0, 0.0]]), PHYSICS)
        part = PHYSICS.substep(count)
        reach = speed + 3.589 * 9.8 / 100.0 * PHYSICS.dt  # its speed plus a frame of buoyancy
        assert reach * part.dt <= CFL * PHYSICS.h + 1e-9  # within the bound ...
        assert count == 1 or reach * PHYSICS.substep(count - 1).dt > CFL * PHYSICS.h  # ... with no part to spare
        assert part.speed_limit == pytest.approx(count * PHYSICS.speed_limit)
    assert substeps(torch.tensor([[0.0, 1e6, 0.0]]), PHYSICS) == MAX_SUBSTEPS  # bounded work per frame


def rise(fps: float, seconds: float = 3.0) -> tuple[float, float]:
    """(median upward speed over the last second, the clock after the last frame) of the plume at `fps`."""
    config = replace(PHYSICS, dt=1.0 / fps)
    source = Source((0.0, 0.05, 0.0), 0.035, round(PER_SECOND / fps), (0.0, 0.117, 0.0), seed=0)
    simulator = paper(config, BOX, source)
    state = simulator.new_state()
    frames, speeds = round(seconds * fps), []
    for frame in range(frames):
        state, _ = simulator.step(state)
        if frame >= frames - round(fps):
            speeds.append(state.velocities[state.alive][:, 1])
    return float(torch.cat(speeds).median()), state.time


def test_the_same_plume_rises_the_same_at_10_30_and_60_fps() -> None:
    """Stepped once per frame, the speed limit (a kernel radius per step) held the 10 fps plume to
    0.87x the 30 fps rise (bench/frame_rate.py on main); within 10% with substeps."""
    reference, clock = rise(30.0)
    assert clock == pytest.approx(3.0, abs=1e-9)  # the substeps add up to whole frames
    for fps in (10.0, 60.0):
        speed, clock = rise(fps)
        assert clock == pytest.approx(3.0, abs=1e-9)
        assert speed == pytest.approx(reference, rel=0.10), fps


def test_sim_step_takes_a_frame_in_substeps() -> None:
    """The differentiable step is one frame too: a fast particle in free flight (no neighbours) moves
    its frame's distance, not the speed limit's, and its gradient flows through every part."""
    config = replace(PHYSICS, alpha=0.0, drag=0.0)
    v = torch.tensor([[0.0, 1.5, 0.0]], requires_grad=True)  # 2.5 kernel radii per frame
    x = torch.zeros(1, 3)
    p, u = sim_step(x, v, config)
    assert substeps(v, config) == 3
    assert float(p.detach()[0, 1]) == pytest.approx(1.5 * config.dt, rel=1e-5)
    assert float(u.detach()[0, 1]) == pytest.approx(1.5, rel=1e-5)
    p[0, 1].backward()
    assert float(v.grad[0, 1]) == pytest.approx(config.dt, rel=1e-5)
