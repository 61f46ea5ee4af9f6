"""Each owner's limits on what they keep (issue 36): unfinished jobs, stored scenes and stored
bytes, from `Settings` (`max_unfinished_jobs_per_owner`, `max_scenes_per_owner`,
`max_stored_bytes_per_owner`). The API checks them before it stores a job or spools nothing more
of an upload; over one it answers 429 (`OverLimit`) naming the limit and how to free room.

The limits are far above one person's normal use: they stop one key from filling the queue,
the database or the disk for everyone. They are counted, not reserved, so requests of one
owner racing each other may pass a limit by the few that run at once. How the workers share
their time among owners is `service.queue`'s (the owner's turn), not a limit here.
"""

from __future__ import annotations

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from service.errors import OverLimit
from service.models import Artifact, Job, JobState, Scene
from service.settings import Settings

JOBS_RETRY_AFTER_S = 60  # jobs finish: worth asking again in a minute


def check_new_job(session: Session, owner: str, settings: Settings, incoming: int = 0) -> None:
    """OverLimit unless `owner` may queue one more job: fewer unfinished jobs than allowed, and
    stored bytes under the limit with the `incoming` bytes the job declares (a bundle's; what any
    other job writes is not known before it runs, 0)."""
    unfinished = session.scalar(
        select(func.count()).select_from(Job).where(Job.owner == owner, Job.state.in_([JobState.QUEUED, JobState.RUNNING]))
    ) or 0
    limit = settings.max_unfinished_jobs_per_owner
    if unfinished >= limit:
        raise OverLimit(
            f"you have {unfinished} unfinished jobs, the most allowed ({limit}): wait for some to finish, or cancel "
            "queued ones (POST /v1/jobs/ID/cancel), then ask again",
            retry_after=JOBS_RETRY_AFTER_S,
        )
    _check_bytes(session, owner, settings, incoming, "this job may write")


def check_new_scene(session: Session, owner: str, settings: Settings, incoming: int) -> None:
    """OverLimit unless `owner` may store one more scene of `incoming` bytes."""
    scenes = session.scalar(select(func.count()).select_from(Scene).where(Scene.owner == owner)) or 0
    limit = settings.max_scenes_per_owner
    if scenes >= limit:
        raise OverLimit(
            f"you have {scenes} scenes, the most allowed ({limit}): delete scenes you no longer need "
            "(DELETE /v1/scenes/ID, once their jobs are deleted), then upload again"
        )
    _check_bytes(session, owner, settings, incoming, "this upload adds")


def stored_bytes(session: Session, owner: str) -> int:
    """What `owner` stores: their scenes' videos and every file their jobs published (run
    folders, videos, exports), as recorded in the database, and what their unfinished jobs
    reserved (`Job.reserved_bytes`: a bundle's declared size, issue 49). Cameras files (at most
    `max_cameras_bytes` each) and job logs are not counted."""
    artifacts = session.scalar(
        select(func.coalesce(func.sum(Artifact.size), 0)).join(Job, Artifact.job_id == Job.id).where(Job.owner == owner)
    ) or 0
    reserved = session.scalar(
        select(func.coalesce(func.sum(Job.reserved_bytes), 0))
        .where(Job.owner == owner, Job.state.in_([JobState.QUEUED, JobState.RUNNING]))
    ) or 0
    videos = session.scalars(select(Scene.videos).where(Scene.owner == owner)).all()
    return int(artifacts) + int(reserved) + sum(int(video.get("size", 0)) for scene in videos for video in scene.values())


def _check_bytes(session: Session, owner: str, settings: Settings, incoming: int, adds: str) -> None:
    used, limit = stored_bytes(session, owner), settings.max_stored_bytes_per_owner
    if used + incoming > limit or used >= limit:
        asked = f"; {adds} {_size(incoming)}" if incoming else ""
        raise OverLimit(
            f"you store {_size(used)}{asked}, and the most allowed is {_size(limit)}: delete jobs or scenes you no "
            "longer need (DELETE /v1/jobs/ID, DELETE /v1/scenes/ID), then ask again"
        )


def _size(n: int) -> str:
    for unit, scale in (("GiB", 1024**3), ("MiB", 1024**2), ("KiB", 1024)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{n} bytes"
