"""`GET /v1/limits`: the bounds of every job parameter, derived from the parameter models
(`fluidcore.spec.limits.field_limits` of each `JobType`'s model), with the server's own cap on new
frames (`Settings.max_predict_frames`). The browser's forms check their values against it before
sending, so they hold no bounds of their own. Public like /openapi.json: the page reads it before
anyone signs in, and it says nothing the schema does not.
"""

from __future__ import annotations

from fastapi import APIRouter

from api.deps import SettingsDep
from api.errors import error_responses
from api.schemas import Limits
from fluidcore.spec.limits import field_limits
from service.job_types import JobType
from service.settings import Settings

router = APIRouter(prefix="/v1", tags=["limits"], responses=error_responses(503))


@router.get("/limits", response_model=Limits)
def get_limits(settings: SettingsDep) -> Limits:
    """For each job type that writes a run, each parameter's bounds by field path (`air_cells`,
    `frames[1]`, `wind.strength`): JSON Schema keywords (`minimum`, `maximum`,
    `exclusiveMinimum`, `enum`, `anyOf`, ...) with the field's `type`, `default` and `description`."""
    return limits(settings)


def limits(settings: Settings) -> Limits:
    found = {job_type.value: field_limits(job_type.params) for job_type in JobType if job_type.writes_run}
    for job_type in (JobType.PREDICT, JobType.INTERACT):  # api.routers.jobs refuses more new frames per job
        found[job_type.value]["frames"]["maximum"] = settings.max_predict_frames
    return found
