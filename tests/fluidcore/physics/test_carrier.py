"""The buoyant-air carrier (fluidcore.physics.carrier): what buoyant air carrying smoke must do
physically, under the step's controls, at any frame rate."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from fluidcore.physics import Box, Controls, PBFConfig, PhysicsInputError, Source, Sphere, wind_force
from fluidcore.physics.air import AirGrid
from fluidcore.physics.carrier import BuoyantAirCarrier
from fluidcore.spec.controls import WindParams
from tests.fluidcore.physics.test_air import circulation, half_plane
from tests.support.simulators import carrier, run

BOX = Box((0.0, 0.0, 0.0), (0.3, 0.4, 0.3))
AXIS = (0.15, 0.15)  # x, z of the plume's axis (the helpers of test_air measure about it)
CONFIG = PBFConfig(alpha=-0.8 * 100 / 9.8, h=0.01)  # 0.8 m/s^2 of buoyancy where the smoke is as dense as at the inlet
SOURCE = Source((AXIS[0], 0.04, AXIS[1]), 0.025, 40, (0.0, 0.2, 0.0), seed=1)


def heights(state) -> torch.Tensor:  # noqa: ANN001
    return state.positions[state.alive][:, 1]


def test_a_starting_plume_rolls_up_into_a_vortex_ring() -> None:
    """The buoyant air rises through the middle of the plume's head and comes back down round it
    in every direction: one circulation of one sign all round the axis."""
    sim = carrier(CONFIG, BOX, SOURCE)
    state, _ = run(sim, sim.new_state(), 25)
    grid = sim.integrator.air
    ys = torch.linspace(0.03, 0.38, 71)
    _, axis = half_plane(grid, state.air, 0.0, torch.tensor([0.0]), ys)
    up = float(axis.max())
    assert up > 0.1  # m/s: the plume's own updraft
    thetas = [k * math.pi / 4.0 for k in range(8)]
    for theta in thetas:
        _, rim = half_plane(grid, state.air, theta, torch.linspace(0.05, 0.13, 17), ys)
        assert float(rim.min()) < -0.05 * up  # air coming down round the head
    gamma = [circulation(grid, state.air, theta, (0.003, 0.13), (0.03, 0.38)) for theta in thetas]
    assert max(gamma) < 0.0 and max(gamma) < 0.5 * min(gamma)  # the same sense and strength all round


def test_the_air_goes_round_a_ball_before_the_smoke_arrives() -> None:
    """A ball above the source is a wall of the projection: when the smoke's top is still below it,
    the smoke at the top already moves outward faster and rises slower than without the ball (the
    air goes round it); the smoke never enters it. (0.064 against 0.040 m/s outward, 0.149
    against 0.171 up, when written.)"""
    ball = Sphere((AXIS[0], 0.22, AXIS[1]), 0.04)
    sim = carrier(CONFIG, BOX, SOURCE)
    below = ball.center[1] - ball.radius - 0.005
    moving = {}
    for name, controls in (("ball", Controls(spheres=(ball,))), ("open", Controls())):
        state = sim.new_state()
        for _ in range(80):
            state, _ = sim.step(state, controls)
            if float(heights(state).max()) >= below:
                break
        x = state.positions[state.alive]
        top = x[x[:, 1] > below - 0.04]
        velocity = sim.velocity_at(state, top)
        across = top[:, [0, 2]] - torch.tensor(AXIS)
        outward = (velocity[:, [0, 2]] * across / across.norm(dim=1, keepdim=True).clamp_min(1e-6)).sum(1)
        moving[name] = (float(outward.mean()), float(velocity[:, 1].mean()))
    assert moving["ball"][0] > 1.3 * moving["open"][0] > 0.0  # outward
    assert moving["ball"][1] < 0.95 * moving["open"][1]  # and slowed on its way up
    state, _ = run(sim, sim.new_state(), 60, Controls(spheres=(ball,)))
    inside = (state.positions[state.alive] - torch.tensor(ball.center)).norm(dim=1) < ball.radius * (1 - 1e-5)
    assert not bool(inside.any())


def test_a_sideways_wind_bends_the_plume_and_keeps_its_smoke() -> None:
    """A wind along +x blowing on the air carries the plume downwind; every marker seeded is either
    still in the box or counted leaving it, as without the wind."""
    wind = WindParams(direction=(1.0, 0.0, 0.0), strength=0.2, profile="uniform")
    controls = Controls(force=wind_force(wind, lambda time: True), terminal_time=wind.terminal_time)
    sim = carrier(CONFIG, BOX, SOURCE)
    centres = {}
    for name, given in (("wind", controls), ("still", Controls())):
        state, stats = run(sim, sim.new_state(), 30, given)
        assert sum(s.seeded for s in stats) == state.n_alive + sum(s.retired for s in stats)
        high = state.positions[state.alive][heights(state) > 0.15]
        centres[name] = float(high[:, 0].mean())
    assert centres["wind"] > centres["still"] + 0.02  # world units downwind


def test_the_wind_drives_the_air_up_to_its_terminal_speed() -> None:
    """A uniform wind on still air (no smoke) speeds it up as terminal x tanh(strength t / terminal)
    (`WindParams.air_speed`), never past the terminal speed."""
    wind = WindParams(direction=(1.0, 0.0, 0.0), strength=1.0, profile="uniform", terminal_speed=0.3)
    sim = carrier(CONFIG, BOX, None, cells=16)
    controls = Controls(force=wind_force(wind, lambda time: True), terminal_time=wind.terminal_time)
    for frames in (10, 30, 60):
        state, _ = run(sim, sim.new_state(), frames, controls)
        speed = float(sim.velocity_at(state, torch.tensor([[0.15, 0.2, 0.15]]))[0, 0])
        expected = wind.air_speed(frames * CONFIG.dt)
        assert speed == pytest.approx(expected, rel=0.08)
        assert speed <= 0.3 * (1 + 1e-4)


def rise(fps: float, seconds: float = 1.5) -> float:
    """The plume's head (0.98 quantile of the markers' height above the source) after `seconds`
    at `fps`, the source seeding the same markers per second."""
    source = replace(SOURCE, rate=max(1, round(40 * 30 / fps)))
    sim = carrier(replace(CONFIG, dt=1.0 / fps), BOX, source)
    state, _ = run(sim, sim.new_state(), round(seconds * fps))
    return float(torch.quantile(heights(state), 0.98)) - source.center[1]


def test_the_carrier_rises_the_same_at_15_24_30_and_60_fps() -> None:
    """Its constants are in seconds and its parts keep the fastest air within two cells: the same
    plume's head after 1.5 s is within 10% of the 30 fps one at every rate."""
    reference = rise(30.0)
    assert reference > 0.1
    for fps in (15.0, 24.0, 60.0):
        assert rise(fps) == pytest.approx(reference, rel=0.10), fps


def test_bad_carrier_settings_are_refused_by_name() -> None:
    grid = AirGrid(BOX, 16)
    device = torch.device("cpu")
    with pytest.raises(PhysicsInputError, match="air must be an AirGrid"):
        BuoyantAirCarrier(CONFIG, BOX, SOURCE, device, None)  # type: ignore[arg-type]
    with pytest.raises(PhysicsInputError, match="viscosity"):
        BuoyantAirCarrier(CONFIG, BOX, SOURCE, device, grid, viscosity=-1.0)
    with pytest.raises(PhysicsInputError, match="diffusivity"):
        BuoyantAirCarrier(CONFIG, BOX, SOURCE, device, grid, diffusivity=float("nan"))
    with pytest.raises(PhysicsInputError, match="source.velocity"):
        BuoyantAirCarrier(CONFIG, BOX, replace(SOURCE, velocity=(0.0, 0.0, 0.0)), device, grid)
    with pytest.raises(PhysicsInputError, match="air.down"):
        BuoyantAirCarrier(CONFIG, BOX, SOURCE, device, AirGrid(BOX, 16, down=(0.0, 0.0, -1.0)))
