"""The job types, declared once: each type's name, its parameter model and what it starts from.

The API's request schema (`api.schemas.JobRequest`), the Celery task names (`service.celery_app
.task_name`), the tasks the worker registers (`worker.tasks`) and the runners it checks for
(`worker.runners`) are all derived from `JobType`, so a new job type is one member here plus its
runner in `worker/runners.py`. Parameter models are strict (an unknown field is a 422 naming it)
and torch-free, so the API validates a request before anything is queued.

A job that starts from a "run" (`render`) renders one video of a succeeded job's run on request
and publishes it with that job's artifacts; it writes no run of its own, and is asked for at
`POST /v1/jobs/{id}/videos/{name}` (api.routers.videos), which serves a stored video without one.
"""

from __future__ import annotations

import enum
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from fluidcore.interaction import Intervention
from fluidcore.names import check_name
from fluidcore.reconstruct.source_hint import SourceHint
from fluidcore.runs import RunKind
from fluidcore.spec.reconstruct import DEFAULT_QUALITY, PRESETS
from fluidcore.spec.simulation import DEFAULT_PHYSICS, PHYSICS_MODES, SimulationConfig

_STRICT = ConfigDict(extra="forbid")

QualityName = Literal[tuple(PRESETS)]  # type: ignore[valid-type]  # the preset names, for the schema
PhysicsName = Literal[tuple(PHYSICS_MODES)]  # type: ignore[valid-type]  # fluidcore.reconstruct.identify

StartsFrom = Literal["scene", "parent", "run"]  # an upload, a run to continue, a run to render


class ReconstructParams(SimulationConfig):
    """`frames` = [start, end): video frame indices (end exclusive); all frames when omitted.
    `source`: where the smoke comes from, when known (world units; checked against the scene
    box): one view cannot tell the source's depth, and the whole plume inherits the guess.
    `air_cells`, `air_vorticity`, `entrainment`: the simulated air and the plume's spreading, off
    by default (`SimulationConfig`, whose docstring gives the measurements)."""

    model_config = _STRICT
    quality: QualityName = DEFAULT_QUALITY
    physics: PhysicsName = DEFAULT_PHYSICS
    frames: tuple[Annotated[int, Field(ge=0)], Annotated[int, Field(ge=1)]] | None = None
    source: SourceHint | None = None

    @model_validator(mode="after")
    def _ordered(self) -> ReconstructParams:
        if self.frames is not None and self.frames[1] <= self.frames[0]:
            raise ValueError(f"frames: end ({self.frames[1]}) must be greater than start ({self.frames[0]})")
        return self


class PredictParams(BaseModel):
    """`frames`: how many new frames to predict after the parent run's last frame."""

    model_config = _STRICT
    frames: int = Field(default=30, ge=1)


class InteractParams(Intervention):
    """A counterfactual continuation of the parent run: wind, a ball, or both (`Intervention`, whose
    rule the request schema states), for `frames` new frames after the parent's frame `from_frame`
    (default: its last; 0 re-simulates the whole clip with the intervention; docs/whatif.md)."""

    model_config = _STRICT
    frames: int = Field(default=30, ge=1)
    from_frame: int | None = Field(default=None, ge=0)


class ResimulateParams(BaseModel):
    """Re-simulate the parent run's frames with physics alone; it takes no parameters."""

    model_config = _STRICT


class RenderParams(BaseModel):
    """`video`: the name of one video of the parent job's run (`fluidcore.artifacts.video_names`:
    a camera of the run, `orbit`, a what-if's `side_by_side`); a safe name here
    (`fluidcore.names`), checked against the run's manifest where it is asked for."""

    model_config = _STRICT
    video: str

    @field_validator("video")
    @classmethod
    def _safe(cls, value: str) -> str:
        return check_name(value, "video")


class JobType(enum.StrEnum):
    """A job type: its name (the value stored in `jobs.type` and sent in requests), its parameter
    model, and whether it starts from an uploaded scene, continues a parent job, or renders a
    video of a succeeded job's run. Each that writes a run is a `fluidcore.runs.RunKind` (same
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

    @property
    def writes_run(self) -> bool:
        """Whether the job writes a run folder (and is created with `POST /v1/jobs`); a render
        publishes a video of its parent's run."""
        return self.starts_from != "run"

    @property
    def run_kind(self) -> RunKind | None:
        """The kind of run this job writes; None for a render."""
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
