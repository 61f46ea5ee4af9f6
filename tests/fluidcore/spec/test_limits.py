"""`fluidcore.spec.limits.field_limits`: each field's bounds read from its model's JSON Schema, by
path, so that what the browser and the CLI state follows the declaration when it changes."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, Field

from fluidcore.spec.limits import field_limits


def _model(top: float) -> type[BaseModel]:
    """A model of every shape the spec uses, with `top` as one field's upper bound."""

    class Inner(BaseModel):
        level: float = Field(default=1.0, ge=0.0, le=top, description="how much")

    class Outer(BaseModel):
        count: int = Field(default=0, ge=0, le=10, json_schema_extra={"anyOf": [{"const": 0}, {"minimum": 4}]})
        mode: Literal["a", "b"] = "a"
        window: tuple[Annotated[int, Field(ge=0)], Annotated[int, Field(ge=1)]] | None = None
        start: int | None = Field(default=None, ge=2)
        inner: Inner | None = None

    return Outer


def test_each_field_by_path_with_its_bounds_default_and_description() -> None:
    limits = field_limits(_model(5.0))
    assert set(limits) == {"count", "mode", "window[0]", "window[1]", "start", "inner.level"}
    assert limits["count"] == {"type": "integer", "minimum": 0, "maximum": 10, "anyOf": [{"const": 0}, {"minimum": 4}], "default": 0}
    assert limits["mode"]["enum"] == ["a", "b"] and limits["mode"]["default"] == "a"
    assert (limits["window[0]"]["minimum"], limits["window[1]"]["minimum"]) == (0, 1)
    assert limits["start"] == {"type": "integer", "minimum": 2, "default": None}  # an optional field: its value's bounds
    assert limits["inner.level"] == {"type": "number", "minimum": 0.0, "maximum": 5.0, "default": 1.0, "description": "how much"}


def test_a_changed_bound_is_a_changed_limit() -> None:
    assert field_limits(_model(5.0))["inner.level"]["maximum"] == 5.0
    assert field_limits(_model(7.5))["inner.level"]["maximum"] == 7.5
