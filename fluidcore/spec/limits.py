"""The bounds each parameter field declares, read from its model's JSON Schema, so that what the
browser checks a form against (GET /v1/limits) and what the CLI's help states are the model's own
declaration and change with it.

A field's limits are the JSON Schema keywords that bound a value (`minimum`, `maximum`,
`exclusiveMinimum`, `exclusiveMaximum`, `enum`, `const`, and an `anyOf` of such branches, e.g.
"0 or at least 8") with its `type`, `default` and `description`, keyed by the field's path:
`air_cells`, `frames[1]` (an item of a tuple), `wind.strength` (a field of a nested model),
`solids[].radius` (a field of every item of a list, whose own limits, `maxItems`, are under
`solids`). An optional field (`X | None`) gives the limits of its value. Torch-free, like the whole spec.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel

Limits = dict[str, Any]
BOUNDS = ("type", "minimum", "maximum", "exclusiveMinimum", "exclusiveMaximum", "enum", "const", "anyOf", "minItems",
          "maxItems")
ABOUT = ("default", "description")


def field_limits(model: type[BaseModel]) -> dict[str, Limits]:
    """The limits of every field of `model` (nested models and tuple items included), by path."""
    schema = model.model_json_schema()
    found: dict[str, Limits] = {}
    _fields(schema, schema.get("$defs", {}), "", found)
    return found


def _fields(schema: dict[str, Any], defs: dict[str, Any], prefix: str, found: dict[str, Limits]) -> None:
    for name, field in schema.get("properties", {}).items():
        _field(field, defs, prefix + name, found)


def _field(field: dict[str, Any], defs: dict[str, Any], path: str, found: dict[str, Limits]) -> None:
    value = _value_schema(field, defs)
    if "properties" in value:
        _fields(value, defs, f"{path}.", found)
    elif "prefixItems" in value:
        for index, item in enumerate(value["prefixItems"]):
            _field(item, defs, f"{path}[{index}]", found)
    else:
        found[path] = {key: value[key] for key in BOUNDS if key in value} | {key: field[key] for key in ABOUT if key in field}
        if "items" in value:
            _field(value["items"], defs, f"{path}[]", found)


def _value_schema(field: dict[str, Any], defs: dict[str, Any]) -> dict[str, Any]:
    """The schema of the field's value: a `$ref` resolved, and of an optional field (an `anyOf`
    with null) the other branch."""
    branches = field.get("anyOf", [])
    if {"type": "null"} in branches:
        (field,) = [branch for branch in branches if branch != {"type": "null"}]
    if "$ref" in field:
        return defs[field["$ref"].rsplit("/", 1)[-1]]
    return field
