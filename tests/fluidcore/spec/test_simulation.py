"""fluidcore.spec.simulation: what a user may switch on beyond the preset, and the air grid's one range."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from fluidcore.errors import InputError
from fluidcore.physics import Box, PhysicsInputError
from fluidcore.physics.air import AirGrid
from fluidcore.spec.reconstruct import PRESETS, get
from fluidcore.spec.simulation import AIR_CELLS, CARRIER_CELLS, SimulationConfig, simulation_config


@pytest.mark.parametrize("name", list(PRESETS))
def test_the_defaults_leave_every_preset_as_it_is(name: str) -> None:
    """A job that leaves the options out runs its preset unchanged (the options replace the
    preset's own settings, so a preset that simulated the air would need its own defaults here)."""
    assert get(name).with_simulation(SimulationConfig()) == PRESETS[name].config


def test_the_options_replace_the_presets_air_and_spreading() -> None:
    chosen = SimulationConfig(motion="paper", air_cells=32, air_vorticity=0.3, entrainment=True)
    quality = get("preview").with_simulation(chosen)
    assert quality.simulation == chosen
    assert quality.model_copy(update={"simulation": SimulationConfig()}) == get("preview")  # nothing else moves


@pytest.mark.parametrize("cells", [AIR_CELLS[0], AIR_CELLS[1]])
def test_the_ends_of_the_grid_range_are_accepted_for_both_models(cells: int) -> None:
    for motion in ("carrier", "paper"):
        assert SimulationConfig(motion=motion, air_cells=cells).cells == cells


def test_each_model_has_its_own_air_when_none_is_given() -> None:
    """The paper model (the default) has still air unless asked for, and may be still when asked (0);
    the carrier is its air (48 cells unless told)."""
    assert SimulationConfig().motion == "paper" and SimulationConfig().cells == 0
    assert SimulationConfig(motion="paper", air_cells=0).cells == 0
    assert SimulationConfig(motion="carrier").cells == CARRIER_CELLS


@pytest.mark.parametrize(("fields", "message"), [
    ({"air_cells": AIR_CELLS[0] - 1}, "air_cells must be 0 (still air) or"),
    ({"air_cells": AIR_CELLS[1] + 1}, "air_cells: Input should be less than or equal to"),
    ({"air_cells": -1}, "air_cells: Input should be greater than or equal to 0"),
    ({"air_cells": 32, "air_vorticity": float("nan")}, "air_vorticity"),
    ({"air_cells": 32, "air_vorticity": 2.5}, "air_vorticity: Input should be less than or equal to 2"),
    ({"motion": "paper", "air_vorticity": 0.5}, "air_vorticity needs the simulated air"),
    ({"motion": "carrier", "air_cells": 0}, "air_cells 0 is still air, which cannot carry the smoke"),
    ({"motion": "carrier", "entrainment": True}, "entrainment is the paper model's spreading"),
    ({"motion": "eulerian"}, "motion: Input should be 'carrier' or 'paper'"),
    ({"entrainment": "perhaps"}, "entrainment"),
    ({"air": 32}, "air: Extra inputs are not permitted"),
])
def test_a_bad_option_is_one_line_naming_it(fields: dict, message: str) -> None:
    with pytest.raises(InputError) as caught:
        simulation_config(**fields)
    assert message in str(caught.value) and "\n" not in str(caught.value)
    with pytest.raises(ValidationError):  # the API validates the same model (service.job_types.ReconstructParams)
        SimulationConfig(**fields)


def test_a_request_model_that_extends_the_settings_leaves_its_own_fields_out_of_the_config() -> None:
    """The API's reconstruct parameters extend `SimulationConfig`; what a config records of them
    is the simulation settings alone."""
    from fluidcore.spec.jobs import ReconstructParams

    params = ReconstructParams(air_cells=16, quality="paper")
    assert type(get("preview").with_simulation(params).simulation) is SimulationConfig
    assert get("preview").with_simulation(params).simulation == SimulationConfig(air_cells=16)


@pytest.mark.parametrize("cells", [AIR_CELLS[0] - 1, AIR_CELLS[1] + 1])
def test_the_air_grid_refuses_what_the_settings_refuse(cells: int) -> None:
    """One range of cells, declared once: the simulator's own check uses it too."""
    with pytest.raises(PhysicsInputError, match=f"{AIR_CELLS[0]}..{AIR_CELLS[1]}"):
        AirGrid(Box((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)), cells)
