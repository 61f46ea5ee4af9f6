"""The CLI's job options come from the spec's parameter models (`fluidnexus.cli.options`): their
help is the field's description and range, their defaults the model's, and a value the model
refuses exits 2 with one line naming the field, before any work starts."""

from __future__ import annotations

import inspect
import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from fluidcore.spec.simulation import AIR_CELLS
from fluidcore.spec.controls import WindParams
from fluidcore.spec.jobs import InteractParams, ReconstructParams
from fluidnexus.cli import app
from fluidnexus.cli.scenes import reconstruct

runner = CliRunner()


def _help(command: str) -> str:
    result = runner.invoke(app, [command, "--help"], env={"COLUMNS": "400"})
    assert result.exit_code == 0, result.output
    return " ".join(result.output.replace("│", " ").split())


def test_help_states_the_models_descriptions_and_ranges() -> None:
    air = ReconstructParams.model_fields["air_cells"]
    assert air.description in _help("reconstruct")
    assert f"(allowed: 0 or {AIR_CELLS[0]}..{AIR_CELLS[1]})" in _help("reconstruct")  # the schema's "0 or at least 8" in range
    strength = WindParams.model_json_schema()["properties"]["strength"]
    interact = _help("interact")
    assert f'"strength": {strength["description"]} (allowed: {strength["minimum"]}..{strength["maximum"]})' in interact
    assert InteractParams.model_fields["from_frame"].description in interact


def test_defaults_are_the_models() -> None:
    options = inspect.signature(reconstruct).parameters
    for name in ("air_cells", "air_vorticity", "entrainment"):
        assert options[name].default.default == ReconstructParams.model_fields[name].default, name


@pytest.mark.parametrize(("args", "message"), [
    (["predict", "--frames", "0"], "error: frames: Input should be greater than or equal to 1"),
    (["interact", "--frames", "2", "--wind", json.dumps({"direction": [1, 0, 0], "strength": 5000})],
     "error: wind.strength: Input should be less than or equal to 1000"),
    (["interact", "--frames", "2", "--ball", json.dumps({"center": [0, 0, 0], "radius": 0.1}), "--from-frame", "-1"],
     "error: from_frame: Input should be greater than or equal to 0"),
    (["interact", "--frames", "0", "--ball", json.dumps({"center": [0, 0, 0], "radius": 0.1})], "error: frames: Input should be"),
])
def test_a_value_the_model_refuses_exits_2_naming_the_field(tmp_path: Path, args: list[str], message: str) -> None:
    command, *options = args
    result = runner.invoke(app, [command, str(tmp_path), *options, "--out", str(tmp_path / "out")])
    assert result.exit_code == 2 and message in result.output, result.output
    assert not (tmp_path / "out").exists()
