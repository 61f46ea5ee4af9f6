"""fluidcore.spec.reconstruct: the nested reconstruction config, checked where it is made, its
presets, and the overrides the benchmarks' `--set` gives it."""

from __future__ import annotations

import json

import pytest
from pydantic import ValidationError

from fluidcore.errors import InputError
from fluidcore.spec.reconstruct import (
    DEFAULT_QUALITY,
    PRESETS,
    FitBudget,
    PresetError,
    ReconstructConfig,
    get,
    quality_fields,
)
from fluidcore.spec.simulation import SimulationConfig


@pytest.mark.parametrize("name", list(PRESETS))
def test_every_preset_says_what_it_is_for_and_reads_back_from_its_json(name: str) -> None:
    preset = PRESETS[name]
    assert preset.config.name == name and preset.description and "\n" not in preset.description
    recorded = json.loads(json.dumps(preset.config.model_dump(mode="json"), allow_nan=False))
    assert ReconstructConfig.model_validate(recorded) == get(name)
    assert preset.config.simulation == SimulationConfig()  # the user's switches start off in every preset
    assert DEFAULT_QUALITY in PRESETS


def test_flat_names_and_dotted_paths_reach_the_same_field() -> None:
    """The names the docs' `--set` commands use (`seed`, `long_side`, `air_cells`, `weights=`) and
    the dotted paths into the nested config are two spellings of one field."""
    flat = get("preview").with_overrides(seed=1, long_side=240, air_cells=32, opacity_spread=None, weights={"flow": 1})
    dotted = get("preview").with_overrides(**{"seed": 1, "fit.long_side": 240, "simulation.air_cells": 32,
                                              "visual.opacity_spread": None, "weights.flow": 1.0})
    assert flat == dotted
    assert (flat.seed, flat.fit.long_side, flat.simulation.air_cells, flat.visual.opacity_spread) == (1, 240, 32, None)
    assert flat.weights.flow == 1.0 and flat.weights.l1 == get("preview").weights.l1  # a partial mapping keeps the rest
    assert flat.fit.position_iterations == get("preview").fit.position_iterations
    assert get("preview").with_overrides(fit={"long_side": 100}).fit == get("preview").fit.model_copy(update={"long_side": 100})


@pytest.mark.parametrize(("overrides", "field"), [
    ({"long_side": 4}, "fit.long_side"),
    ({"position_iterations": 0}, "fit.position_iterations"),
    ({"coarse_to_fine": []}, "fit.coarse_to_fine"),
    ({"coarse_to_fine": [1.0, 0.5]}, "coarse_to_fine must be fractions"),
    ({"coarse_to_fine": [0.5, 1.5]}, "fit.coarse_to_fine[1]"),
    ({"particles_per_frame": "30"}, "fit.particles_per_frame"),
    ({"per_physical": 0}, "visual.per_physical"),
    ({"initial_opacity": 1.0}, "visual.initial_opacity"),
    ({"min_scale": 2.0}, "max_scale (1.0) must not be below min_scale"),
    ({"opacity_spread": -0.5}, "visual.opacity_spread"),
    ({"opacity_concentration": "yes"}, "visual.opacity_concentration"),
    ({"symmetry_views": -1}, "priors.symmetry_views"),
    ({"symmetry_weight": float("inf")}, "priors.symmetry_weight"),
    ({"lr_position": 0.0}, "optimiser.lr_position"),
    ({"weights": {"flow": -1}}, "weights.flow"),
    ({"weights": {"colour": 1}}, "weights.colour"),
    ({"air_cells": 4}, "air_cells must be 0 (still air) or 8..128"),
    ({"motion": "paper", "air_vorticity": 0.5}, "air_vorticity needs the simulated air"),
    ({"seed": 1.5}, "seed"),
    ({"name": ""}, "name"),
    ({"visual_per_physical": 4}, "unknown field 'visual_per_physical'"),
    ({"fit.nope": 1}, "unknown field 'fit.nope'"),
    ({"long_side.x": 1}, "unknown field 'long_side.x'"),
])
def test_a_bad_override_is_one_line_naming_its_field(overrides: dict, field: str) -> None:
    with pytest.raises(PresetError) as caught:
        get("preview").with_overrides(**overrides)
    assert field in str(caught.value) and "\n" not in str(caught.value)
    assert isinstance(caught.value, InputError)


def test_a_config_is_checked_where_it_is_made_and_cannot_change_after() -> None:
    with pytest.raises(ValidationError, match="long_side"):
        FitBudget(long_side=2, position_iterations=1, appearance_iterations=1, first_frame_factor=1,
                  coarse_to_fine=(1.0,), particles_per_frame=1)
    config = get("preview")
    with pytest.raises(ValidationError):
        config.fit.long_side = 10  # type: ignore[misc]
    with pytest.raises(PresetError, match="quality must be one of preview, standard, paper"):
        get("ultra")


def test_a_flat_quality_record_nests_by_the_same_names() -> None:
    """Runs of format 1 and 2 recorded the quality flat; `quality_fields` nests it (dropping what
    no field names any more), and leaves a nested record as it is."""
    nested = get("standard").model_dump(mode="json")
    flat = {key: value for part, fields in nested.items() if isinstance(fields, dict) and part != "weights"
            for key, value in fields.items()}
    flat = {**flat, "name": "standard", "seed": 0, "weights": nested["weights"]}
    flat["visual_per_physical"] = flat.pop("per_physical")
    flat["air_flow"] = 0.0  # a feature removed since
    assert ReconstructConfig.model_validate(quality_fields(flat)) == get("standard")
    assert quality_fields(nested) == nested
