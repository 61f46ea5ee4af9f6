"""The parameters of each job type, composed from the spec's types: what a request's `params`
holds (`service.job_types.JobType` names the model of each type; `api.schemas.JobRequest`
derives the request bodies, and so the OpenAPI schema, from them; `fluidcore.spec.limits` the
bounds the browser reads at GET /v1/limits; the CLI's flags their help and bounds).

Strict (an unknown field is a 422 naming it) and torch-free, so the API validates a request
before anything is queued.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from fluidcore.errors import InputError, describe_validation
from fluidcore.names import check_name
from fluidcore.spec.source_hint import SourceHint
from fluidcore.spec.controls import FromFrame, Intervention
from fluidcore.spec.reconstruct import DEFAULT_QUALITY, PRESETS
from fluidcore.spec.scene import UpAxis
from fluidcore.spec.simulation import DEFAULT_PHYSICS, PHYSICS_MODES, SimulationConfig
from fluidcore.spec.solids import Solids

_STRICT = ConfigDict(extra="forbid")
Params = TypeVar("Params", bound=BaseModel)

QualityName = Literal[tuple(PRESETS)]  # type: ignore[valid-type]  # the preset names, for the schema
PhysicsName = Literal[tuple(PHYSICS_MODES)]  # type: ignore[valid-type]  # fluidcore.reconstruct.identify


# Frames a background plate may span: a plate is a still scene, a few seconds say all it can
# (its per-pixel median), and each of its frames is decoded beside the clip's.
MAX_PLATE_FRAMES = 300


class ReconstructParams(SimulationConfig):
    """`frames` = [start, end): video frame indices (end exclusive); all frames when omitted.
    `background_frames` = [start, end): frames of the same videos that show no smoke (before the
    source starts, say), the background plate; estimated from the smoke's frames when omitted.
    `source`: where the smoke comes from, when known (world units; checked against the scene
    box): one view cannot tell the source's depth, and the whole plume inherits the guess.
    `air_cells`, `air_vorticity`, `entrainment`: the simulated air and the plume's spreading, off
    by default (`SimulationConfig`, whose docstring gives the measurements). `world_up`: the axis
    the world's up points along ("+z" for Blender's files); read from the camera file's `up` or the
    cameras' mean image up when omitted (`fluidcore.cameras.world_up`). `solids`: static balls in
    the scene the smoke flows around (`fluidcore.spec.solids`; checked against the scene box),
    simulated by the reconstruction and every prediction and what-if from it."""

    model_config = _STRICT
    quality: QualityName = DEFAULT_QUALITY
    physics: PhysicsName = DEFAULT_PHYSICS
    frames: tuple[Annotated[int, Field(ge=0)], Annotated[int, Field(ge=1)]] | None = None
    source: SourceHint | None = None
    background_frames: tuple[Annotated[int, Field(ge=0)], Annotated[int, Field(ge=1)]] | None = None
    world_up: UpAxis | None = None
    solids: Solids

    @model_validator(mode="after")
    def _ordered(self) -> ReconstructParams:
        for name, span in (("frames", self.frames), ("background_frames", self.background_frames)):
            if span is not None and span[1] <= span[0]:
                raise ValueError(f"{name}: end ({span[1]}) must be greater than start ({span[0]})")
        plate = self.background_frames
        if plate is not None and plate[1] - plate[0] > MAX_PLATE_FRAMES:
            raise ValueError(f"background_frames: {plate[1] - plate[0]} frames, at most {MAX_PLATE_FRAMES}: a plate "
                             "is a still background, a few seconds of it are enough")
        return self


NewFrames = Annotated[int, Field(default=30, ge=1, description="how many new frames to simulate after the branch frame")]


class PredictParams(BaseModel):
    """`frames`: how many new frames to predict after the parent run's last frame."""

    model_config = _STRICT
    frames: NewFrames


class InteractParams(Intervention):
    """A counterfactual continuation of the parent run: wind, a ball, or both (`Intervention`, whose
    rule the request schema states), for `frames` new frames after the parent's frame `from_frame`
    (default: its last; 0 re-simulates the whole clip with the intervention; docs/whatif.md)."""

    model_config = _STRICT
    frames: NewFrames
    from_frame: FromFrame


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


BUNDLE_FORMATS = ("vdb", "ply", "density")  # the sequences a job offers as one zip (fluidcore.exports)
BundleFormat = Literal[BUNDLE_FORMATS]  # type: ignore[valid-type]


class BundleParams(BaseModel):
    """A sequence of the parent job's run as one zip (`fluidcore.exports.export_bundle`):
    `format` one of BUNDLE_FORMATS, `frames` = [start, end) (default: every finished frame, the
    last 600 at most), `voxel_size` for the grid formats (world units, at most the kernel radius;
    default a quarter of it). Checked against the run's manifest where it is asked for."""

    model_config = _STRICT
    format: BundleFormat
    # strict: a string "0.01" or a `true` is refused, not coerced (issue 49); a JSON integer is a number
    frames: tuple[Annotated[int, Field(ge=0, strict=True)], Annotated[int, Field(ge=1, strict=True)]] | None = None
    voxel_size: Annotated[float, Field(gt=0, allow_inf_nan=False, strict=True)] | None = None


class JobParamsError(InputError):
    """Job parameters that cannot be used; the message names each field."""


def job_params(model: type[Params], **fields: Any) -> Params:
    """`model` built from a command line's values (the API validates its bodies itself), with
    one line naming each bad field on failure."""
    try:
        return model(**fields)
    except ValidationError as exc:
        raise JobParamsError(describe_validation(exc)) from None
