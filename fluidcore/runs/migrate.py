"""Manifests of every readable format version brought up to the current one on read (the only
place that knows what an older version wrote differently), and a manifest's bytes parsed."""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

from pydantic import ValidationError

from fluidcore.runs.layout import FORMAT, FORMAT_VERSION, READABLE_VERSIONS, RunError, RunKind
from fluidcore.runs.records import settings_model
from fluidcore.spec.reconstruct import quality_fields


def _nested_settings(settings: dict[str, Any]) -> dict[str, Any]:
    """A reconstruction's settings of format 1 or 2 as format 3 has them: the flat quality nested
    (`fluidcore.spec.reconstruct.quality_fields`), and the visual settings, which version 3 reads
    off the quality, folded into it (version 1 did not record the concentration rule in the
    quality: its visual settings say whether the run followed it)."""
    visual = settings.pop("visual", None) or {}
    quality = settings.get("quality")
    if isinstance(quality, Mapping):
        settings["quality"] = quality_fields(
            {"opacity_concentration": visual.get("opacity_concentration", False), **quality})
    return settings


def _motion_recorded(settings: dict[str, Any]) -> dict[str, Any]:
    """A reconstruction's settings whose quality names no motion model as written before the
    carrier existed: the paper's (`fluidcore.spec.simulation.MOTION_MODELS`), whose still air an
    `air_cells` of 0 then meant."""
    quality = settings.get("quality")
    if isinstance(quality, Mapping):
        simulation = quality.get("simulation")
        if isinstance(simulation, Mapping) and "motion" not in simulation:
            settings["quality"] = {**quality, "simulation": {**simulation, "motion": "paper"}}
    return settings


def _scene_with_air(scene: Any, settings: dict[str, Any], kind: RunKind) -> Any:
    """A scene record of format 1 or 2 with the air its run simulated, which those versions kept
    in the settings: a reconstruction in its flat quality (kept there too: the quality still asks
    for the air), a continuation in its own fields (taken out: they are the scene's now). A record
    that is not a mapping is left for `RunRecord.scene` to refuse."""
    if kind is RunKind.RECONSTRUCT:
        quality = settings.get("quality")
        held = quality if isinstance(quality, Mapping) else {}
        air = {"cells": held.get("air_cells", 0), "vorticity": held.get("air_vorticity", 0.0)}
    else:
        air = {"cells": settings.pop("air_cells", 0), "vorticity": settings.pop("air_vorticity", 0.0)}
    return {**scene, "air": air} if isinstance(scene, Mapping) else scene


def migrate(manifest: dict[str, Any], where: str) -> dict[str, Any]:
    """A manifest of any readable version as the current version: checked, settings completed
    with the defaults of their kind's model (version 1 left out what a feature added later), the
    air of versions 1 and 2 moved from the settings into the scene record, a reconstruction's
    motion model named where it was written before there was a choice (`_motion_recorded`)."""
    if manifest.get("format") != FORMAT:
        raise RunError(f"run: {where} is not a {FORMAT} manifest")
    if manifest.get("format_version") not in READABLE_VERSIONS:
        raise RunError(f"run: format_version {manifest.get('format_version')} is not supported")
    try:
        kind = RunKind(manifest.get("kind"))
    except ValueError:
        raise RunError(f"run: {where} has kind {manifest.get('kind')!r}, not one of {[k.value for k in RunKind]}") from None
    model = settings_model(kind)
    settings = dict(manifest.get("settings") or {})
    migrated: dict[str, Any] = {}
    if manifest["format_version"] < 3:
        migrated["scene"] = _scene_with_air(manifest.get("scene"), settings, kind)
        if kind is RunKind.RECONSTRUCT:
            settings = _nested_settings(settings)
    if kind is RunKind.RECONSTRUCT:
        settings = _motion_recorded(settings)
    if manifest["format_version"] == 1:  # free-form then: what no model field names is dropped
        settings = {k: v for k, v in settings.items() if k in model.model_fields}
    if kind is not RunKind.RECONSTRUCT and "branch_frame" not in settings and manifest.get("frames"):
        settings["branch_frame"] = int(manifest["frames"][0]["t"]) - 1  # version 1 before --from-frame
    try:
        typed = model.model_validate(settings)
    except ValidationError as exc:
        raise RunError(f"run: {where}: settings do not fit a {kind} run ({exc.errors()[0]['loc']}: {exc.errors()[0]['msg']})") from None
    return {**manifest, "format_version": FORMAT_VERSION, "kind": kind.value, **migrated, "settings": typed.model_dump(mode="json")}


def parse_manifest(data: bytes, where: str) -> dict[str, Any]:
    """The manifest in `data`, migrated (`migrate`); `where` names it in errors."""
    try:
        manifest = json.loads(data)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise RunError(f"run: {where} is not valid JSON ({exc})") from None
    if not isinstance(manifest, dict):
        raise RunError(f"run: {where} is not a {FORMAT} manifest")
    return migrate(manifest, where)
