"""What-ifs branched off any frame of a run (`run_interact(..., from_frame=F)`, `--from-frame`):
at frame 0 (the whole clip re-simulated with the intervention) and mid-clip; the manifest names
the parent and the branch frame."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from fluidcore.spec.controls import InteractionParams, parse_interaction
from fluidcore.predict import run_interact, run_predict
from fluidcore.runs import Run
from fluidnexus.cli import app
from tests.support.predict_scenes import live, plume_run

BRANCH = 5
WIND = parse_interaction({"direction": [1.0, 0.0, 0.0], "strength": 0.3, "start_frame": 2}, None).wind
BALL = parse_interaction(None, {"center": [0.0, 0.2, 0.0], "radius": 0.05}).ball  # in the plume's way


@pytest.fixture(scope="module")
def parent(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return plume_run(tmp_path_factory.mktemp("plume") / "parent", frames=8, warmup=30)


def _mean_x(run: Run, t: int) -> float:
    return float(live(run.read_frame(t))[:, 0].mean())


def test_mid_clip_branch_starts_from_that_frame(parent: Path, tmp_path: Path) -> None:
    factual = Run.open(run_predict(parent, tmp_path / "factual", frames=5, from_frame=BRANCH))
    windy = Run.open(run_interact(parent, tmp_path / "windy", InteractionParams(wind=WIND), frames=5, from_frame=BRANCH))
    assert windy.frames() == factual.frames() == list(range(BRANCH + 1, BRANCH + 6))
    assert windy.manifest["settings"]["branch_frame"] == BRANCH
    assert windy.parent.path.resolve() == parent.resolve()
    # the branch continues the parent's frame 5: its clock goes on from there
    assert windy.read_frame(BRANCH + 1).time == pytest.approx(Run.open(parent).read_frame(BRANCH + 1).time)
    for t in (BRANCH + 1, BRANCH + 2):  # the wind starts at new frame 2: identical to the factual branch before
        assert torch.equal(live(windy.read_frame(t)), live(factual.read_frame(t)))
    assert _mean_x(windy, BRANCH + 5) > _mean_x(factual, BRANCH + 5) + 1e-3  # then it blows the plume along +x


def test_branch_at_frame_zero_resimulates_the_clip_with_the_ball(parent: Path, tmp_path: Path) -> None:
    factual = Run.open(run_predict(parent, tmp_path / "factual0", frames=7, from_frame=0))
    ball = Run.open(run_interact(parent, tmp_path / "ball0", InteractionParams(ball=BALL), frames=7, from_frame=0))
    assert ball.frames() == list(range(1, 8)) and ball.manifest["settings"]["branch_frame"] == 0
    # buoyancy and look are identified on the whole observed window, not on the single frame 0
    assert ball.manifest["settings"]["identified_on_frame"] == Run.open(parent).frames()[-1]
    centre = torch.tensor(BALL.center)
    for t in ball.frames():
        assert float(torch.linalg.vector_norm(live(ball.read_frame(t)) - centre, dim=1).min()) >= BALL.radius - 1e-5
    assert not torch.equal(live(ball.read_frame(7)), live(factual.read_frame(7)))


def test_branch_frame_must_be_a_finished_frame(parent: Path, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="from_frame: 99 is not a finished frame of the parent run"):
        run_interact(parent, tmp_path / "late", InteractionParams(wind=WIND), frames=2, from_frame=99)
    assert not (tmp_path / "late").exists()
    wind = json.dumps({"direction": [1, 0, 0], "strength": 0.3})
    result = CliRunner().invoke(app, ["interact", str(parent), "--frames", "2", "--wind", wind, "--from-frame", "99",
                                      "--out", str(tmp_path / "cli")])
    assert result.exit_code == 2 and "error: from_frame: 99 is not a finished frame of the parent run" in result.output


def test_cli_branch_reports_the_branch_frame(parent: Path, tmp_path: Path) -> None:
    ball = json.dumps({"center": [0.0, 0.2, 0.0], "radius": 0.05})
    result = CliRunner().invoke(app, ["interact", str(parent), "--frames", "2", "--ball", ball, "--from-frame", "3",
                                      "--out", str(tmp_path / "cli"), "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["frames"] == [4, 5] and report["settings"]["branch_frame"] == 3
