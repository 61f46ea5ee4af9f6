"""The air as part of the saved state (issue 23, item 2): every frame of a run that simulates the
air saves it, and every continuation (prediction, branch, resumption, re-simulation) goes on from
the saved air instead of still air; a run written before the air was saved loads as still air."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from fluidcore import synth
from fluidcore.physics.build import build_simulator
from fluidcore.predict import run_predict, run_resimulate
from fluidcore.reconstruct import Reconstructor, prepare, read_inputs
from fluidcore.runs import AIR_FIELDS, FrameState, Run, RunError, SavedAir, state_file
from fluidcore.smoke import SmokeState
from fluidcore.spec.reconstruct import get
from tests.support.predict_scenes import plume_run

CELLS = 12  # a coarse grid: the tests need moving air, not resolved air


def speed(air: SavedAir) -> float:
    return max(float(np.abs(f).max()) for f in air.faces)


def faces_equal(a: SavedAir, b: SavedAir) -> bool:
    return all(np.array_equal(x, y) for x, y in zip(a.faces, b.faces)) and np.array_equal(a.origin, b.origin) and a.spacing == b.spacing


def without_air(run_dir: Path, t: int) -> None:
    """Rewrite frame t of a run as a run written before the air was saved would hold it."""
    path = run_dir / state_file(t)
    with np.load(path) as data:
        kept = {k: data[k] for k in data.files if not k.startswith("air_")}
    with path.open("wb") as file:
        np.savez(file, **kept)


@pytest.fixture(scope="module")
def airy(tmp_path_factory) -> Path:
    return plume_run(tmp_path_factory.mktemp("airy") / "run", frames=3, warmup=20, quality={"air_cells": CELLS})


def test_a_saved_frame_round_trips_the_air(airy: Path, tmp_path: Path) -> None:
    saved = Run.open(airy).read_frame(2)
    assert saved.air is not None and speed(saved.air) > 0.0  # the buoyant plume has set the air moving
    saved.save(tmp_path / "f.npz")
    again = FrameState.load(tmp_path / "f.npz")
    assert faces_equal(again.air, saved.air)
    state = SmokeState.from_frame(again, "cpu")
    assert state.particles.air is not None
    assert faces_equal(state.to_frame().air, saved.air)


def test_a_frame_without_the_air_loads_as_still_air(airy: Path, tmp_path: Path) -> None:
    saved = Run.open(airy).read_frame(2)
    old = FrameState(saved.positions, saved.velocities, saved.alive, saved.time, saved.gaussians, saved.extra)
    old.save(tmp_path / "old.npz")
    with np.load(tmp_path / "old.npz") as data:
        assert not any(k.startswith("air_") for k in data.files)
    loaded = FrameState.load(tmp_path / "old.npz")
    assert loaded.air is None and SmokeState.from_frame(loaded, "cpu").particles.air is None


def test_air_of_a_later_format_or_a_wrong_shape_is_refused(airy: Path, tmp_path: Path) -> None:
    saved = Run.open(airy).read_frame(1)
    arrays = saved._arrays()
    np.savez(tmp_path / "later.npz", **{**arrays, "air_version": np.asarray(2)})
    with pytest.raises(RunError, match="air_version 2"):
        FrameState.load(tmp_path / "later.npz")
    np.savez(tmp_path / "bad.npz", **{**arrays, AIR_FIELDS[0]: arrays[AIR_FIELDS[0]][:-1]})
    with pytest.raises(RunError, match="air_x"):
        FrameState.load(tmp_path / "bad.npz")


def test_the_numpy_sampler_reads_the_air_as_the_simulator_does(airy: Path) -> None:
    """SavedAir.velocity_at (torch-free, for exports and the API) against AirGrid.velocity_at."""
    run = Run.open(airy)
    saved = run.read_frame(2)
    assert run.scene.air.cells == CELLS  # the run's scene records the air it simulates
    grid = build_simulator(run.scene).integrator.air
    box = run.scene.box
    air = SmokeState.from_frame(saved, "cpu").particles.air
    points = torch.rand(500, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    lo, hi = torch.tensor(box.lo, dtype=torch.float64), torch.tensor(box.hi, dtype=torch.float64)
    points = (lo - 0.1 * (hi - lo) + points * 1.2 * (hi - lo)).float()  # some beyond the grid: border values
    expected = grid.velocity_at(air, points).numpy()
    np.testing.assert_allclose(saved.air.velocity_at(points.numpy()), expected, atol=1e-6 * max(speed(saved.air), 1e-6))


def test_a_branch_continues_the_saved_air_and_an_old_parent_starts_still(airy: Path, tmp_path: Path) -> None:
    kept = Run.open(run_predict(airy, tmp_path / "kept", frames=1, from_frame=1))
    parent = Run.open(airy)
    saved = parent.read_frame(1).air
    first = kept.read_frame(2).air
    # one step on from the saved air: nearly the same field (cosine), not a field spun up from rest
    a = np.concatenate([f.ravel() for f in saved.faces])
    b = np.concatenate([f.ravel() for f in first.faces])
    assert float(a @ b / np.linalg.norm(a) / np.linalg.norm(b)) > 0.9
    old = tmp_path / "old"
    plume_run(old, frames=3, warmup=20, quality={"air_cells": CELLS})
    without_air(old, 1)
    assert Run.open(old).read_frame(1).air is None
    fresh = Run.open(run_predict(old, tmp_path / "fresh", frames=1, from_frame=1)).read_frame(2).air
    assert fresh is not None and speed(fresh) < 0.5 * speed(first)  # still air had one step to start moving


def test_resimulation_starts_from_the_first_frames_air_and_steps_it(airy: Path, tmp_path: Path) -> None:
    parent = Run.open(airy)
    resim = Run.open(run_resimulate(airy, tmp_path / "resim"))
    assert faces_equal(resim.read_frame(0).air, parent.read_frame(0).air)
    state = SmokeState.from_frame(parent.read_frame(0), "cpu").particles
    state, _ = build_simulator(resim.scene).step(state)
    np.testing.assert_allclose(resim.read_frame(1).air.faces[1], state.air.faces[1].numpy(), atol=1e-6)


@pytest.fixture(scope="module")
def scene() -> synth.SynthScene:
    return synth.generate(synth.SynthSpec(frames=3, width=32, height=48, views=2, fps=10.0))


def _reconstructor(scene: synth.SynthScene) -> Reconstructor:
    spec = scene.spec
    quality = get("preview").with_overrides(long_side=48, particles_per_frame=spec.particles_per_step, position_iterations=3,
                                            appearance_iterations=2, first_frame_factor=1, air_cells=CELLS,
                                            motion="carrier")
    box = spec.box()
    inputs = read_inputs(scene.cameras, {"view_01": scene.videos["view_01"]}, frame_range=(0, 3), quality=quality)
    return Reconstructor(prepare(scene.cameras, inputs, fps=spec.fps, quality=quality, box=(np.array(box.lo), np.array(box.hi))))


def test_reconstruction_carries_the_air_and_a_resumed_run_continues_it(scene, tmp_path: Path) -> None:
    """S1 with the carrier's air: each frame saves the air stepped from the fitted particles; a run stopped
    after frame 1 and resumed writes the same air at frame 2 as an uninterrupted one."""
    straight = _reconstructor(scene).run(tmp_path / "straight")
    airs = [straight.read_frame(t).air for t in straight.frames()]
    assert all(a is not None for a in airs) and speed(airs[-1]) > 0.0
    assert max(airs[-1].cells) == CELLS  # cells on the box's long side
    recorded = straight.manifest["scene"]  # the air it simulates, recorded: the carrier's grid and its eddy viscosity
    assert recorded["motion"] == "carrier" and recorded["air"]["cells"] == CELLS and recorded["air"]["viscosity"] > 0.0
    calls = iter([False, False, True])
    partial = _reconstructor(scene).run(tmp_path / "resumed", should_stop=lambda: next(calls))
    assert partial.frames() == [0, 1]
    resumed = _reconstructor(scene).run(tmp_path / "resumed")
    assert faces_equal(resumed.read_frame(2).air, airs[2])
