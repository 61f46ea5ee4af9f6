"""A job's bundles as the service keeps them (`JobType.BUNDLE`: a sequence of its run as one zip,
`fluidcore.exports.export_bundle`): the artifact name of each, the bundle jobs that make them,
and the stored ones. The worker publishes a bundle with the job it bundles, as a render's video
(`service.leases.publish_shown`); the API lists them and asks for new ones (api.routers.bundles).
"""

from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.orm import Session

from fluidcore.exports import BundlePlan
from fluidcore.spec.jobs import BundleParams
from service.job_types import JobType
from service.models import Artifact, Job

BUNDLE_FOLDER = "bundles"
BUNDLE_TYPE = "application/zip"


def artifact_name(plan: BundlePlan) -> str:
    """The artifact name (and the path under the job's prefix) of a bundle: `bundles/NAME.zip`,
    NAME saying what it holds (`BundlePlan.name`), so the same request finds the same file."""
    return f"{BUNDLE_FOLDER}/{plan.name}"


def params_plan(params: BundleParams) -> BundlePlan:
    """The plan a bundle job's stored parameters name: the API stores them resolved (frames and
    voxel size filled in), so this names the file without reading the run."""
    assert params.frames is not None, "a bundle job's frames are stored resolved"
    return BundlePlan(params.format, params.frames, params.voxel_size, None)


def bundle_jobs(session: Session, job_id: str) -> dict[str, Job]:
    """The latest bundle job of each bundle of `job_id` that was asked for, by artifact name."""
    rows = session.scalars(
        select(Job).where(Job.parent_job_id == job_id, Job.type == JobType.BUNDLE).order_by(Job.created_at, Job.id)
    ).all()
    return {artifact_name(params_plan(BundleParams.model_validate(job.params))): job for job in rows}


def stored_bundles(session: Session, job_id: str) -> list[Artifact]:
    """The artifacts of the job's stored bundles, by name."""
    rows = session.scalars(
        select(Artifact).where(Artifact.job_id == job_id, Artifact.kind == "bundle").order_by(Artifact.name)
    )
    return list(rows)
