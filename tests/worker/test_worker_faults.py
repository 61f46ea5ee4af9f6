"""Faults inside one job's run (issue 16): a cancel in a stage without frames (prepare) is
honoured, a storage error while publishing leaves nothing half-published, a runner whose job
was taken over stops (fencing token), heartbeats keep a silent job alive, the reaper sends a
dead worker's job again, and a restart of Redis or of PostgreSQL mid-run loses no job."""

from __future__ import annotations

import glob
import json
import os
import pwd
import shutil
import signal
import subprocess
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path

import pytest

from service.database import session_scope
from service.leases import JobBusy
from service.models import Job, JobState, utcnow
from service.storage import LocalStorage, StorageError, job_prefix
from worker.runners import RunInputs
from service.queue import reap_stale
from tests.support.service import FAKE_RUNNERS, fake_job, free_port, sqlite_url
from tests.support.worker import Deployment, World, start_worker, stop, wait_for


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
        if key.startswith(f"{job_prefix(job_id)}/videos"):
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
    assert world.storage.list(f"{job_prefix(job_id)}/videos/") == []  # the one video that made it was removed

    world.storage.put_file = put_file  # type: ignore[method-assign]
    assert world.executor("retry").run(job_id) == "succeeded"
    assert {a.kind for a in world.artifacts(job_id).values()} >= {"video", "orbit", "manifest"}


def test_a_runner_whose_job_was_taken_over_stops_and_writes_nothing(world: World) -> None:
    """One job never runs twice at once: once a second runner claims it (after the first one's
    heartbeats stopped for a lease), the first stops at its next report, and the second finishes."""
    job_id = world.job(scene_id=world.scene(), params={"frames": [0, 4]})
    first, second = world.executor("first"), world.executor("second")
    outcomes = []

    def taken_over_after_one_frame(inputs: RunInputs) -> list[Path]:
        def progress(fraction: float, stage: str) -> None:
            inputs.progress(fraction, stage)
            if not outcomes:  # the first runner looks dead (e.g. its database link dropped for a lease)
                with session_scope(world.sessions) as session:
                    session.get(Job, job_id).heartbeat_at -= timedelta(seconds=world.settings.job_lease_seconds + 1)
                outcomes.append(second.run(job_id))  # meanwhile, another worker takes the job over

        return fake_job(RunInputs(**{**inputs.__dict__, "progress": progress}))

    first.runners = {**FAKE_RUNNERS, "reconstruct": taken_over_after_one_frame}
    assert first.run(job_id) is None  # stopped: LeaseLost at its next report
    assert outcomes == ["succeeded"]
    job = world.get(job_id)
    assert job.state == JobState.SUCCEEDED and job.lease_token == 2 and job.worker == "second"
    computed = world.tmp_path / "cache-first" / f"computed-{job_id}.txt"
    assert computed.read_text().split() == ["0", "1"]  # stopped at the report of the frame in flight, unpushed


def test_a_runner_that_wakes_after_the_reaper_queued_its_job_writes_nothing(world: World) -> None:
    """Issue 36 item 6: a worker frozen (SIGSTOP) for more than a lease has its job queued again by
    the reaper; when it wakes up (SIGCONT) it stops at its next report without writing progress,
    checkpoints, artifacts or an end state, so the job says what happens to it (queued, "waiting
    to resume") instead of running to success reported `queued`. The next claim resumes it."""
    from service.job_states import RESUME_STAGE
    from tests.support.service import RecordingQueue

    job_id = world.job(scene_id=world.scene(), params={"frames": [0, 4]})
    lease = world.settings.job_lease_seconds
    queue = RecordingQueue()
    seen = []

    def frozen_after_one_frame(inputs: RunInputs) -> list[Path]:
        def progress(fraction: float, stage: str) -> None:
            inputs.progress(fraction, stage)
            if not seen:  # frozen here for more than a lease ...
                with session_scope(world.sessions) as session:
                    session.get(Job, job_id).heartbeat_at -= timedelta(seconds=lease + 1)
                assert reap_stale(world.sessions, queue, lease) == [job_id]  # ... and the reaper's pass ran
                job = world.get(job_id)
                seen.append((job.state, job.stage, job.progress, len(world.storage.list(f"jobs/{job_id}/run/"))))

        return fake_job(RunInputs(**{**inputs.__dict__, "progress": progress}))

    assert world.executor("frozen", {**FAKE_RUNNERS, "reconstruct": frozen_after_one_frame}).run(job_id) is None
    ((state, stage, progress, files),) = seen
    assert (state, stage) == (JobState.QUEUED, RESUME_STAGE)
    job = world.get(job_id)  # it woke up: nothing it did afterwards reached the job or storage
    assert (job.state, job.stage, job.progress, job.attempts) == (JobState.QUEUED, RESUME_STAGE, progress, 1)
    assert len(world.storage.list(f"jobs/{job_id}/run/")) == files and world.artifacts(job_id) == {}
    assert world.executor("second").run(job_id) == "succeeded"  # the message the reaper sent
    job = world.get(job_id)
    assert (job.attempts, job.worker, job.lease_token) == (2, "second", 2)


def test_heartbeats_keep_a_job_without_progress_alive(world: World) -> None:
    world.settings = world.settings.model_copy(update={"job_lease_seconds": 4})
    job_id = world.job(scene_id=world.scene(), params={"frames": [0, 1]})
    claims = []

    def silent_for_two_leases(inputs: RunInputs) -> list[Path]:
        time.sleep(6)  # no progress report: only the heartbeat thread says the job is alive
        try:
            world.executor("second").claim(job_id)
            claims.append("claimed")
        except JobBusy as busy:
            claims.append(f"busy {busy.retry_in:.0f}")
        return fake_job(inputs)

    assert world.executor(runners={**FAKE_RUNNERS, "reconstruct": silent_for_two_leases}).run(job_id) == "succeeded"
    assert claims and claims[0].startswith("busy")


def test_the_reaper_sends_a_dead_workers_job_again(world: World) -> None:
    from service.queue import RESUME_STAGE
    from tests.support.service import RecordingQueue

    lease = world.settings.job_lease_seconds
    stale = world.job(scene_id=world.scene(), state=JobState.RUNNING, heartbeat_at=utcnow() - timedelta(seconds=lease + 1))
    alive = world.job(scene_id="s1", state=JobState.RUNNING, heartbeat_at=utcnow())
    spent = world.job(scene_id="s1", state=JobState.RUNNING, attempts=3,
                      heartbeat_at=utcnow() - timedelta(seconds=lease + 1))
    queue = RecordingQueue()
    assert sorted(reap_stale(world.sessions, queue, lease)) == sorted([stale, spent])
    assert reap_stale(world.sessions, queue, lease) == []  # taken once
    assert world.get(stale).state == JobState.QUEUED and world.get(stale).stage == RESUME_STAGE
    assert world.get(alive).state == JobState.RUNNING
    assert world.executor().run(stale) == "succeeded"  # resumes
    assert world.executor().run(spent) == "failed"  # out of attempts: failed by its claim, not run again
    assert "gave up after 3 attempts" in world.get(spent).error


def test_the_reaper_sends_a_queued_job_again_once_a_worker_sat_idle_a_lease(world: World) -> None:
    """Issue 20 item 5: a queued job whose broker message was lost is sent again, but only once an
    idle worker proves it (a busy worker or a fresh job is left alone), and once a lease at most."""
    from service.worker_beats import WorkerBeacon
    from tests.support.service import RecordingQueue

    lease = world.settings.job_lease_seconds
    old = utcnow() - timedelta(seconds=lease + 1)
    lost = world.job(scene_id=world.scene(), task_id="t1", created_at=old)
    fresh = world.job(scene_id="s1", task_id="t2")  # just sent: its message is on its way
    waiting = world.job(scene_id="s1", created_at=old)  # no task yet: waits on a parent (service.chaining)
    queue, beacon = RecordingQueue(), WorkerBeacon(world.sessions, "host:1", period_s=60)
    assert reap_stale(world.sessions, queue, lease) == []  # no worker at all: nothing proves a loss
    with beacon.working():
        beacon.beat()
        assert reap_stale(world.sessions, queue, lease) == []  # the worker is busy: the job just waits
    beacon._idle_since = old
    beacon.beat()
    assert reap_stale(world.sessions, queue, lease) == [lost] and queue.sent == [(lost, "reconstruct")]
    assert reap_stale(world.sessions, queue, lease) == []  # once a lease
    assert world.get(fresh).resent_at is None and world.get(waiting).resent_at is None
    assert world.executor().run(lost) == "succeeded"


def test_a_job_sent_twice_runs_once(world: World) -> None:
    """The claim that makes the reaper's resend safe: two deliveries of one job, the second while the
    first runs, start the runner once (the second is told the job is busy, then finds it done)."""
    import threading

    job_id = world.job(scene_id=world.scene())
    started, release, runs = threading.Event(), threading.Event(), []

    def held_open(inputs: RunInputs) -> list[Path]:
        runs.append(inputs.job_id)
        started.set()
        release.wait(30)
        return fake_job(inputs)

    first = threading.Thread(target=lambda: world.executor("w1", {**FAKE_RUNNERS, "reconstruct": held_open}).run(job_id))
    first.start()
    assert started.wait(30)
    with pytest.raises(JobBusy):
        world.executor("w2").run(job_id)
    release.set()
    first.join(30)
    assert world.executor("w2").run(job_id) is None  # the duplicate finds the job finished
    job = world.get(job_id)
    assert runs == [job_id] and job.state == JobState.SUCCEEDED and job.attempts == 1 and job.lease_token == 1


def test_a_killed_workers_job_is_picked_up_within_30_s(redis_postgres: Deployment) -> None:
    """Redis + PostgreSQL, real worker processes: the whole first worker is killed mid-job; its
    message stays unacknowledged in Redis (visibility timeout: hours), so what brings the job back
    is the lease (16 s) and the reaper, run here every quarter lease as the API runs it."""
    deployment = redis_postgres
    lease = deployment.settings.job_lease_seconds
    first = start_worker(deployment.settings, frame_seconds=0.4)
    second = None
    try:
        job_id = deployment.submit(frames=30)
        wait_for(lambda: len(deployment.storage.list(f"jobs/{job_id}/run/states/")) >= 3, 120, "three checkpoints")
        stop(first, signal.SIGKILL)
        killed = time.monotonic()
        second = start_worker(deployment.settings, frame_seconds=0.4)
        while (job := deployment.job(job_id)).lease_token < 2 and time.monotonic() - killed < 60:
            reap_stale(deployment.sessions, deployment.queue, lease)
            time.sleep(lease / 4)
        picked_up = time.monotonic() - killed
        assert job.lease_token == 2 and job.state == JobState.RUNNING, job.state
        assert picked_up < 30, f"picked up {picked_up:.1f} s after the kill"
        print(f"picked up {picked_up:.1f} s after the kill (lease {lease} s)")
        wait_for(lambda: deployment.job(job_id).state == JobState.SUCCEEDED, 120, "the resumed job to succeed")
    finally:
        stop(first, signal.SIGKILL)
        if second is not None:
            stop(second)


def _reap_until_all_succeed(deployment: Deployment, job_ids: list[str], timeout: float) -> list[str]:
    """Run the reaper every second, as the API does, until every job succeeded (asserted, with
    each job's state and error otherwise); returns the jobs the reaper sent again."""
    deadline, reaped = time.monotonic() + timeout, []
    while time.monotonic() < deadline and {deployment.job(j).state for j in job_ids} != {JobState.SUCCEEDED}:
        reaped += reap_stale(deployment.sessions, deployment.queue, deployment.settings.job_lease_seconds)
        time.sleep(1)
    jobs = [deployment.job(j) for j in job_ids]
    assert [job.state for job in jobs] == [JobState.SUCCEEDED] * len(jobs), [(job.state, job.error) for job in jobs]
    return reaped


@pytest.mark.skipif(shutil.which("redis-server") is None, reason="needs redis-server")
@pytest.mark.parametrize("append_only", ["yes", "no"])
def test_a_redis_restart_during_a_run_loses_no_job(tmp_path: Path, append_only: str) -> None:
    """A private Redis is restarted while one job runs and another waits in its queue: both finish,
    none is left running. With an append-only file (as docker-compose.yml runs it) the queued
    message survives; without persistence every message is lost (issue 20 item 5) and the reaper,
    seeing the worker's heartbeat idle for a lease, sends the queued job again. Set
    RELIABILITY_JSON to a path to record the timings."""
    port = free_port()
    command = ["redis-server", "--port", str(port), "--bind", "127.0.0.1", "--appendonly", append_only, "--save", "",
               "--dir", str(tmp_path), "--logfile", str(tmp_path / "redis.log")]
    redis = subprocess.Popen(command)
    deployment = Deployment(tmp_path, sqlite_url(tmp_path), f"redis://127.0.0.1:{port}/0")
    worker = start_worker(deployment.settings, frame_seconds=0.3)
    try:
        running, waiting = deployment.submit(frames=16), deployment.submit(frames=2)
        wait_for(lambda: len(deployment.storage.list(f"jobs/{running}/run/states/")) >= 3, 120, "three checkpoints")
        redis.terminate()
        redis.wait(30)
        redis = subprocess.Popen(command)
        start = time.monotonic()
        reaped = _reap_until_all_succeed(deployment, [running, waiting], timeout=180)
        if append_only == "no":
            assert waiting in reaped, reaped
            timings = {"both_jobs_succeeded_after_s": round(time.monotonic() - start, 1), "queued_job_sent_again": True}
            print(f"redis restart without persistence: {timings}")
            if os.environ.get("RELIABILITY_JSON"):  # the record behind docs/reliability.md
                Path(os.environ["RELIABILITY_JSON"]).write_text(json.dumps(timings, indent=1) + "\n")
    finally:
        stop(worker)
        redis.terminate()
        redis.wait(30)
        deployment.engine.dispose()


def _run_or_raise(command: list[str]) -> None:
    """Run a PostgreSQL tool; on failure raise with its output (initdb and pg_ctl say why there)."""
    done = subprocess.run(command, timeout=120, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} exited {done.returncode}: {done.stderr or done.stdout}")


@dataclass(frozen=True)
class PrivateCluster:
    """A PostgreSQL cluster of this test's own, which it may stop and start: the shared one on
    5432 serves other tests at the same time and must never be restarted."""

    pg_ctl: list[str]  # the pg_ctl command line (data folder, log, server options), run as the cluster's owner
    port: int

    @property
    def url(self) -> str:
        return f"postgresql+psycopg://postgres@127.0.0.1:{self.port}/postgres"

    def ctl(self, *args: str) -> None:
        _run_or_raise([*self.pg_ctl, *args])


@pytest.fixture
def private_postgres() -> Iterator[PrivateCluster]:
    """initdb + pg_ctl in a temporary folder. PostgreSQL refuses to run as root, so as root the
    cluster belongs to the `postgres` user (runuser). Stopped and removed even when the test fails."""
    initdb = shutil.which("initdb") or next(iter(sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"))), None)
    if initdb is None:
        pytest.skip("needs PostgreSQL's initdb (not on PATH nor in /usr/lib/postgresql/*/bin)")
    as_owner: list[str] = []
    if os.geteuid() == 0:
        if shutil.which("runuser") is None:
            pytest.skip("running as root: needs runuser to run PostgreSQL as the postgres user")
        try:
            owner = pwd.getpwnam("postgres")
        except KeyError:
            pytest.skip("running as root: needs a postgres user to own the private cluster")
        as_owner = ["runuser", "-u", "postgres", "--"]
    folder = Path(tempfile.mkdtemp(prefix="fnx-pg-"))  # not under pytest's tmp_path: only root may enter that
    bin_dir = Path(os.path.realpath(initdb)).parent
    port = free_port()
    options = f"-p {port} -k {folder} -c listen_addresses=127.0.0.1 -c fsync=off"  # fsync: a throwaway cluster
    cluster = PrivateCluster([*as_owner, str(bin_dir / "pg_ctl"), "-D", str(folder / "data"), "-l",
                              str(folder / "server.log"), "-o", options, "-w", "-t", "30"], port)
    try:
        if as_owner:
            os.chown(folder, owner.pw_uid, owner.pw_gid)
        _run_or_raise([*as_owner, str(bin_dir / "initdb"), "-D", str(folder / "data"), "--auth=trust", "-U", "postgres",
                       "-N"])
        cluster.ctl("start")
        yield cluster
    finally:  # whatever state the test left it in (a failed start included): no server outlives the test
        subprocess.run([*cluster.pg_ctl, "stop", "-m", "immediate"], timeout=60, capture_output=True)
        shutil.rmtree(folder, ignore_errors=True)


def test_a_postgres_restart_during_a_run_loses_no_job(tmp_path: Path, private_postgres: PrivateCluster) -> None:
    """A private PostgreSQL is stopped (fast: sessions are cut, as a restart by an operator or a
    failover does) while one job runs and another waits in the queue (embedded broker, so the
    database is the only thing that fails), and started again 3 s later: both finish, none is
    left running, and the running one resumed from its checkpoints. The worker cannot give the
    job back while the database is down, so it waits out its lease (16 s) before it resumes."""
    deployment = Deployment(tmp_path, private_postgres.url, broker_url=None)
    worker = start_worker(deployment.settings, frame_seconds=0.3)
    try:
        running, waiting = deployment.submit(frames=20), deployment.submit(frames=2)
        wait_for(lambda: len(deployment.storage.list(f"jobs/{running}/run/states/")) >= 3, 120, "three checkpoints")
        private_postgres.ctl("stop", "-m", "fast")
        time.sleep(3)  # the runner reads its job row at every frame (0.3 s): it meets the outage
        private_postgres.ctl("start")
        reaped = _reap_until_all_succeed(deployment, [running, waiting], timeout=120)
        assert deployment.job(running).attempts == 2  # the outage did reach the running job: it stopped, then resumed
        computed = [int(t) for t in (deployment.settings.resolved_work_dir() / f"computed-{running}.txt")
                    .read_text().split()]
        assert sorted(set(computed)) == list(range(20))
        assert len(computed) <= 21  # resumed from its checkpoints: at most the frame in flight computed twice
        print(f"{len(computed) - 20} frames computed twice, reaped by the test's reaper: {reaped}")
    finally:
        stop(worker)
        deployment.engine.dispose()


def test_progress_never_drops_while_a_resumed_job_prepares(world: World) -> None:
    """Issue 20 item 9: a job resumed at 0.43 reported 0 while it prepared again."""
    from worker.execution import ProgressReporter

    job_id = world.job(scene_id=world.scene(), state=JobState.RUNNING, progress=0.43, lease_token=2)
    reporter = ProgressReporter(world.sessions, job_id, token=2)
    reporter.report(0.0, "preparing")
    assert world.get(job_id).progress == 0.43 and world.get(job_id).stage == "preparing"
    reporter.report(0.6, "fit")
    assert world.get(job_id).progress == 0.6
