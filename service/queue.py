"""How a job reaches the workers. The Celery implementation is the real one; tests of the API's own
logic may pass another `JobQueue` to `create_app`."""

from __future__ import annotations

from datetime import timedelta
from typing import Protocol

from sqlalchemy import or_, select, update
from sqlalchemy.orm import Session, sessionmaker

from service.celery_app import make_celery, task_name
from service.database import session_scope
from service.job_types import JobType
from service.models import SENDING, Job, JobState, utcnow
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
    API process) send it once. Then send again the queued jobs whose message was lost
    (`_resend_lost`). Returns the job ids."""
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
                .values(state=JobState.QUEUED, stage=RESUME_STAGE, heartbeat_at=None, resent_at=utcnow())
            ).rowcount
        if taken:
            queue.enqueue(job_id, JobType(job_type))
            reaped.append(job_id)
    return reaped + _resend_lost(sessions, queue, lease_seconds)


def _resend_lost(sessions: sessionmaker[Session], queue: JobQueue, lease_seconds: float) -> list[str]:
    """Send again the queued jobs (sent once, not waiting on a parent) that have waited a lease while
    a live worker sat idle for that whole lease: an idle worker takes a message at once, so theirs
    was lost (a broker restarted without persistence, a purged queue, a worker killed holding its
    prefetched message). Sending twice is safe: the claim's fencing token lets one runner run the
    job, and a message for a job already running or finished is dropped. Each job is sent at most
    once a lease, taken by a conditional UPDATE on `resent_at` so concurrent reapers send it once."""
    from service.worker_beats import idle_for_a_lease

    cutoff = utcnow() - timedelta(seconds=lease_seconds)
    with session_scope(sessions) as session:
        if not idle_for_a_lease(session, lease_seconds):
            return []
        lost = session.execute(
            select(Job.id, Job.type, Job.resent_at).where(
                Job.state == JobState.QUEUED, Job.task_id.is_not(None), Job.task_id != SENDING,
                Job.created_at < cutoff, or_(Job.resent_at.is_(None), Job.resent_at < cutoff),
            )
        ).all()
    resent = []
    for job_id, job_type, resent_at in lost:
        with session_scope(sessions) as session:
            unchanged = Job.resent_at.is_(None) if resent_at is None else Job.resent_at == resent_at
            taken = session.execute(
                update(Job).where(Job.id == job_id, Job.state == JobState.QUEUED, unchanged).values(resent_at=utcnow())
            ).rowcount
        if taken:
            queue.enqueue(job_id, JobType(job_type))
            resent.append(job_id)
    return resent


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
