"""Real Celery worker processes: jobs travel through a real broker (Redis, or the embedded
filesystem transport) to `celery -A worker.tasks worker`, with test-double runners loaded
through the FLUIDNEXUS_RUNNERS seam. The end-to-end test with fluidcore itself is
tests/service/test_service_e2e.py."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import pytest

from service.database import session_scope
from service.models import Job, JobState
from service.queue import CeleryQueue, requeue_orphans
from service.settings import Settings
from tests.support.service import database_url
from tests.support.worker import Deployment, start_worker, stop, wait_for

def test_job_through_redis_to_a_worker_process_and_cancel(redis_postgres: Deployment) -> None:
    worker = start_worker(redis_postgres.settings, frame_seconds=0.3)
    try:
        done = redis_postgres.submit(frames=3)
        wait_for(lambda: redis_postgres.job(done).state == JobState.SUCCEEDED, 60, "the job to succeed")
        assert redis_postgres.job(done).progress == 1.0

        slow = redis_postgres.submit(frames=50)
        wait_for(lambda: redis_postgres.job(slow).progress > 0, 30, "the slow job to start")
        with session_scope(redis_postgres.sessions) as session:
            session.get(Job, slow).cancel_requested = True
        wait_for(lambda: redis_postgres.job(slow).state == JobState.CANCELLED, 30, "the cancel to land")
        assert redis_postgres.job(slow).progress < 0.5
    finally:
        stop(worker)


def test_embedded_broker_job_resumes_after_the_worker_is_killed(tmp_path: Path) -> None:
    """Embedded mode: filesystem broker + SQLite. A killed worker's job is sent again (as
    `fluidnexus serve` does on start) and the new worker continues from the checkpoints."""
    with database_url("sqlite", tmp_path) as url:
        deployment = Deployment(tmp_path, url, broker_url=None)
        first = start_worker(deployment.settings, frame_seconds=0.4)
        try:
            job_id = deployment.submit(frames=20)  # 8 s of work left when it is killed: no race
            states = f"jobs/{job_id}/run/states/"
            wait_for(lambda: len(deployment.storage.list(states)) >= 3, 60, "three checkpointed frames")
        finally:
            stop(first, signal.SIGKILL)
        assert deployment.job(job_id).state == JobState.RUNNING
        assert requeue_orphans(deployment.sessions, deployment.queue) == [job_id]

        second = start_worker(deployment.settings)
        try:
            wait_for(lambda: deployment.job(job_id).state == JobState.SUCCEEDED, 60, "the resumed job to succeed")
        finally:
            stop(second)
        computed = [int(t) for t in (deployment.settings.resolved_work_dir() / f"computed-{job_id}.txt")
                    .read_text().split()]
        assert sorted(set(computed)) == list(range(20))
        assert len(computed) <= 21  # at most the frame in flight when the worker died was computed twice
        assert deployment.job(job_id).attempts == 2
        deployment.engine.dispose()


def test_celery_queue_reports_an_unreachable_broker(tmp_path: Path) -> None:
    """What /readyz and POST /v1/jobs see when Redis is down: QueueUnavailable, not a hang."""
    from service.queue import QueueUnavailable
    from tests.support.service import free_port

    down = CeleryQueue(Settings(data_dir=tmp_path, broker_url=f"redis://127.0.0.1:{free_port()}/0"))
    with pytest.raises(QueueUnavailable, match="broker"):
        down.ping()
    with pytest.raises(QueueUnavailable, match="did not accept"):
        down.enqueue("some-job", "reconstruct")
    CeleryQueue(Settings(data_dir=tmp_path)).ping()  # the embedded filesystem broker is always there


def test_embedded_broker_keeps_its_files_in_the_data_folder(tmp_path: Path) -> None:
    """kombu's filesystem transport writes its exchange table to ./control unless told where:
    `fluidnexus serve` must not litter the folder it is started from. A fresh process, because
    kombu declares an exchange once per process."""
    started_in = tmp_path / "cwd"
    started_in.mkdir()
    send = (
        "from service.queue import CeleryQueue; from service.settings import Settings; "
        f"CeleryQueue(Settings(data_dir={str(tmp_path / 'data')!r})).enqueue('some-job', 'reconstruct')"
    )
    subprocess.run([sys.executable, "-c", send], cwd=started_in, check=True, timeout=60)
    assert list(started_in.iterdir()) == []
    assert list((tmp_path / "data").rglob("*.exchange"))
