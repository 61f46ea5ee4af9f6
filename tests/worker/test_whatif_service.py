"""What-ifs through the service: `from_frame` in the interact job's parameters (checked against
the parent run's finished frames before queueing), and the interact runner's artifacts (the
side-by-side video, the last frame in every export format and the run's frames as a VDB sequence)
published with their kinds."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from fluidcore.exports import EXPORTERS
from fluidcore.spec.controls import InteractionParams, parse_interaction
from fluidcore.predict import run_interact
from fluidcore.runs import Run
from fluidcore.video import probe
from tests.support.predict_scenes import plume_run
from service.database import session_scope
from service.job_types import JobType
from service.models import Job, JobState
from tests.support.service import keyed_client, scene_files, upload_parts
from worker.execution import _published_as
from worker.runners import RunInputs, interact, render

BALL = {"center": [0.0, 0.2, 0.0], "radius": 0.05}


@pytest.fixture
def client(tmp_path: Path) -> Iterator[tuple[TestClient, dict[str, str]]]:
    yield from keyed_client(tmp_path)


def test_from_frame_must_be_a_finished_frame_of_the_parent(client, tmp_path: Path) -> None:
    http, auth = client
    scene = http.post("/v1/scenes", files=upload_parts(scene_files(tmp_path / "scene")), headers=auth).json()
    parent = http.post("/v1/jobs", json={"type": "reconstruct", "scene_id": scene["id"]}, headers=auth).json()["id"]
    manifest = Run.open(plume_run(tmp_path / "parent", frames=3)).manifest  # frames 0..2 of a real run
    http.app.state.storage.put_bytes(f"jobs/{parent}/run/manifest.json", json.dumps(manifest).encode())
    with session_scope(http.app.state.sessionmaker) as session:
        session.get(Job, parent).state = JobState.SUCCEEDED
    ball = {"center": [0.0, 0.2, 0.0], "radius": 0.05}
    request = {"type": "interact", "parent_job_id": parent, "params": {"frames": 5, "ball": ball, "from_frame": 1}}
    created = http.post("/v1/jobs", json=request, headers=auth)
    assert created.status_code == 202, created.text
    assert created.json()["params"]["from_frame"] == 1
    for bad, message in ((7, "params.from_frame: 7 is not a finished frame"), (-1, "from_frame")):
        request["params"]["from_frame"] = bad
        response = http.post("/v1/jobs", json=request, headers=auth)
        assert response.status_code == 422 and message in response.text, response.text


def test_interact_runner_branches_and_returns_its_input_view_and_exports(tmp_path: Path) -> None:
    parent = plume_run(tmp_path / "parent", frames=4)
    inputs = RunInputs(
        job_id="j", job_type=JobType.INTERACT, run_dir=tmp_path / "run", render_dir=tmp_path / "out", device="cpu",
        params={"frames": 2, "from_frame": 1, "wind": {"direction": [1, 0, 0], "strength": 0.3}},
        progress=lambda fraction, stage: None, should_cancel=lambda: False, parent_run=parent,
    )
    files = interact(inputs)
    run = Run.open(tmp_path / "run")
    assert run.frames() == [2, 3] and run.manifest["settings"]["branch_frame"] == 1
    published = {path.name: _published_as(path)[:3] for path in files}
    videos = {name: kind for name, kind in published.items() if kind[0] == "videos"}
    assert videos == {}  # a what-if renders its videos on request
    exports = {name for name, (folder, kind, _) in published.items() if (folder, kind) == ("exports", "export")}
    assert len(exports) == len(EXPORTERS) + 1 and {"splats_000003.ply", "smoke_000002.vdb", "smoke_000003.vdb"} <= exports


@pytest.mark.parametrize("video", ["orbit", "side_by_side"])
def test_render_runner_renders_one_video_of_the_parent_run_with_progress_per_frame(tmp_path: Path, video: str) -> None:
    parent = plume_run(tmp_path / "parent", frames=4)
    what_if = run_interact(parent, tmp_path / "what_if", InteractionParams(ball=parse_interaction(None, BALL).ball), frames=2)
    seen: list[tuple[float, str]] = []
    inputs = RunInputs(
        job_id="r", job_type=JobType.RENDER, run_dir=tmp_path / "run", render_dir=tmp_path / "out", device="cpu",
        params={"video": video}, progress=lambda fraction, stage: seen.append((fraction, stage)),
        should_cancel=lambda: False, parent_run=what_if,
    )
    files = render(inputs)
    assert files == [tmp_path / "out" / f"{video}.mp4"] and _published_as(files[0])[:2] == ("videos", video)
    assert probe(files[0]).n_frames == 2
    # per rendered frame: the orbit's 2; the side-by-side's 2 what-if and 2 factual (a prediction from the parent's end)
    assert [f for f, _ in seen] == [(i + 1) / len(seen) for i in range(len(seen))] and len(seen) == 2 * (1 + (video == "side_by_side"))
    assert {stage for _, stage in seen} == {"render"} and not (tmp_path / "run").exists()  # a render writes no run


def test_interact_runner_ends_its_progress_with_the_export_stage(tmp_path: Path) -> None:
    parent = plume_run(tmp_path / "parent", frames=4)
    seen: list[tuple[float, str]] = []
    inputs = RunInputs(
        job_id="j", job_type=JobType.INTERACT, run_dir=tmp_path / "run", render_dir=tmp_path / "out", device="cpu",
        params={"frames": 2, "wind": {"direction": [1, 0, 0], "strength": 0.3}},
        progress=lambda fraction, stage: seen.append((fraction, stage)), should_cancel=lambda: False, parent_run=parent,
    )
    interact(inputs)
    fractions = [f for f, _ in seen]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0  # never backwards, full at the end
    assert [stage for _, stage in seen][-2:] == ["render", "export"]  # no video to render: straight to the exports
