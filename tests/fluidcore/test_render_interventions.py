"""Renders of what-ifs: the ball drawn where it projects (on by default for interact runs, off
for scoring), and the side-by-side factual | what-if video of an interact job."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from fluidcore import artifacts, run_frames
from fluidcore import video
from fluidcore.spec.controls import InteractionParams, parse_interaction
from fluidcore.jobs import JobInputError
from fluidcore.predict import run_interact
from fluidcore.runs import Run
from fluidnexus.cli import app
from tests.support.predict_scenes import plume_run

BALL = {"center": [0.0, 0.2, 0.0], "radius": 0.05}


@pytest.fixture(scope="module")
def parent(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return plume_run(tmp_path_factory.mktemp("plume") / "parent", frames=6, warmup=30)


@pytest.fixture(scope="module")
def what_if(parent: Path, tmp_path_factory: pytest.TempPathFactory) -> Run:
    ball = parse_interaction(None, BALL).ball
    return Run.open(run_interact(parent, tmp_path_factory.mktemp("wi") / "run", InteractionParams(ball=ball), frames=3, from_frame=2))


def test_ball_is_drawn_in_a_render_where_it_projects(what_if: Run) -> None:
    camera = next(iter(what_if.cameras().values()))
    plain = run_frames.render_frames(what_if, camera, interventions=False)
    drawn = run_frames.render_frames(what_if, camera, interventions=True)
    (u, v), = camera.project_numpy(np.array(BALL["center"]))[0]
    changed = np.any(plain != drawn, axis=-1)
    assert changed[:, int(v), int(u)].all()  # at the ball's centre, on every frame (it is there from new frame 0)
    radius_px = camera.fx * BALL["radius"] / camera.project_numpy(np.array(BALL["center"]))[1][0]
    ys, xs = np.nonzero(changed[0])
    assert np.hypot(xs + 0.5 - u, ys + 0.5 - v).max() < radius_px + 3  # and nowhere else


def test_cli_render_draws_interventions_of_interact_runs_by_default(what_if: Run, tmp_path: Path) -> None:
    name = next(iter(what_if.cameras()))
    runner = CliRunner()
    for flag, folder in (([], "default"), (["--no-interventions"], "plain")):
        result = runner.invoke(app, ["render", str(what_if.path), "--camera", name, "--png-dir", str(tmp_path / folder), *flag])
        assert result.exit_code == 0, result.output
    default, plain = (sorted((tmp_path / f).iterdir()) for f in ("default", "plain"))
    assert default[0].read_bytes() != plain[0].read_bytes()


@pytest.mark.parametrize("from_frame", [2, 5])  # inside the parent (its own frames are the factual) and at its end
def test_side_by_side_puts_factual_and_what_if_next_to_each_other(parent: Path, tmp_path: Path, from_frame: int) -> None:
    ball = parse_interaction(None, BALL).ball
    run = Run.open(run_interact(parent, tmp_path / "run", InteractionParams(ball=ball), frames=3, from_frame=from_frame))
    files = artifacts.render_artifacts(run.path, tmp_path / "videos", ["side_by_side"])
    assert tmp_path / "videos" / "side_by_side.mp4" in files
    camera = run.cameras()[run.manifest["input_views"][0]]
    assert video.probe(tmp_path / "videos" / "side_by_side.mp4").n_frames == 3
    large = camera.scaled(96, 128)  # the content, without video coding at the test's tiny size
    both = artifacts.render_side_by_side(run, large)
    assert both.shape[:2] == (3, 128) and both.shape[2] > 2 * 96
    np.testing.assert_array_equal(both[:, 30:, -96:], run_frames.render_frames(run, large, interventions=True)[:, 30:])
    if from_frame == 2:  # the parent holds frames 3..5: they are the factual side
        np.testing.assert_array_equal(both[:, 30:, :96], run_frames.render_frames(Run.open(parent), large, [3, 4, 5])[:, 30:])


def test_only_a_reconstruction_renders_videos_before_it_ends_and_any_video_renders_by_name(
    parent: Path, what_if: Run, tmp_path: Path
) -> None:
    inputs = what_if.manifest["input_views"]
    cameras = list(what_if.cameras())
    assert artifacts.video_names(what_if) == [*cameras, "orbit", "side_by_side"] and len(cameras) > len(inputs)
    assert artifacts.video_names(Run.open(parent)) == [*cameras, "orbit"]
    assert artifacts.eager_videos(Run.open(parent)) == inputs and artifacts.eager_videos(what_if) == []
    other = next(name for name in cameras if name not in inputs)
    files = artifacts.render_artifacts(what_if.path, tmp_path / "one", [other])
    assert files == [tmp_path / "one" / f"{other}.mp4"] and sorted((tmp_path / "one").iterdir()) == files
    with pytest.raises(JobInputError, match="'spin' is not a video of this run"):
        artifacts.render_artifacts(what_if.path, tmp_path / "bad", ["spin"])
    assert not (tmp_path / "bad").exists()


def test_what_if_artifacts_report_progress_per_frame_and_share_one_length(what_if: Run, tmp_path: Path) -> None:
    seen: list[tuple[float, str]] = []
    inputs = what_if.manifest["input_views"]
    names = ["side_by_side", *inputs, "orbit"]  # the side-by-side is rendered last, reusing the input view
    files = artifacts.render_artifacts(what_if.path, tmp_path / "videos", names, progress=lambda f, s: seen.append((f, s)))
    assert sorted(f.name for f in files) == sorted([*(f"{n}.mp4" for n in inputs), "orbit.mp4", "side_by_side.mp4"])
    n = len(what_if.frames())
    assert len(seen) == n * (len(inputs) + 2)  # every input view, the orbit, the factual side
    assert [f for f, _ in seen] == sorted(f for f, _ in seen) and seen[-1] == (1.0, "render") and seen[0][0] < 0.5
    assert {video.probe(f).n_frames for f in files} == {n}  # one length: the players stay in step


def test_orbit_of_a_what_if_draws_the_ball(what_if: Run) -> None:
    drawn = artifacts.render_orbit(what_if, interventions=True)
    plain = artifacts.render_orbit(what_if)
    assert drawn.shape == plain.shape and drawn.shape[0] == len(what_if.frames())
    assert np.all(np.any(drawn != plain, axis=(1, 2, 3)))  # on every frame of the turn


def test_published_videos_are_scaled_to_the_fit_size(what_if: Run, tmp_path: Path) -> None:
    camera = what_if.cameras()[what_if.manifest["input_views"][0]]
    long_side = max(camera.width, camera.height) // 2
    artifacts.render_artifacts(what_if.path, tmp_path / "videos", ["orbit"], long_side=long_side)
    info = video.probe(tmp_path / "videos" / "orbit.mp4")
    assert max(info.width, info.height) in (long_side, long_side + 1)  # + 1: MP4 pads odd sizes
