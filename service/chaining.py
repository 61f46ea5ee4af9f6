"""What follows a job's end, and continuations of unfinished jobs.

Every end of a job, whoever saw it (the worker that ran it or claimed it, the API cancelling a
queued job, the reaper), goes through `job_ended`: the job's completion webhook is sent, and the
jobs waiting on it are released (`release_children`). A predict / interact / resimulate job may
name a parent that is still queued or running: it is stored `queued` with no broker task
("waiting for job PARENT") and sent to the workers when the parent succeeds; when the parent
fails or is cancelled it is cancelled with the reason ("parent job P failed"), and so, in turn,
are the jobs waiting on it, each with its webhook. Cancelled, not failed: nothing went wrong
with the continuation itself, it can never run.

`release_children` also runs right after the API stores a waiting job (the parent may have ended
between the API's check and its commit), and in every reaper pass for the jobs whose parent ended
without releasing them (`release_stranded`: the process that ended it died first). Several may run
at once: each waiting job is taken by one atomic UPDATE (`service.queue.take_for_sending`), so it
is sent, or cancelled, exactly once.
"""

from __future__ import annotations

import logging

from sqlalchemy import select
from sqlalchemy.orm import Session, aliased, sessionmaker

from service import webhooks
from service.database import session_scope
from service.job_states import Actor, cancel
from service.models import Job, JobState
from service.queue import JobQueue, send, take_for_sending
from service.settings import Settings

log = logging.getLogger(__name__)


def job_ended(session: Session, job_id: str, queue: JobQueue | None, actor: Actor, settings: Settings) -> list[Job]:
    """Call after committing the end of `job_id`: send its completion webhook, release the jobs
    waiting on it and send the webhooks of those its end cancelled. Returns the released jobs.
    `actor`: who ended it; `queue` None (a worker that sends nothing, in tests) leaves the
    continuations of a job that succeeded waiting."""
    job = session.get(Job, job_id, populate_existing=True)
    if job is None or not JobState(job.state).finished:
        return []
    webhooks.announce(settings, [job])
    return release_children(session, job_id, queue, actor, settings)


def release_children(
    session: Session, parent_id: str, queue: JobQueue | None, actor: Actor, settings: Settings
) -> list[Job]:
    """Send or cancel the jobs waiting on `parent_id`, according to its state now, and those
    waiting on each one cancelled in turn, each cancelled one's webhook sent; returns them.
    Commits as it goes (each child is its own small transaction)."""
    parent_state = session.scalar(select(Job.state).where(Job.id == parent_id))
    if parent_state is None or not JobState(parent_state).finished:
        return []
    if parent_state == JobState.SUCCEEDED and queue is None:
        return []
    waiting = session.scalars(
        select(Job.id).where(Job.parent_job_id == parent_id, Job.state == JobState.QUEUED, Job.task_id.is_(None))
    ).all()
    released: list[Job] = []
    for child_id in waiting:
        if not take_for_sending(session, child_id, None):  # another caller got it first
            continue
        # Read again, and for a cancel locked (PostgreSQL): its owner may have cancelled it since
        # the take. A send holds no lock while the broker answers.
        child = session.get(
            Job, child_id, populate_existing=True, with_for_update=parent_state != JobState.SUCCEEDED
        )
        if child is None or child.state != JobState.QUEUED:
            session.rollback()
            continue
        released.append(child)
        if parent_state == JobState.SUCCEEDED:
            assert queue is not None
            outcome = "sent" if send(session, child, queue) else "waiting for the queue"
            log.info("job %s: parent done, %s", child_id, outcome)
            continue
        reason = "was cancelled" if parent_state == JobState.CANCELLED else "failed"
        cancel(child, actor, reason=f"parent job {parent_id} {reason}")
        session.commit()
        log.info("job %s: cancelled: %s", child_id, child.error)
        webhooks.announce(settings, [child])
        released += release_children(session, child_id, queue, actor, settings)
    return released


def release_stranded(sessions: sessionmaker[Session], queue: JobQueue, settings: Settings) -> list[str]:
    """A pass of the API's reaper (api.app, after service.queue.reap_stale): release the jobs still
    waiting on a parent that has ended, whose `job_ended` never ran (the worker or API process
    that ended it died right after the end's commit). Returns the ids of the jobs released."""
    parent = aliased(Job)
    with session_scope(sessions) as session:
        ended = session.scalars(
            select(parent.id).distinct().join(Job, Job.parent_job_id == parent.id).where(
                Job.state == JobState.QUEUED, Job.task_id.is_(None),
                parent.state.in_([JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED]),
            )
        ).all()
    released: list[str] = []
    for parent_id in ended:
        with session_scope(sessions) as session:
            released += [child.id for child in release_children(session, parent_id, queue, Actor.REAPER, settings)]
    return released
