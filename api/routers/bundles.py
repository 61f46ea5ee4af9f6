"""`/v1/jobs/{id}/bundles`: a sequence of a job's run as one zip (vdb, ply or density frames with
`bundle.json`, `fluidcore.exports.export_bundle`), listed and made on request.

A bundle is made by a `bundle` job on the workers (`service.job_types.JobType.BUNDLE`), with
progress per frame, and stored with the asking job's artifacts under a name that says what it
holds (`service.bundles.artifact_name`). The request is checked against the run's manifest
before anything is queued (frames finished, voxel size, grid and declared size within their caps:
a 422 naming the field; a declared size past what its owner may still store: a 429); a stored
bundle is answered from storage (200, with its size) and one being made with the job making it
(202), so asking twice, even at once, never makes it twice (`service.bundle_requests`). Deleting
the bundle job deletes its bundle. Downloads stream from the artifacts route, Range-aware.
"""

from __future__ import annotations

from fastapi import APIRouter, Response, status

from api.deps import OwnerDep, QueueDep, SessionDep, SettingsDep, StorageDep
from api.errors import StrictJSONRoute, error_responses
from api.schemas import BundleList, BundleOut
from api.views import artifact_out, job_out
from fluidcore.exports import BundlePlan, bundle_voxel_size, default_frames
from fluidcore.spec.jobs import BUNDLE_FORMATS, BundleParams
from service import bundle_requests
from service.bundle_requests import BundleAnswer, bundled_job
from service.bundles import BUNDLE_FOLDER, bundle_jobs, stored_bundles
from service.models import JobState
from service.runs import stored_run
from service.settings import Settings
from service.storage import Storage

router = APIRouter(prefix="/v1/jobs", tags=["bundles"], route_class=StrictJSONRoute, responses=error_responses(401, 422, 503))


@router.get("/{job_id}/bundles", response_model=BundleList, responses=error_responses(404, 409))
def list_bundles(job_id: str, owner: OwnerDep, session: SessionDep, storage: StorageDep, settings: SettingsDep) -> BundleList:
    """The job's bundles, stored or being made, and what a new one may ask for: the formats, the
    frames it holds by default, the kernel radius (a voxel size's bound) and the default voxel size."""
    job = bundled_job(session, job_id, owner)
    frames = h = None
    if job.state == JobState.SUCCEEDED:
        run = stored_run(storage, job.id)
        frames, h = default_frames(run), run.scene.physics.h
    stored = {row.name: row for row in stored_bundles(session, job.id)}
    making = bundle_jobs(session, job.id)
    names = sorted(set(stored) | set(making))
    items = [_bundle_out(BundleAnswer(name, stored.get(name), making.get(name)), storage, settings) for name in names]
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
    why (a frame not finished, a voxel size out of (0, h], a grid over the caps, a declared size
    over a bundle's 20 GiB); one whose declared size does not fit what the owner may still store
    is a 429 (`service.bundle_requests`)."""
    answer = bundle_requests.request_bundle(session, storage, queue, settings, job_id, owner, params)
    if answer.stored is None:
        response.status_code = status.HTTP_202_ACCEPTED
    return _bundle_out(answer, storage, settings)


def _bundle_out(answer: BundleAnswer, storage: Storage, settings: Settings) -> BundleOut:
    plan = BundlePlan.from_name(answer.name.removeprefix(f"{BUNDLE_FOLDER}/"))
    return BundleOut(
        name=answer.name, format=plan.fmt, frames=plan.frames, voxel_size=plan.voxel_size,
        artifact=None if answer.stored is None else artifact_out(answer.stored, storage, settings),
        bundle_job=None if answer.making is None else job_out(answer.making),
    )
