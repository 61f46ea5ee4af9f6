"""How a job reaches the workers. The Celery implementation is the real one; tests of the API's own
logic may pass another `JobQueue` to `create_app`.

Fairness among owners is decided here, once, at the send (`send`): each owner has at most
`JobQueue.owner_share` jobs sent to the broker or running (`Settings.jobs_in_flight_per_owner`);
a job beyond waits in the database, queued "waiting for its turn" (`HELD`), and is sent when one
of its owner's jobs ends (`send_turns`, called by the worker that ended it, and the reaper's
every pass), oldest first. The broker stays a plain FIFO: what it holds is at most a share per
owner, so another owner's single job is sent at once and waits behind at most the shares ahead
of it, never behind a whole backlog (issue 36: 300 jobs of one key once delayed another's by
5 min 40 s)."""

from __future__ import annotations

import logging
from datetime import datetime, timedelta
from typing import Protocol

from sqlalchemy import and_, func, or_, select, update
from sqlalchemy.orm import Session, sessionmaker
from sqlalchemy.sql.elements import ColumnElement

from service.celery_app import make_celery, task_name
from service.database import session_scope
from service.job_types import JobType
from service.job_states import QUEUED_STAGE, RESUME_STAGE, TURN_STAGE, UNSENT_STAGE, orphaned, send_again
from service.models import HELD, SENDING, UNSENT, Job, JobState, utcnow
from service.settings import GPU_QUEUE, Settings

log = logging.getLogger(__name__)


class QueueUnavailable(Exception):
    """The broker did not take the message."""


class JobQueue(Protocol):
    owner_share: int  # jobs of one owner sent or running at once; the rest wait their turn (`send`)

    def enqueue(self, job_id: str, job_type: JobType) -> str:
        """Send the job to a worker; returns the broker's task id."""

    def ping(self) -> None:
        """Raise QueueUnavailable unless the broker answers (for /readyz)."""


class CeleryQueue:
    """Sends each job's task to the `gpu` queue by name (`task_name`): the tasks themselves live in
    `worker.tasks`, which the API never imports."""

    def __init__(self, settings: Settings) -> None:
        self.app = make_celery(settings)
        self.owner_share = settings.jobs_in_flight_per_owner

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
    waits (state "queued", stage "waiting for the queue").

    Before its first send a job waits its owner's turn: while the owner has `queue.owner_share`
    jobs sent or running, it is marked `HELD` with the stage "waiting for its turn ..." and
    `send_turns` sends it when one of them ends. A job sent once (the reaper's sends) keeps its
    turn. Returns False only when the broker refused the job."""
    if _first_send(job) and _in_flight(session, job.owner, job.id) >= queue.owner_share:
        job.task_id, job.stage = HELD, TURN_STAGE
        session.commit()
        return True
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


def _first_send(job: Job) -> bool:
    """Whether `send` hands the job to the broker for the first time: a new job, a released
    continuation, a job the broker refused before (all marked `SENDING` by their caller), but
    not one the reaper sends again (its old task id kept) or one resuming a lost attempt."""
    return job.task_id == SENDING and job.stage != RESUME_STAGE


def _in_flight(session: Session, owner: str, other_than: str | None = None) -> int:
    """The owner's jobs sent to the broker (or being sent) or running, but `other_than`."""
    query = select(func.count()).select_from(Job).where(
        Job.owner == owner,
        or_(
            Job.state == JobState.RUNNING,
            and_(Job.state == JobState.QUEUED, Job.task_id.is_not(None), Job.task_id.not_in([UNSENT, HELD])),
        ),
    )
    if other_than is not None:
        query = query.where(Job.id != other_than)
    return session.scalar(query) or 0


def send_turns(session: Session, ended: str, queue: JobQueue) -> list[str]:
    """Send the jobs whose turn the end of job `ended` gave (its owner's, `_send_owner_turns`);
    the worker calls it after every job it ends. Returns their ids."""
    owner = session.scalar(select(Job.owner).where(Job.id == ended))
    return [] if owner is None else _send_owner_turns(session, owner, queue)


def _send_owner_turns(session: Session, owner: str, queue: JobQueue) -> list[str]:
    """Send the owner's oldest jobs waiting for their turn (`HELD`) while the owner has fewer than
    `queue.owner_share` jobs sent or running; returns their ids. Each is taken by one atomic
    UPDATE (`take_for_sending`), so concurrent callers (the worker that ended a job, the
    reapers) send it once. At most a share is sent per call; commits as it goes."""
    sent: list[str] = []
    for _ in range(queue.owner_share):
        if _in_flight(session, owner) >= queue.owner_share:
            break
        job_id = session.scalar(
            select(Job.id).where(Job.owner == owner, Job.state == JobState.QUEUED, Job.task_id == HELD)
            .order_by(Job.created_at, Job.id).limit(1)
        )
        if job_id is None:
            break
        if not take_for_sending(session, job_id, HELD):
            continue  # another caller took it; count again
        job = session.get(Job, job_id)
        assert job is not None
        session.refresh(job)
        if not send(session, job, queue):
            break  # refused by the broker: UNSENT, the reaper sends it when the broker answers
        if job.task_id != HELD:
            sent.append(job_id)
    return sent


def _send_turns_of_all(sessions: sessionmaker[Session], queue: JobQueue) -> list[str]:
    """`send_turns` for every owner with a job waiting for its turn (the reaper's pass: a turn
    freed by an end no worker reported, a cancel or a delete is used within a quarter lease)."""
    with session_scope(sessions) as session:
        owners = session.scalars(
            select(Job.owner).where(Job.state == JobState.QUEUED, Job.task_id == HELD).distinct()
        ).all()
    sent = []
    for owner in owners:
        with session_scope(sessions) as session:
            sent += _send_owner_turns(session, owner, queue)
    return sent


def reap_stale(sessions: sessionmaker[Session], queue: JobQueue, lease_seconds: float) -> list[str]:
    """Send again every running job whose heartbeat is older than the lease: its worker died, or
    lost the broker or the database for longer than the lease (its fencing token stops it when it
    comes back). The next claim resumes from the checkpoints, or fails the job once it has used
    up its attempts. Each job is taken by one conditional UPDATE (`job_states.send_again`), so
    concurrent reapers (one per API process) send it once. Then send the jobs the broker did not
    take or whose hand-off to it never ended (`_send_unsent`), the queued jobs whose message was
    lost (`_resend_lost`) and the jobs whose owner's turn came (`_send_turns_of_all`). Returns the
    ids of the jobs the broker took."""
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
    unsent = _send_unsent(sessions, queue, cutoff)
    return reaped + unsent + _resend_lost(sessions, queue, lease_seconds) + _send_turns_of_all(sessions, queue)


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
                Job.state == JobState.QUEUED, Job.task_id.is_not(None), Job.task_id.not_in([SENDING, UNSENT, HELD]),
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
