"""A job's lease as the worker reads and writes it (service.leases): the claim and what it refuses,
the fence a superseded runner meets, progress and heartbeat, publishing artifacts, the ends, and
the scene files a reconstruction fetches (service.scenes.files). On SQLite and PostgreSQL."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path

import pytest
from sqlalchemy.orm import Session, sessionmaker

from fluidcore.errors import InputError
from service import leases, scenes
from service.database import make_engine, make_sessionmaker, migrate, session_scope
from service.job_states import RESUME_STAGE, RETRY_STAGE
from service.leases import JobBusy, LeaseLost
from service.models import Artifact, Job, JobState, Scene, utcnow
from tests.support.service import database_url

LEASE_S, MAX_ATTEMPTS = 60.0, 3


@pytest.fixture(params=["sqlite", "postgres"])
def sessions(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[sessionmaker[Session]]:
    with database_url(request.param, tmp_path) as url:
        migrate(url)
        engine = make_engine(url)
        yield make_sessionmaker(engine)
        engine.dispose()


def add_job(sessions: sessionmaker[Session], **fields: object) -> str:
    with session_scope(sessions) as session:
        job = Job(owner="alice", type="predict", **fields)
        session.add(job)
        session.flush()
        return job.id


def read(sessions: sessionmaker[Session], job_id: str) -> Job:
    with session_scope(sessions) as session:
        job = session.get(Job, job_id)
        assert job is not None
        session.expunge(job)
        return job


def claim(sessions: sessionmaker[Session], job_id: str, worker: str = "w1") -> leases.Claim | leases.Ended | None:
    with session_scope(sessions) as session:
        return leases.claim(session, job_id, worker, LEASE_S, MAX_ATTEMPTS)


def test_a_claim_starts_the_job_under_a_new_token_with_its_chain(sessions: sessionmaker[Session]) -> None:
    root = add_job(sessions, state=JobState.SUCCEEDED)
    parent = add_job(sessions, state=JobState.SUCCEEDED, parent_job_id=root)
    job_id = add_job(sessions, parent_job_id=parent, params={"frames": 4}, lease_token=5)
    got = claim(sessions, job_id)
    assert got == leases.Claim(job_id, "predict", {"frames": 4}, None, (parent, root), 6)
    job = read(sessions, job_id)
    assert (job.state, job.worker, job.attempts, job.lease_token) == (JobState.RUNNING, "w1", 1, 6)


def test_a_live_lease_makes_the_claim_wait_and_an_expired_one_is_taken(sessions: sessionmaker[Session]) -> None:
    beat = utcnow() - timedelta(seconds=20)
    live = add_job(sessions, state=JobState.RUNNING, heartbeat_at=beat, lease_token=2, attempts=1)
    with pytest.raises(JobBusy) as busy:
        claim(sessions, live, "w2")
    assert LEASE_S - 20 - 5 < busy.value.retry_in <= LEASE_S - 20
    assert read(sessions, live).lease_token == 2  # nothing written
    expired = add_job(sessions, state=JobState.RUNNING, heartbeat_at=utcnow() - timedelta(seconds=LEASE_S + 1),
                      lease_token=2, attempts=1)
    got = claim(sessions, expired, "w2")
    assert isinstance(got, leases.Claim) and got.token == 3 and read(sessions, expired).attempts == 2


def test_a_claim_ends_what_it_must_not_run(sessions: sessionmaker[Session]) -> None:
    assert claim(sessions, "no-such-job") is None
    done = add_job(sessions, state=JobState.SUCCEEDED, lease_token=1)
    assert claim(sessions, done) is None and read(sessions, done).lease_token == 1
    asked = add_job(sessions, cancel_requested=True)
    assert claim(sessions, asked) == leases.Ended(asked, JobState.CANCELLED)
    assert read(sessions, asked).state == JobState.CANCELLED
    lost = add_job(sessions, stage=RESUME_STAGE, attempts=MAX_ATTEMPTS)
    assert claim(sessions, lost) == leases.Ended(lost, JobState.FAILED)
    job = read(sessions, lost)
    assert job.state == JobState.FAILED and job.error == (
        f"gave up after {MAX_ATTEMPTS} attempts: the worker running it was lost each time"
    )
    retried = add_job(sessions, stage=RETRY_STAGE, attempts=MAX_ATTEMPTS)  # not lost: a transient fault's retry
    assert claim(sessions, retried) is not None


def test_a_second_claim_waits_for_the_first_to_commit(sessions: sessionmaker[Session]) -> None:
    if sessions.kw["bind"].dialect.name != "postgresql":
        pytest.skip("row locks are PostgreSQL's; SQLite serialises writers on its own")
    job_id = add_job(sessions)
    outcome: list[object] = []

    def second() -> None:
        try:
            outcome.append(claim(sessions, job_id, "w2"))
        except JobBusy as busy:
            outcome.append(busy)

    with session_scope(sessions) as session:
        assert leases.claim(session, job_id, "w1", LEASE_S, MAX_ATTEMPTS) is not None
        other = threading.Thread(target=second)
        other.start()
        other.join(0.5)
        assert other.is_alive() and outcome == []  # blocked on the row lock
    other.join(10)
    assert len(outcome) == 1 and isinstance(outcome[0], JobBusy)
    assert read(sessions, job_id).worker == "w1"


def test_a_superseded_runner_holds_the_job_no_more(sessions: sessionmaker[Session]) -> None:
    job_id = add_job(sessions)
    first = claim(sessions, job_id)
    assert first is not None
    with session_scope(sessions) as session:
        assert leases.holds(session, job_id, first.token) and leases.held(session, job_id, first.token).id == job_id
    with session_scope(sessions) as session:  # the lease expired: another runner claims it
        session.get(Job, job_id).heartbeat_at = utcnow() - timedelta(seconds=LEASE_S + 1)
    assert claim(sessions, job_id, "w2") is not None
    with session_scope(sessions) as session:
        assert not leases.holds(session, job_id, first.token)
        with pytest.raises(LeaseLost, match=f"job {job_id} was claimed by another runner"):
            leases.held(session, job_id, first.token)
        with pytest.raises(LeaseLost):
            leases.held(session, "no-such-job", first.token)


def test_progress_never_drops_and_reports_a_cancel(sessions: sessionmaker[Session]) -> None:
    job_id = add_job(sessions, state=JobState.RUNNING, progress=0.4, lease_token=1, stage_seconds={"fit": 2.0})
    with session_scope(sessions) as session:
        assert leases.stage_seconds(session, job_id) == {"fit": 2.0}
        assert leases.stage_seconds(session, "no-such-job") == {}
        assert not leases.record_progress(leases.held(session, job_id, 1), 0.1, "preparing", {"fit": 2.0, "preparing": 1.5})
    job = read(sessions, job_id)
    assert (job.progress, job.stage, job.stage_seconds) == (0.4, "preparing", {"fit": 2.0, "preparing": 1.5})
    assert job.heartbeat_at is not None and utcnow() - job.heartbeat_at < timedelta(seconds=30)
    with session_scope(sessions) as session:
        session.get(Job, job_id).cancel_requested = True
    with session_scope(sessions) as session:
        assert leases.cancel_requested(session, job_id)
        assert leases.record_progress(leases.held(session, job_id, 1), 0.7, "fit", {})
    assert read(sessions, job_id).progress == 0.7


def test_a_heartbeat_moves_only_the_heartbeat(sessions: sessionmaker[Session]) -> None:
    old = utcnow() - timedelta(seconds=40)
    job_id = add_job(sessions, state=JobState.RUNNING, heartbeat_at=old, lease_token=1, progress=0.5, stage="fit")
    with session_scope(sessions) as session:
        leases.beat(leases.held(session, job_id, 1))
    job = read(sessions, job_id)
    assert job.heartbeat_at > old and (job.progress, job.stage) == (0.5, "fit")


def artifact(job_id: str, name: str, size: int) -> Artifact:
    return Artifact(job_id=job_id, name=name, kind="file", key=f"jobs/{job_id}/{name}", size=size,
                    content_type="application/octet-stream")


def stored(sessions: sessionmaker[Session], job_id: str) -> dict[str, int]:
    with session_scope(sessions) as session:
        return {a.name: a.size for a in session.query(Artifact).filter(Artifact.job_id == job_id)}


def test_publishing_replaces_the_whole_set_and_a_render_only_its_names(sessions: sessionmaker[Session]) -> None:
    parent = add_job(sessions, state=JobState.RUNNING, lease_token=1)
    with session_scope(sessions) as session:
        leases.publish_artifacts(session, leases.held(session, parent, 1), [artifact(parent, "a", 1), artifact(parent, "b", 1)])
    with session_scope(sessions) as session:  # the retry's set replaces the first's
        leases.publish_artifacts(session, leases.held(session, parent, 1), [artifact(parent, "b", 2), artifact(parent, "c", 2)])
    assert stored(sessions, parent) == {"b": 2, "c": 2}
    with session_scope(sessions) as session:
        leases.publish_shown(session, parent, [artifact(parent, "c", 3), artifact(parent, "d", 3)])
    assert stored(sessions, parent) == {"b": 2, "c": 3, "d": 3}


def test_the_ends_record_the_seconds(sessions: sessionmaker[Session]) -> None:
    plain = add_job(sessions, state=JobState.RUNNING)
    hooked = add_job(sessions, state=JobState.RUNNING, webhook_url="https://example.org/hook")
    given_up = add_job(sessions)
    with session_scope(sessions) as session:
        leases.end(session.get(Job, plain), JobState.CANCELLED, None, {"fit": 1.0})
        leases.end(session.get(Job, hooked), JobState.SUCCEEDED, None, {"fit": 2.0})
        leases.end(session.get(Job, given_up), JobState.FAILED, "gave up", None)
    ended = {job_id: read(sessions, job_id) for job_id in (plain, hooked, given_up)}
    assert (ended[plain].state, ended[plain].stage_seconds) == (JobState.CANCELLED, {"fit": 1.0})
    assert (ended[hooked].state, ended[hooked].stage_seconds) == (JobState.SUCCEEDED, {"fit": 2.0})
    assert (ended[given_up].state, ended[given_up].error, ended[given_up].stage_seconds) == (JobState.FAILED, "gave up", {})


def test_a_job_handed_back_is_queued_with_no_lease(sessions: sessionmaker[Session]) -> None:
    running = add_job(sessions, state=JobState.RUNNING, heartbeat_at=utcnow())
    with session_scope(sessions) as session:
        leases.hand_back(session.get(Job, running), {"fit": 3.0})
    job = read(sessions, running)
    assert (job.state, job.stage, job.heartbeat_at, job.stage_seconds) == (JobState.QUEUED, RETRY_STAGE, None, {"fit": 3.0})


def test_a_runner_whose_job_the_reaper_queued_again_holds_it_no_more(sessions: sessionmaker[Session]) -> None:
    """Issue 36 item 6: a frozen worker's job is queued again by the reaper once its heartbeat is a
    lease old; the runner that wakes up after that may write nothing (no heartbeat, progress,
    hand-back or end), before or after the next claim, so the job never runs reported `queued`."""
    from service.queue import reap_stale
    from tests.support.service import RecordingQueue

    job_id = add_job(sessions)
    frozen = claim(sessions, job_id)
    assert frozen is not None
    with session_scope(sessions) as session:  # frozen for more than a lease
        session.get(Job, job_id).heartbeat_at = utcnow() - timedelta(seconds=LEASE_S + 1)
    assert reap_stale(sessions, RecordingQueue(), LEASE_S) == [job_id]
    job = read(sessions, job_id)
    assert (job.state, job.stage, job.lease_token) == (JobState.QUEUED, RESUME_STAGE, frozen.token)
    with session_scope(sessions) as session:  # it wakes up: every write meets the fence
        with pytest.raises(LeaseLost, match=f"job {job_id} was queued again \\(waiting to resume"):
            leases.held(session, job_id, frozen.token)
    assert read(sessions, job_id).state == JobState.QUEUED
    resumed = claim(sessions, job_id, "w2")
    assert resumed is not None and resumed.token == frozen.token + 1
    with session_scope(sessions) as session:
        with pytest.raises(LeaseLost, match="claimed by another runner"):
            leases.held(session, job_id, frozen.token)
        assert leases.held(session, job_id, resumed.token).worker == "w2"


def test_a_scene_s_files_are_its_stored_keys(sessions: sessionmaker[Session]) -> None:
    with session_scope(sessions) as session:
        scene = Scene(owner="alice", cameras_key="scenes/s/cameras.json", cameras=["c0", "c1"], n_frames=6, fps=30.0,
                      videos={"c0": {"key": "scenes/s/c0.mp4"}, "c1": {"key": "scenes/s/c1.mp4"}})
        session.add(scene)
        session.flush()
        scene_id = scene.id
    with session_scope(sessions) as session:
        assert scenes.files(session, scene_id) == scenes.SceneFiles(
            "scenes/s/cameras.json", {"c0": "scenes/s/c0.mp4", "c1": "scenes/s/c1.mp4"}
        )
        with pytest.raises(InputError, match="scene gone no longer exists"):
            scenes.files(session, "gone")
