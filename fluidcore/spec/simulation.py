"""What the simulator adds beyond the fit's budget: the air around the smoke and the plume's
spreading, and the physics modes a reconstruction may simulate with.

Both the air and the spreading are issue 23's and both are off by default, because on the
benchmark scenes neither helps everywhere (docs/bench_generalise.md, "The reconstruction carries
the air", "Entrainment" and "Issue 23 at its close"). With the air grid on (32 cells, mean of
seeds 0-2), the wind what-ifs gain in the late window (D +0.18 dB, F +0.63), and a run carries an
air velocity that its density exports hold (VFX tools use it for motion blur and re-simulation)
and the browser draws. The factual future loses 0.24 dB on D and 0.16 on F, and F's ball what-if
loses 0.47 dB. With entrainment on, the predicted plume's width at f120 goes from 0.67 to 0.87 of
the truth's on D and from 0.70 to 0.94 on F. A user who wants the air or the wider plume should be
able to ask for them.

`SimulationConfig` is one model, torch-free, so the API validates a request before anything is
queued; the CLI, the API (`service.job_types.ReconstructParams` extends it) and the worker share
it, a reconstruction records it (`ReconstructConfig.simulation`) and every continuation of the run
follows it. The physics mode is not one of its fields: a reconstruction records the mode with how
its physics was found (`fluidcore.runs.PhysicsRecord`), and one record of it is enough.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from fluidcore.errors import InputError, describe_validation

# Cells on the scene box's long side: the one range of the air grid (fluidcore.physics.air.AirGrid
# checks it too). From 8, the smallest grid that still has two cells across a plume a quarter of the
# box wide. Up to 128: `bench physics --air` measured the air step at 7 % of a 50k-particle PBF step
# at 32 cells, 17 % at 48 and 34-40 % at 64, growing with the cell count cubed, so 128 costs about
# three PBF steps per step (docs/bench_physics.md, "The air grid").
AIR_CELLS = (8, 128)
# Vorticity confinement epsilon (Fedkiw, Stam & Jensen 2001, dimensionless). Solver libraries
# document ranges of 0.01-0.5 and 0.1-2.0 for it; above 2 the confinement force outgrows the
# buoyancy that drives the air.
MAX_AIR_VORTICITY = 2.0

PHYSICS_MODES = {"auto": "scalarflow", "scalarflow": "scalarflow", "fluidnexus": "fluidnexus_smoke"}  # -> prior preset
DEFAULT_PHYSICS = "auto"  # identified from the input video (fluidcore.reconstruct.identify), the presets as priors


class SimulationConfigError(InputError):
    """Simulation settings that cannot be used; the message names the field."""


class SimulationConfig(BaseModel):
    """`air_cells`: simulate the air around the smoke on a grid with this many cells on the scene
    box's long side (0, the default: still air). `air_vorticity`: that air's vorticity confinement
    (0 = off; needs the air). `entrainment`: identify the plume's spreading rate from the input
    view and simulate it in every continuation (off: the paper's column)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    # The air around the smoke (fluidcore.physics.air.AirGrid): 0 = still air, the default until issue
    # 23's measurements on both dev scenes and ScalarFlow (module docstring). The reconstruction steps
    # it frame by frame and saves it with every frame; continuations go on from it.
    # The schema states the "0 or AIR_CELLS" rule too (`_air_settings` checks it), so /openapi.json and
    # GET /v1/limits, which the browser's forms read, refuse what the model refuses.
    air_cells: int = Field(default=0, ge=0, le=AIR_CELLS[1], json_schema_extra={"anyOf": [{"const": 0}, {"minimum": AIR_CELLS[0]}]}, description=(
        f"simulate the air around the smoke on a grid of this many cells on the scene box's long side "
        f"({AIR_CELLS[0]}..{AIR_CELLS[1]}; 0: still air, the default); saved with every frame, its velocity in the density exports. "
        "At 32 cells on the dev scenes (3 seeds): the same time (1.00-1.04x), the future 0.2 dB worse, a wind what-if 0.1-0.3 dB better"))
    air_vorticity: float = Field(default=0.0, ge=0.0, le=MAX_AIR_VORTICITY,
                                 description="the simulated air's vorticity confinement epsilon (0: off; needs air_cells)")
    # Off by default: on, the predicted plume's width comes within 20% of the truth's on both dev
    # scenes and D's future gains 0.3 dB, but the wind what-ifs lose (F 0.9 dB); with the air grid
    # too (air_cells 32) the wind gains instead, but F's ball loses 0.6 dB (docs/bench_generalise.md,
    # "Entrainment").
    entrainment: bool = Field(default=False, description="identify the plume's spreading rate from the input view and "
                              "simulate it in every continuation (false: the paper's column). Two more trial simulations; "
                              "on the dev scenes the predicted width went from 0.67-0.70 to 0.87-0.94 of the truth's, a wind "
                              "what-if lost 0.2-0.9 dB; a video that shows no spreading gets none (the health report says so)")

    @model_validator(mode="after")
    def _air_settings(self) -> SimulationConfig:
        if 0 < self.air_cells < AIR_CELLS[0]:
            raise ValueError(f"air_cells must be 0 (still air) or {AIR_CELLS[0]}..{AIR_CELLS[1]}, got {self.air_cells}")
        if self.air_vorticity > 0 and self.air_cells == 0:
            raise ValueError("air_vorticity needs the simulated air: set air_cells too")
        return self


def simulation_config(**fields: object) -> SimulationConfig:
    """The settings from the command line's flags, with one line naming each bad field on failure."""
    try:
        return SimulationConfig(**fields)
    except ValidationError as exc:
        raise SimulationConfigError(describe_validation(exc)) from None
