"""`fluidnexus bench predict`: one JSON object, scores per view and per horizon, both baselines,
and refusal of a reconstruction that saw more than the observed window."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import pytest
from tests.support.predict_scenes import SPEC, plume_run
from typer.testing import CliRunner

from fluidcore import synth

OBSERVED, FUTURE = (0, 3), (3, 6)


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A synthetic scene with videos for both cameras, and a 'reconstruction' of its first 3 frames."""
    folder = tmp_path_factory.mktemp("scene")
    synth.write(synth.generate(replace(SPEC, frames=FUTURE[1])), folder)
    return folder, plume_run(folder / "reconstruction", frames=OBSERVED[1], warmup=0)


def bench(args: list[str]):  # noqa: ANN201 - click Result
    from fluidnexus.cli import app

    return CliRunner().invoke(app, ["bench", "predict", *args])


def test_json_holds_every_view_every_horizon_and_both_baselines(scene: tuple[Path, Path], tmp_path: Path) -> None:
    folder, reconstruction = scene
    result = bench([
        "--scene", str(folder), "--input-view", "view_00", "--observed", "0:3", "--future", "3:6",
        "--gt", "view_01=videos/view_01.mp4", "--reconstruction", str(reconstruction), "--out", str(tmp_path), "--json",
    ])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert set(report["views"]) == {"view_00", "view_01"}
    assert report["views"]["view_00"]["role"] == "input" and report["views"]["view_01"]["role"] == "held-out"
    for view in report["views"].values():
        for key in ("prediction_psnr", "freeze_psnr", "copy_input_psnr"):
            assert len(view["per_horizon"][key]) == FUTURE[1] - FUTURE[0]
            assert all(math.isfinite(x) and x > 5 for x in view["per_horizon"][key])
        assert 5 < view["resimulation_psnr"] < 100
    assert report["refinement"].startswith("skipped")
    assert report["seconds_per_predicted_frame"] > report["seconds_per_predicted_frame_simulation"] > 0
    assert set(report["beats_at_every_horizon"]) == {"freeze", "copy_input"}


def test_a_reconstruction_of_another_window_is_refused(scene: tuple[Path, Path], tmp_path: Path) -> None:
    folder, reconstruction = scene
    result = bench([
        "--scene", str(folder), "--input-view", "view_00", "--observed", "0:2", "--future", "2:6",
        "--reconstruction", str(reconstruction), "--out", str(tmp_path), "--json",
    ])
    assert result.exit_code == 2 and "--reconstruction" in result.output


def test_future_must_follow_the_observed_window(scene: tuple[Path, Path], tmp_path: Path) -> None:
    folder, reconstruction = scene
    result = bench(["--scene", str(folder), "--input-view", "view_00", "--observed", "0:3", "--future", "4:6",
                    "--reconstruction", str(reconstruction)])
    assert result.exit_code == 2 and "--future must start where --observed ends" in result.output
