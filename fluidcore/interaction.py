"""Counterfactual parameters: wind and ball, validated once and shared by the CLI, the API and the browser.

Plain pydantic models with no torch import, so the API process can validate a job's
parameters before anything is queued. World units throughout; frames are counted from the
first new (predicted) frame.
"""

from __future__ import annotations

import math

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

Vec3 = tuple[float, float, float]

MAX_WIND_STRENGTH = 1.0e3  # world units / s^2 at the source height; beyond this nothing is smoke any more
MAX_WIND_GROWTH = 50.0  # per world unit of height; exp(50 * 1) is already far past physical


def _finite(vector: Vec3, field: str) -> Vec3:
    if not all(math.isfinite(c) for c in vector):
        raise ValueError(f"{field} must be finite, got {list(vector)}")
    return vector


class WindParams(BaseModel):
    """Wind: force = strength * direction * exp(growth * height above the source), from start_frame on."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    direction: Vec3
    strength: float = Field(ge=0.0, le=MAX_WIND_STRENGTH)
    growth: float = Field(default=0.0, ge=-MAX_WIND_GROWTH, le=MAX_WIND_GROWTH)
    start_frame: int = Field(default=0, ge=0)
    end_frame: int | None = Field(default=None, ge=0)

    @field_validator("direction")
    @classmethod
    def _unit_direction(cls, direction: Vec3) -> Vec3:
        _finite(direction, "direction")
        norm = math.sqrt(sum(c * c for c in direction))
        if norm < 1e-9:
            raise ValueError("direction must be a non-zero vector")
        return (direction[0] / norm, direction[1] / norm, direction[2] / norm)

    @model_validator(mode="after")
    def _window(self) -> WindParams:
        if self.end_frame is not None and self.end_frame <= self.start_frame:
            raise ValueError(f"end_frame ({self.end_frame}) must be after start_frame ({self.start_frame})")
        return self

    def active(self, frame: int) -> bool:
        """Whether the wind blows during new frame `frame`."""
        return frame >= self.start_frame and (self.end_frame is None or frame < self.end_frame)


class BallParams(BaseModel):
    """A rigid ball with one-way coupling: fluid never inside it; it moves at a constant velocity."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    center: Vec3
    radius: float = Field(gt=0.0)
    start_frame: int = Field(default=0, ge=0)
    velocity: Vec3 = (0.0, 0.0, 0.0)

    @field_validator("center", "velocity")
    @classmethod
    def _finite_vectors(cls, vector: Vec3, info) -> Vec3:  # type: ignore[no-untyped-def]
        return _finite(vector, info.field_name)

    @field_validator("radius")
    @classmethod
    def _finite_radius(cls, radius: float) -> float:
        if not math.isfinite(radius):
            raise ValueError("radius must be finite")
        return radius

    def check_in_box(self, lo: Vec3, hi: Vec3) -> None:
        """Reject a ball whose centre lies outside the scene box (it could never touch the smoke)."""
        if not all(l <= c <= h for c, l, h in zip(self.center, lo, hi)):
            raise ValueError(f"ball center {list(self.center)} is outside the scene box {list(lo)}..{list(hi)}")
        if self.radius > max(h - l for l, h in zip(lo, hi)):
            raise ValueError(f"ball radius {self.radius} is larger than the scene box")


class InteractionParams(BaseModel):
    """Wind, ball, or both."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    wind: WindParams | None = None
    ball: BallParams | None = None
