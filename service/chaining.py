"""Continuations of unfinished jobs: a predict / interact / resimulate job may name a parent that is
still queued or running. It is stored `queued` with no broker task ("waiting for job PARENT") and
sent to the workers when the parent succeeds; when the parent fails or is cancelled it fails with
the reason, and so do the jobs waiting on it in turn.

`release_children` is called by the worker after every job ends and by the API right after it
stores a waiting job (the parent may have ended between the API's check and its commit). Both
may run at once: each waiting job is taken by one atomic UPDATE (`task_id` NULL -> SENDING), so
it is sent exactly once.
"""

from __future__ import annotations

import logging

from sqlalchemy import select, update
from sqlalchemy.orm import Session

from service.job_types import JobType
from service.models import SENDING, Job, JobState, utcnow
from service.queue import JobQueue, QueueUnavailable

log = logging.getLogger(__name__)


def waiting_stage(parent_id: str) -> str:
    return f"waiting for job {parent_id}"


def release_children(session: Session, parent_id: str, queue: JobQueue) -> list[str]:
    """Send or fail the jobs waiting on `parent_id`, according to its state now; returns their ids.

    Commits as it goes (each child is its own small transaction)."""
    parent_state = session.scalar(select(Job.state).where(Job.id == parent_id))
    if parent_state is None or not JobState(parent_state).finished:
        return []
    waiting = session.scalars(
        select(Job.id).where(Job.parent_job_id == parent_id, Job.state == JobState.QUEUED, Job.task_id.is_(None))
    ).all()
    released = []
    for child_id in waiting:
        taken = session.execute(
            update(Job).where(Job.id == child_id, Job.state == JobState.QUEUED, Job.task_id.is_(None)).values(task_id=SENDING)
        ).rowcount
        session.commit()
        if not taken:  # the other caller got it first
            continue
        released.append(child_id)
        if parent_state == JobState.SUCCEEDED:
            _send(session, child_id, queue)
        else:
            reason = "was cancelled" if parent_state == JobState.CANCELLED else "failed"
            _fail(session, child_id, f"parent job {parent_id} {reason}")
            released += release_children(session, child_id, queue)
    return released


def _send(session: Session, job_id: str, queue: JobQueue) -> None:
    job = session.get(Job, job_id)
    assert job is not None
    try:
        job.task_id = queue.enqueue(job.id, JobType(job.type))
        job.stage = "queued"
    except QueueUnavailable as exc:
        job.state, job.error, job.finished_at = JobState.FAILED, str(exc), utcnow()
    session.commit()
    log.info("job %s: parent done, %s", job_id, "sent" if job.state == JobState.QUEUED else f"failed: {job.error}")


def _fail(session: Session, job_id: str, error: str) -> None:
    job = session.get(Job, job_id)
    assert job is not None
    job.state, job.stage, job.error, job.finished_at = JobState.FAILED, "failed", error, utcnow()
    session.commit()
