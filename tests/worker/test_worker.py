"""The job executor (what every Celery task runs) against real databases and storage, with
test-double runners that follow fluidcore's contract (per-frame states, resume, cancel)."""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy.exc import IntegrityError

from fluidcore.errors import InputError
from service.database import session_scope
from service.leases import JobBusy
from service.models import Job, JobState, utcnow
from service.storage import LocalStorage, StorageError, log_key, run_prefix
from worker.execution import RUN_SHARE
from worker.runners import RunInputs
from tests.support.service import FAKE_RUNNERS, SimulatedCrash, empty_tables, fake_job, sqlite_url
from tests.support.worker import World


@pytest.fixture(params=["sqlite", "postgres"])
def world(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[World]:
    if request.param == "postgres":
        url = empty_tables(request.getfixturevalue("postgres_url"))
    else:
        url = sqlite_url(tmp_path)
    world = World(tmp_path, url, LocalStorage(tmp_path / "storage"))
    yield world
    world.engine.dispose()


def test_reconstruct_runs_to_success_and_publishes_artifacts(world: World) -> None:
    job_id = world.job(scene_id=world.scene(), params={"frames": [0, 3]})
    assert world.executor().run(job_id) == "succeeded"
    job = world.get(job_id)
    assert job.state == JobState.SUCCEEDED and job.progress == 1.0 and job.error is None
    assert job.attempts == 1 and job.worker == "w1" and job.started_at <= job.finished_at
    assert list(job.stage_seconds) == ["preparing", "fit", "publish"] and all(s >= 0 for s in job.stage_seconds.values())

    artifacts = world.artifacts(job_id)
    assert {n: (a.kind, a.camera) for n, a in artifacts.items()} == {
        "videos/cam0.mp4": ("video", "cam0"), "videos/cam1.mp4": ("video", "cam1"), "videos/orbit.mp4": ("orbit", None),
        "run/manifest.json": ("manifest", None), "run/states/frame_000000.npz": ("state", None),
        "run/states/frame_000001.npz": ("state", None), "run/states/frame_000002.npz": ("state", None),
    }
    for artifact in artifacts.values():
        assert world.storage.stat(artifact.key).size == artifact.size > 0
    assert world.executor().run(job_id) is None  # a duplicate delivery of a finished job does nothing


def test_a_render_job_publishes_its_video_with_its_parents_artifacts(world: World) -> None:
    """A render job (a video asked for on request) gets the parent's run chain like any
    continuation, writes no run of its own, and adds its video to the parent's artifacts under
    the parent's keys; a second render of the same video replaces the row, never a second one."""
    parent = world.job(scene_id=world.scene(), params={"frames": [0, 2]})
    assert world.executor().run(parent) == "succeeded"
    before = set(world.artifacts(parent))
    seen: list[RunInputs] = []

    def render(inputs: RunInputs) -> list[Path]:
        seen.append(inputs)
        return FAKE_RUNNERS["render"](inputs)

    for attempt in range(2):
        job_id = world.job("render", parent_job_id=parent, params={"video": "side_by_side"})
        assert world.executor(f"r{attempt}", {**FAKE_RUNNERS, "render": render}).run(job_id) == "succeeded"
        assert world.get(job_id).progress == 1.0 and world.artifacts(job_id) == {}
        assert world.storage.list(f"{run_prefix(job_id)}/") == []  # no run of its own
    assert seen[0].parent_run is not None and seen[0].parent_run.name == parent
    artifacts = world.artifacts(parent)
    assert set(artifacts) - before == {"videos/side_by_side.mp4"}
    row = artifacts["videos/side_by_side.mp4"]
    assert (row.kind, row.camera, row.key) == ("side_by_side", None, f"jobs/{parent}/videos/side_by_side.mp4")
    assert world.storage.stat(row.key).size == row.size > 0


def test_continuation_gets_the_parent_run_from_storage(world: World) -> None:
    parent = world.job(scene_id=world.scene(), params={"frames": [0, 2]})
    world.executor("a").run(parent)
    seen: list[tuple[RunInputs, dict]] = []

    def interact(inputs: RunInputs) -> list[Path]:
        assert inputs.parent_run is not None
        seen.append((inputs, json.loads((inputs.parent_run / "manifest.json").read_text())))
        return fake_job(inputs)

    child = world.job("interact", parent_job_id=parent, params={"frames": 2, "wind": {"direction": [1, 0, 0]}})
    assert world.executor("b", {**FAKE_RUNNERS, "interact": interact}).run(child) == "succeeded"
    [(inputs, parent_manifest)] = seen
    assert parent_manifest["kind"] == "reconstruct"
    assert inputs.params["wind"] == {"direction": [1, 0, 0]} and inputs.cameras_path is None
    assert not inputs.parent_run.exists()  # the local copy is removed when the job ends

    # A continuation of a continuation: the whole chain is back where its manifests say it is.
    def predict(inputs: RunInputs) -> list[Path]:
        assert inputs.parent_run is not None
        grandparent = inputs.parent_run / json.loads((inputs.parent_run / "manifest.json").read_text())["parent"]
        seen.append((inputs, json.loads((grandparent / "manifest.json").read_text())))
        return fake_job(inputs)

    grandchild = world.job("predict", parent_job_id=child, params={"frames": 2})
    assert world.executor("b", {**FAKE_RUNNERS, "predict": predict}).run(grandchild) == "succeeded"
    assert seen[-1][1]["kind"] == "reconstruct"
    assert list((world.tmp_path / "cache-b" / "jobs").iterdir()) == []


def test_killed_worker_resumes_from_checkpoints_on_another(world: World) -> None:
    job_id = world.job(scene_id=world.scene(), params={"frames": [0, 5], "crash_after": 2})
    first = world.executor("first")
    with pytest.raises(SimulatedCrash):
        first.run(job_id)
    assert world.get(job_id).state == JobState.RUNNING
    checkpointed = [i.key.rsplit("/", 1)[1] for i in world.storage.list(f"{run_prefix(job_id)}/states/")]
    assert checkpointed == ["frame_000000.npz", "frame_000001.npz"]

    second = world.executor("second")
    with pytest.raises(JobBusy):  # the first worker's lease is still live
        second.run(job_id)
    with session_scope(world.sessions) as session:
        job = session.get(Job, job_id)
        job.heartbeat_at = utcnow() - timedelta(seconds=61)
        job.params = {"frames": [0, 5]}
    assert second.run(job_id) == "succeeded"
    computed = (world.tmp_path / "cache-second" / f"computed-{job_id}.txt").read_text().split()
    assert computed == ["2", "3", "4"]
    job = world.get(job_id)
    assert job.attempts == 2 and job.worker == "second"
    assert list((world.tmp_path / "cache-second" / "jobs").iterdir()) == []  # local copies removed at the end


def test_a_continuation_resumes_under_another_work_dir(world: World) -> None:
    """Runs name their parent relative to themselves and a worker fetches a job's ancestors beside
    its run, in the job's own folder: a predict of a predict started under one work dir finishes under
    another, from its checkpoints, with every parent reference resolving inside the new work dir."""
    reconstruct = world.job(scene_id=world.scene(), params={"frames": [0, 2]})
    predict = world.job("predict", parent_job_id=reconstruct, params={"frames": 2})
    for job_id in (reconstruct, predict):
        assert world.executor("a").run(job_id) == "succeeded"
    chained = world.job("predict", parent_job_id=predict, params={"frames": 4, "crash_after": 2})
    with pytest.raises(SimulatedCrash):
        world.executor("a").run(chained)
    with session_scope(world.sessions) as session:
        job = session.get(Job, chained)
        job.heartbeat_at = utcnow() - timedelta(seconds=61)  # the crashed worker's lease ran out
        job.params = {"frames": 4}

    chains: list[list[Path]] = []

    def follow_chain(inputs: RunInputs) -> list[Path]:
        chain, run = [], inputs.run_dir
        while (parent := json.loads((run / "manifest.json").read_text())["parent"]) is not None:
            run = (run / parent).resolve()
            chain.append(run)
        chains.append(chain)
        return fake_job(inputs)

    other = world.executor("b", {**FAKE_RUNNERS, "predict": follow_chain})
    assert other.work_dir != world.executor("a").work_dir
    assert other.run(chained) == "succeeded"
    assert (world.tmp_path / "cache-b" / f"computed-{chained}.txt").read_text().split() == ["2", "3"]
    [chain] = chains
    runs = other.work_dir / "jobs" / chained / "runs"
    assert chain == [runs / predict, runs / reconstruct]  # both resolved inside work dir b, in the job's folder
    assert world.get(chained).attempts == 2


def test_jobs_on_one_work_dir_keep_their_own_copies_of_a_shared_parent(world: World) -> None:
    """Two continuations of one run on workers sharing a work dir: the second one runs and ends
    (pulling the parent again, then removing its local copies) while the first is between frames;
    the first still finds its parent's run intact."""
    parent = world.job(scene_id=world.scene(), params={"frames": [0, 2]})
    assert world.executor("a").run(parent) == "succeeded"
    second = world.job("predict", parent_job_id=parent, params={"frames": 2})
    parent_frames: list[list[str]] = []

    def first_runner(inputs: RunInputs) -> list[Path]:
        assert world.executor("a").run(second) == "succeeded"  # same work dir, meanwhile
        parent_frames.append(sorted(p.name for p in (inputs.parent_run / "states").iterdir()))
        return fake_job(inputs)

    first = world.job("predict", parent_job_id=parent, params={"frames": 2})
    assert world.executor("a", {**FAKE_RUNNERS, "predict": first_runner}).run(first) == "succeeded"
    assert parent_frames == [["frame_000000.npz", "frame_000001.npz"]]


def test_progress_and_stage_time_are_visible_while_running(world: World) -> None:
    import time

    snapshots: list[Job] = []

    def slow(inputs: RunInputs) -> list[Path]:
        inputs.progress(0.5, "fit")
        time.sleep(1.2)  # past the one-second write throttle
        inputs.progress(0.6, "fit")
        snapshots.append(world.get(inputs.job_id))
        return []

    job_id = world.job(scene_id=world.scene())
    assert world.executor(runners={**FAKE_RUNNERS, "reconstruct": slow}).run(job_id) == "succeeded"
    [running] = snapshots
    assert running.state == JobState.RUNNING and running.stage == "fit"
    assert running.progress == pytest.approx(0.6 * RUN_SHARE)  # the runner's share of the whole job
    assert running.stage_seconds["fit"] >= 1.2


def test_a_job_whose_worker_keeps_dying_is_failed(world: World) -> None:
    job_id = world.job(scene_id=world.scene(), state=JobState.RUNNING, attempts=3)
    assert world.executor().run(job_id) == "failed"  # by its claim: it never ran
    job = world.get(job_id)
    assert job.state == JobState.FAILED and "gave up after 3 attempts" in job.error


def test_cancel_stops_between_frames(world: World) -> None:
    job_id = world.job(scene_id=world.scene(), params={"frames": [0, 6]})
    executor = world.executor()

    def cancel_after_two(inputs: RunInputs) -> list[Path]:
        def progress(fraction: float, stage: str) -> None:
            inputs.progress(fraction, stage)
            if fraction >= 2 / 6:
                with session_scope(world.sessions) as session:
                    session.get(Job, job_id).cancel_requested = True

        return fake_job(RunInputs(**{**inputs.__dict__, "progress": progress}))

    executor.runners = {**FAKE_RUNNERS, "reconstruct": cancel_after_two}
    assert executor.run(job_id) == "cancelled"
    job = world.get(job_id)
    assert job.state == JobState.CANCELLED and job.finished_at is not None
    assert 0 < job.progress < 0.5
    assert len(world.storage.list(f"{run_prefix(job_id)}/states/")) == 2
    assert world.artifacts(job_id) == {}


def test_a_job_cancelled_while_queued_never_runs(world: World) -> None:
    job_id = world.job(scene_id=world.scene(), state=JobState.QUEUED, cancel_requested=True)
    assert world.executor().run(job_id) == "cancelled"
    assert world.get(job_id).state == JobState.CANCELLED
    assert world.storage.list(f"{run_prefix(job_id)}/") == []


def test_an_input_error_fails_the_job_with_its_message(world: World) -> None:
    message = "ball center [9, 9, 9] is outside the scene box"

    def failing(inputs: RunInputs) -> list[Path]:
        inputs.progress(0.5, "fit")
        raise InputError(message)

    job_id = world.job(scene_id=world.scene())
    assert world.executor(runners={**FAKE_RUNNERS, "reconstruct": failing}).run(job_id) == "failed"
    job = world.get(job_id)
    assert job.state == JobState.FAILED and job.error == message and job.finished_at is not None


def test_an_internal_errors_text_stays_out_of_the_job_log_its_owner_reads(world: World) -> None:
    """Issue 20: a raw SQL IntegrityError reached the job's owner. The incident id is in the job's
    log (GET /v1/jobs/{id}/logs); the SQL and the traceback only in the worker's own log."""
    error = IntegrityError("INSERT INTO artifacts (job_id, name) VALUES (?, ?)", ("j1", "videos/x.mp4"), Exception("UNIQUE"))

    def failing(inputs: RunInputs) -> list[Path]:
        raise error

    job_id = world.job(scene_id=world.scene())
    assert world.executor(runners={**FAKE_RUNNERS, "reconstruct": failing}).run(job_id) == "failed"
    incident = re.fullmatch(r"internal error \(id ([0-9a-f]{12})\): see the worker log", world.get(job_id).error or "")
    assert incident is not None
    job_log = world.storage.read_bytes(log_key(job_id)).decode()
    assert incident[1] in job_log and "INSERT INTO" not in job_log and "Traceback" not in job_log


@pytest.mark.parametrize(
    "error",
    [RuntimeError("CUDA out of memory"), ValueError("operands could not be broadcast together"),
     IntegrityError("INSERT INTO artifacts ...", {}, Exception("UNIQUE constraint failed: artifacts.key"))],
)
def test_any_other_runner_error_is_an_internal_error_with_an_id_in_the_log(
    world: World, error: Exception, caplog: pytest.LogCaptureFixture
) -> None:
    """A bug (even a ValueError) is not bad input: the job's error names only an id, and the
    worker's log holds the traceback under that id; no exception text reaches the job."""

    def failing(inputs: RunInputs) -> list[Path]:
        raise error

    job_id = world.job(scene_id=world.scene())
    assert world.executor(runners={**FAKE_RUNNERS, "reconstruct": failing}).run(job_id) == "failed"
    assert_internal_error(world.get(job_id).error, str(error), caplog)


def test_a_bug_deep_inside_a_fluidcore_job_is_an_internal_error_and_bad_input_is_not(
    world: World, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """fluidcore's own runners: a numpy call that raises ValueError deep inside a what-if fails the
    job as an internal error; a ball outside the parent's box fails it with its message."""
    from tests.support.predict_scenes import plume_run
    from worker.runners import FLUIDCORE_RUNNERS
    from worker.sync import FolderMirror

    parent = world.job(state=JobState.SUCCEEDED)
    FolderMirror(world.storage, plume_run(world.tmp_path / "plume", frames=3), run_prefix(parent)).push()
    executor = world.executor(runners={**FAKE_RUNNERS, **FLUIDCORE_RUNNERS})
    outside = world.job("interact", parent_job_id=parent, params={"frames": 2, "ball": {"center": [9, 9, 9], "radius": 0.05}})
    assert executor.run(outside) == "failed"
    assert world.get(outside).error.startswith("ball.center [9.0, 9.0, 9.0] is outside the scene box")

    def broken_dot(*args: object, **kwargs: object) -> None:
        raise ValueError("shapes (3,) and (2,) not aligned")

    monkeypatch.setattr(np, "dot", broken_dot)  # fluidcore.predict.interventions: the wind's base height
    wind = {"direction": [1, 0, 0], "strength": 0.1}
    windy = world.job("interact", parent_job_id=parent, params={"frames": 2, "wind": wind})
    assert executor.run(windy) == "failed"
    assert_internal_error(world.get(windy).error, "not aligned", caplog)


def assert_internal_error(error: str | None, text: str, caplog: pytest.LogCaptureFixture) -> None:
    """The job's `error` is "internal error (id X): see the worker log" and nothing else; the log
    has X with the exception and its traceback."""
    match = re.fullmatch(r"internal error \(id ([0-9a-f]{12})\): see the worker log", error or "")
    assert match is not None, error
    [record] = [r for r in caplog.records if match[1] in r.getMessage() and r.exc_info is not None]
    assert text in str(record.exc_info[1]) and "Traceback (most recent call last)" in caplog.text


def test_transient_storage_fault_gives_the_job_back_for_a_retry(world: World) -> None:
    def storage_down(inputs: RunInputs) -> list[Path]:
        raise StorageError("put jobs/x: connection refused")

    job_id = world.job(scene_id=world.scene())
    with pytest.raises(StorageError):
        world.executor(runners={**FAKE_RUNNERS, "reconstruct": storage_down}).run(job_id)
    job = world.get(job_id)
    assert job.state == JobState.QUEUED and job.heartbeat_at is None and job.stage == "waiting to retry"
    assert world.executor("retry").run(job_id) == "succeeded"  # no lease to wait for


def test_s3_storage_round_trip(tmp_path: Path) -> None:
    """The same executor against the S3 backend (moto's server), SQLite database."""
    from moto.server import ThreadedMotoServer

    from service.storage import MinioStorage
    from tests.support.service import free_port

    port = free_port()
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    try:
        storage = MinioStorage(f"127.0.0.1:{port}", "k", "s", "fluidnexus", region="us-east-1")
        storage.ensure_bucket()
        world = World(tmp_path, sqlite_url(tmp_path), storage)
        job_id = world.job(scene_id=world.scene(), params={"frames": [0, 2]})
        assert world.executor().run(job_id) == "succeeded"
        video = world.artifacts(job_id)["videos/cam0.mp4"]
        assert storage.stat(video.key).size == video.size
        world.engine.dispose()
    finally:
        server.stop()
