"""How a job reaches the workers. The Celery implementation is the real one; tests of the API's own
logic may pass another `JobQueue` to `create_app`."""

from __future__ import annotations

import logging
from datetime import datetime, timedelta
from typing import Protocol

from sqlalchemy import and_, or_, select, update
from sqlalchemy.orm import Session, sessionmaker
from sqlalchemy.sql.elements import ColumnElement

from service.celery_app import make_celery, task_name
from service.database import session_scope
from service.job_types import JobType
from service.job_states import QUEUED_STAGE, RESUME_STAGE, UNSENT_STAGE, orphaned, send_again
from service.models import SENDING, UNSENT, Job, JobState, utcnow
from service.settings import GPU_QUEUE, Settings

log = logging.getLogger(__name__)


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


def send(session: Session, job: Job, queue: JobQueue) -> bool:
    """Hand a stored queued job to the broker; commits, and returns whether the broker took it.
    The one rule for every enqueue: a new job, an upload's reconstruction, a released
    continuation, a render asked for, and the reaper's sends.

    Sent, its stage is "queued". When the broker does not take it, the job stays queued, marked
    `UNSENT` with the stage "waiting for the queue", and the reaper sends it once the broker
    answers (`reap_stale`); a job the reaper sends again keeps "waiting to resume" either way.
    Why: the database row is the job, the broker only carries the news of it, so an outage of
    the broker delays jobs and loses none. Failing the job, or deleting it (and an upload with
    it), would lose what a client asked for: a continuation queued hours before, a running job
    the reaper recovers, a large upload. A 503 for a job that is stored and will run would not be
    the truth either, and would invite a retry that runs it twice; the job itself says why it
    waits (state "queued", stage "waiting for the queue")."""
    try:
        job.task_id = queue.enqueue(job.id, JobType(job.type))
        sent = True
    except QueueUnavailable as exc:
        log.warning("job %s: %s; sent when the broker answers", job.id, exc)
        job.task_id, sent = UNSENT, False
    if job.stage != RESUME_STAGE:  # kept: the claim reads it (the last attempt was lost)
        job.stage = QUEUED_STAGE if sent else UNSENT_STAGE
    session.commit()
    return sent


def take_for_sending(session: Session, job_id: str, task_id: str | None) -> bool:
    """Mark a queued job `SENDING` if its `task_id` is still `task_id` (NULL: waiting for its
    parent; `UNSENT`): one atomic UPDATE, so of the callers racing for it one sends it. Commits.
    `resent_at` records when the hand-off began: one that never ends is the reaper's (`_stuck`)."""
    unchanged = Job.task_id.is_(None) if task_id is None else Job.task_id == task_id
    taken = session.execute(
        update(Job).where(Job.id == job_id, Job.state == JobState.QUEUED, unchanged).values(
            task_id=SENDING, resent_at=utcnow()
        )
    ).rowcount
    session.commit()
    return bool(taken)


def reap_stale(sessions: sessionmaker[Session], queue: JobQueue, lease_seconds: float) -> list[str]:
    """Send again every running job whose heartbeat is older than the lease: its worker died, or
    lost the broker or the database for longer than the lease (its fencing token stops it when it
    comes back). The next claim resumes from the checkpoints, or fails the job once it has used
    up its attempts. Each job is taken by one conditional UPDATE (`job_states.send_again`), so
    concurrent reapers (one per API process) send it once. Then send the jobs the broker did not
    take or whose hand-off to it never ended (`_send_unsent`) and the queued jobs whose message
    was lost (`_resend_lost`). Returns the ids of the jobs the broker took."""
    cutoff = utcnow() - timedelta(seconds=lease_seconds)
    with session_scope(sessions) as session:
        stale = session.execute(
            select(Job.id, Job.lease_token).where(Job.state == JobState.RUNNING, Job.heartbeat_at < cutoff)
        ).all()
    reaped = []
    for job_id, token in stale:
        with session_scope(sessions) as session:
            if send_again(session, job_id, token, cutoff) and _send_by_id(session, job_id, queue):
                reaped.append(job_id)
    return reaped + _send_unsent(sessions, queue, cutoff) + _resend_lost(sessions, queue, lease_seconds)


def _send_by_id(session: Session, job_id: str, queue: JobQueue) -> bool:
    job = session.get(Job, job_id)
    assert job is not None
    return send(session, job, queue)


def _stuck(cutoff: datetime) -> ColumnElement[bool]:
    """A queued job whose hand-off to the broker began before `cutoff` and never ended (`SENDING`
    since: the process sending it died between storing it and the broker's answer)."""
    began = or_(Job.resent_at < cutoff, and_(Job.resent_at.is_(None), Job.created_at < cutoff))
    return and_(Job.state == JobState.QUEUED, Job.task_id == SENDING, began)


def _send_unsent(sessions: sessionmaker[Session], queue: JobQueue, cutoff: datetime) -> list[str]:
    """Send the queued jobs the broker did not take (`send`) and those whose hand-off began before
    `cutoff` and never ended (`_stuck`), oldest first; the first it still refuses ends the pass
    (the next tries again), so a broker that is down costs one attempt."""
    with session_scope(sessions) as session:
        unsent = session.scalars(
            select(Job.id).where(or_(and_(Job.state == JobState.QUEUED, Job.task_id == UNSENT), _stuck(cutoff)))
            .order_by(Job.created_at, Job.id)
        ).all()
    sent = []
    for job_id in unsent:
        with session_scope(sessions) as session:
            if not _take_unsent(session, job_id, cutoff):
                continue  # another reaper took it
            if not _send_by_id(session, job_id, queue):
                break
            sent.append(job_id)
    return sent


def _take_unsent(session: Session, job_id: str, cutoff: datetime) -> bool:
    """`take_for_sending` of an unsent job, or of a stuck one by one conditional UPDATE (still
    stuck), so of concurrent reapers one sends it. Commits."""
    if take_for_sending(session, job_id, UNSENT):
        return True
    taken = session.execute(update(Job).where(Job.id == job_id, _stuck(cutoff)).values(resent_at=utcnow())).rowcount
    session.commit()
    return bool(taken)


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
            select(Job.id, Job.resent_at).where(
                Job.state == JobState.QUEUED, Job.task_id.is_not(None), Job.task_id.not_in([SENDING, UNSENT]),
                Job.created_at < cutoff, or_(Job.resent_at.is_(None), Job.resent_at < cutoff),
            )
        ).all()
    resent = []
    for job_id, resent_at in lost:
        with session_scope(sessions) as session:
            unchanged = Job.resent_at.is_(None) if resent_at is None else Job.resent_at == resent_at
            taken = session.execute(
                update(Job).where(Job.id == job_id, Job.state == JobState.QUEUED, unchanged).values(resent_at=utcnow())
            ).rowcount
            if taken and _send_by_id(session, job_id, queue):
                resent.append(job_id)
    return resent


def requeue_orphans(sessions: sessionmaker[Session], queue: JobQueue) -> list[str]:
    """Send again every job a previous embedded server left `running`: its worker died with it, and
    the filesystem broker does not redeliver a message that was already taken. The new run resumes
    from the job's checkpoints. Returns the job ids."""
    with session_scope(sessions) as session:
        jobs = session.scalars(select(Job).where(Job.state == JobState.RUNNING)).all()
        for job in jobs:
            orphaned(job)
            send(session, job, queue)
        return [job.id for job in jobs]
