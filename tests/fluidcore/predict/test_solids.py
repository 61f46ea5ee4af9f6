"""Prediction and what-ifs of a run whose scene holds solids (issue 48): the continuation
simulates the parent's scene, its static balls included, so the smoke never enters them, and a
what-if's own ball joins them. The same plume without the solid passes through where it sits."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from fluidcore.predict.job import run_interact, run_predict
from fluidcore.runs import Run
from fluidcore.spec.controls import BallParams, InteractionParams
from fluidcore.spec.solids import SolidBall
from tests.support.predict_scenes import live, plume_run

FRAMES = 12
SOLID = SolidBall(center=(0.0, 0.2, 0.0), radius=0.05)  # above the source (y 0.075), in the plume's way
WHAT_IF_BALL = BallParams(center=(0.0, 0.32, 0.0), radius=0.04)  # above the solid, still in the plume


def _nearest(run: Run, center: tuple[float, float, float]) -> tuple[float, float]:
    """How close the live particles and the visual Gaussians of the run's frames came to `center`."""
    particles = gaussians = float("inf")
    point = torch.tensor(center)
    for t in run.frames():
        saved = run.read_frame(t)
        particles = min(particles, float(torch.linalg.vector_norm(live(saved) - point, dim=1).min()))
        means = torch.from_numpy(saved.gaussians["means"])
        gaussians = min(gaussians, float(torch.linalg.vector_norm(means - point, dim=1).min()))
    return particles, gaussians


@pytest.fixture(scope="module")
def parent(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return plume_run(tmp_path_factory.mktemp("plume") / "parent", frames=2, warmup=30, solids=(SOLID,))


def test_a_prediction_keeps_the_smoke_out_of_the_runs_solid(parent: Path, tmp_path: Path) -> None:
    run = Run.open(run_predict(parent, tmp_path / "predicted", frames=FRAMES))
    assert run.scene.solids == (SOLID,)  # recorded, and passed on down a chain of continuations
    assert min(_nearest(run, SOLID.center)) >= SOLID.radius * (1 - 1e-5)
    bare = plume_run(tmp_path / "bare", frames=2, warmup=30)
    without = Run.open(run_predict(bare, tmp_path / "without", frames=FRAMES))
    assert _nearest(without, SOLID.center)[0] < 0.5 * SOLID.radius  # the solid sits where the smoke goes


def test_a_what_ifs_ball_joins_the_scenes_solids(parent: Path, tmp_path: Path) -> None:
    run = Run.open(run_interact(parent, tmp_path / "what-if", InteractionParams(ball=WHAT_IF_BALL), frames=FRAMES))
    assert run.scene.solids == (SOLID,)
    assert min(_nearest(run, SOLID.center)) >= SOLID.radius * (1 - 1e-5)
    assert min(_nearest(run, WHAT_IF_BALL.center)) >= WHAT_IF_BALL.radius * (1 - 1e-5)
