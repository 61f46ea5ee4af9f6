"""The job types, declared once: each type's name, its parameter model and what it starts from.

The API's request schema (`api.schemas.JobRequest`), the Celery task names (`service.celery_app
.task_name`), the tasks the worker registers (`worker.tasks`) and the runners it checks for
(`worker.runners`) are all derived from `JobType`, so a new job type is one member here plus its
runner in `worker/runners.py`. The parameter models are the spec's (`fluidcore.spec.jobs`: strict,
torch-free, so the API validates a request before anything is queued).

A job that starts from a "run" makes a file of a succeeded job's run on request and publishes it
with that job's artifacts; it writes no run of its own. A `render` renders one video, asked for
at `POST /v1/jobs/{id}/videos/{name}` (api.routers.videos), a `bundle` one zip of a sequence, at
`POST /v1/jobs/{id}/bundles` (api.routers.bundles); each route answers a stored file without one.
"""

from __future__ import annotations

import enum
from typing import Literal

from pydantic import BaseModel, ValidationError

from fluidcore.runs import RunKind
from fluidcore.spec.jobs import (
    BundleParams,
    InteractParams,
    PredictParams,
    ReconstructParams,
    RenderParams,
    ResimulateParams,
)

StartsFrom = Literal["scene", "parent", "run"]  # an upload, a run to continue, a run to make a file of


class JobType(enum.StrEnum):
    """A job type: its name (the value stored in `jobs.type` and sent in requests), its parameter
    model, and whether it starts from an uploaded scene, continues a parent job, or makes a file
    (a video, a bundle) of a succeeded job's run. Each that writes a run is a `fluidcore.runs.RunKind` (same
    value): the kind of run it writes."""

    params: type[BaseModel]
    starts_from: StartsFrom

    def __new__(cls, value: str, params: type[BaseModel], starts_from: StartsFrom) -> JobType:
        member = str.__new__(cls, value)
        member._value_ = str(value)
        member.params = params
        member.starts_from = starts_from
        return member

    RECONSTRUCT = RunKind.RECONSTRUCT, ReconstructParams, "scene"
    PREDICT = RunKind.PREDICT, PredictParams, "parent"
    INTERACT = RunKind.INTERACT, InteractParams, "parent"
    RESIMULATE = RunKind.RESIMULATE, ResimulateParams, "parent"
    RENDER = "render", RenderParams, "run"
    BUNDLE = "bundle", BundleParams, "run"

    @property
    def writes_run(self) -> bool:
        """Whether the job writes a run folder (and is created with `POST /v1/jobs`); a render or
        a bundle publishes a file of its parent's run."""
        return self.starts_from != "run"

    @property
    def run_kind(self) -> RunKind | None:
        """The kind of run this job writes; None for a render or a bundle."""
        return RunKind(self.value) if self.writes_run else None

    @property
    def input_field(self) -> str:
        """The request field naming what the job starts from."""
        return "scene_id" if self.starts_from == "scene" else "parent_job_id"

    def default_params(self) -> BaseModel | None:
        """The parameters a request gets when it sends none, or None when they are required
        (interact: wind or ball must be given)."""
        try:
            return self.params()
        except ValidationError:
            return None
