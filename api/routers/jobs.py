"""`/v1/jobs`: create (idempotently), read, list, cancel, delete."""

from __future__ import annotations

import hashlib
import json
from datetime import UTC, datetime
from typing import Annotated

from fastapi import APIRouter, Body, Header, HTTPException, Response, status
from sqlalchemy import delete, func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from api.deps import OwnerDep, PageLimit, PageOffset, QueueDep, SessionDep, SettingsDep, StorageDep
from api.errors import StrictJSONRoute, error_responses
from api.idempotency import replay
from api.routers.scenes import capture_geometry_of, check_reconstruct_params, owned_scene
from api.schemas import JobLinks, JobLogs, JobOut, JobRequest, JobTimings, Page
from service import webhooks
from service.chaining import release_children, waiting_stage
from fluidcore.spec.jobs import InteractParams
from service.job_types import JobType
from service.models import Artifact, Job, JobState, utcnow
from service.queue import JobQueue, QueueUnavailable
from service.settings import Settings
from service.storage import ObjectNotFound, Storage, job_prefix, log_key, run_prefix

router = APIRouter(
    prefix="/v1/jobs", tags=["jobs"], route_class=StrictJSONRoute, responses=error_responses(401, 422, 503)
)

@router.post(
    "", status_code=status.HTTP_202_ACCEPTED, response_model=JobOut, responses=error_responses(404, 409, 413)
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
    that was queued (a 503 binds nothing: the retry creates the job).

    A continuation may name a parent that is still queued or running: it waits (stage "waiting
    for job PARENT") and starts when the parent succeeds, or fails saying why the parent did not.
    """
    idempotency_key = idempotency_key or None  # an empty header is no key
    body = request.model_dump(mode="json")
    request_hash = hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()
    if idempotency_key is not None:
        existing = replay(session, Job, owner, idempotency_key, request_hash)
        if existing is not None:
            response.headers["Idempotent-Replayed"] = "true"
            return job_out(existing)

    if request.webhook is not None:
        _check_webhook(str(request.webhook), settings)
    waits_for = _check_references(session, storage, owner, request, settings)
    job = Job(
        owner=owner,
        type=request.type,
        scene_id=getattr(request, "scene_id", None),
        parent_job_id=getattr(request, "parent_job_id", None),
        params=body["params"],
        idempotency_key=idempotency_key,
        request_hash=request_hash,
        stage=waiting_stage(waits_for) if waits_for else "queued",
        webhook_url=body.get("webhook"),
    )
    session.add(job)
    try:
        session.commit()
    except IntegrityError:  # a concurrent request with the same Idempotency-Key won the race
        session.rollback()
        existing = replay(session, Job, owner, idempotency_key or "", request_hash)
        if existing is None:
            raise
        response.headers["Idempotent-Replayed"] = "true"
        return job_out(existing)

    if waits_for:  # sent by whoever sees the parent end; it may have ended since the check above
        release_children(session, waits_for, queue)
        session.refresh(job)
        return job_out(job)
    send(session, job, queue)
    return job_out(job)


def send(session: Session, job: Job, queue: JobQueue) -> None:
    """Hand a stored job to the workers. When the queue is down the job fails and the answer is
    a 503; its Idempotency-Key is released: the retry the 503 invites must create a job and
    queue it, not replay this one that never reached a worker."""
    try:
        job.task_id = queue.enqueue(job.id, job.type)
    except QueueUnavailable as exc:
        job.state, job.error, job.finished_at = JobState.FAILED, str(exc), utcnow()
        job.idempotency_key = None
        session.commit()
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, str(exc)) from None
    session.commit()


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
    query = select(Job).where(Job.owner == owner)
    for column, value in ((Job.state, state), (Job.type, type), (Job.scene_id, scene_id), (Job.parent_job_id, parent_job_id)):
        if value is not None:
            query = query.where(column == value)
    total = session.scalar(select(func.count()).select_from(query.subquery())) or 0
    rows = session.scalars(query.order_by(Job.created_at.desc(), Job.id).limit(limit).offset(offset)).all()
    next_offset = offset + limit if offset + limit < total else None
    return Page[JobOut](items=[job_out(j) for j in rows], total=total, limit=limit, offset=offset, next_offset=next_offset)


@router.get("/{job_id}", response_model=JobOut, responses=error_responses(404))
def get_job(job_id: str, owner: OwnerDep, session: SessionDep) -> JobOut:
    return job_out(owned_job(session, job_id, owner))


@router.get("/{job_id}/logs", response_model=JobLogs, responses=error_responses(404))
def get_job_logs(job_id: str, owner: OwnerDep, session: SessionDep, storage: StorageDep, offset: PageOffset = 0) -> JobLogs:
    """The job's log lines so far (every attempt), from line `offset` on: poll with `next_offset`."""
    job = owned_job(session, job_id, owner)
    try:
        lines = storage.read_bytes(log_key(job.id)).decode(errors="replace").splitlines()
    except ObjectNotFound:
        lines = []
    return JobLogs(job_id=job.id, lines=lines[offset:], next_offset=max(offset, len(lines)))


@router.post(
    "/{job_id}/cancel", status_code=status.HTTP_202_ACCEPTED, response_model=JobOut, responses=error_responses(404, 409)
)
def cancel_job(job_id: str, owner: OwnerDep, session: SessionDep) -> JobOut:
    """A queued job is cancelled at once; a running one stops at its next frame boundary."""
    job = owned_job(session, job_id, owner, for_update=True)
    if JobState(job.state).finished:
        raise HTTPException(status.HTTP_409_CONFLICT, f"job {job_id} already {job.state}")
    job.cancel_requested = True
    if job.state == JobState.QUEUED:
        job.state, job.stage, job.finished_at = JobState.CANCELLED, "cancelled", utcnow()
    session.commit()
    return job_out(job)


@router.delete("/{job_id}", status_code=status.HTTP_204_NO_CONTENT, responses=error_responses(404, 409))
def delete_job(job_id: str, owner: OwnerDep, session: SessionDep, storage: StorageDep) -> None:
    """Delete a finished job, its run folder and its artifacts (the records of its videos'
    renders with it); refused (409) while it runs, has continuations, or renders a video."""
    job = owned_job(session, job_id, owner, for_update=True)
    if not JobState(job.state).finished:
        raise HTTPException(status.HTTP_409_CONFLICT, f"job {job_id} is {job.state}; cancel it first")
    children = session.scalars(select(Job).where(Job.parent_job_id == job.id)).all()
    continued = [child.id for child in children if JobType(child.type).writes_run]
    if continued:
        raise HTTPException(
            status.HTTP_409_CONFLICT, f"job {job_id} is continued by jobs {', '.join(continued)}; delete them first"
        )
    rendering = [child.id for child in children if not JobState(child.state).finished]
    if rendering:
        raise HTTPException(
            status.HTTP_409_CONFLICT, f"job {job_id} has videos rendering in jobs {', '.join(rendering)}; cancel them first"
        )
    session.execute(delete(Artifact).where(Artifact.job_id == job.id))
    for child in children:
        session.delete(child)
    session.flush()  # the renders before the job they name
    session.delete(job)
    session.commit()  # rows first: a failed file removal leaves garbage, never a dangling row
    storage.delete_prefix(f"{job_prefix(job.id)}/")


def owned_job(session: Session, job_id: str, owner: str, for_update: bool = False) -> Job:
    """The job if it exists and belongs to `owner`; 404 otherwise."""
    query = select(Job).where(Job.id == job_id)
    job = session.scalars(query.with_for_update() if for_update else query).first()
    if job is None or job.owner != owner:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"job {job_id} not found")
    return job


def _check_webhook(url: str, settings: Settings) -> None:
    """An internal target is a 422 now; the worker checks the address again when it connects."""
    try:
        webhooks.check_target(url, settings.webhook_allow_private)
    except webhooks.RefusedTarget as exc:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, f"webhook: {exc}") from None


def _check_references(
    session: Session, storage: Storage, owner: str, request: JobRequest, settings: Settings
) -> str | None:
    """The scene or parent job exists, belongs to the caller, and fits the parameters.

    Returns the parent's id when the new job has to wait for it (queued or running)."""
    if JobType(request.type).starts_from == "scene":
        scene = owned_scene(session, request.scene_id, owner)
        box = capture_geometry_of(storage, scene)["box"] if request.params.source is not None else None
        check_reconstruct_params(request.params, scene.n_frames, box, "params")
        return None
    # Any job that writes a run can be continued: every such type leaves the same run-folder format.
    parent = owned_job(session, request.parent_job_id, owner)
    if not JobType(parent.type).writes_run:
        raise HTTPException(
            status.HTTP_422_UNPROCESSABLE_CONTENT, f"parent_job_id: job {parent.id} renders a video; it has no run to continue"
        )
    if parent.state in (JobState.FAILED, JobState.CANCELLED):
        raise HTTPException(
            status.HTTP_409_CONFLICT, f"parent job {parent.id} is {parent.state}; it cannot be continued"
        )
    frames = getattr(request.params, "frames", None)
    if frames is not None and frames > settings.max_predict_frames:
        raise HTTPException(
            status.HTTP_422_UNPROCESSABLE_CONTENT,
            f"params.frames: at most {settings.max_predict_frames} new frames per job",
        )
    if parent.state != JobState.SUCCEEDED:
        return parent.id  # the run scene is checked by the worker once the parent's run exists
    if isinstance(request.params, InteractParams):
        _check_in_run_scene(storage, parent.id, request.params)
    return None


def _check_in_run_scene(storage: Storage, parent_id: str, params: InteractParams) -> None:
    """Wind and ball against the parent run's scene (box, time step, speed limit), and the branch
    frame against its finished frames, read from its manifest: a ball outside the box, a wind
    that tears the smoke apart or a frame the parent never reached is a 422 now, not a failed job
    later."""
    from fluidcore.spec.controls import InteractionError, branch_frame
    from fluidcore.runs import MANIFEST, RunError, RunRecord

    try:
        record = RunRecord.from_bytes(storage.read_bytes(f"{run_prefix(parent_id)}/{MANIFEST}"), f"parent job {parent_id}'s run")
        scene = record.scene
    except ObjectNotFound:
        raise HTTPException(status.HTTP_409_CONFLICT, f"parent job {parent_id} has no run in storage") from None
    except RunError as exc:
        raise HTTPException(status.HTTP_409_CONFLICT, str(exc)) from None
    try:
        if params.from_frame is not None:  # without one the job branches off the parent's last frame
            branch_frame(params.from_frame, record.frames(), f"parent job {parent_id}")
    except InteractionError as exc:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, f"params.{exc}") from None
    try:
        params.check_scene(scene, params.frames)
    except InteractionError as exc:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, f"params: {exc}") from None


def job_out(job: Job) -> JobOut:
    now = datetime.now(UTC)
    started, finished = job.started_at, job.finished_at
    queued_until = started or finished or now
    timings = JobTimings(
        created_at=job.created_at,
        started_at=started,
        finished_at=finished,
        queued_seconds=(queued_until - job.created_at).total_seconds(),
        run_seconds=((finished or now) - started).total_seconds() if started else None,
        stages=job.stage_seconds or {},
    )
    base = f"/v1/jobs/{job.id}"
    return JobOut(
        id=job.id,
        type=job.type,
        state=job.state,
        stage=job.stage,
        progress=job.progress,
        scene_id=job.scene_id,
        parent_job_id=job.parent_job_id,
        params=job.params,
        error=job.error,
        cancel_requested=job.cancel_requested,
        attempts=job.attempts,
        timings=timings,
        links=JobLinks(self=base, artifacts=f"{base}/artifacts", cancel=f"{base}/cancel"),
    )
