"""The run folder: written frame by frame, read back exactly, resumed, and refused when it is another run."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fluidcore.cameras import Camera
from fluidcore.runs import FrameState, Run, RunError, Scene


def _camera(name: str = "cam") -> Camera:
    pose = np.eye(4)
    pose[2, 3] = 2.0
    return Camera(name, 50.0, 50.0, 16.0, 12.0, 32, 24, pose)


def _scene() -> Scene:
    return Scene(
        box_lo=(-1.0, 0.0, -1.0),
        box_hi=(1.0, 2.0, 1.0),
        up=(0.0, 1.0, 0.0),
        physics={"rho0": 2.0, "alpha": -3.0, "h": 0.1, "length_scale": 37.5},
        source={"center": [0.0, 0.1, 0.0], "radius": 0.1, "rate": 3, "velocity": [0.0, 0.1, 0.0], "seed": 1},
    )


def _create(path, **changes):
    args = dict(
        kind="reconstruct",
        cameras={"cam": _camera()},
        input_views=["cam"],
        frame_range=(0, 3),
        fps=30.0,
        channels=1,
        background_color=[1.0],
        scene=_scene(),
        settings={"quality": "preview", "iterations": 5},
    )
    args.update(changes)
    return Run.create(path, **args)


def _state(seed: int, n: int = 6, g: int = 4) -> FrameState:
    rng = np.random.default_rng(seed)
    return FrameState(
        positions=rng.normal(size=(n, 3)).astype(np.float32),
        velocities=rng.normal(size=(n, 3)).astype(np.float32),
        alive=rng.random(n) > 0.3,
        time=0.1 * seed,
        gaussians={
            "means": rng.normal(size=(g, 3)),
            "log_scales": rng.normal(size=(g, 3)),
            "quats": rng.normal(size=(g, 4)),
            "opacity_logits": rng.normal(size=g),
            "colors": rng.random((g, 1)),
        },
        extra={"rng": np.arange(5, dtype=np.uint8)},
    )


def test_frames_round_trip_and_manifest_records_losses(tmp_path):
    run = _create(tmp_path / "run")
    written = [_state(1), _state(2)]
    for t, state in enumerate(written):
        run.write_frame(t, state, {"visual": 0.5 + t}, seconds=1.5)
    reopened = Run.open(tmp_path / "run")
    assert reopened.frames() == [0, 1]
    assert reopened.next_frame() == 2
    assert not reopened.manifest["complete"]
    assert reopened.frame_log(1)["losses"] == {"visual": 1.5}
    back = reopened.read_frame(1)
    np.testing.assert_array_equal(back.positions, written[1].positions)
    np.testing.assert_array_equal(back.alive, written[1].alive)
    np.testing.assert_array_equal(back.extra["rng"], written[1].extra["rng"])
    np.testing.assert_allclose(back.gaussians["quats"], written[1].gaussians["quats"].astype(np.float32))
    assert reopened.cameras()["cam"] == _camera()
    assert reopened.scene == _scene()
    manifest = json.loads((tmp_path / "run" / "manifest.json").read_text())
    assert manifest["frames"][0]["file"] == "states/frame_000000.npz"
    assert {"fluidnexus", "numpy", "python"} <= manifest["versions"].keys()


def test_reopening_the_same_run_resumes_and_a_different_one_is_refused(tmp_path):
    run = _create(tmp_path / "run")
    run.write_frame(0, _state(1), {"visual": 1.0}, seconds=1.0)
    again = _create(tmp_path / "run")
    assert again.next_frame() == 1
    with pytest.raises(RunError, match="settings"):
        _create(tmp_path / "run", settings={"quality": "paper"})
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    with pytest.raises(RunError, match="not a run folder"):
        _create(tmp_path / "other")
    assert (tmp_path / "other" / "notes.txt").read_text() == "mine"


def test_completion_and_out_of_order_frames(tmp_path):
    run = _create(tmp_path / "run", frame_range=(5, 7))
    with pytest.raises(RunError, match="expects 5"):
        run.write_frame(6, _state(1), {}, seconds=0.0)
    run.write_frame(5, _state(1), {}, seconds=0.0)
    run.write_frame(6, _state(2), {}, seconds=0.0)
    assert run.manifest["complete"]
    with pytest.raises(RunError, match="not in this run"):
        run.read_frame(7)


def test_bad_states_and_losses_are_refused(tmp_path):
    run = _create(tmp_path / "run")
    bad = _state(1)
    bad.positions[0, 0] = np.nan
    with pytest.raises(RunError, match="positions"):
        FrameState(bad.positions, bad.velocities, bad.alive, bad.time, bad.gaussians)
    with pytest.raises(RunError, match="not finite"):
        run.write_frame(0, _state(1), {"visual": float("nan")}, seconds=0.0)
    with pytest.raises(RunError, match="lack"):
        FrameState(bad.velocities, bad.velocities, bad.alive, 0.0, {"means": np.zeros((1, 3))})


def test_export_keeps_live_particles_and_background_round_trips(tmp_path):
    run = _create(tmp_path / "run")
    state = _state(3)
    exported = state.export()
    assert len(exported["positions"]) == int(state.alive.sum())
    np.testing.assert_array_equal(exported["velocities"], state.velocities[state.alive])
    assert exported["gaussian_colors"].shape == (4, 1)
    image = np.random.default_rng(0).random((24, 32, 1)).astype(np.float32)
    run.write_background({"cam": image})
    np.testing.assert_array_equal(Run.open(tmp_path / "run").background_images()["cam"], image)


def test_open_rejects_folders_that_are_not_runs(tmp_path):
    with pytest.raises(RunError, match="no manifest.json"):
        Run.open(tmp_path)
    (tmp_path / "manifest.json").write_text("{not json")
    with pytest.raises(RunError, match="not valid JSON"):
        Run.open(tmp_path)
