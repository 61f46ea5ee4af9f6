"""Request and response bodies. Job requests are derived from `service.job_types.JobType`: one
model per type that writes a run, `{"type", "scene_id" | "parent_job_id", "params"}`, with the
type's own parameter model, so a bad request is a 422 naming the field before anything is queued
(a `render` job is asked for at `POST /v1/jobs/{id}/videos/{name}`, api.routers.videos, a
`bundle` job at `POST /v1/jobs/{id}/bundles`, api.routers.bundles)."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Generic, Literal, TypeVar, Union

from pydantic import BaseModel, ConfigDict, Field, HttpUrl, UrlConstraints, create_model

from fluidcore.health import Level as HealthLevel
from fluidcore.health import Remedy as HealthRemedy
from fluidcore.spec.controls import WindParams
from service.job_types import JobType
from service.models import ARTIFACT_KINDS, JobState

T = TypeVar("T")


def job_request_model(job_type: JobType) -> type[BaseModel]:
    """`ReconstructRequest`, `PredictRequest`, ...: the body that creates a job of this type.
    `params` may be left out when the type's parameters all have defaults."""
    default = job_type.default_params()
    return create_model(
        f"{job_type.value.capitalize()}Request",
        __config__=ConfigDict(extra="forbid"),
        type=(Literal[job_type.value], ...),
        **{job_type.input_field: (str, ...)},
        params=(job_type.params, ... if default is None else default),
        webhook=(
            Annotated[HttpUrl, UrlConstraints(max_length=2048)] | None,
            Field(default=None, description="POSTed, signed, when the job ends (service.webhooks)"),
        ),
    )


JOB_REQUESTS: dict[JobType, type[BaseModel]] = {
    job_type: job_request_model(job_type) for job_type in JobType if job_type.writes_run
}
JobRequest = Annotated[Union[tuple(JOB_REQUESTS.values())], Field(discriminator="type")]  # noqa: UP007


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
    url: str = Field(description="the uploaded video as sent: GET it with the API key (honours HTTP Range)")


class SceneVideoLink(BaseModel):
    """Where to play one camera's uploaded video (GET /v1/scenes/{id}/videos)."""

    camera: str
    url: str = Field(description="GET it with the API key (honours HTTP Range)")
    presigned_url: str = Field(description="time-limited URL that needs no API key (for <video src>)")


class SceneVideoLinks(BaseModel):
    scene_id: str
    items: list[SceneVideoLink]


Vec3 = tuple[float, float, float]


class SceneBox(BaseModel):
    min: Vec3
    max: Vec3


class SingleCameraView(BaseModel):
    """The scene box of one video's camera made from a field of view (`GET /v1/cameras/single`)."""

    box: SceneBox
    edges: list[list[list[float]]] = Field(description="the box's edges as [[u, v], [u, v]] in the video's pixels "
                                                       "(continuous: pixel (i, j) covers [i, i+1) x [j, j+1))")


class SourceDepth(BaseModel):
    """How a reconstruction placed its source along the input ray (`fluidcore.scene_info`, from
    the run manifest's `settings.source_estimate`)."""

    cue: str = Field(description="triangulated, generated views, floor, box axis or given (docs/cameras.md)")
    range: tuple[Vec3, Vec3] | None = Field(
        description="one input view: the nearest and farthest centres on its ray inside the box, all of which "
        "the view accepts (a source hint may pin any); null when two or more views triangulate it"
    )


class SceneSource(BaseModel):
    center: Vec3
    radius: float
    depth: SourceDepth | None = Field(default=None, description="null when the user gave the whole source")
    job_id: str | None = Field(default=None, description="the reconstruction job whose run this source is from")


class SceneSolid(BaseModel):
    """A static ball of the reconstruction's scene (`fluidcore.spec.solids.SolidBall`), world units."""

    center: Vec3
    radius: float


class CameraPlace(BaseModel):
    center: Vec3
    forward: Vec3


class HealthCheck(BaseModel):
    name: str
    level: HealthLevel
    message: str = Field(description="the finding and what to do, in the API's words")
    finding: str = Field(description="what was found, without what to do")
    advice: list[HealthRemedy] = Field(description="what to give next (the browser words these as its form's fields)")
    value: float | None = None


class HealthReport(BaseModel):
    """How far to trust the reconstruction (`fluidcore.health`): a warning says the result is
    likely poor and what to give next, a note what one view or the identification could not tell."""

    warnings: list[str]
    notes: list[str]
    checks: list[HealthCheck]


class SceneGeometry(BaseModel):
    """World units (fluidcore.scene_info): a ball must lie inside `box` (null when the camera file
    declares none and the cameras share no bounded view); `source` is the smoke source the
    scene's latest finished reconstruction estimated (null before there is one)."""

    box: SceneBox | None
    up: Vec3
    source: SceneSource | None
    solids: list[SceneSolid] = Field(default_factory=list, description="the static balls the scene's latest finished "
                                     "reconstruction simulated (its params.solids); empty before one")
    cameras: dict[str, CameraPlace]
    health: HealthReport | None = Field(default=None, description="the latest finished reconstruction's; null before one")


class SceneOut(BaseModel):
    id: str
    name: str
    created_at: datetime
    cameras: list[str]
    videos: dict[str, SceneVideo]
    n_frames: int
    fps: float
    geometry: SceneGeometry | None = Field(default=None, description="GET /v1/scenes/{id} only (not in listings)")
    reconstruct_job_id: str | None = Field(default=None, description="POST with `reconstruct` only: the queued reconstruction")


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


class JobLogs(BaseModel):
    job_id: str
    lines: list[str] = Field(description="log lines from the requested offset on, oldest first")
    next_offset: int = Field(description="the offset to ask for next time (lines seen so far)")


class JobOut(BaseModel):
    id: str
    type: JobType
    state: JobState
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


ArtifactKind = Literal[ARTIFACT_KINDS]  # type: ignore[valid-type]  # the order a job lists them in


class ArtifactOut(BaseModel):
    name: str = Field(description="path inside the job's results, e.g. 'videos/cam02.mp4'")
    kind: ArtifactKind
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


class VideoOut(BaseModel):
    """One video a job can show: stored (`artifact`), or rendered when asked for (`render_job`)."""

    name: str = Field(description="a camera of the run, 'orbit', a what-if's 'side_by_side'")
    kind: Literal["video", "orbit", "side_by_side"]
    camera: str | None
    artifact: ArtifactOut | None = Field(description="the stored MP4; null until it is rendered")
    render_job: JobOut | None = Field(
        description="the latest job that renders it on request (poll it for progress); null when none was asked for"
    )


class VideoList(BaseModel):
    job_id: str
    items: list[VideoOut]


class BundleOut(BaseModel):
    """One bundle of a job's run: stored (`artifact`, with its size), or being made (`bundle_job`)."""

    name: str = Field(description="the artifact's name, which says what it holds, e.g. 'bundles/vdb_f000000-000030_v0.01.zip'")
    format: str
    frames: tuple[int, int] = Field(description="[start, end) of the run's frames")
    voxel_size: float | None = Field(description="world units; null for ply")
    artifact: ArtifactOut | None = Field(description="the stored zip; null until it is made")
    bundle_job: JobOut | None = Field(description="the latest job that makes it (poll it for progress); null when none")


class BundleList(BaseModel):
    """A job's bundles, and what a new one may ask for (`POST .../bundles` with BundleParams)."""

    job_id: str
    formats: list[str]
    frames: tuple[int, int] | None = Field(description="the frames a bundle holds when it names none; null before success")
    kernel_radius: float | None = Field(description="h, world units: a voxel size is at most this")
    default_voxel_size: float | None = Field(description="the grid formats' voxel size when none is asked for")
    items: list[BundleOut]


class Health(BaseModel):
    status: Literal["ok", "unavailable"]
    checks: dict[str, str] = {}


class RunScene(BaseModel):
    box_lo: list[float] = Field(description="scene box, lowest corner (world units)")
    box_hi: list[float] = Field(description="scene box, highest corner (world units)")
    up: list[float]
    source: dict[str, Any] = Field(description="the smoke source as the run recorded it (fluidcore.physics.Source)")
    dt: float | None = Field(default=None, description="the simulation's time step, seconds (one video frame)")
    solids: list[SceneSolid] = Field(default_factory=list, description="the scene's static balls (world units)")


class AirSample(BaseModel):
    points: list[float] = Field(description="x0, y0, z0, x1, ...: a lattice of points over the scene box (world units)")
    velocities: list[float] = Field(description="vx0, vy0, vz0, vx1, ...: the air's velocity at each point (world units/s)")


class ParticlesOut(BaseModel):
    job_id: str
    frame: int
    frames: list[int] = Field(description="frames the run has written so far")
    total: int = Field(description="live particles in the frame, before subsampling")
    positions: list[float] = Field(description="x0, y0, z0, x1, ...: world units, evenly subsampled")
    scene: RunScene
    air: AirSample | None = Field(default=None, description="the air saved with the frame, sampled on a coarse lattice "
                                  "(a run whose scene simulates the air, air.cells > 0); null: the run's air is still")


FieldLimits = dict[str, Any]  # fluidcore.spec.limits: the JSON Schema keywords that bound one field
Limits = dict[str, dict[str, FieldLimits]]  # by job type, then by field path ("air_cells", "wind.strength")

MAX_WIND_HEIGHTS = 64  # the what-if view asks for a handful (an arrow each)


class WindHeights(BaseModel):
    """A wind and the heights (world units along the scene's up) to evaluate it at."""

    model_config = ConfigDict(extra="forbid")
    wind: WindParams
    source_height: float = Field(description="the run's source centre along up: the base height of a wind that names none")
    heights: list[float] = Field(min_length=1, max_length=MAX_WIND_HEIGHTS)


class WindAccelerations(BaseModel):
    accelerations: list[float] = Field(description="the wind's acceleration (units/s^2) at each height, in order")
