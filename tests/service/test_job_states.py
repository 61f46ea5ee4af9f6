"""The job state machine (service.job_states): every allowed state change, by whom; every other
one refused without a write; what each transition function records; and the reaper's
conditional `send_again` taking a stale job once."""

from __future__ import annotations

import itertools
from datetime import timedelta
from pathlib import Path

import pytest

from service import job_states
from service.database import make_engine, make_sessionmaker, migrate, session_scope
from service.job_states import Actor, IllegalTransition
from service.models import Job, JobState, utcnow
from tests.support.service import sqlite_url

Q, R, S, F, C = "queued", "running", "succeeded", "failed", "cancelled"
ALLOWED = {  # (from, to): who may; written out here, not read from the module under test
    (Q, R): {"worker"},
    (R, R): {"worker"},
    (R, S): {"worker"},
    (R, F): {"worker"},
    (R, C): {"worker"},
    (R, Q): {"worker", "reaper"},
    (Q, C): {"API", "worker", "reaper"},  # the reaper: a continuation whose parent's end went unnoticed
    (Q, F): {"worker"},
}


@pytest.mark.parametrize(("current", "to", "actor"), list(itertools.product(JobState, JobState, Actor)))
def test_each_change_is_allowed_to_exactly_the_actors_that_make_it(current: JobState, to: JobState, actor: Actor) -> None:
    allowed = actor.value in ALLOWED.get((current.value, to.value), set())
    if allowed:
        job_states.check("j", current, to, actor)
    else:
        with pytest.raises(IllegalTransition, match=f"the {actor} may not move it from {current} to {to}"):
            job_states.check("j", current, to, actor)


def job(state: JobState, **fields: object) -> Job:
    defaults: dict[str, object] = {"stage": "queued", "attempts": 0, "lease_token": 0, "progress": 0.0}
    return Job(id="j1", owner="alice", type="reconstruct", state=state, **{**defaults, **fields})


def test_start_claims_a_queued_or_expired_job_with_a_new_token() -> None:
    queued = job(JobState.QUEUED, error="old")
    assert job_states.start(queued, "w1") == 1
    assert (queued.state, queued.stage, queued.error, queued.worker, queued.attempts) == (R, "preparing", None, "w1", 1)
    first_start = queued.started_at
    assert first_start is not None and queued.heartbeat_at is not None
    assert job_states.start(queued, "w2") == 2  # its lease expired: claimed again, started_at kept
    assert queued.started_at == first_start and queued.worker == "w2" and queued.attempts == 2


def test_the_end_states_record_what_ended_the_job() -> None:
    done = job(JobState.RUNNING, stage="publish")
    job_states.succeed(done)
    assert (done.state, done.stage, done.progress) == (S, "done", 1.0) and done.finished_at is not None
    failed = job(JobState.RUNNING, stage="reconstruct")
    job_states.fail(failed, "frames: bad", Actor.WORKER)
    assert (failed.state, failed.stage, failed.error) == (F, "reconstruct", "frames: bad")  # the stage it failed in
    orphan = job(JobState.QUEUED, stage="waiting for job p")
    job_states.cancel(orphan, Actor.REAPER, reason="parent job p failed")
    assert (orphan.state, orphan.stage, orphan.error) == (C, "cancelled", "parent job p failed")
    cancelled = job(JobState.QUEUED, error="old")
    job_states.cancel(cancelled, Actor.API)
    assert (cancelled.state, cancelled.stage, cancelled.error) == (C, "cancelled", None)
    assert cancelled.finished_at is not None


def test_a_job_goes_back_to_the_queue_with_no_lease() -> None:
    faulted = job(JobState.RUNNING, heartbeat_at=utcnow())
    job_states.give_back(faulted)
    assert (faulted.state, faulted.stage, faulted.heartbeat_at) == (Q, "waiting to retry", None)
    orphan = job(JobState.RUNNING, heartbeat_at=utcnow())
    job_states.orphaned(orphan)
    assert (orphan.state, orphan.stage, orphan.heartbeat_at) == (Q, job_states.RESUME_STAGE, None)


@pytest.mark.parametrize(
    ("state", "change"),
    [
        (JobState.SUCCEEDED, lambda j: job_states.succeed(j)),
        (JobState.FAILED, lambda j: job_states.fail(j, "again", Actor.WORKER)),
        (JobState.CANCELLED, lambda j: job_states.cancel(j, Actor.WORKER)),
        (JobState.SUCCEEDED, lambda j: job_states.start(j, "w")),
        (JobState.QUEUED, lambda j: job_states.give_back(j)),
        (JobState.CANCELLED, lambda j: job_states.orphaned(j)),
        (JobState.RUNNING, lambda j: job_states.cancel(j, Actor.API)),  # the API asks; the runner stops it
        (JobState.RUNNING, lambda j: job_states.fail(j, "x", Actor.API)),
    ],
)
def test_a_refused_change_writes_nothing(state: JobState, change) -> None:  # type: ignore[no-untyped-def]
    row = job(state, error="kept")
    with pytest.raises(IllegalTransition):
        change(row)
    assert (row.state, row.stage, row.error, row.finished_at, row.attempts) == (state, "queued", "kept", None, 0)


def test_send_again_takes_a_stale_running_job_once(tmp_path: Path) -> None:
    url = sqlite_url(tmp_path)
    migrate(url)
    sessions = make_sessionmaker(make_engine(url))
    stale = utcnow() - timedelta(seconds=60)
    with session_scope(sessions) as session:
        session.add(job(JobState.RUNNING, heartbeat_at=stale, lease_token=3))
    cutoff = utcnow() - timedelta(seconds=30)
    with session_scope(sessions) as session:
        assert not job_states.send_again(session, "j1", token=2, stale_before=cutoff)  # another claim since
        assert job_states.send_again(session, "j1", token=3, stale_before=cutoff)
        assert not job_states.send_again(session, "j1", token=3, stale_before=cutoff)  # taken already
    with session_scope(sessions) as session:
        row = session.get(Job, "j1")
        assert (row.state, row.stage, row.heartbeat_at) == (Q, job_states.RESUME_STAGE, None) and row.resent_at is not None
