"""Counterfactuals with physical meaning: a wind pushes the plume along itself, harder when
stronger; a ball is never entered and the smoke goes around it; both act only in their window."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from fluidcore.spec.controls import BallParams, InteractionError, InteractionParams, WindParams, parse_interaction
from fluidcore.predict.job import run_interact, run_predict
from fluidcore.runs import Run
from tests.support.predict_scenes import horizontal_distance, live, plume_run

FRAMES = 15
BALL = {"center": [0.0, 0.2, 0.0], "radius": 0.05}  # above the source (y 0.075), in the plume's way


@pytest.fixture(scope="module")
def parent(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return plume_run(tmp_path_factory.mktemp("plume") / "parent", frames=2, warmup=30)


@pytest.fixture(scope="module")
def calm(parent: Path, tmp_path_factory: pytest.TempPathFactory) -> Run:
    return Run.open(run_predict(parent, tmp_path_factory.mktemp("calm") / "run", frames=FRAMES))


def last_positions(run: Run) -> torch.Tensor:
    return live(run.read_frame(run.frames()[-1]))


def test_wind_pushes_the_centre_of_mass_along_itself_monotonically_in_strength(parent: Path, calm: Run, tmp_path: Path) -> None:
    direction = torch.tensor([1.0, 0.0, 1.0]) / 2**0.5
    shifts = [float(last_positions(calm).mean(0) @ direction)]
    for strength in (0.05, 0.1, 0.2):
        wind = {"direction": direction.tolist(), "strength": strength}
        run = Run.open(run_interact(parent, tmp_path / f"wind{strength}", InteractionParams(wind=WindParams(**wind)), frames=FRAMES))
        positions = last_positions(run)
        shifts.append(float(positions.mean(0) @ direction))
        sideways = positions.mean(0) - float(positions.mean(0) @ direction) * direction
        assert abs(float(sideways[0] - sideways[2])) < 0.2 * (shifts[-1] - shifts[0])  # along the wind, not across
    assert all(b > a for a, b in zip(shifts, shifts[1:])), shifts


def test_wind_acts_only_inside_its_frame_window(parent: Path, calm: Run, tmp_path: Path) -> None:
    wind = {"direction": [1.0, 0.0, 0.0], "strength": 0.2, "start_frame": 4, "end_frame": 8}
    run = Run.open(run_interact(parent, tmp_path / "gust", InteractionParams(wind=WindParams(**wind)), frames=10))
    frames = run.frames()
    for k in range(4):  # before the gust: exactly the calm prediction
        assert torch.equal(live(run.read_frame(frames[k])), live(calm.read_frame(frames[k])))
    assert not torch.equal(live(run.read_frame(frames[4])), live(calm.read_frame(frames[4])))
    # Particles carry the momentum after the gust, but the push itself stopped: the plume's
    # mean x velocity no longer grows once the wind is over (drag only takes speed away).
    speed = [float(torch.from_numpy(run.read_frame(t).velocities[run.read_frame(t).alive])[:, 0].mean()) for t in frames]
    assert speed[7] > speed[3] + 1e-3
    assert speed[9] <= speed[7] + 1e-4


def test_no_particle_is_ever_inside_the_ball_and_the_plume_goes_around_it(parent: Path, calm: Run, tmp_path: Path) -> None:
    run = Run.open(run_interact(parent, tmp_path / "ball", InteractionParams(ball=BallParams(**BALL)), frames=FRAMES))
    center = torch.tensor(BALL["center"])
    for t in run.frames():
        saved = run.read_frame(t)
        assert torch.linalg.vector_norm(live(saved) - center, dim=1).min() >= BALL["radius"] * (1 - 1e-5)
        means = torch.from_numpy(saved.gaussians["means"])
        assert torch.linalg.vector_norm(means - center, dim=1).min() >= BALL["radius"] * (1 - 1e-5)
    # The smoke level with and above the ball has been pushed sideways, away from its axis.
    with_ball, without = last_positions(run), last_positions(calm)
    level = lambda x: x[x[:, 1] > BALL["center"][1]]  # noqa: E731
    spread_ball = horizontal_distance(level(with_ball), BALL["center"]).mean()
    spread_calm = horizontal_distance(level(without), BALL["center"]).mean()
    assert spread_ball > 1.1 * spread_calm


def test_a_moving_ball_arriving_later_changes_nothing_before_it_arrives(parent: Path, calm: Run, tmp_path: Path) -> None:
    ball = {**BALL, "center": [-0.15, 0.2, 0.0], "velocity": [0.3, 0.0, 0.0], "start_frame": 5}
    run = Run.open(run_interact(parent, tmp_path / "thrown", InteractionParams(ball=BallParams(**ball)), frames=10))
    frames = run.frames()
    for k in range(5):
        assert torch.equal(live(run.read_frame(frames[k])), live(calm.read_frame(frames[k])))
    for k in range(5, 10):  # from its start frame the ball is at center + velocity * elapsed time
        center = torch.tensor(ball["center"]) + torch.tensor(ball["velocity"]) * (k - 5) / 30.0
        distance = torch.linalg.vector_norm(live(run.read_frame(frames[k])) - center, dim=1)
        assert distance.min() >= BALL["radius"] * (1 - 1e-5)


def test_wind_and_ball_at_once(parent: Path, calm: Run, tmp_path: Path) -> None:
    wind = {"direction": [1.0, 0.0, 0.0], "strength": 0.1}
    both = InteractionParams(wind=WindParams(**wind), ball=BallParams(**BALL))
    run = Run.open(run_interact(parent, tmp_path / "both", both, frames=FRAMES))
    positions = last_positions(run)
    assert float(positions[:, 0].mean()) > float(last_positions(calm)[:, 0].mean())
    assert torch.linalg.vector_norm(positions - torch.tensor(BALL["center"]), dim=1).min() >= BALL["radius"] * (1 - 1e-5)
    assert run.manifest["settings"]["wind"]["strength"] == 0.1 and run.manifest["settings"]["ball"]["radius"] == 0.05


@pytest.mark.parametrize(
    ("wind", "ball", "message"),
    [
        (None, {"center": [0.0, 5.0, 0.0], "radius": 0.05}, "ball.center .* outside the scene box"),
        ({"direction": [1, 0, 0], "strength": 500.0}, None, "wind.strength"),
        ({"direction": [1, 0, 0], "strength": float("nan")}, None, "wind.strength"),
        (None, {"center": [0.0, 0.2, 0.0], "radius": -1.0}, "ball.radius"),
        ({"direction": [1, 0, 0], "strength": 0.1, "start_frame": 99}, None, "wind.start_frame"),
        (None, None, "needs a wind, a ball or both"),
    ],
)
def test_invalid_interactions_are_refused_before_anything_is_written(
    parent: Path, tmp_path: Path, wind: dict | None, ball: dict | None, message: str
) -> None:
    with pytest.raises(InteractionError, match=message):
        params = parse_interaction(wind, ball)  # the edge: the CLI and the API validate here
        run_interact(parent, tmp_path / "out", params, frames=FRAMES)
    assert not (tmp_path / "out").exists()


def test_the_absurd_wind_limit_is_the_simulators_speed_limit(parent: Path) -> None:
    """The torch-free manifest check and the simulator agree on what this scene resolves."""
    run = Run.open(parent)
    config = run.scene.physics
    limit = config.speed_limit / config.dt
    for strength, ok in ((0.99 * limit, True), (1.01 * limit, False)):
        params = parse_interaction({"direction": [1, 0, 0], "strength": strength}, None)
        if ok:
            params.check_scene(run.scene, FRAMES)
        else:
            with pytest.raises(InteractionError, match="wind.strength"):
                params.check_scene(run.scene, FRAMES)


@pytest.mark.parametrize("motion", ["paper", "carrier"])
def test_a_real_reconstruction_can_be_blown_sideways(tmp_path: Path, motion: str) -> None:
    """The whole chain on a run written by the reconstruction itself (fluidcore.synth scene), with
    either motion model."""
    from fluidcore import run_frames, synth
    from fluidcore.reconstruct import job as reconstruct_job
    from fluidcore.spec.reconstruct import get

    spec = synth.SynthSpec(frames=3, width=24, height=32, views=2)
    cameras = synth.write(synth.generate(spec), tmp_path / "scene")
    quality = get("preview").with_overrides(position_iterations=2, appearance_iterations=1, first_frame_factor=1, motion=motion)
    inputs = {"view_00": tmp_path / "scene/videos/view_00.mp4"}
    parent = reconstruct_job.run_reconstruct(cameras, inputs, tmp_path / "rec", quality=quality)
    calm = Run.open(run_predict(parent, tmp_path / "calm", frames=8))
    wind = InteractionParams(wind=WindParams(direction=(0, 0, 1), strength=0.5))
    windy = Run.open(run_interact(parent, tmp_path / "windy", wind, frames=8))
    assert calm.frames() == windy.frames() == list(range(3, 11))
    shift = float(last_positions(windy)[:, 2].mean() - last_positions(calm)[:, 2].mean())
    free = 0.5 * (1 / 30) ** 2 * 8 * 9 / 2  # wind alone, no drag, 8 semi-implicit Euler steps: a dt^2 n(n+1)/2
    # Drag and particles born later (pushed for less time) take some of it away; nothing adds to it. The
    # carrier's wind moves the air, which moves the smoke after it; its inlet blows straight up, so the
    # young plume's smoke at the source is not blown (0.2 free when written).
    assert (0.3 if motion == "paper" else 0.1) * free < shift < free
    video = run_frames.render_frames(windy, windy.cameras()["view_01"])
    assert video.shape[0] == 8


def test_the_wind_blows_in_exactly_the_frames_its_window_names() -> None:
    """Frames become seconds in one place (predict.interventions) and the window is
    WindParams.active's, whatever float error the simulator's accumulated time carries."""
    from fluidcore.physics import PRESETS, Source
    from fluidcore.predict.interventions import interventions

    wind = WindParams(direction=(1, 0, 0), strength=0.5, start_frame=2, end_frame=4)
    config, start = PRESETS["scalarflow"], 1.0
    force = interventions(InteractionParams(wind=wind), config, Source((0, 0, 0), 0.1, 1), (0, 1, 0), start).force
    p = torch.zeros(1, 3)
    for frame in range(-1, 7):
        for error in (-1e-9, 1e-9):
            blows = bool(force(p, start + frame * config.dt + error).any())
            assert blows == wind.active(frame), (frame, error)


def test_the_air_gains_the_winds_velocity_in_its_window_and_keeps_it() -> None:
    """The wind moves the air as well as the smoke: the air's velocity is the acceleration
    integrated over the seconds blown up to the wind's terminal speed (`WindParams.air_speed`),
    zero before the window and frozen after it."""
    from fluidcore.physics import PRESETS, Source
    from fluidcore.predict.interventions import interventions

    wind = WindParams(direction=(0, 0, 1), strength=0.5, profile="uniform", start_frame=3, end_frame=9)
    config, start = PRESETS["scalarflow"], 2.0
    air = interventions(InteractionParams(wind=wind), config, Source((0, 0, 0), 0.1, 1), (0, 1, 0), start).air
    p = torch.zeros(1, 3)
    speed = lambda frame: float(air(p, start + frame * config.dt)[0, 2])  # noqa: E731
    assert speed(3) == 0.0
    assert speed(5) == pytest.approx(wind.air_speed(2 * config.dt)) == pytest.approx(0.5 * 2 * config.dt, rel=1e-3)
    assert speed(9) == pytest.approx(wind.air_speed(6 * config.dt)) == speed(30)
    assert wind.air_speed(1e3) == pytest.approx(wind.terminal_speed) == pytest.approx(0.5 * 5.0)  # bounded: 5 s of its strength


def test_sparse_smoke_moves_with_the_wind_blown_air_not_at_drag_terminal_speed() -> None:
    """Drag towards still air caps a wind-blown sparse particle at a / k; with the air moving
    too, the particle keeps up with the air, v = a t."""
    from dataclasses import replace

    from fluidcore.physics import PRESETS, wind_air, wind_force
    from fluidcore.physics.step import advance

    config = replace(PRESETS["scalarflow"], alpha=0.0)
    wind = WindParams(direction=(1, 0, 0), strength=0.3, profile="uniform")
    force, air = wind_force(wind, lambda time: True), wind_air(wind, lambda time: time)
    steps = 60
    speeds = {}
    for name, field in (("still air", None), ("moving air", air)):
        x, v = torch.zeros(1, 3), torch.zeros(1, 3)
        for k in range(steps):
            out = advance(x, v, config, time=k * config.dt, force=force, air=field)
            x, v = out.positions, out.velocities
        speeds[name] = float(v[0, 0])
    seconds = steps * config.dt  # a lone particle's own kernel density weakens its drag a little
    assert speeds["still air"] == pytest.approx(wind.strength / config.drag, rel=0.15)
    assert speeds["moving air"] == pytest.approx(wind.strength * seconds, rel=0.05)


def test_a_wind_with_its_own_base_height_ramps_from_zero_in_world_units_wherever_the_source_is() -> None:
    """A ramp from zero at world height 0.065 to 0.2 at 0.765 (profile linear, base_height 0.765,
    growth 1 / 0.7) pushes the same at every height whichever source the reconstruction found."""
    from fluidcore.spec.controls import InteractionParams
    from fluidcore.physics import PRESETS, Source
    from fluidcore.predict.interventions import interventions

    wind = WindParams(direction=(0, 0, -1), strength=0.2, growth=1 / 0.7, profile="linear", base_height=0.765)
    heights = torch.tensor([0.0, 0.065, 0.415, 0.765])
    p = torch.stack([torch.zeros(4), heights, torch.zeros(4)], dim=1)
    expected = torch.tensor([0.0, 0.0, 0.1, 0.2])
    for source_height in (0.03, 0.1, 0.3):
        source = Source((0.0, source_height, 0.0), 0.04, 1)
        force = interventions(InteractionParams(wind=wind), PRESETS["fluidnexus_smoke"], source, (0, 1, 0), 0.0).force
        pushed = -force(p, 0.0)[:, 2]
        assert torch.allclose(pushed, expected, atol=1e-6), (source_height, pushed)
