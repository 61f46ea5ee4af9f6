"""fluidcore.reconstruct.simulation_options: what a user may switch on beyond the preset."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from fluidcore.errors import InputError
from fluidcore.reconstruct.presets import PRESETS, get
from fluidcore.reconstruct.simulation_options import AIR_CELLS, SimulationOptions, simulation_options


@pytest.mark.parametrize("name", list(PRESETS))
def test_the_defaults_leave_every_preset_as_it_is(name: str) -> None:
    """A job that leaves the options out runs its preset unchanged (the options replace the
    preset's own settings, so a preset that simulated the air would need its own defaults here)."""
    assert SimulationOptions().applied_to(PRESETS[name]) == PRESETS[name]


def test_the_options_replace_the_presets_air_and_spreading() -> None:
    quality = SimulationOptions(air_cells=32, air_vorticity=0.3, entrainment=True).applied_to(get("preview"))
    assert (quality.air_cells, quality.air_vorticity, quality.entrainment) == (32, 0.3, True)
    assert quality.long_side == get("preview").long_side  # nothing else moves


@pytest.mark.parametrize("cells", [0, AIR_CELLS[0], AIR_CELLS[1]])
def test_still_air_and_the_ends_of_the_grid_range_are_accepted(cells: int) -> None:
    assert SimulationOptions(air_cells=cells).air_cells == cells


@pytest.mark.parametrize(("fields", "message"), [
    ({"air_cells": AIR_CELLS[0] - 1}, "air_cells must be 0 (still air) or"),
    ({"air_cells": AIR_CELLS[1] + 1}, "air_cells: Input should be less than or equal to"),
    ({"air_cells": -1}, "air_cells: Input should be greater than or equal to 0"),
    ({"air_cells": 32, "air_vorticity": float("nan")}, "air_vorticity"),
    ({"air_cells": 32, "air_vorticity": 2.5}, "air_vorticity: Input should be less than or equal to 2"),
    ({"air_vorticity": 0.5}, "air_vorticity needs the simulated air"),
    ({"entrainment": "perhaps"}, "entrainment"),
    ({"air": 32}, "air: Extra inputs are not permitted"),
])
def test_a_bad_option_is_one_line_naming_it(fields: dict, message: str) -> None:
    with pytest.raises(InputError) as caught:
        simulation_options(**fields)
    assert message in str(caught.value) and "\n" not in str(caught.value)
    with pytest.raises(ValidationError):  # the API validates the same model (service.job_types.ReconstructParams)
        SimulationOptions(**fields)
