"""Jobs as the API keeps them: an owner's job, listings, the checks and the storing of a new job,
cancelling and deleting, and what a job left (its log, its artifacts). Every
state change goes through `service.job_states`; every send through `service.queue.send`.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

from pydantic import BaseModel
from sqlalchemy import delete as delete_rows
from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from fluidcore.runs import RunError
from fluidcore.spec.controls import InteractionError, branch_frame
from fluidcore.spec.jobs import BundleParams, InteractParams, ReconstructParams
from service import bundles, scenes, videos
from service.chaining import job_ended, release_children
from service.database import commit_or_conflict
from service.errors import Conflict, DuplicateRequest, NotFound, RefusedParams
from service.job_states import QUEUED_STAGE, Actor, cancel, waiting_stage
from service.job_types import JobType
from service.models import ARTIFACT_KINDS, SENDING, Artifact, Job, JobState, Scene
from service.queue import JobQueue, send
from service.runs import read_manifest
from service.settings import Settings
from service.storage import ObjectNotFound, Storage, job_prefix, log_key


@dataclass(frozen=True)
class JobFilter:
    """What a listing keeps (None: any)."""

    state: JobState | None = None
    type: JobType | None = None
    scene_id: str | None = None
    parent_job_id: str | None = None


def get(session: Session, job_id: str) -> Job:
    """The job, whoever owns it (a signed download link names it); NotFound otherwise."""
    job = session.get(Job, job_id)
    if job is None:
        raise NotFound.named("job", job_id)
    return job


def owned(session: Session, job_id: str, owner: str, for_update: bool = False) -> Job:
    """The job if it exists and belongs to `owner`; NotFound otherwise. `for_update` locks its row
    (PostgreSQL) until the session commits."""
    query = select(Job).where(Job.id == job_id)
    job = session.scalars(query.with_for_update() if for_update else query).first()
    if job is None or job.owner != owner:
        raise NotFound.named("job", job_id)
    return job


def page(session: Session, owner: str, kept: JobFilter, limit: int, offset: int) -> tuple[list[Job], int]:
    """One page of the owner's jobs, newest first, and how many match in all."""
    query = select(Job).where(Job.owner == owner)
    for column, value in (
        (Job.state, kept.state), (Job.type, kept.type), (Job.scene_id, kept.scene_id), (Job.parent_job_id, kept.parent_job_id),
    ):
        if value is not None:
            query = query.where(column == value)
    total = session.scalar(select(func.count()).select_from(query.subquery())) or 0
    rows = session.scalars(query.order_by(Job.created_at.desc(), Job.id).limit(limit).offset(offset)).all()
    return list(rows), total


def children(session: Session, job_id: str) -> list[Job]:
    """The jobs that name `job_id` as their parent (continuations and renders)."""
    return list(session.scalars(select(Job).where(Job.parent_job_id == job_id)).all())


def ancestors(session: Session, job: Job) -> tuple[str, ...]:
    """The job's parent, then its parent, ...: the runs a continuation continues."""
    chain: list[str] = []
    parent_id = job.parent_job_id
    while parent_id is not None:
        chain.append(parent_id)
        parent_id = session.scalar(select(Job.parent_job_id).where(Job.id == parent_id))
    return tuple(chain)


def check_references(
    session: Session, storage: Storage, owner: str, job_type: JobType, source_id: str, params: BaseModel,
    max_predict_frames: int,
) -> str | None:
    """The scene or parent job (`source_id`) exists, belongs to `owner`, and fits the parameters.

    Returns the parent's id when the new job has to wait for it (queued or running)."""
    if job_type.starts_from == "scene":
        assert isinstance(params, ReconstructParams)  # the one type that starts from a scene
        scene = scenes.owned(session, source_id, owner)
        placed = params.source is not None or bool(params.solids)  # the capture's box is read only to check them
        box = scenes.capture_geometry(storage, scene)["box"] if placed else None
        scenes.check_reconstruct_params(params, scene.n_frames, box, "params")
        return None
    # Any job that writes a run can be continued: every such type leaves the same run-folder format.
    parent = owned(session, source_id, owner)
    if not JobType(parent.type).writes_run:
        raise RefusedParams(f"parent_job_id: job {parent.id} makes a {parent.type} of job {parent.parent_job_id}; "
                            "it has no run to continue")
    if parent.state in (JobState.FAILED, JobState.CANCELLED):
        raise Conflict(f"parent job {parent.id} is {parent.state}; it cannot be continued")
    frames = getattr(params, "frames", None)
    if frames is not None and frames > max_predict_frames:
        raise RefusedParams(f"params.frames: at most {max_predict_frames} new frames per job")
    if parent.state != JobState.SUCCEEDED:
        return parent.id  # the run scene is checked by the worker once the parent's run exists
    if isinstance(params, InteractParams):
        _check_in_run_scene(storage, parent.id, params)
    return None


def _check_in_run_scene(storage: Storage, parent_id: str, params: InteractParams) -> None:
    """Wind and ball against the parent run's scene (box, time step, speed limit), and the branch
    frame against its finished frames, read from its manifest: a ball outside the box, a wind
    that tears the smoke apart or a frame the parent never reached is refused now, not a failed
    job later."""
    try:
        record = read_manifest(storage, parent_id, f"parent job {parent_id}'s run")
        scene = record.scene
    except ObjectNotFound:
        raise Conflict(f"parent job {parent_id} has no run in storage") from None
    except RunError as exc:
        raise Conflict(str(exc)) from None
    try:
        if params.from_frame is not None:  # without one the job branches off the parent's last frame
            branch_frame(params.from_frame, record.frames(), f"parent job {parent_id}")
    except InteractionError as exc:
        raise RefusedParams(f"params.{exc}") from None
    try:
        params.check_scene(scene, params.frames)
    except InteractionError as exc:
        raise RefusedParams(f"params: {exc}") from None


def create(session: Session, queue: JobQueue, settings: Settings, job: Job, waits_for: str | None) -> None:
    """Store a new job and hand it on: one waiting for its parent `waits_for` is released by
    whoever sees the parent end (service.chaining; the parent may have ended since the caller's
    check, so it is tried here too), any other is sent now (service.queue.send, whose rule covers
    a broker that is down). Stored `SENDING`, so no release or reaper pass sends it meanwhile.

    The insert is where a concurrent delete shows: its scene or parent, checked by the caller,
    deleted since (the database refuses the row's reference) is a Conflict saying so, and nothing
    is stored. DuplicateRequest: a concurrent request with the same Idempotency-Key stored its
    job first."""
    job.stage = waiting_stage(waits_for) if waits_for else QUEUED_STAGE
    job.task_id = None if waits_for else SENDING
    session.add(job)
    try:
        session.commit()
    except IntegrityError:
        session.rollback()
        deleted = _deleted_reference(session, job)
        if deleted is not None:
            raise Conflict(f"{deleted} was deleted while this job was being created; nothing was queued") from None
        if job.idempotency_key is not None:
            raise DuplicateRequest(f"job with Idempotency-Key {job.idempotency_key!r}") from None
        if not JobType(job.type).writes_run:  # uq_jobs_file_in_the_making: another job makes this file now
            raise DuplicateRequest(f"{job.type} of {made_file(job)} of job {job.parent_job_id}") from None
        raise
    if waits_for:
        release_children(session, waits_for, queue, Actor.API, settings)
        session.refresh(job)
    else:
        send(session, job, queue)


def made_file(job: Job) -> str | None:
    """The artifact name of the file a render or bundle job publishes with its parent's
    artifacts (`service.videos`, `service.bundles`); None for a job that writes a run."""
    if job.type == JobType.RENDER:
        return videos.artifact_name(job.params["video"])
    if job.type == JobType.BUNDLE:
        return bundles.artifact_name(bundles.params_plan(BundleParams.model_validate(job.params)))
    return None


def file_job(owner: str, job_type: JobType, parent_id: str, params: BaseModel, reserved_bytes: int = 0) -> Job:
    """A new render or bundle job of `parent_id`'s run. Its `request_hash` is the hash of the file
    it makes, which the database allows one unfinished job at a time (`models.FILE_IN_THE_MAKING`):
    requests racing each other make it once (`create` raises DuplicateRequest for the others)."""
    job = Job(owner=owner, type=job_type, parent_job_id=parent_id, params=params.model_dump(mode="json"),
              reserved_bytes=reserved_bytes)
    job.request_hash = hashlib.sha256(f"{parent_id}/{made_file(job)}".encode()).hexdigest()
    return job


def _deleted_reference(session: Session, job: Job) -> str | None:
    """The parent job or scene a refused new job names that no longer exists, if one does not."""
    if job.parent_job_id is not None and session.get(Job, job.parent_job_id) is None:
        return f"parent job {job.parent_job_id}"
    if job.scene_id is not None and session.get(Scene, job.scene_id) is None:
        return f"scene {job.scene_id}"
    return None


def request_cancel(session: Session, queue: JobQueue, settings: Settings, job_id: str, owner: str) -> Job:
    """A queued job is cancelled at once, and what follows its end follows (`job_ended`: its
    webhook, the jobs waiting on it cancelled); a running one is asked to stop (its runner does at
    its next report, and the worker's end does the rest). Conflict for a job that already ended."""
    job = owned(session, job_id, owner, for_update=True)
    if JobState(job.state).finished:
        raise Conflict(f"job {job_id} already {job.state}")
    job.cancel_requested = True
    cancelled_now = job.state == JobState.QUEUED
    if cancelled_now:
        cancel(job, Actor.API)
    session.commit()
    if cancelled_now:
        job_ended(session, job.id, queue, Actor.API, settings)
    return job


def delete(session: Session, storage: Storage, job_id: str, owner: str) -> None:
    """Delete a finished job, its run folder and its artifacts (the records of the render and
    bundle jobs that made files of it with it); Conflict while it runs, has continuations, or
    has such a file being made."""
    job = owned(session, job_id, owner, for_update=True)
    if not JobState(job.state).finished:
        raise Conflict(f"job {job_id} is {job.state}; cancel it first")
    below = children(session, job.id)
    continued = [child.id for child in below if JobType(child.type).writes_run]
    if continued:
        raise Conflict(f"job {job_id} is continued by jobs {', '.join(continued)}; delete them first")
    rendering = [child.id for child in below if not JobState(child.state).finished]
    if rendering:
        raise Conflict(f"job {job_id} has videos or bundles being made in jobs {', '.join(rendering)}; cancel them first")
    session.execute(delete_rows(Artifact).where(Artifact.job_id == job.id))
    made = _made_artifact(session, job)
    if made is not None:  # issue 49: a deleted bundle job's bundle stayed listed and stored
        session.delete(made)
    for child in below:
        session.delete(child)
    session.flush()  # the renders and bundles before the job they name
    session.delete(job)
    # rows first: a failed file removal leaves garbage, never a dangling row
    commit_or_conflict(session, f"job {job_id} was named by a new job while it was being deleted; nothing was deleted")
    storage.delete_prefix(f"{job_prefix(job.id)}/")
    if made is not None:
        storage.delete(made.key)


def _made_artifact(session: Session, job: Job) -> Artifact | None:
    """The file a succeeded render or bundle job published with its parent's artifacts: it goes
    with the job (a failed or cancelled one made none; the file then is another job's)."""
    name = made_file(job)
    if name is None or job.state != JobState.SUCCEEDED or job.parent_job_id is None:
        return None
    return artifact(session, job.parent_job_id, name)


def log_lines(storage: Storage, job_id: str) -> list[str]:
    """The job's log lines so far, every attempt's (none before it first ran)."""
    try:
        return storage.read_bytes(log_key(job_id)).decode(errors="replace").splitlines()
    except ObjectNotFound:
        return []


def artifacts(session: Session, job_id: str) -> list[Artifact]:
    """The job's artifacts grouped by kind in ARTIFACT_KINDS' order (videos first, then bundles,
    exports, states), by name within a kind."""
    rows = session.scalars(select(Artifact).where(Artifact.job_id == job_id)).all()
    return sorted(rows, key=lambda row: (ARTIFACT_KINDS.index(row.kind), row.name))


def artifact(session: Session, job_id: str, name: str) -> Artifact | None:
    """The job's artifact `name`, if it has one."""
    return session.scalars(select(Artifact).where(Artifact.job_id == job_id, Artifact.name == name)).first()
