"""The air grid (fluidcore.physics.air): what the air must do physically, and that the simulator
without it is today's simulator."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from fluidcore.spec.controls import WindParams
from fluidcore.physics import PRESETS, Box, Controls, ParticleState, PhysicsInputError, Source, Sphere, step_record, wind_force
from fluidcore.physics.air import AirGrid, AirState, cell_velocity, curl
from fluidcore.predict.job import run_predict
from fluidcore.runs import Run
from fluidcore.spec.scene import Air
from tests.support.predict_scenes import plume_run
from tests.support.simulators import paper, run

CFG = PRESETS["scalarflow"]
BOX = Box((0.0, 0.0, 0.0), (0.3, 0.4, 0.3))
AXIS = (0.15, 0.15)  # x, z of the blob's vertical axis


def blob(radius: float, centre: tuple[float, float, float], seed: int = 0) -> ParticleState:
    """A ball of particles at the rest density, at rest."""
    n = int(8.0 * CFG.rho0 / CFG.h**3 * 4.0 / 3.0 * math.pi * radius**3)
    u = torch.rand(3 * n, 3, generator=torch.Generator().manual_seed(seed)) * 2.0 - 1.0
    u = u[u.norm(dim=1) <= 1.0][:n]
    return ParticleState.from_positions(torch.tensor(centre) + radius * u)


def uniform(acceleration: tuple[float, float, float]):
    return lambda positions, time: positions.new_tensor(acceleration).expand_as(positions)


def half_plane(grid: AirGrid, air: AirState, theta: float, rs: torch.Tensor, ys: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Radial and vertical air velocity (len(rs), len(ys)) on the vertical half-plane at azimuth theta."""
    r, y = torch.meshgrid(rs, ys, indexing="ij")
    points = torch.stack([AXIS[0] + r * math.cos(theta), y, AXIS[1] + r * math.sin(theta)], -1).reshape(-1, 3)
    v = grid.velocity_at(air, points).view(*r.shape, 3)
    return v[..., 0] * math.cos(theta) + v[..., 2] * math.sin(theta), v[..., 1]


def circulation(grid: AirGrid, air: AirState, theta: float, r: tuple[float, float], y: tuple[float, float]) -> float:
    """Line integral of the air velocity counter-clockwise (in r, y) around a rectangle of the
    half-plane at azimuth theta (trapezoid rule, 64 points a side)."""
    rs, ys = torch.linspace(*r, 64), torch.linspace(*y, 64)
    bottom, _ = half_plane(grid, air, theta, rs, ys[:1])
    top, _ = half_plane(grid, air, theta, rs, ys[-1:])
    _, right = half_plane(grid, air, theta, rs[-1:], ys)
    _, left = half_plane(grid, air, theta, rs[:1], ys)
    integral = lambda f, step: float(torch.trapezoid(f.flatten(), dx=step))  # noqa: E731
    dr, dy = (r[1] - r[0]) / 63, (y[1] - y[0]) / 63
    return integral(bottom, dr) + integral(right, dy) - integral(top, dr) - integral(left, dy)


def test_a_buoyant_blob_rolls_up_into_a_vortex_ring_within_20_frames() -> None:
    grid = AirGrid(BOX, 32)
    state = blob(0.04, (AXIS[0], 0.1, AXIS[1]))
    state, _ = run(paper(CFG, BOX, air=grid), state, 20)
    thetas = [k * math.pi / 4.0 for k in range(8)]
    ys = torch.linspace(0.03, 0.35, 65)
    _, axis = half_plane(grid, state.air, 0.0, torch.tensor([0.0]), ys)
    up = float(axis.max())
    assert up > 0.02  # world units / s: the buoyant air rises through the ring's centre
    for theta in thetas:  # ... and comes back down round its rim, in every direction
        _, rim = half_plane(grid, state.air, theta, torch.linspace(0.04, 0.12, 17), ys)
        assert float(rim.min()) < -0.1 * up
    # Circulation around the ring's core, in the half-plane of each azimuth: one sign (clockwise in
    # (r, y), as up inside and down outside make it) and the same strength all round.
    gamma = [circulation(grid, state.air, theta, (0.005, 0.12), (0.03, 0.35)) for theta in thetas]
    assert max(gamma) < 0.0
    assert max(gamma) < 0.5 * min(gamma)


def enstrophy(grid: AirGrid, air: AirState) -> float:
    """Sum over cells of |curl u|^2 (central differences of the cell-centred velocity)."""
    return float(curl(cell_velocity(air.faces), grid.spacing).pow(2).sum())


def test_vorticity_confinement_puts_back_swirl() -> None:
    smoke = blob(0.04, (AXIS[0], 0.1, AXIS[1])).positions  # held still: only the air differs
    values = []
    for epsilon in (0.0, 1.0):
        grid = AirGrid(BOX, 32, vorticity=epsilon)
        air = grid.still()
        for step in range(15):
            grid.step(air, smoke, CFG, step * CFG.dt)
        values.append(enstrophy(grid, air))
    assert values[1] > 1.15 * values[0]  # +23 % when written


@pytest.mark.parametrize("spheres", [(), (Sphere((0.15, 0.2, 0.15), 0.05),)], ids=["open", "ball"])
def test_projection_leaves_divergence_below_the_solvers_tolerance(spheres: tuple[Sphere, ...]) -> None:
    grid = AirGrid(BOX, 32, tolerance=1e-4)
    air = grid.still()
    generator = torch.Generator().manual_seed(1)
    air.faces = tuple(torch.randn(f.shape, generator=generator) for f in air.faces)  # type: ignore[assignment]
    stats = grid.project(air, spheres)
    after = torch.where(grid.solid(spheres, 0.0, air.device), 0.0, grid.divergence(air)).abs().max()
    assert stats.divergence_before > 100.0  # a random field is far from divergence-free
    assert float(after) <= grid.tolerance * stats.divergence_before
    assert float(after) == pytest.approx(stats.divergence_after)
    floor = air.faces[1][:, 0, :]
    assert float(floor.abs().max()) == 0.0  # nothing crosses the floor
    if not spheres:
        assert stats.iterations == 1  # the preconditioner is the exact inverse without a ball


def test_air_flows_around_a_ball_not_into_it_and_faster_past_its_sides() -> None:
    box = Box((0.0, 0.0, 0.0), (0.4, 0.3, 0.3))
    centre, radius = torch.tensor([0.2, 0.15, 0.15]), 0.05
    grid = AirGrid(box, 32)
    air = grid.still()
    ball = (Sphere(tuple(centre.tolist()), radius),)
    for step in range(10):
        grid.step(air, torch.zeros(0, 3), CFG, step * CFG.dt, ball, uniform((0.5, 0.0, 0.0)))
    generator = torch.Generator().manual_seed(0)
    far = torch.rand(4000, 3, generator=generator) * torch.tensor([0.4, 0.3, 0.3])
    far = far[(far - centre).norm(dim=1) > 3.0 * radius]
    u_far = float(grid.velocity_at(air, far)[:, 0].mean())
    assert u_far > 0.1
    directions = torch.randn(4000, 3, generator=generator)
    directions = directions / directions.norm(dim=1, keepdim=True)
    surface = grid.velocity_at(air, centre + radius * directions)
    normal = (surface * directions).sum(1)
    assert float(normal.abs().mean()) < 0.1 * u_far  # no flow into the ball (a voxelised wall: a few % leak)
    assert float(grid.velocity_at(air, centre + 0.5 * radius * directions).abs().max()) == 0.0
    sides = directions[directions[:, 0].abs() < 0.2]  # the belt across the flow
    past = grid.velocity_at(air, centre + 1.25 * radius * sides).norm(dim=1).mean()
    assert float(past) > 1.1 * u_far  # potential flow: 1.26 x at 1.25 radii


@pytest.mark.parametrize("ball", [False, True], ids=["open", "ball"])
def test_a_wind_accelerates_still_air_to_a_t_away_from_obstacles(ball: bool) -> None:
    box = Box((0.0, 0.0, 0.0), (0.4, 0.3, 0.3))
    centre, radius, a = torch.tensor([0.2, 0.15, 0.15]), 0.04, 0.4
    grid = AirGrid(box, 32)
    air = grid.still()
    spheres = (Sphere(tuple(centre.tolist()), radius),) if ball else ()
    steps = 12
    for step in range(steps):
        grid.step(air, torch.zeros(0, 3), CFG, step * CFG.dt, spheres, uniform((a, 0.0, 0.0)))
    expected = torch.tensor([a * steps * CFG.dt, 0.0, 0.0])
    points = torch.rand(3000, 3, generator=torch.Generator().manual_seed(2)) * torch.tensor([0.4, 0.3, 0.3])
    points = points[(points - centre).norm(dim=1) > 3.0 * radius]
    error = (grid.velocity_at(air, points) - expected).norm(dim=1) / expected.norm()
    if ball:  # the ball's disturbance falls as (radius / r)^3: ~2 % at three radii
        assert float(error.mean()) < 0.05 and float(error.max()) < 0.1
    else:
        assert float(error.max()) < 1e-4


def test_still_air_grid_is_todays_still_air_bit_for_bit() -> None:
    """With no buoyancy and no wind the grid stays at rest, and the particles move exactly as with
    air=None (today's path): the grid adds nothing of its own."""
    source = Source((0.15, 0.03, 0.15), 0.025, 30, (0.0, 0.05, 0.0), seed=1)
    spheres = (Sphere((0.15, 0.15, 0.15), 0.04),)
    today, still = paper(CFG, BOX, source), paper(CFG, BOX, source, air=AirGrid(BOX, 16, buoyancy=0.0))
    a, _ = run(today, today.new_state(), 25, Controls(spheres=spheres))
    b, _ = run(still, still.new_state(), 25, Controls(spheres=spheres))
    assert a.air is None and b.air is not None
    assert all(float(f.abs().max()) == 0.0 for f in b.air.faces)
    assert torch.equal(a.positions, b.positions) and torch.equal(a.velocities, b.velocities)


def test_the_air_moves_the_smoke_and_the_smoke_moves_the_air() -> None:
    """Coupling both ways, on both backends: buoyant smoke sets the air rising, and a sparse
    particle at rest beside it is then carried up by drag (with still air it would only rise
    at buoyancy alone)."""
    results = {}
    for backend in ("torch", "auto"):
        state = blob(0.04, (AXIS[0], 0.1, AXIS[1]))
        tracer = torch.tensor([[AXIS[0], 0.05, AXIS[1]]])  # alone below the blob: sparse, so drag acts fully
        slot = int(state.add(tracer, torch.zeros(1, 3)))
        with_air, _ = run(paper(CFG, BOX, air=AirGrid(BOX, 32), backend=backend), state, 15)
        state, _ = run(paper(CFG, BOX, backend=backend), state, 15)
        results[backend] = (state.positions[slot, 1], with_air.positions[slot, 1])
        # 3.4 mm higher (of a 3 cm rise in still air) on both backends when written
        assert float(with_air.positions[slot, 1] - state.positions[slot, 1]) > 0.002
    torch.testing.assert_close(results["torch"][1], results["auto"][1], atol=1e-4, rtol=0.0)


def test_state_copies_carry_the_air() -> None:
    grid = AirGrid(BOX, 8)
    state, _ = paper(CFG, BOX, air=grid).step(blob(0.03, (AXIS[0], 0.1, AXIS[1])))
    copy = state.clone()
    assert copy.air is not state.air and all(torch.equal(a, b) for a, b in zip(copy.air.faces, state.air.faces))
    assert state.padded(state.capacity + 10).air is not state.air


@pytest.mark.parametrize("kwargs, field", [
    ({"cells": 2}, "cells"), ({"cells": 1000}, "cells"), ({"cells": 32.0}, "cells"), ({"buoyancy": -1.0}, "buoyancy"),
    ({"vorticity": float("nan")}, "vorticity"), ({"tolerance": 0.0}, "tolerance"), ({"max_iterations": 0}, "max_iterations"),
    ({"down": (0.0, 0.0, 0.0)}, "down"),
])
def test_bad_air_settings_are_refused_by_name(kwargs: dict, field: str) -> None:
    with pytest.raises(PhysicsInputError, match=field):
        AirGrid(BOX, **kwargs)


def test_the_floor_must_be_where_gravity_points() -> None:
    with pytest.raises(PhysicsInputError, match="air.down"):
        paper(CFG, BOX, air=AirGrid(BOX, 8, down=(0.0, 0.0, -1.0)))
    grid = AirGrid(BOX, 8)
    with pytest.raises(PhysicsInputError, match=r"air.faces\[0\]"):
        grid.step(AirGrid(Box((0, 0, 0), (1, 1, 1)), 8).still(), torch.zeros(0, 3), CFG, 0.0)


HARD_CASES = {
    # a strong wind growing with height (the simulator's speed limit caps it)
    "strong wind": dict(source=Source((0.15, 0.03, 0.15), 0.02, 30, (0.0, 0.1, 0.0), seed=1),
                        wind=WindParams(direction=(1.0, 0.0, 0.0), strength=5.0, growth=10.0)),
    # a ball sitting on the source
    "ball on the source": dict(source=Source((0.15, 0.03, 0.15), 0.02, 30, (0.0, 0.1, 0.0), seed=2),
                               spheres=(Sphere((0.15, 0.05, 0.15), 0.03),)),
    # a thin, fast plume (a narrow source launched at the speed limit)
    "thin fast plume": dict(source=Source((0.15, 0.02, 0.15), 0.006, 12, (0.0, 0.6, 0.0), seed=3)),
    # smoke born in a corner against the floor and two walls, under a wind into them
    "smoke at the walls": dict(source=Source((0.01, 0.01, 0.01), 0.01, 20, (0.0, 0.05, 0.0), seed=4),
                               wind=WindParams(direction=(-1.0, 0.0, 0.0), strength=1.0, growth=0.0)),
}


def run_hard_case(name: str, frames: int) -> None:
    case = HARD_CASES[name]
    wind = case.get("wind")
    force = None if wind is None else wind_force(wind, blowing=lambda time: True)
    grid = AirGrid(BOX, 32, vorticity=0.5)
    sim = paper(CFG, BOX, case["source"], air=grid)
    controls = Controls(force=force, spheres=case.get("spheres", ()))
    state = sim.new_state()
    seeded = left = 0
    for _ in range(frames):
        state, stats = sim.step(state, controls)
        seeded, left = seeded + stats.seeded, left + stats.retired
        limit = CFG.substep(stats.substeps).speed_limit  # the air is held to the substeps' limit
        x = state.positions[state.alive]
        assert bool(torch.isfinite(x).all()) and bool(torch.isfinite(state.velocities[state.alive]).all())
        assert bool((x >= x.new_tensor(BOX.lo)).all() and (x <= x.new_tensor(BOX.hi)).all())
        assert all(bool(torch.isfinite(f).all()) and float(f.abs().max()) <= limit * 1.5 for f in state.air.faces)
        assert stats.air_unconverged == 0  # every projection reached its tolerance
    assert state.n_alive > 0
    assert state.n_alive + left == seeded  # the mass is accounted for: in the box, or counted leaving it


# In the default suite, as issue 23 asks: the four cases take 17 CPU-s together (300 frames each,
# one thread, the 2-core machine), about 9 s of the suite's wall time at -n 2.
@pytest.mark.parametrize("name", list(HARD_CASES))
def test_hard_cases_stay_finite_and_inside_the_box_for_300_frames(name: str) -> None:
    run_hard_case(name, 300)


def test_a_pressure_solve_that_stops_short_is_reported() -> None:
    """A projection cut off before its tolerance says so (AirStats.converged), the step counts it
    and the frame's record carries it; one given the iterations it needs reports nothing. A ball
    above the smoke makes the solve iterate (without walls its preconditioner is exact)."""
    ball = (Sphere((AXIS[0], 0.2, AXIS[1]), 0.05),)
    for iterations, short in ((1, True), (200, False)):
        grid = AirGrid(BOX, 16, max_iterations=iterations)
        _, stats = paper(CFG, BOX, air=grid).step(blob(0.04, (AXIS[0], 0.1, AXIS[1])), Controls(spheres=ball))
        assert (stats.air_unconverged > 0) == short and stats.air_divergence > 0.0
        record = step_record(stats)
        assert record["left_box"] == 0.0 and (record["air_unconverged"] > 0) == short
    assert step_record(None) == {}


@pytest.mark.gpu
def test_the_air_runs_on_cuda_as_on_cpu() -> None:
    grid = AirGrid(BOX, 32)
    state = blob(0.04, (AXIS[0], 0.1, AXIS[1]))
    smoke = state.positions[state.alive]
    airs = {device: grid.still(device) for device in ("cpu", "cuda")}
    for device, air in airs.items():
        for step in range(10):
            grid.step(air, smoke.to(device), CFG, step * CFG.dt, (Sphere((0.15, 0.25, 0.15), 0.04),), uniform((0.2, 0.0, 0.0)))
    for cpu, cuda in zip(airs["cpu"].faces, airs["cuda"].faces):
        torch.testing.assert_close(cuda.cpu(), cpu, atol=1e-4, rtol=1e-3)


def test_a_prediction_simulates_the_air_its_reconstruction_asks_for_and_passes_it_on(tmp_path: Path) -> None:
    """simulation.air_cells (0 by default) switches the air grid on in prediction, recorded in the
    scene so that a continuation keeps it; the default parent predicts with still air as before."""
    still = plume_run(tmp_path / "still", frames=2, warmup=20)
    airy = plume_run(tmp_path / "air", frames=2, warmup=20, quality={"air_cells": 16})
    plain = Run.open(run_predict(still, tmp_path / "p0", frames=4))
    with_air = Run.open(run_predict(airy, tmp_path / "p1", frames=4))
    chained = Run.open(run_predict(with_air.path, tmp_path / "p2", frames=2))
    stepped = [entry["losses"] for entry in with_air.manifest["frames"][1:]]  # each frame records its step
    assert stepped and all("left_box" in losses and "air_divergence" in losses for losses in stepped)
    assert plain.scene.air == Air()
    assert with_air.scene.air == Air(16) and chained.scene.air == Air(16)
    last = plain.frames()[-1]
    a, b = plain.read_frame(last), with_air.read_frame(last)
    assert a.positions.shape == b.positions.shape and not np.array_equal(a.positions[a.alive], b.positions[b.alive])


def test_air_resampled_onto_a_finer_grid_keeps_its_flow() -> None:
    """A continuation on another grid than its parent's starts from the parent's air: a uniform
    sideways breeze (divergence-free, parallel to the closed floor) stays that breeze."""
    coarse, fine = AirGrid(BOX, 16), AirGrid(BOX, 24)
    air = coarse.still()
    air.faces[0].fill_(0.2)
    moved = fine.resample(air)
    assert fine.check(moved) is moved and coarse.resample(air) is air
    assert torch.allclose(moved.faces[0], torch.full_like(moved.faces[0], 0.2), atol=1e-4)
    assert float(moved.faces[1].abs().max()) < 1e-4 and float(moved.faces[2].abs().max()) < 1e-4


def test_a_prediction_keeps_the_air_settings_and_continues_a_coarser_parents_air(tmp_path: Path) -> None:
    """simulation.air_vorticity reaches the prediction and its continuations; a parent whose scene
    records another grid than its frames' air was saved on (an older run continued at a finer
    grid) is continued from its air resampled, not refused."""
    airy = plume_run(tmp_path / "air", frames=2, warmup=20, quality={"air_cells": 16, "air_vorticity": 0.3})
    with_air = Run.open(run_predict(airy, tmp_path / "p1", frames=3))
    chained = Run.open(run_predict(with_air.path, tmp_path / "p2", frames=2))
    stepped = [entry["losses"] for entry in with_air.manifest["frames"][1:]]  # each frame records its step
    assert stepped and all("left_box" in losses and "air_divergence" in losses for losses in stepped)
    assert with_air.scene.air == Air(16, 0.3) and chained.scene.air == Air(16, 0.3)
    manifest = Path(airy) / "manifest.json"
    data = json.loads(manifest.read_text())
    data["scene"]["air"]["cells"] = 24
    manifest.write_text(json.dumps(data))
    finer = Run.open(run_predict(airy, tmp_path / "p3", frames=3))
    air = finer.read_frame(finer.frames()[-1]).air
    assert finer.scene.air == Air(24, 0.3) and air is not None
    assert air.faces[0].shape == tuple(n + (a == 0) for a, n in enumerate(AirGrid(with_air.scene.box, 24).shape))
