"""The controls of a what-if: the wind, the ball and the frame it branches from, validated once
and shared by the CLI, the API (and through it the browser) and the jobs.

Plain pydantic models with no torch import, so the API process can validate a job's
parameters before anything is queued. World units and seconds throughout; frames are
counted from the first new (predicted) frame, except `from_frame`, a frame of the parent run.

Validation happens in two stages because the scene is not known when a request arrives:
the models themselves reject what is wrong in any scene (NaN, a zero direction, a negative
radius, a strength no smoke survives), and `InteractionParams.check_scene`, the one scene
check, rejects what is wrong in the run's scene (a ball outside the scene box, a wind too
strong for the simulator to resolve, an intervention that starts after the last predicted
frame). The validated models are what the physics receives (`fluidcore.predict.interventions`).
Two rules live here and nowhere else: the wind's gain with height (`WindParams.gain`, which the
physics evaluates per particle and the API per height for the browser's arrows) and the frame a
continuation branches from (`branch_frame`, which the API checks before queueing and the job
before it writes).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from typing import Annotated, Any, Literal, Protocol, TypeVar

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from fluidcore.errors import InputError, describe_validation
from fluidcore.spec.solids import ball_box_problem

Vec3 = tuple[float, float, float]
Height = TypeVar("Height")  # a float, or a torch tensor of heights

MAX_WIND_STRENGTH = 1.0e3  # world units / s^2 at the source height; beyond this nothing is smoke any more
MAX_WIND_GROWTH = 50.0  # per world unit of height; exp(50 * 1) is already far past physical
MAX_GAIN_EXPONENT = 60.0  # exp(60) ~ 1e26: far past physical, still finite in float32 after scaling
# A wind's terminal speed when none is given: the speed its strength gives still air in this many
# seconds (it then reaches 76% of it, tanh(1), in as many seconds). Longer than the dev scenes'
# what-ifs blow (3.3-3.5 s), so there the air reaches 88% of the unbounded a t at their end.
WIND_TERMINAL_SECONDS = 5.0
MAX_WIND_SPEED = 1.0e3  # world units / s: a terminal speed beyond this is no longer a wind around smoke

_STRICT = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class InteractionError(InputError):
    """Counterfactual parameters that cannot be applied; the message names the field."""


WindProfile = Literal["exponential", "linear", "uniform"]  # fluidcore.physics.WIND_PROFILES


class WindParams(BaseModel):
    """Wind: acceleration = strength * direction * gain(z), z = height above the base height
    (world units, along the scene's up), blowing during new frames [start_frame, end_frame).

    The base height is `base_height` where given (a world height: a wind placed in the scene's
    own coordinates, the same whatever the reconstruction estimated the source to be) and the
    source centre's height otherwise (`reference_height`, the one definition).

    gain(z) by `profile`:
      exponential  exp(growth * z)         the paper's wind (the default);
      linear       max(0, 1 + growth * z)  a ramp in height, as the official release's force;
      uniform      1                       the same push everywhere (growth must be 0).
    The acceleration drives the air around the smoke as well as the smoke itself, so the smoke is
    carried by the air the wind sets moving (fluidcore.physics.forces.wind_air). It drives the air
    up to a terminal speed, `terminal_speed` x gain(z) along `direction`, as a quadratic drag of
    the surroundings would: still air blown for t seconds moves at terminal x gain x
    tanh(strength t / terminal) (`air_speed`); without one given, the speed its strength gives in
    WIND_TERMINAL_SECONDS (filled in when the wind is made, so a run records the speed it used).
    A linear ramp from zero at height y0 to `strength` at y1 is profile "linear" with
    base_height y1 and growth 1 / (y1 - y0).
    Units: `strength` in world units / s^2 (the acceleration at the base height), `growth`
    per world unit of height, `direction` unitless (normalised here), `base_height` world units.
    `end_frame` is exclusive; None means the wind blows until the end of the run.
    """

    model_config = _STRICT

    direction: Vec3 = Field(description="where the wind blows (x, y, z; normalised)")
    strength: float = Field(ge=0.0, le=MAX_WIND_STRENGTH, description="the acceleration at the base height, units/s^2")
    growth: float = Field(default=0.0, ge=-MAX_WIND_GROWTH, le=MAX_WIND_GROWTH,
                          description="how the gain changes with height, per unit of height (0 for a uniform wind)")
    profile: WindProfile = Field(default="exponential", description="the gain with height z: exponential "
                                 "exp(growth z), linear max(0, 1 + growth z) or uniform 1")
    start_frame: int = Field(default=0, ge=0, description="the new frame it starts blowing on")
    end_frame: int | None = Field(default=None, ge=0, description="the new frame it stops on (exclusive; null: never)")
    base_height: float | None = Field(default=None, description="the world height where `strength` holds "
                                      "(null: the source centre's)")
    terminal_speed: float | None = Field(default=None, gt=0.0, le=MAX_WIND_SPEED, description=(
        f"the air's speed the wind blows up to at the base height, units/s (null: what its strength gives in "
        f"{WIND_TERMINAL_SECONDS:g} s)"))

    @field_validator("direction")
    @classmethod
    def _unit_direction(cls, direction: Vec3) -> Vec3:
        # hypot, not sqrt(sum of squares): squaring 1e300 overflows and the "unit" vector became 0.
        norm = math.hypot(*direction)
        if not norm >= 1e-9:
            raise ValueError(f"direction must be a non-zero vector, got {list(direction)}")
        return (direction[0] / norm, direction[1] / norm, direction[2] / norm)

    @model_validator(mode="after")
    def _window(self) -> WindParams:
        if self.end_frame is not None and self.end_frame <= self.start_frame:
            raise ValueError(f"end_frame ({self.end_frame}) must be after start_frame ({self.start_frame})")
        if self.profile == "uniform" and self.growth != 0.0:
            raise ValueError("growth must be 0 for a uniform wind (it is the same at every height)")
        if self.terminal_speed is None and self.strength > 0.0:  # recorded as used (class docstring)
            object.__setattr__(self, "terminal_speed", min(self.strength * WIND_TERMINAL_SECONDS, MAX_WIND_SPEED))
        return self

    @property
    def terminal_time(self) -> float | None:
        """Seconds the wind's push takes to bring still air to its terminal speed at a constant
        rate (terminal / strength): the time constant of `air_speed`. None for a wind of no strength."""
        if self.strength == 0.0 or self.terminal_speed is None:
            return None
        return self.terminal_speed / self.strength

    def air_speed(self, seconds: float) -> float:
        """The speed (units/s, at gain 1) the wind has given still air after blowing `seconds`:
        terminal x tanh(seconds / terminal_time); 0 before it blows or without strength."""
        tau = self.terminal_time
        if tau is None or seconds <= 0.0:
            return 0.0
        return float(self.terminal_speed) * math.tanh(seconds / tau)  # type: ignore[arg-type]

    def active(self, frame: int) -> bool:
        """Whether the wind blows during new frame `frame`: the one definition of its window
        (the physics asks it for every step through `fluidcore.predict.interventions`, the
        renders before drawing the wind arrow)."""
        return frame >= self.start_frame and (self.end_frame is None or frame < self.end_frame)

    @property
    def same_at_every_height(self) -> bool:
        """Whether `gain` is 1 everywhere: growth 0 makes every profile uniform, so a picture of
        the wind need not name its profile."""
        return self.growth == 0.0

    def reference_height(self, source_height: float) -> float:
        """The height (world units along up) where the acceleration is `strength`: `base_height`
        when the wind names one, else the height of the run's source centre."""
        return source_height if self.base_height is None else self.base_height

    def gain(self, height: Height) -> Height:
        """gain(z) at `height` z above the base height, by `profile` (the class docstring); the
        exponent is capped at MAX_GAIN_EXPONENT so a large growth far above the base stays finite.

        The one definition: `height` is a float (the scene check, the browser's arrows through the
        API) or a torch tensor of particle heights (`fluidcore.physics.forces`; this module imports
        no torch, so a tensor is clamped and exponentiated by its own methods)."""
        exponent = self.growth * height
        if self.profile == "uniform":
            return 1.0 + 0.0 * exponent
        if self.profile == "linear":
            return _clamp(1.0 + exponent, low=0.0)
        return _exp(_clamp(exponent, high=MAX_GAIN_EXPONENT))

    def peak_acceleration(self, lo: Vec3, hi: Vec3, base_height: float, up: Vec3 = (0.0, 1.0, 0.0)) -> float:
        """The largest wind acceleration anywhere in the box [lo, hi] (every gain is monotonic in
        height, so it peaks at a corner)."""
        heights = [sum(u * c for u, c in zip(up, corner)) - base_height for corner in _corners(lo, hi)]
        return self.strength * max(self.gain(h) for h in heights)


class BallParams(BaseModel):
    """A rigid ball with one-way coupling: the fluid is never inside it, it never feels the fluid.

    The ball enters the scene at `center` on new frame `start_frame` and from then on moves at
    the constant `velocity` (world units / s); before `start_frame` the scene has no ball.
    """

    model_config = _STRICT

    center: Vec3 = Field(description="where it enters, world units (inside the scene box)")
    radius: float = Field(gt=0.0, description="world units (at most the scene box's size)")
    start_frame: int = Field(default=0, ge=0, description="the new frame it enters on")
    velocity: Vec3 = Field(default=(0.0, 0.0, 0.0), description="its constant velocity, world units/s")

    def active(self, frame: int) -> bool:
        """Whether the ball is in the scene during new frame `frame` (the one definition)."""
        return frame >= self.start_frame

    def center_at(self, frame: int, dt: float) -> Vec3:
        """Where the ball is at the end of new frame `frame` (world units; `dt` seconds per
        frame): at `center` at the end of `start_frame`, moving at `velocity` since."""
        elapsed = (frame - self.start_frame) * dt
        return (
            self.center[0] + self.velocity[0] * elapsed,
            self.center[1] + self.velocity[1] * elapsed,
            self.center[2] + self.velocity[2] * elapsed,
        )

    def check_in_box(self, lo: Vec3, hi: Vec3) -> None:
        """Reject a ball whose centre lies outside the scene box (it could never touch the smoke),
        by the rule a scene's solids follow too (`fluidcore.spec.solids.ball_box_problem`)."""
        problem = ball_box_problem(self.center, self.radius, lo, hi, "ball")
        if problem is not None:
            raise InteractionError(problem)


class _Physics(Protocol):  # fluidcore.physics.PBFConfig
    dt: float

    @property
    def speed_limit(self) -> float: ...


class _Source(Protocol):  # fluidcore.physics.Source
    center: Vec3


class RunScene(Protocol):
    """What `InteractionParams.check_scene` reads of a run's scene: `fluidcore.spec.scene.Scene`
    (named by what it holds, since fluidcore.runs imports this module)."""

    box_lo: Vec3
    box_hi: Vec3
    up: Vec3
    physics: _Physics
    source: _Source


class InteractionParams(BaseModel):
    """Wind, ball, or both."""

    model_config = _STRICT

    wind: WindParams | None = None
    ball: BallParams | None = None

    def check_scene(self, scene: RunScene, frames: int) -> None:
        """Reject parameters that are valid in general but meaningless in this run's scene
        (`fluidcore.spec.scene.Scene`, torch-free, so the API can refuse a job before queueing it; the
        prediction job asks the same before it writes anything).

        A wind is absurd when, at its peak inside the box, it alone would take a particle at
        rest past the simulator's speed limit within one step (a * dt > speed_limit, one kernel
        radius per step): from there on the speed clamp, not the wind, decides the motion.
        """
        lo, hi, up = scene.box_lo, scene.box_hi, scene.up
        dt, speed_limit = scene.physics.dt, scene.physics.speed_limit
        center = scene.source.center
        if self.wind is not None:
            _check_start(self.wind.start_frame, frames, "wind")
            base_height = self.wind.reference_height(sum(u * c for u, c in zip(up, center)))
            _check_base_height(self.wind.base_height, lo, hi, up)
            peak = self.wind.peak_acceleration(lo, hi, base_height, up)
            if peak * dt > speed_limit:
                raise InteractionError(
                    f"wind.strength {self.wind.strength} with wind.growth {self.wind.growth} reaches "
                    f"{peak:.3g} units/s^2 in the scene box; this scene resolves at most "
                    f"{speed_limit / dt:.3g} units/s^2 (speed limit {speed_limit:.3g} units/s reached in one "
                    f"{dt:.3g} s step); lower the strength or the growth"
                )
        if self.ball is not None:
            _check_start(self.ball.start_frame, frames, "ball")
            self.ball.check_in_box(lo, hi)


# How far (in box heights) a wind's base height may lie outside the scene box's heights. A base
# placed in the scene's coordinates describes this scene's air; one far outside it (-1e308) passed
# the scene check, whose gain is capped, and then overflowed the physics' float32 heights to NaN.
BASE_HEIGHT_REACH = 10.0


def _check_base_height(base_height: float | None, lo: Vec3, hi: Vec3, up: Vec3) -> None:
    """InteractionError unless `base_height` (when given) lies within BASE_HEIGHT_REACH box heights
    of the scene box's heights along `up`."""
    if base_height is None:
        return
    heights = [sum(u * c for u, c in zip(up, corner)) for corner in _corners(lo, hi)]
    bottom, top = min(heights), max(heights)
    reach = BASE_HEIGHT_REACH * (top - bottom)
    if not bottom - reach <= base_height <= top + reach:
        raise InteractionError(
            f"wind.base_height {base_height:g} lies more than {BASE_HEIGHT_REACH:g} box heights from the scene box "
            f"(heights {bottom:.3g}..{top:.3g} along up); give a height in this scene's coordinates"
        )


class Intervention(InteractionParams):
    """Wind, ball or both, and at least one: what a what-if applies (a prediction applies the empty
    `InteractionParams`). The one home of that rule: the CLI, the prediction job and the API's
    interact parameters (service.job_types) build this model, and its JSON Schema states the rule
    (`anyOf`), so /openapi.json refuses what the API refuses."""

    model_config = ConfigDict(json_schema_extra={"anyOf": [
        {"required": [name], "properties": {name: {"not": {"type": "null"}}}} for name in ("wind", "ball")
    ]})

    @model_validator(mode="after")
    def _wind_or_ball(self) -> Intervention:
        if self.wind is None and self.ball is None:
            raise ValueError(NEEDS_WIND_OR_BALL)
        return self


FROM_FRAME_RULE = "a finished frame of the parent run"
FromFrame = Annotated[int | None, Field(
    default=None, ge=0, description=f"the frame a continuation branches off, {FROM_FRAME_RULE} (`branch_frame`); "
    "default: its last frame; 0 re-simulates the whole clip with the intervention")]


def branch_frame(from_frame: int | None, frames: Sequence[int], run: str) -> int:
    """The parent's frame a continuation starts from: `from_frame`, which must be one of the
    parent run's finished `frames` (ascending), or its last frame when None. The one check of
    that rule: the API asks it of a parent's manifest before queueing, the job of the run itself
    before it writes; `run` names the parent in the message."""
    if not frames:
        raise InteractionError(f"from_frame: {run} has no finished frame to start from")
    if from_frame is None:
        return frames[-1]
    if from_frame not in frames:
        raise InteractionError(f"from_frame: {from_frame} is not {FROM_FRAME_RULE} ({run}: frames {frames[0]}..{frames[-1]})")
    return from_frame


NEEDS_WIND_OR_BALL = "interact needs a wind, a ball or both (predict asks for neither)"

Given = str | Mapping[str, Any] | BaseModel | None
Controls = TypeVar("Controls", bound=InteractionParams)


def parse_interaction(
    wind: Given, ball: Given, model: type[Controls] = InteractionParams, **fields: Any  # type: ignore[assignment]
) -> Controls:
    """Build validated parameters (`model`: `Intervention` for a what-if, `fluidcore.spec.jobs
    .InteractParams` with its other `fields` for the CLI's interact job) from JSON text, dicts or
    the models themselves, with one readable message on failure.

    Pydantic's own message spans several lines with documentation links; the CLI and the API
    show ours, which names each offending field as `wind.strength`, `ball.center[2]`, ...
    """
    try:
        return model(wind=json_object(wind, "wind"), ball=json_object(ball, "ball"), **fields)
    except ValidationError as exc:
        raise InteractionError(describe_validation(exc)) from None


def json_object(value: Given, field: str) -> dict[str, Any] | BaseModel | None:
    """`value` (JSON text, a mapping or a model) as a dict or the model, None as None; an
    InteractionError naming `field` (a model's field or the command line's flag) for text that is
    not JSON or not an object. The command line's JSON options (`--wind`, `--ball`) read through it."""
    if value is None or isinstance(value, BaseModel):
        return value
    if isinstance(value, str):
        try:
            value = json.loads(value)
        except json.JSONDecodeError as exc:
            raise InteractionError(f"{field} is not valid JSON: {exc}") from None
    if not isinstance(value, Mapping):
        raise InteractionError(f"{field} must be a JSON object, got {type(value).__name__}")
    return dict(value)


def _check_start(start_frame: int, frames: int, field: str) -> None:
    if start_frame >= frames:
        raise InteractionError(
            f"{field}.start_frame ({start_frame}) is not within the {frames} predicted frames; "
            f"it would never act"
        )


def _corners(lo: Vec3, hi: Vec3) -> list[Vec3]:
    return [(x, y, z) for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]


def _clamp(value: Height, low: float | None = None, high: float | None = None) -> Height:
    if isinstance(value, float):
        return min(max(value, -math.inf if low is None else low), math.inf if high is None else high)
    return value.clamp(min=low, max=high)  # type: ignore[attr-defined]  # a torch tensor


def _exp(value: Height) -> Height:
    return math.exp(value) if isinstance(value, float) else value.exp()  # type: ignore[attr-defined]
