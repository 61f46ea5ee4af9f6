"""`/v1/jobs/{id}/bundles`: a sequence of a job's run as one zip (vdb, ply or density frames with
`bundle.json`, `fluidcore.exports.export_bundle`), listed and made on request.

A bundle is made by a `bundle` job on the workers (`service.job_types.JobType.BUNDLE`), with
progress per frame, and stored with the asking job's artifacts under a name that says what it
holds (`service.bundles.artifact_name`). The request is checked against the run's manifest
before anything is queued (frames finished, voxel size and grid within their caps: a 422 naming
the field); a stored bundle is answered from storage (200, with its size) and one being made with
the job making it (202), so asking twice never makes it twice. Downloads stream from the
artifacts route, Range-aware.
"""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Response, status
from sqlalchemy.orm import Session

from api.deps import OwnerDep, QueueDep, SessionDep, SettingsDep, StorageDep
from api.errors import StrictJSONRoute, error_responses
from api.schemas import BundleList, BundleOut
from api.views import artifact_out, job_out
from fluidcore.exports import BundlePlan, bundle_voxel_size, default_frames, plan_bundle
from fluidcore.spec.jobs import BUNDLE_FORMATS, BundleParams
from service import jobs, quotas
from service.bundles import BUNDLE_FOLDER, artifact_name, bundle_jobs, stored_bundles
from service.job_types import JobType
from service.models import Artifact, Job, JobState
from service.runs import stored_run
from service.settings import Settings
from service.storage import Storage

router = APIRouter(prefix="/v1/jobs", tags=["bundles"], route_class=StrictJSONRoute, responses=error_responses(401, 422, 503))


@router.get("/{job_id}/bundles", response_model=BundleList, responses=error_responses(404, 409))
def list_bundles(job_id: str, owner: OwnerDep, session: SessionDep, storage: StorageDep, settings: SettingsDep) -> BundleList:
    """The job's bundles, stored or being made, and what a new one may ask for: the formats, the
    frames it holds by default, the kernel radius (a voxel size's bound) and the default voxel size."""
    job = _job_with_run(session, job_id, owner)
    frames = h = None
    if job.state == JobState.SUCCEEDED:
        run = stored_run(storage, job.id)
        frames, h = default_frames(run), run.scene.physics.h
    stored = {row.name: row for row in stored_bundles(session, job.id)}
    making = bundle_jobs(session, job.id)
    names = sorted(set(stored) | set(making))
    items = [_bundle_out(name, stored.get(name), making.get(name), storage, settings) for name in names]
    return BundleList(job_id=job.id, formats=list(BUNDLE_FORMATS), frames=frames, kernel_radius=h,
                      default_voxel_size=None if h is None else bundle_voxel_size(h), items=items)


@router.post(
    "/{job_id}/bundles", response_model=BundleOut, status_code=status.HTTP_200_OK,
    responses={202: {"model": BundleOut, "description": "being made: poll `bundle_job`"}, **error_responses(404, 409, 429)},
)
def request_bundle(
    job_id: str, params: BundleParams, owner: OwnerDep, session: SessionDep, storage: StorageDep,
    settings: SettingsDep, queue: QueueDep, response: Response,
) -> BundleOut:
    """The bundle if it is stored (200; nothing is made), else the job making it (202): the one
    already queued or running, or a new one. A request the run cannot satisfy is a 422 that says
    why (a frame not finished, a voxel size out of (0, h], a grid over the caps)."""
    job = _job_with_run(session, job_id, owner, for_update=True)  # one job per bundle, however many ask at once
    if job.state != JobState.SUCCEEDED:
        raise HTTPException(status.HTTP_409_CONFLICT, f"job {job.id} is {job.state}; its bundles are made once it has succeeded")
    plan = plan_bundle(stored_run(storage, job.id), params.format, params.frames, params.voxel_size, f"job {job.id}'s run")
    name = artifact_name(plan)
    stored = jobs.artifact(session, job.id, name)
    if stored is not None:
        return _bundle_out(name, stored, None, storage, settings)
    making = bundle_jobs(session, job.id).get(name)
    response.status_code = status.HTTP_202_ACCEPTED
    if making is not None and not JobState(making.state).finished:
        return _bundle_out(name, None, making, storage, settings)
    quotas.check_new_job(session, owner, settings)
    resolved = BundleParams(format=plan.fmt, frames=plan.frames, voxel_size=plan.voxel_size)
    making = Job(owner=owner, type=JobType.BUNDLE, parent_job_id=job.id, params=resolved.model_dump(mode="json"))
    jobs.create(session, queue, settings, making, waits_for=None)
    return _bundle_out(name, None, making, storage, settings)


def _job_with_run(session: Session, job_id: str, owner: str, for_update: bool = False) -> Job:
    """The caller's job, one that writes a run (a render or bundle job has none to bundle: 404)."""
    job = jobs.owned(session, job_id, owner, for_update=for_update)
    if not JobType(job.type).writes_run:
        raise HTTPException(status.HTTP_404_NOT_FOUND,
                            f"job {job_id} makes a {job.type} of job {job.parent_job_id}; it has no run of its own to bundle")
    return job


def _bundle_out(name: str, stored: Artifact | None, making: Job | None, storage: Storage, settings: Settings) -> BundleOut:
    plan = BundlePlan.from_name(name.removeprefix(f"{BUNDLE_FOLDER}/"))
    return BundleOut(
        name=name, format=plan.fmt, frames=plan.frames, voxel_size=plan.voxel_size,
        artifact=None if stored is None else artifact_out(stored, storage, settings),
        bundle_job=None if making is None else job_out(making),
    )
