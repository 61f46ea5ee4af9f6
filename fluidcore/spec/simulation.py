"""What the simulator adds beyond the fit's budget: the motion model, the air around the smoke
and the plume's spreading, and the physics modes a reconstruction may simulate with.

The motion model (`MOTION_MODELS`, issue 46): "paper", the paper's position-based particles with
their own buoyancy and density-gated drag (fluidcore.physics.paper), the default because its
images measure better: over seeds 0-2 its predicted future is 0.5 / 0.2 / 0.8 dB better on D /
F / ScalarFlow, its input-view fit 1.3-2.8 dB better, and its reconstruction takes 0.3-0.8x the
carrier's CPU time; "carrier", buoyant air on a grid carrying the smoke's particles as markers
(fluidcore.physics.carrier), selectable for what its motion measures better: a ball's effect
(score 0.35 / 0.51 on D / F against 0.25 / 0.30), F's velocities (0.56 / 0.64 of zero at f45 /
f90 against 0.70 / 0.73), the plume's head (0.9 / 1.1 cm off against 1.6-2.0), and novel views 0.3-0.4 dB better on D
and ScalarFlow (0.4 worse on F) (docs/bench_generalise.md, "The buoyant-air
carrier"). The air settings below are the paper model's options; for the carrier the air is the
motion, `air_cells` its grid.

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

from typing import Literal

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

# How the smoke moves (`fluidcore.physics.build.integrator` builds each; module docstring).
MOTION_MODELS = ("carrier", "paper")
MotionModel = Literal["carrier", "paper"]
DEFAULT_MOTION: MotionModel = "paper"  # the module docstring says why
# The carrier's grid when the user gives none: 48 cells on the box's long side (32 x 48 x 32 on the
# dev scenes, cells of 1.6 cm). Forward from the true source of D, the velocity error at frame 45
# was 0.48 at these cells and 0.46 at 72 (../shared/notes/motion_ceiling.md), for a third of the time.
CARRIER_CELLS = 48

PHYSICS_MODES = {"auto": "scalarflow", "scalarflow": "scalarflow", "fluidnexus": "fluidnexus_smoke"}  # -> prior preset
DEFAULT_PHYSICS = "auto"  # identified from the input video (fluidcore.reconstruct.identify), the presets as priors


def _still_or_grid(schema: dict) -> None:
    """The JSON Schema of `air_cells` states the "0 or AIR_CELLS" rule (`_air_settings` checks it)
    on its integer branch, so /openapi.json and GET /v1/limits, which the browser's forms read,
    refuse what the model refuses."""
    for branch in schema.get("anyOf", []):
        if branch.get("type") == "integer":
            branch["anyOf"] = [{"const": 0}, {"minimum": AIR_CELLS[0]}]


class SimulationConfigError(InputError):
    """Simulation settings that cannot be used; the message names the field."""


class SimulationConfig(BaseModel):
    """`motion`: the motion model (module docstring). `air_cells`: the air's grid, cells on the
    scene box's long side (None: the model's own, CARRIER_CELLS for the carrier, still air for
    the paper's particles; 0: still air, the paper model only). `air_vorticity`: that air's
    vorticity confinement (0 = off; needs the air). `entrainment`: the paper model's plume
    spreading, identified from the input view and simulated in every continuation (off: the
    paper's column; the carrier's air spreads its plume itself)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    motion: MotionModel = Field(default=DEFAULT_MOTION, description=(
        "how the smoke moves: paper (the paper's particles with their own buoyancy and drag, the default) or carrier "
        "(buoyant air on a grid carrying the smoke). On the dev scenes and ScalarFlow the paper model's future and "
        "input-view fit measure better and it takes 0.3-0.8x the time; the carrier's ball what-ifs, plume head and, on "
        "one dev scene, velocities measure better (docs/bench_generalise.md)"))

    # The air around the smoke (fluidcore.physics.air.AirGrid): 0 = still air, the default until issue
    # 23's measurements on both dev scenes and ScalarFlow (module docstring). The reconstruction steps
    # it frame by frame and saves it with every frame; continuations go on from it.
    air_cells: int | None = Field(default=None, ge=0, le=AIR_CELLS[1], json_schema_extra=_still_or_grid, description=(
        f"the air's grid: cells on the scene box's long side ({AIR_CELLS[0]}..{AIR_CELLS[1]}; omitted: {CARRIER_CELLS} for the "
        "carrier, still air for the paper model; 0: still air, paper model only); saved with every frame, its velocity "
        "in the density exports. For the paper model at 32 cells on the dev scenes (3 seeds): the same time, the future "
        "0.2 dB worse, a wind what-if 0.1-0.3 dB better"))
    air_vorticity: float = Field(default=0.0, ge=0.0, le=MAX_AIR_VORTICITY,
                                 description="the simulated air's vorticity confinement epsilon (0: off; needs air_cells)")
    # Off by default: on, the predicted plume's width comes within 20% of the truth's on both dev
    # scenes and D's future gains 0.3 dB, but the wind what-ifs lose (F 0.9 dB); with the air grid
    # too (air_cells 32) the wind gains instead, but F's ball loses 0.6 dB (docs/bench_generalise.md,
    # "Entrainment").
    entrainment: bool = Field(default=False, description="paper model only: identify the plume's spreading rate from the "
                              "input view and simulate it in every continuation (false: the paper's column). Two more trial simulations; "
                              "on the dev scenes the predicted width went from 0.67-0.70 to 0.87-0.94 of the truth's, a wind "
                              "what-if lost 0.2-0.9 dB; a video that shows no spreading gets none (the health report says so)")

    @model_validator(mode="after")
    def _air_settings(self) -> SimulationConfig:
        if self.air_cells is not None and 0 < self.air_cells < AIR_CELLS[0]:
            raise ValueError(f"air_cells must be 0 (still air) or {AIR_CELLS[0]}..{AIR_CELLS[1]}, got {self.air_cells}")
        if self.motion == "carrier" and self.air_cells == 0:
            raise ValueError(f"air_cells 0 is still air, which cannot carry the smoke: give {AIR_CELLS[0]}..{AIR_CELLS[1]} "
                             "cells (or omit it) for the carrier, or choose motion paper")
        if self.motion == "carrier" and self.entrainment:
            raise ValueError("entrainment is the paper model's spreading: the carrier's air spreads its plume itself "
                             "(choose motion paper to use it)")
        if self.air_vorticity > 0 and self.cells == 0:
            raise ValueError("air_vorticity needs the simulated air: set air_cells too")
        return self

    @property
    def cells(self) -> int:
        """The air grid's cells on the box's long side (0: still air): `air_cells`, else the
        motion model's own."""
        if self.air_cells is not None:
            return self.air_cells
        return CARRIER_CELLS if self.motion == "carrier" else 0


def simulation_config(**fields: object) -> SimulationConfig:
    """The settings from the command line's flags, with one line naming each bad field on failure."""
    try:
        return SimulationConfig(**fields)
    except ValidationError as exc:
        raise SimulationConfigError(describe_validation(exc)) from None
