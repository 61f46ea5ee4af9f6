"""A running job's lease, as the worker holding it reads and writes it: the claim, the fencing
check, progress and heartbeat, the cancel flag, the artifacts it publishes, and how it ends the
job or hands it back after a transient fault (each state change through service.job_states;
what follows an end is service.chaining's).

A claim (`claim`) raises the job's `lease_token` (service.job_states.start); from then on every
write of the runner goes through `held`, which raises `LeaseLost` once the job is not running
under that token any more: the reaper queued it again (its heartbeats stopped reaching the
database for longer than the lease: a frozen worker, a cut-off one) or another claim raised the
token. A runner that wakes up after that writes nothing more (no progress, checkpoint, artifact
or end state), so the job's state says what happens to it, never `queued` while a stale runner
finishes it.
Each function works inside the caller's session, so the caller's `session_scope` is the commit.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from datetime import timedelta

from sqlalchemy import delete, select
from sqlalchemy.orm import Session

from service import job_states
from service.job_states import RESUME_STAGE, Actor
from service.jobs import ancestors
from service.models import Artifact, Job, JobState, utcnow

log = logging.getLogger(__name__)


class LeaseLost(Exception):
    """The job was queued again or claimed by another runner (our heartbeats stopped reaching the
    database for longer than the lease): stop at once and write nothing more; the job is the
    next claim's."""


class JobBusy(Exception):
    """Another worker holds a live lease on the job; try again after `retry_in` seconds."""

    def __init__(self, retry_in: float) -> None:
        super().__init__(f"job is running elsewhere; retry in {retry_in:.0f} s")
        self.retry_in = retry_in


@dataclass(frozen=True)
class Claim:
    """What a runner needs of the job it claimed, read while the claim held the row."""

    job_id: str
    job_type: str  # checked against JobType when the job runs: an unknown one fails the job
    params: dict
    scene_id: str | None
    ancestors: tuple[str, ...]  # parent job first, then its parent, ...: the runs this one continues
    token: int  # the job's lease_token this claim set


@dataclass(frozen=True)
class Ended:
    """A claim that ended the job instead of starting it: what follows an end is the caller's to
    do once it commits (service.chaining.job_ended)."""

    job_id: str
    state: JobState


def claim(
    session: Session, job_id: str, worker: str, lease_seconds: float, max_attempts: int
) -> Claim | Ended | None:
    """Mark the job running on `worker` under a new lease token, unless it is finished (None) or
    another worker's lease is live (JobBusy). The row is locked (`FOR UPDATE` on PostgreSQL) until
    the caller commits, so of two workers given the same job one claims it. A claim that finds a
    cancel asked for cancels the job; one that finds the last attempt lost (running with an
    expired lease, or sent again by the reaper) with the attempts spent fails it (both `Ended`)."""
    job = session.scalars(select(Job).where(Job.id == job_id).with_for_update()).first()
    if job is None:
        log.warning("job %s does not exist; dropping its task", job_id)
        return None
    if JobState(job.state).finished:
        return None
    now = utcnow()
    lease = timedelta(seconds=lease_seconds)
    if job.state == JobState.RUNNING and job.heartbeat_at is not None and now - job.heartbeat_at < lease:
        raise JobBusy((job.heartbeat_at + lease - now).total_seconds())  # its runner cancels it, if asked
    if job.cancel_requested:
        job_states.cancel(job, Actor.WORKER)
        return Ended(job.id, JobState.CANCELLED)
    # Found running with an expired lease, or sent again by the reaper (service.queue): the
    # last attempt died (e.g. hard time limit, OOM kill).
    lost = job.state == JobState.RUNNING or job.stage == RESUME_STAGE
    if lost and job.attempts >= max_attempts:
        error = f"gave up after {job.attempts} attempts: the worker running it was lost each time"
        job_states.fail(job, error, Actor.WORKER)
        return Ended(job.id, JobState.FAILED)
    token = job_states.start(job, worker)
    log.info("job %s (%s): attempt %d on %s", job.id, job.type, job.attempts, worker)
    return Claim(job.id, job.type, dict(job.params), job.scene_id, ancestors(session, job), token)


def held(session: Session, job_id: str, token: int) -> Job:
    """The job row, if it is running under lease token `token`; else LeaseLost (the fence every
    write of a runner passes first)."""
    job = session.get(Job, job_id)
    if job is None or job.lease_token != token:
        raise LeaseLost(f"job {job_id} was claimed by another runner")
    if job.state != JobState.RUNNING:
        raise LeaseLost(f"job {job_id} was queued again ({job.stage}) after its heartbeat stopped for a lease")
    return job


def holds(session: Session, job_id: str, token: int) -> bool:
    """Whether the job's lease token is still `token`, without raising (a runner ending decides by
    it whether its local folder is still its own to remove)."""
    return session.scalar(select(Job.lease_token).where(Job.id == job_id)) == token


def stage_seconds(session: Session, job_id: str) -> dict[str, float]:
    """The seconds per stage stored so far (earlier attempts'), which a resumed runner adds to."""
    job = session.get(Job, job_id)
    return dict(job.stage_seconds or {}) if job else {}


def record_progress(job: Job, fraction: float, stage: str, seconds: dict[str, float]) -> bool:
    """Write a runner's progress, stage, seconds per stage and a heartbeat to its `held` job.
    Returns whether a cancel was asked for, which the runner honours at once."""
    # Never below what was stored: a resumed run prepares again from 0 before it reaches
    # its checkpoints, and a client's progress bar must not jump back.
    job.progress, job.stage, job.heartbeat_at = max(job.progress or 0.0, fraction), stage, utcnow()
    job.stage_seconds = dict(seconds)
    return job.cancel_requested


def beat(job: Job) -> None:
    """Refresh the `held` job's heartbeat: a runner that reports nothing for a long time must not
    look dead to the reaper."""
    job.heartbeat_at = utcnow()


def cancel_requested(session: Session, job_id: str) -> bool:
    """Whether the job's owner asked for a cancel (read without the lease: it only stops work)."""
    return bool(session.scalar(select(Job.cancel_requested).where(Job.id == job_id)))


def publish_artifacts(session: Session, job: Job, rows: list[Artifact]) -> None:
    """Replace all of the `held` job's artifact rows by `rows`, whole: a retry publishes its
    complete set again, and only the lease holder publishes."""
    session.execute(delete(Artifact).where(Artifact.job_id == job.id))
    session.add_all(rows)


def publish_shown(session: Session, shown: str, rows: list[Artifact]) -> None:
    """A render or bundle job's files, added to the artifacts of the job `shown` they show,
    replacing only its rows of the same names: its other artifacts stay. The caller holds the
    render or bundle job's lease (`held`) in this session."""
    session.execute(delete(Artifact).where(Artifact.job_id == shown, Artifact.name.in_([r.name for r in rows])))
    session.add_all(rows)


def end(job: Job, state: JobState, error: str | None, seconds: dict[str, float] | None) -> None:
    """Put the job in the end state `state` as the worker (service.job_states): failed with
    `error`, and with its runner's `seconds` per stage (None: its task gives up without a runner).
    What follows the end (its webhook, its waiting continuations) is the caller's to do once it
    commits (service.chaining.job_ended)."""
    if seconds is not None:
        job.stage_seconds = seconds
    if state == JobState.SUCCEEDED:
        job_states.succeed(job)
    elif state == JobState.CANCELLED:
        job_states.cancel(job, Actor.WORKER)
    else:
        job_states.fail(job, error or "", Actor.WORKER)


def hand_back(job: Job, seconds: dict[str, float]) -> None:
    """A transient fault: the `held` job queued again with no live lease and its runner's
    `seconds` per stage, so the task's retry claims it at once."""
    job_states.give_back(job)
    job.stage_seconds = seconds
