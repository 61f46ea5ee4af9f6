"""Continuations of unfinished jobs: a predict / interact / resimulate job may name a parent that is
still queued or running. It is stored `queued` with no broker task ("waiting for job PARENT") and
sent to the workers when the parent succeeds; when the parent fails or is cancelled it fails with
the reason, and so do the jobs waiting on it in turn.

`release_children` is called by the worker after every job ends and by the API right after it
stores a waiting job (the parent may have ended between the API's check and its commit). Both
may run at once: each waiting job is taken by one atomic UPDATE (`service.queue.take_for_sending`),
so it is sent exactly once.
"""

from __future__ import annotations

import logging

from sqlalchemy import select
from sqlalchemy.orm import Session

from service.job_states import FAILED_STAGE, Actor, fail
from service.models import Job, JobState
from service.queue import JobQueue, send, take_for_sending

log = logging.getLogger(__name__)


def release_children(session: Session, parent_id: str, queue: JobQueue, actor: Actor) -> list[str]:
    """Send or fail the jobs waiting on `parent_id`, according to its state now; returns their ids.
    `actor`: who saw the parent end (the worker that ran it, or the API storing a child).

    Commits as it goes (each child is its own small transaction)."""
    parent_state = session.scalar(select(Job.state).where(Job.id == parent_id))
    if parent_state is None or not JobState(parent_state).finished:
        return []
    waiting = session.scalars(
        select(Job.id).where(Job.parent_job_id == parent_id, Job.state == JobState.QUEUED, Job.task_id.is_(None))
    ).all()
    released = []
    for child_id in waiting:
        if not take_for_sending(session, child_id, None):  # the other caller got it first
            continue
        released.append(child_id)
        child = session.get(Job, child_id)
        assert child is not None
        if parent_state == JobState.SUCCEEDED:
            outcome = "sent" if send(session, child, queue) else "waiting for the queue"
            log.info("job %s: parent done, %s", child_id, outcome)
        else:
            reason = "was cancelled" if parent_state == JobState.CANCELLED else "failed"
            fail(child, f"parent job {parent_id} {reason}", actor, stage=FAILED_STAGE)
            session.commit()
            log.info("job %s: parent done, failed: %s", child_id, child.error)
            released += release_children(session, child_id, queue, actor)
    return released
