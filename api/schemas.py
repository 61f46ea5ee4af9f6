"""Request and response bodies. Job parameters are typed per job type, so a bad request is a 422
naming the field before anything is queued."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Generic, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field, model_validator

from fluidcore.interaction import BallParams, WindParams

T = TypeVar("T")
Quality = Literal["preview", "standard", "paper"]
JobTypeName = Literal["reconstruct", "predict", "interact", "resimulate"]
JobStateName = Literal["queued", "running", "succeeded", "failed", "cancelled"]

_STRICT = ConfigDict(extra="forbid")


class ReconstructParams(BaseModel):
    """`frames` = [start, end): video frame indices (end exclusive); all frames when omitted."""

    model_config = _STRICT
    quality: Quality = "preview"
    frames: tuple[Annotated[int, Field(ge=0)], Annotated[int, Field(ge=1)]] | None = None

    @model_validator(mode="after")
    def _ordered(self) -> ReconstructParams:
        if self.frames is not None and self.frames[1] <= self.frames[0]:
            raise ValueError(f"frames: end ({self.frames[1]}) must be greater than start ({self.frames[0]})")
        return self


class PredictParams(BaseModel):
    """`frames`: how many new frames to predict after the parent run's last frame."""

    model_config = _STRICT
    frames: int = Field(default=30, ge=1)


class InteractParams(BaseModel):
    """A counterfactual continuation of the parent run: wind, a ball, or both, for `frames` new frames."""

    model_config = _STRICT
    frames: int = Field(default=30, ge=1)
    wind: WindParams | None = None
    ball: BallParams | None = None

    @model_validator(mode="after")
    def _something(self) -> InteractParams:
        if self.wind is None and self.ball is None:
            raise ValueError("interact needs wind, ball or both")
        return self


class ResimulateParams(BaseModel):
    """`fluidcore.predict.job.run_resimulate` on the parent run; it takes no parameters."""

    model_config = _STRICT


class ReconstructRequest(BaseModel):
    model_config = _STRICT
    type: Literal["reconstruct"]
    scene_id: str
    params: ReconstructParams = ReconstructParams()


class PredictRequest(BaseModel):
    model_config = _STRICT
    type: Literal["predict"]
    parent_job_id: str
    params: PredictParams = PredictParams()


class InteractRequest(BaseModel):
    model_config = _STRICT
    type: Literal["interact"]
    parent_job_id: str
    params: InteractParams


class ResimulateRequest(BaseModel):
    model_config = _STRICT
    type: Literal["resimulate"]
    parent_job_id: str
    params: ResimulateParams = ResimulateParams()


JobRequest = Annotated[
    ReconstructRequest | PredictRequest | InteractRequest | ResimulateRequest, Field(discriminator="type")
]


class Page(BaseModel, Generic[T]):
    items: list[T]
    total: int
    limit: int
    offset: int
    next_offset: int | None


class SceneVideo(BaseModel):
    filename: str
    width: int
    height: int
    fps: float
    n_frames: int
    codec: str
    size: int


class SceneOut(BaseModel):
    id: str
    name: str
    created_at: datetime
    cameras: list[str]
    videos: dict[str, SceneVideo]
    n_frames: int
    fps: float


class JobTimings(BaseModel):
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    queued_seconds: float | None = Field(description="created -> started (or now, while queued)")
    run_seconds: float | None = Field(description="started -> finished (or now, while running)")
    stages: dict[str, float] = Field(description="seconds per stage, in the order the stages ran")


class JobLinks(BaseModel):
    self: str
    artifacts: str
    cancel: str


class JobOut(BaseModel):
    id: str
    type: JobTypeName
    state: JobStateName
    stage: str
    progress: float = Field(ge=0.0, le=1.0)
    scene_id: str | None
    parent_job_id: str | None
    params: dict[str, Any]
    error: str | None
    cancel_requested: bool
    attempts: int
    timings: JobTimings
    links: JobLinks


class ArtifactOut(BaseModel):
    name: str = Field(description="path inside the job's results, e.g. 'videos/cam02.mp4'")
    kind: Literal["video", "orbit", "state", "manifest", "file"]
    camera: str | None
    size: int
    content_type: str
    url: str = Field(description="API download URL (Bearer auth; honours HTTP Range)")
    presigned_url: str = Field(
        description="time-limited URL that needs no API key (for <video src>): object storage's own, "
        "or signed by the API for local storage"
    )


class ArtifactList(BaseModel):
    job_id: str
    items: list[ArtifactOut]


class Health(BaseModel):
    status: Literal["ok", "unavailable"]
    checks: dict[str, str] = {}
