"""Command-line options derived from the spec's parameter models (`fluidcore.spec.jobs`,
`fluidcore.spec.controls`): each option's default and help come from its field's declaration
(`fluidcore.spec.limits.field_limits`), so the CLI states the bounds the API and the browser
enforce. The values themselves are checked by building the model (`fluidcore.spec.jobs.job_params`),
whose error names the field (exit code 2)."""

from __future__ import annotations

import json
from typing import Any

import typer
from pydantic import BaseModel

from fluidcore.spec.limits import Limits, field_limits


def spec_option(model: type[BaseModel], field: str, flag: str, **kwargs: Any) -> Any:
    """A typer option for `model`'s `field`: the field's default (or `default=...` to require it)
    and its description with its range as help."""
    limits = field_limits(model)[field]
    default = kwargs.pop("default", limits.get("default"))
    return typer.Option(default, flag, help=field_help(limits), **kwargs)


def field_help(limits: Limits) -> str:
    """A field's description and, where it is bounded, what it allows: "... (allowed: 0 or 8..128)"
    (not in square brackets, which typer's rich help reads as markup)."""
    allowed = allowed_values(limits)
    return f"{limits.get('description', '')} (allowed: {allowed})" if allowed else limits.get("description", "")


def json_help(model: type[BaseModel]) -> str:
    """The JSON object `model` reads, each field with its description and range, for an option
    that takes one (`--wind`, `--ball`)."""
    limits = field_limits(model)
    fields = [f'"{name}": {field_help(limits[name]) if name in limits else field.description}'
              for name, field in model.model_fields.items()]
    return "{" + ", ".join(fields) + "}"


def allowed_values(limits: Limits) -> str:
    """What a field allows in words ("0 or 8..128", ">= 0", "> 0", "a | b"); "" when unbounded."""
    base = {key: value for key, value in limits.items() if key != "anyOf"}
    return " or ".join(filter(None, (_range(base | branch) for branch in limits.get("anyOf", [{}]))))


BOUND_SIGNS = (("exclusiveMinimum", ">"), ("minimum", ">="), ("exclusiveMaximum", "<"), ("maximum", "<="))


def _range(limits: Limits) -> str:
    if "const" in limits:
        return json.dumps(limits["const"])
    if "enum" in limits:
        return " | ".join(map(str, limits["enum"]))
    if "minimum" in limits and "maximum" in limits:
        return f"{limits['minimum']}..{limits['maximum']}"
    return " and ".join(f"{sign} {limits[key]}" for key, sign in BOUND_SIGNS if key in limits)
