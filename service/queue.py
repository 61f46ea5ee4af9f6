"""How a job reaches the workers. The Celery implementation is the real one; tests of the API's own
logic may pass another `JobQueue` to `create_app`."""

from __future__ import annotations

from datetime import timedelta
from typing import Protocol

from sqlalchemy import select, update
from sqlalchemy.orm import Session, sessionmaker

from service.celery_app import make_celery, task_name
from service.database import session_scope
from service.job_types import JobType
from service.models import Job, JobState, utcnow
from service.settings import GPU_QUEUE, Settings


class QueueUnavailable(Exception):
    """The broker did not take the message."""


class JobQueue(Protocol):
    def enqueue(self, job_id: str, job_type: JobType) -> str:
        """Send the job to a worker; returns the broker's task id."""

    def ping(self) -> None:
        """Raise QueueUnavailable unless the broker answers (for /readyz)."""


class CeleryQueue:
    """Sends each job's task to the `gpu` queue by name (`task_name`): the tasks themselves live in
    `worker.tasks`, which the API never imports."""

    def __init__(self, settings: Settings) -> None:
        self.app = make_celery(settings)

    def enqueue(self, job_id: str, job_type: JobType) -> str:
        try:
            result = self.app.send_task(task_name(JobType(job_type)), args=[job_id], queue=GPU_QUEUE)
        except Exception as exc:  # kombu raises many transport-specific errors
            raise QueueUnavailable(f"the job broker did not accept the job: {exc}") from exc
        return result.id

    def ping(self) -> None:
        try:
            with self.app.connection_for_write() as connection:
                connection.ensure_connection(max_retries=1, timeout=2)
        except Exception as exc:
            raise QueueUnavailable(f"broker unreachable: {exc}") from exc


RESUME_STAGE = "waiting to resume"


def reap_stale(sessions: sessionmaker[Session], queue: JobQueue, lease_seconds: float) -> list[str]:
    """Send again every running job whose heartbeat is older than the lease: its worker died, or
    lost the broker or the database for longer than the lease (its fencing token stops it when it
    comes back). The next claim resumes from the checkpoints, or fails the job once it has used
    up its attempts. Each job is taken by one conditional UPDATE, so concurrent reapers (one per
    API process) send it once. Returns the job ids."""
    cutoff = utcnow() - timedelta(seconds=lease_seconds)
    with session_scope(sessions) as session:
        stale = session.execute(
            select(Job.id, Job.type, Job.lease_token).where(Job.state == JobState.RUNNING, Job.heartbeat_at < cutoff)
        ).all()
    reaped = []
    for job_id, job_type, token in stale:
        with session_scope(sessions) as session:
            taken = session.execute(
                update(Job)
                .where(Job.id == job_id, Job.state == JobState.RUNNING, Job.lease_token == token, Job.heartbeat_at < cutoff)
                .values(state=JobState.QUEUED, stage=RESUME_STAGE, heartbeat_at=None)
            ).rowcount
        if taken:
            queue.enqueue(job_id, JobType(job_type))
            reaped.append(job_id)
    return reaped


def requeue_orphans(sessions: sessionmaker[Session], queue: JobQueue) -> list[str]:
    """Send again every job a previous embedded server left `running`: its worker died with it, and
    the filesystem broker does not redeliver a message that was already taken. The new run resumes
    from the job's checkpoints. Returns the job ids."""
    with session_scope(sessions) as session:
        jobs = session.scalars(select(Job).where(Job.state == JobState.RUNNING)).all()
        for job in jobs:
            job.state, job.stage, job.heartbeat_at = JobState.QUEUED, RESUME_STAGE, None
        orphans = [(job.id, JobType(job.type)) for job in jobs]
    for job_id, job_type in orphans:
        queue.enqueue(job_id, job_type)
    return [job_id for job_id, _ in orphans]
