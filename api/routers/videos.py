"""`/v1/jobs/{id}/videos`: the videos a job can show, and rendering one on request.

A reconstruction renders its input views before it ends, a continuation (predict, what-if,
resimulate) none (`fluidcore.artifacts.eager_videos`); any other video of a job's run (a camera,
the orbit, a what-if's side-by-side) is rendered when a client asks for it: a `render` job (`service.job_types.JobType.RENDER`) on the workers, with
progress per rendered frame, that stores the MP4 under the asking job's keys and lists it with
its artifacts. A video already stored is answered from storage (200) and nothing renders; one
being rendered is answered with the render job already on it (202), so asking twice never
renders twice.
"""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Response, status
from pydantic import ValidationError
from sqlalchemy.orm import Session

from api.deps import OwnerDep, QueueDep, SessionDep, SettingsDep, StorageDep
from api.errors import error_responses
from api.schemas import VideoList, VideoOut
from api.views import artifact_out, job_out
from fluidcore.artifacts import video_names
from service import jobs, quotas
from fluidcore.spec.jobs import RenderParams
from service.errors import DuplicateRequest
from service.job_types import JobType
from service.models import Artifact, Job, JobState
from service.runs import stored_run
from service.settings import Settings
from service.storage import Storage
from service.videos import artifact_name, render_jobs, stored_videos, video_kind

router = APIRouter(prefix="/v1/jobs", tags=["videos"], responses=error_responses(401, 422, 503))


@router.get("/{job_id}/videos", response_model=VideoList, responses=error_responses(404, 409))
def list_videos(job_id: str, owner: OwnerDep, session: SessionDep, storage: StorageDep, settings: SettingsDep) -> VideoList:
    """Every video of the job's run: stored ones with their artifact, the others with the render
    job last asked for (or none); `POST .../videos/{name}` renders a missing one."""
    job = _job_with_videos(session, job_id, owner)
    stored = stored_videos(session, job.id)
    names = video_names(stored_run(storage, job.id)) if job.state == JobState.SUCCEEDED else []
    names += sorted(set(stored) - set(names))  # what a run folder alone shows (a refined prediction's videos)
    renders = render_jobs(session, job.id)
    items = [_video_out(name, stored.get(name), renders.get(name), storage, settings) for name in names]
    return VideoList(job_id=job.id, items=items)


@router.post(
    "/{job_id}/videos/{video}", response_model=VideoOut, status_code=status.HTTP_200_OK,
    responses={202: {"model": VideoOut, "description": "being rendered: poll `render_job`"}, **error_responses(404, 409, 429)},
)
def request_video(
    job_id: str, video: str, owner: OwnerDep, session: SessionDep, storage: StorageDep, settings: SettingsDep,
    queue: QueueDep, response: Response,
) -> VideoOut:
    """The video if it is stored (200; nothing is rendered), else the job rendering it (202):
    the one already queued or running, or a new one. `video` is a camera of the run, `orbit`,
    or a what-if's `side_by_side` (`GET .../videos` lists them); any other name is a 404."""
    try:
        video = RenderParams(video=video).video
    except ValidationError as exc:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, exc.errors()[0]["msg"]) from None
    job = _job_with_videos(session, job_id, owner, for_update=True)  # one render per video, however many ask at once
    if job.state != JobState.SUCCEEDED:
        raise HTTPException(status.HTTP_409_CONFLICT, f"job {job.id} is {job.state}; its videos render once it has succeeded")
    stored = jobs.artifact(session, job.id, artifact_name(video))
    if stored is not None:
        return _video_out(video, stored, None, storage, settings)
    names = video_names(stored_run(storage, job.id))
    if video not in names:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"job {job.id} has no video {video!r}; its videos: {', '.join(names)}")
    render = render_jobs(session, job.id).get(video)
    response.status_code = status.HTTP_202_ACCEPTED
    if render is not None and not JobState(render.state).finished:
        return _video_out(video, None, render, storage, settings)
    quotas.check_new_job(session, owner, settings)
    render = jobs.file_job(owner, JobType.RENDER, job.id, RenderParams(video=video))
    try:
        jobs.create(session, queue, settings, render, waits_for=None)
    except DuplicateRequest:  # an identical request stored its render first: answer with that one
        render = render_jobs(session, job.id)[video]
    return _video_out(video, None, render, storage, settings)


def _job_with_videos(session: Session, job_id: str, owner: str, for_update: bool = False) -> Job:
    """The caller's job, one that writes a run (a render job has no videos of its own: 404)."""
    job = jobs.owned(session, job_id, owner, for_update=for_update)
    if not JobType(job.type).writes_run:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"job {job_id} renders a video of job {job.parent_job_id}; it has none of its own")
    return job


def _video_out(name: str, stored: Artifact | None, render: Job | None, storage: Storage, settings: Settings) -> VideoOut:
    kind, camera = video_kind(name)
    return VideoOut(
        name=name, kind=kind, camera=camera,
        artifact=None if stored is None else artifact_out(stored, storage, settings),
        render_job=None if render is None else job_out(render),
    )
