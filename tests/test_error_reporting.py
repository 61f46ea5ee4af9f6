"""A user's mistake and a bug are told apart everywhere (fluidcore.errors): a `fluidcore.errors.InputError`
is shown as it is (CLI `error: ...` exit 2, API 422), anything else, even a ValueError from
deep inside numpy, is an internal error: an id for the user, the traceback in the log under
that id (CLI exit 1, API 500). The worker's side is in test_worker.py."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from typer.testing import CliRunner

from fluidcore.errors import InputError
from fluidnexus.cli import app
from tests.support.predict_scenes import plume_run
from service.database import session_scope
from service.models import Scene
from tests.support.service import keyed_client, scene_files, upload_parts

WIND = json.dumps({"direction": [1, 0, 0], "strength": 0.1})
ID = re.compile(r"internal error \(id ([0-9a-f]{12})\)")


def broken(*args: object, **kwargs: object) -> None:
    """Stands for a bug in a numpy call: numpy's own error type, ValueError."""
    raise ValueError("shapes (3,) and (2,) not aligned")


def logged_traceback(caplog: pytest.LogCaptureFixture, incident: str) -> BaseException:
    """The exception logged with its traceback under `incident`."""
    [record] = [r for r in caplog.records if incident in r.getMessage() and r.exc_info is not None]
    return record.exc_info[1]


def test_every_fluidcore_error_a_user_can_fix_derives_from_input_error() -> None:
    from fluidcore import exports, jobs, metrics, runs, synth, video
    from fluidcore.cameras import camera
    from fluidcore.generative import finetune, models, novel_view, refine
    from fluidcore.reconstruct import identify, images, loop, scene_physics
    from fluidcore.render import gaussians
    from fluidcore.spec import controls, physics, reconstruct, scene, simulation, source_hint

    kinds = [
        exports.ExportError, source_hint.SourceHintError, images.EstimationError, reconstruct.PresetError, simulation.SimulationConfigError,
        loop.ReconstructionError, identify.IdentificationError, scene_physics.PhysicsChoiceError, camera.CameraError,
        novel_view.NovelViewError, refine.RefineError, finetune.FinetuneError, jobs.JobInputError, metrics.MetricError,
        physics.PhysicsInputError, scene.SceneError, gaussians.RenderError, runs.RunError, controls.InteractionError, video.VideoError,
        synth.SynthError, models.MissingWeights,
    ]
    assert [k.__name__ for k in kinds if not issubclass(k, InputError)] == []


def test_cli_reports_a_bug_deep_inside_a_job_as_an_internal_error_with_an_id(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    parent = plume_run(tmp_path / "parent", frames=3)
    monkeypatch.setattr(np, "dot", broken)  # fluidcore.predict.interventions: the wind's base height
    result = CliRunner().invoke(app, ["interact", str(parent), "--frames", "2", "--wind", WIND, "--out", str(tmp_path / "out")])
    assert result.exit_code == 1, result.output
    match = ID.search(result.output)
    assert match is not None and "error: internal error" in result.output, result.output
    assert "not aligned" in str(logged_traceback(caplog, match[1]))


def test_cli_still_reports_bad_input_as_exit_2_with_its_message(tmp_path: Path) -> None:
    parent = plume_run(tmp_path / "parent", frames=3)
    args = ["interact", str(parent), "--frames", "2", "--wind", WIND, "--from-frame", "7", "--out", str(tmp_path / "out")]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 2 and "error: from_frame: 7 is not a finished frame of the parent run" in result.output, result.output
    assert "internal error" not in result.output


def test_cli_prints_the_bugs_traceback_on_stderr_without_any_logging_setup(tmp_path: Path) -> None:
    """The real console script: no logging configured, the traceback still reaches stderr."""
    parent = plume_run(tmp_path / "parent", frames=3)
    script = (
        "import sys, numpy\n"
        "def broken(*a, **k): raise ValueError('shapes (3,) and (2,) not aligned')\n"
        "numpy.dot = broken\n"
        "from fluidnexus.cli import main\n"
        f"sys.argv = ['fluidnexus', 'interact', {str(parent)!r}, '--frames', '2', '--wind', {WIND!r}, '--out', {str(tmp_path / 'out')!r}]\n"
        "main()\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path), "OMP_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 1, done.stderr
    last = done.stderr.strip().splitlines()[-1]
    match = ID.search(last)
    assert match is not None and last.startswith("error: internal error") and "not aligned" not in last, done.stderr
    assert "Traceback (most recent call last)" in done.stderr and f"id {match[1]}" in done.stderr.split("Traceback")[0]


@pytest.fixture
def client(tmp_path: Path) -> Iterator[tuple[TestClient, dict[str, str]]]:
    yield from keyed_client(tmp_path)


def test_api_answers_4xx_for_a_user_error_and_500_with_an_id_for_a_bug(
    client, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    http, auth = client
    scene = http.post("/v1/scenes", files=upload_parts(scene_files(tmp_path / "scene")), headers=auth).json()["id"]
    assert http.get(f"/v1/scenes/{scene}", headers=auth).status_code == 200

    with monkeypatch.context() as patch:  # a bug deep inside the geometry reader (fluidcore.cameras.Camera.center)
        patch.setattr(np, "eye", broken)
        answer = TestClient(http.app, raise_server_exceptions=False).get(f"/v1/scenes/{scene}", headers=auth)
    assert answer.status_code == 500, answer.text
    match = ID.fullmatch(answer.json()["detail"])
    assert match is not None and "not aligned" not in answer.text, answer.text
    assert "not aligned" in str(logged_traceback(caplog, match[1]))

    with session_scope(http.app.state.sessionmaker) as session:  # a camera file fluidcore refuses: CameraError
        http.app.state.storage.put_bytes(session.get(Scene, scene).cameras_key, b'{"frames": 3}')
    answer = http.get(f"/v1/scenes/{scene}", headers=auth)
    assert answer.status_code == 422 and "missing field frames" in answer.json()["detail"], answer.text
