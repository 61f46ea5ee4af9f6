"""The job state machine: the state changes a job may make, who makes each, and one function per
change that checks it is allowed before it writes (an illegal change raises `IllegalTransition`,
it is never written).

    queued  -> running     worker   claims it (`start`)
    running -> running     worker   claims it again once its last runner's lease expired (`start`)
    running -> succeeded   worker   the lease holder's runner finished (`succeed`)
    running -> failed      worker   bad input, a bug, a time limit, retries spent (`fail`)
    running -> cancelled   worker   cancel asked for, seen at a report or at a claim (`cancel`)
    running -> queued      worker   a transient fault: given back for the task's retry (`give_back`)
    running -> queued      reaper   its heartbeat is older than the lease (`send_again`), or serve
                                    starts again after its embedded worker died with it (`orphaned`)
    queued  -> cancelled   API      cancelled before it ran (`cancel`); worker: a claim finds it asked
                   API, worker, reaper   its parent did not succeed: cancelled with the reason
                                    (service.chaining, run by whoever sees the parent end)
    queued  -> failed      worker   lost on every attempt, or transient retries spent while it
                                    waited for its retry

A queued job is in one of five sub-states, told by `Job.task_id`, none a state a client acts on:
waiting for its parent (NULL, stage `waiting_stage(parent)`), being handed to the broker
(`SENDING`, since `resent_at` or its creation; a lease later the reaper sends it: the process
handing it on died), not taken by the broker (`UNSENT`, stage `UNSENT_STAGE`: service.queue.send, the one
rule for a broker that is down), waiting for its owner's turn (`HELD`, stage `TURN_STAGE`:
service.queue.send, the one rule of fairness among owners) and sent (the broker's task id).
Running jobs are fenced (service.leases.held): a runner writes only while the job is running
under the `lease_token` it claimed with, which only `start` raises. So a runner whose job the
reaper queued again (its heartbeat stopped for a lease: a frozen or cut-off worker) writes
nothing more when it wakes up, and the job says what happens to it: queued, "waiting to
resume", until a claim runs it again.
"""

from __future__ import annotations

import enum
from datetime import datetime

from sqlalchemy import update
from sqlalchemy.orm import Session

from service.errors import Conflict
from service.models import Job, JobState, utcnow

QUEUED, RUNNING = JobState.QUEUED, JobState.RUNNING
SUCCEEDED, FAILED, CANCELLED = JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED

QUEUED_STAGE = "queued"
UNSENT_STAGE = "waiting for the queue"  # the broker did not take it; the reaper sends it (service.queue)
RESUME_STAGE = "waiting to resume: its worker stopped responding"  # the claim counts the attempt as lost
TURN_STAGE = "waiting for its turn behind your earlier jobs"  # service.queue.send: the owner's share is full
RETRY_STAGE = "waiting to retry"  # given back after a transient fault; its task retries
STARTING_STAGE = "preparing"
DONE_STAGE = "done"
CANCELLED_STAGE = "cancelled"
FAILED_STAGE = "failed"


def waiting_stage(parent_id: str) -> str:
    """The stage of a continuation waiting for its parent to end (service.chaining)."""
    return f"waiting for job {parent_id}"


class Actor(enum.StrEnum):
    API = "API"  # a client's request
    WORKER = "worker"  # the runner holding the job's lease (or its task, giving up)
    REAPER = "reaper"  # the API's stale-job reaper, and serve's start-up requeue


_API, _WORKER, _REAPER = Actor.API, Actor.WORKER, Actor.REAPER
TRANSITIONS: dict[tuple[JobState, JobState], frozenset[Actor]] = {
    (QUEUED, RUNNING): frozenset({_WORKER}),
    (RUNNING, RUNNING): frozenset({_WORKER}),
    (RUNNING, SUCCEEDED): frozenset({_WORKER}),
    (RUNNING, FAILED): frozenset({_WORKER}),
    (RUNNING, CANCELLED): frozenset({_WORKER}),
    (RUNNING, QUEUED): frozenset({_WORKER, _REAPER}),
    (QUEUED, CANCELLED): frozenset({_API, _WORKER, _REAPER}),
    (QUEUED, FAILED): frozenset({_WORKER}),
}


class IllegalTransition(Conflict):
    """A state change the machine does not allow, or not to this actor."""


def check(job_id: str, current: JobState | str, to: JobState, actor: Actor) -> None:
    """Raise IllegalTransition unless `actor` may move a job from `current` to `to`."""
    if actor not in TRANSITIONS.get((JobState(current), to), frozenset()):
        raise IllegalTransition(f"job {job_id}: the {actor} may not move it from {current} to {to}")


def _move(job: Job, to: JobState, actor: Actor) -> None:
    check(job.id, job.state, to, actor)
    job.state = to


def start(job: Job, worker: str) -> int:
    """A worker claims the job: running on `worker`, one more attempt, a new lease token (returned)."""
    _move(job, RUNNING, Actor.WORKER)
    now = utcnow()
    job.stage, job.error = STARTING_STAGE, None
    job.started_at = job.started_at or now
    job.heartbeat_at, job.worker, job.attempts = now, worker, job.attempts + 1
    job.lease_token += 1
    return job.lease_token


def succeed(job: Job) -> None:
    _move(job, SUCCEEDED, Actor.WORKER)
    job.stage, job.progress, job.error, job.finished_at = DONE_STAGE, 1.0, None, utcnow()


def fail(job: Job, error: str, actor: Actor, stage: str | None = None) -> None:
    """Failed with `error` (what its owner reads); the stage it failed in is kept unless given."""
    _move(job, FAILED, actor)
    job.error, job.finished_at = error, utcnow()
    job.stage = stage or job.stage


def cancel(job: Job, actor: Actor, reason: str | None = None) -> None:
    """Cancelled; `reason` (the job's `error`) says why when its owner did not ask for it (a
    continuation whose parent did not succeed: service.chaining)."""
    _move(job, CANCELLED, actor)
    job.stage, job.error, job.finished_at = CANCELLED_STAGE, reason, utcnow()


def give_back(job: Job) -> None:
    """A transient fault: queued again with no live lease, so the task's retry claims it at once."""
    _move(job, QUEUED, Actor.WORKER)
    job.stage, job.heartbeat_at = RETRY_STAGE, None


def orphaned(job: Job) -> None:
    """A job an embedded worker left running when serve stopped: queued to resume."""
    _move(job, QUEUED, Actor.REAPER)
    job.stage, job.heartbeat_at = RESUME_STAGE, None


def send_again(session: Session, job_id: str, token: int, stale_before: datetime) -> bool:
    """A running job whose heartbeat is older than `stale_before`: queued to resume, by one
    conditional UPDATE (still running, same token, still stale), so of concurrent reapers one
    takes it. Returns whether this caller did."""
    check(job_id, RUNNING, QUEUED, Actor.REAPER)
    return bool(
        session.execute(
            update(Job)
            .where(Job.id == job_id, Job.state == RUNNING, Job.lease_token == token, Job.heartbeat_at < stale_before)
            .values(state=QUEUED, stage=RESUME_STAGE, heartbeat_at=None, resent_at=utcnow())
        ).rowcount
    )
