"""Faults inside one job's run (issue 16): a cancel in a stage without frames (prepare) is
honoured, and a storage error while publishing leaves nothing half-published."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from service.database import session_scope
from service.models import Job, JobState
from service.storage import LocalStorage, StorageError, videos_prefix
from worker.runners import RunInputs
from service_support import FAKE_RUNNERS, fake_job, sqlite_url
from test_worker import World


@pytest.fixture
def world(tmp_path: Path) -> Iterator[World]:
    world = World(tmp_path, sqlite_url(tmp_path), LocalStorage(tmp_path / "storage"))
    yield world
    world.engine.dispose()


def test_a_cancel_during_prepare_is_honoured(world: World) -> None:
    """The runner's prepare stage reports progress but has no frames, so it never asks should_cancel."""
    job_id = world.job(scene_id=world.scene(), params={"frames": [0, 3]})
    reports = []

    def long_prepare(inputs: RunInputs) -> list[Path]:
        with session_scope(world.sessions) as session:  # the user cancels while the job prepares
            session.get(Job, job_id).cancel_requested = True
        for step in range(5):
            reports.append(step)
            inputs.progress(0.01 * step, "prepare" if step == 0 else f"prepare step {step}")
        return fake_job(inputs)

    assert world.executor(runners={**FAKE_RUNNERS, "reconstruct": long_prepare}).run(job_id) == "cancelled"
    job = world.get(job_id)
    assert job.state == JobState.CANCELLED and reports == [0]  # stopped at the first report
    assert world.artifacts(job_id) == {}


def test_a_cancel_while_fetching_inputs_stops_before_the_runner(world: World) -> None:
    job_id = world.job(scene_id=world.scene())
    executor = world.executor(runners={**FAKE_RUNNERS, "reconstruct": lambda inputs: pytest.fail("ran")})
    fetch = executor._fetch_inputs

    def slow_fetch(*args):  # type: ignore[no-untyped-def]
        with session_scope(world.sessions) as session:
            session.get(Job, job_id).cancel_requested = True
        return fetch(*args)

    executor._fetch_inputs = slow_fetch  # type: ignore[method-assign]
    assert executor.run(job_id) == "cancelled"


def test_a_storage_error_while_publishing_lists_and_keeps_nothing_half_written(world: World) -> None:
    job_id = world.job(scene_id=world.scene(), params={"frames": [0, 2]})
    put_file = world.storage.put_file
    published = []

    def full_after_one_video(key, path, content_type="application/octet-stream"):  # type: ignore[no-untyped-def]
        if key.startswith(videos_prefix(job_id)):
            if published:
                raise StorageError(f"put {key}: no space left on device")
            published.append(key)
        return put_file(key, path, content_type)

    world.storage.put_file = full_after_one_video  # type: ignore[method-assign]
    with pytest.raises(StorageError, match="no space left"):
        world.executor().run(job_id)
    job = world.get(job_id)
    assert job.state == JobState.QUEUED and job.stage == "waiting to retry"  # the task retries, then fails it
    assert world.artifacts(job_id) == {}
    assert world.storage.list(f"{videos_prefix(job_id)}/") == []  # the one video that made it was removed

    world.storage.put_file = put_file  # type: ignore[method-assign]
    assert world.executor("retry").run(job_id) == "succeeded"
    assert {a.kind for a in world.artifacts(job_id).values()} >= {"video", "orbit", "manifest"}
