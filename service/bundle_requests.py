"""A bundle asked for (`POST /v1/jobs/{id}/bundles`): answered from storage when it is stored,
with the job making it when one is, else by a new `bundle` job, checked and sized first.

Why here and not in `service.bundles`: this is the one operation on bundles that creates a job
(`service.jobs`, which reads `service.bundles` for a bundle job's file name). What issue 49 fixed:
the bundle's declared size (`fluidcore.exports.BundlePlan.bytes`) is capped and reserved against
its owner's stored bytes before anything is queued, and requests racing each other make one job
(`service.jobs.file_job`; before, ten identical requests at once started six).
"""

from __future__ import annotations

from dataclasses import dataclass

from sqlalchemy.orm import Session

from fluidcore.exports import plan_bundle
from fluidcore.runs import STATES_DIR, RunRecord, state_file
from fluidcore.spec.jobs import BundleParams
from service import jobs, quotas
from service.bundles import artifact_name, bundle_jobs
from service.errors import Conflict, DuplicateRequest, NotFound
from service.job_types import JobType
from service.models import Artifact, Job, JobState
from service.queue import JobQueue
from service.runs import stored_run
from service.settings import Settings
from service.storage import Storage, run_prefix


@dataclass(frozen=True)
class BundleAnswer:
    """A bundle by its artifact name: `stored` once made, else `making`, the job making it."""

    name: str
    stored: Artifact | None
    making: Job | None


def bundled_job(session: Session, job_id: str, owner: str, for_update: bool = False) -> Job:
    """The caller's job, one that writes a run (a render or bundle job has none to bundle: NotFound)."""
    job = jobs.owned(session, job_id, owner, for_update=for_update)
    if not JobType(job.type).writes_run:
        raise NotFound(f"job {job_id} makes a {job.type} of job {job.parent_job_id}; it has no run of its own to bundle")
    return job


def request_bundle(session: Session, storage: Storage, queue: JobQueue, settings: Settings, job_id: str, owner: str,
                   params: BundleParams) -> BundleAnswer:
    """The bundle `params` asks of the caller's succeeded job `job_id`: stored, being made, or
    queued now. ExportError (a 422) for a request the run cannot satisfy or over
    `fluidcore.exports.MAX_BUNDLE_BYTES`; OverLimit when its declared size does not fit what
    its owner may still store or they have too many unfinished jobs."""
    job = bundled_job(session, job_id, owner, for_update=True)
    if job.state != JobState.SUCCEEDED:
        raise Conflict(f"job {job.id} is {job.state}; its bundles are made once it has succeeded")
    run = stored_run(storage, job.id)
    sizes = state_sizes(storage, job.id, run) if params.format == "ply" else None
    plan = plan_bundle(run, params.format, params.frames, params.voxel_size, f"job {job.id}'s run", state_bytes=sizes)
    name = artifact_name(plan)
    stored = jobs.artifact(session, job.id, name)
    if stored is not None:
        return BundleAnswer(name, stored, None)
    making = bundle_jobs(session, job.id).get(name)
    if making is not None and not JobState(making.state).finished:
        return BundleAnswer(name, None, making)
    quotas.check_new_job(session, owner, settings, incoming=plan.bytes or 0)
    resolved = BundleParams(format=plan.fmt, frames=plan.frames, voxel_size=plan.voxel_size)
    making = jobs.file_job(owner, JobType.BUNDLE, job.id, resolved, reserved_bytes=plan.bytes or 0)
    try:
        jobs.create(session, queue, settings, making, waits_for=None)
    except DuplicateRequest:  # an identical request stored its job first: answer with that one
        making = bundle_jobs(session, job.id)[name]
    return BundleAnswer(name, None, making)


def state_sizes(storage: Storage, job_id: str, run: RunRecord) -> dict[int, int]:
    """Each stored frame's state file size, by frame, from one listing of the run's states (what
    a ply bundle's declared size is bounded by, `fluidcore.exports.frame_bytes`)."""
    prefix = f"{run_prefix(job_id)}/"
    frame_of = {state_file(t): t for t in run.frames()}
    listed = ((info.key.removeprefix(prefix), info.size) for info in storage.list(f"{prefix}{STATES_DIR}/"))
    return {frame_of[name]: size for name, size in listed if name in frame_of}
