"""`/v1/jobs`: create (idempotently), read, list, cancel, delete. The work is `service.jobs`'."""

from __future__ import annotations

import hashlib
import json
from typing import Annotated

from fastapi import APIRouter, Body, Header, HTTPException, Response, status

from api.deps import OwnerDep, PageLimit, PageOffset, QueueDep, SessionDep, SettingsDep, StorageDep
from api.errors import StrictJSONRoute, error_responses
from api.idempotency import replay
from api.schemas import JobLogs, JobOut, JobRequest, Page
from api.views import job_out
from service import jobs, quotas, webhooks
from service.errors import DuplicateRequest
from service.job_types import JobType
from service.models import Job, JobState
from service.settings import Settings

router = APIRouter(
    prefix="/v1/jobs", tags=["jobs"], route_class=StrictJSONRoute, responses=error_responses(401, 422, 503)
)

@router.post(
    "", status_code=status.HTTP_202_ACCEPTED, response_model=JobOut, responses=error_responses(404, 409, 413, 429)
)
def create_job(
    request: Annotated[JobRequest, Body()],
    owner: OwnerDep,
    session: SessionDep,
    queue: QueueDep,
    storage: StorageDep,
    settings: SettingsDep,
    response: Response,
    idempotency_key: Annotated[str | None, Header(max_length=256)] = None,
) -> JobOut:
    """Queue a job. A repeated request with the same `Idempotency-Key` returns the first job
    that was queued.

    A continuation may name a parent that is still queued or running: it waits (stage "waiting
    for job PARENT") and starts when the parent succeeds, or is cancelled saying why the parent
    did not (`error`: "parent job PARENT failed" or "... was cancelled"). A scene or parent
    deleted while the job is being created is a 409.
    While the job broker is down a job waits queued with stage "waiting for the queue" and is
    sent when the broker answers again (`service.queue.send`); one waiting behind its owner's
    earlier jobs has stage "waiting for its turn ...". 429 when the owner has too many unfinished
    jobs or stores too much (`service.quotas`).
    """
    idempotency_key = idempotency_key or None  # an empty header is no key
    body = request.model_dump(mode="json")
    request_hash = hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()
    if idempotency_key is not None:
        existing = replay(session, Job, owner, idempotency_key, request_hash)
        if existing is not None:
            response.headers["Idempotent-Replayed"] = "true"
            return job_out(existing)

    quotas.check_new_job(session, owner, settings)
    if request.webhook is not None:
        _check_webhook(str(request.webhook), settings)
    job_type = JobType(request.type)
    source_id = getattr(request, job_type.input_field)
    waits_for = jobs.check_references(
        session, storage, owner, job_type, source_id, request.params, settings.max_predict_frames
    )
    job = Job(
        owner=owner,
        type=job_type,
        scene_id=getattr(request, "scene_id", None),
        parent_job_id=getattr(request, "parent_job_id", None),
        params=body["params"],
        idempotency_key=idempotency_key,
        request_hash=request_hash,
        webhook_url=body.get("webhook"),
    )
    try:
        jobs.create(session, queue, settings, job, waits_for)
    except DuplicateRequest:  # a concurrent request with the same Idempotency-Key won the race
        existing = replay(session, Job, owner, idempotency_key or "", request_hash)
        if existing is None:
            raise
        response.headers["Idempotent-Replayed"] = "true"
        return job_out(existing)
    return job_out(job)


@router.get("", response_model=Page[JobOut])
def list_jobs(
    owner: OwnerDep,
    session: SessionDep,
    state: JobState | None = None,
    type: JobType | None = None,
    scene_id: str | None = None,
    parent_job_id: str | None = None,
    limit: PageLimit = 20,
    offset: PageOffset = 0,
) -> Page[JobOut]:
    """The caller's jobs, newest first, optionally filtered."""
    kept = jobs.JobFilter(state=state, type=type, scene_id=scene_id, parent_job_id=parent_job_id)
    rows, total = jobs.page(session, owner, kept, limit, offset)
    next_offset = offset + limit if offset + limit < total else None
    return Page[JobOut](items=[job_out(j) for j in rows], total=total, limit=limit, offset=offset, next_offset=next_offset)


@router.get("/{job_id}", response_model=JobOut, responses=error_responses(404))
def get_job(job_id: str, owner: OwnerDep, session: SessionDep) -> JobOut:
    return job_out(jobs.owned(session, job_id, owner))


@router.get("/{job_id}/logs", response_model=JobLogs, responses=error_responses(404))
def get_job_logs(job_id: str, owner: OwnerDep, session: SessionDep, storage: StorageDep, offset: PageOffset = 0) -> JobLogs:
    """The job's log lines so far (every attempt), from line `offset` on: poll with `next_offset`."""
    job = jobs.owned(session, job_id, owner)
    lines = jobs.log_lines(storage, job.id)
    return JobLogs(job_id=job.id, lines=lines[offset:], next_offset=max(offset, len(lines)))


@router.post(
    "/{job_id}/cancel", status_code=status.HTTP_202_ACCEPTED, response_model=JobOut, responses=error_responses(404, 409)
)
def cancel_job(job_id: str, owner: OwnerDep, session: SessionDep, queue: QueueDep, settings: SettingsDep) -> JobOut:
    """A queued job is cancelled at once; a running one stops at its next frame boundary. Either
    way its webhook is sent when it ends, and the continuations waiting on it are cancelled."""
    return job_out(jobs.request_cancel(session, queue, settings, job_id, owner))


@router.delete("/{job_id}", status_code=status.HTTP_204_NO_CONTENT, responses=error_responses(404, 409))
def delete_job(job_id: str, owner: OwnerDep, session: SessionDep, storage: StorageDep) -> None:
    """Delete a finished job, its run folder and its artifacts (the records of its videos'
    renders with it); refused (409) while it runs, has continuations, or renders a video."""
    jobs.delete(session, storage, job_id, owner)


def _check_webhook(url: str, settings: Settings) -> None:
    """An internal target is a 422 now; the worker checks the address again when it connects."""
    try:
        webhooks.check_target(url, settings.webhook_allow_private)
    except webhooks.RefusedTarget as exc:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, f"webhook: {exc}") from None
