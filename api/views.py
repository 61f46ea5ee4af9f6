"""How the API shows the service's rows: a job and an artifact as its responses carry them, shared
by the routers that answer with them (jobs, videos, artifacts), so no router imports another."""

from __future__ import annotations

from datetime import UTC, datetime
from urllib.parse import quote

from api.schemas import ArtifactOut, JobLinks, JobOut, JobTimings
from api.downloads import download_links
from service.models import Artifact, Job
from service.settings import Settings
from service.storage import Storage


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


def artifact_path(job_id: str, name: str) -> str:
    return f"/v1/jobs/{job_id}/artifacts/{quote(name)}"


def artifact_out(row: Artifact, storage: Storage, settings: Settings) -> ArtifactOut:
    """An artifact as the API lists it, with its download URL and a time-limited one for <video>."""
    path, presigned = download_links(storage, settings, row.key, artifact_path(row.job_id, row.name))
    return ArtifactOut(
        name=row.name, kind=row.kind, camera=row.camera, size=row.size, content_type=row.content_type,
        url=path, presigned_url=presigned,
    )
