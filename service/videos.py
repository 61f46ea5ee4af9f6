"""A job's videos as the service keeps them: the artifact name, kind and storage key of each (the
worker publishes them, the API lists them and asks for the missing ones), and the render jobs
that make one on request (`JobType.RENDER`). The names themselves, and which a finished job
renders before it ends, are `fluidcore.artifacts`' (`video_names`, `eager_videos`).
"""

from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.orm import Session

from fluidcore.artifacts import SCENE_VIDEOS
from service.job_types import JobType
from service.models import Artifact, Job
from service.storage import job_prefix

VIDEO_FOLDER = "videos"
VIDEO_TYPE = "video/mp4"


def artifact_name(video: str) -> str:
    """The artifact name (and the path under the job's prefix) of a video: `videos/NAME.mp4`."""
    return f"{VIDEO_FOLDER}/{video}.mp4"


def video_key(job_id: str, video: str) -> str:
    """Where the video is stored: under the job's own prefix, whoever rendered it."""
    return f"{job_prefix(job_id)}/{artifact_name(video)}"


def video_kind(video: str) -> tuple[str, str | None]:
    """(artifact kind, camera): `orbit` and `side_by_side` are their own kinds, any other video
    is a camera's (a refined prediction's `refined_CAMERA` too)."""
    return (video, None) if video in SCENE_VIDEOS else ("video", video)


def render_jobs(session: Session, job_id: str) -> dict[str, Job]:
    """The latest render job of each video of `job_id` that was asked for, by video name."""
    rows = session.scalars(
        select(Job).where(Job.parent_job_id == job_id, Job.type == JobType.RENDER).order_by(Job.created_at, Job.id)
    ).all()
    return {job.params["video"]: job for job in rows}


def stored_videos(session: Session, job_id: str) -> dict[str, Artifact]:
    """The artifacts of the job's stored videos, by video name."""
    rows = session.scalars(select(Artifact).where(Artifact.job_id == job_id, Artifact.name.like(f"{VIDEO_FOLDER}/%.mp4")))
    return {row.name.removeprefix(f"{VIDEO_FOLDER}/").removesuffix(".mp4"): row for row in rows}
