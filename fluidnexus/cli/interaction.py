"""`fluidnexus predict | resimulate | interact`: continue a reconstruction with the simulator.

Each command writes a new run folder (the shared run format, with the parent recorded), so
`fluidnexus render RUN2` renders its new frames like any other run. Counterfactual parameters
are validated before any work starts; a bad value prints `error: ...` and exits with code 2.
"""

from __future__ import annotations

import sys
from pathlib import Path

import typer

from fluidnexus.cli.errors import check_device, emit, run_fields, user_errors
from fluidnexus.cli.generative import ModelsDir

RUN_ARG = typer.Argument(..., help="Run folder to continue (a reconstruction, or a prediction).")
OUT_OPT = typer.Option(..., "--out", help="Folder for the new run; an unfinished run there is resumed.")
DEVICE_OPT = typer.Option("cpu", "--device", help="torch device: cpu, cuda, cuda:1, ...")
JSON_OPT = typer.Option(False, "--json", help="Print one JSON object (run, kind, frames, parent) on stdout.")
FROM_OPT = typer.Option(None, "--from-frame", min=0, help="Branch off this frame of RUN (default: its last frame).")


def register(app: typer.Typer, bench: typer.Typer) -> None:
    """Add predict, resimulate and interact to the top-level app."""
    app.command("predict")(predict)
    app.command("resimulate")(resimulate)
    app.command("interact")(interact)


def predict(
    run: Path = RUN_ARG,
    frames: int = typer.Option(..., "--frames", min=1, help="How many frames to predict after the last one."),
    out: Path = OUT_OPT,
    from_frame: int | None = FROM_OPT,
    device: str = DEVICE_OPT,
    models: ModelsDir = None,
    as_json: bool = JSON_OPT,
) -> None:
    """Simulate the smoke forward FRAMES frames after the last reconstructed frame (Algorithm S2);
    with video-model weights in the models folder, refine them and reconstruct on them."""
    from fluidcore.generative.stages import GenerativeSettings
    from fluidcore.jobs import JobContext
    from fluidcore.predict.job import run_predict

    with user_errors():
        check_device(device)
        path = run_predict(
            run, out, frames=frames, from_frame=from_frame, generative=GenerativeSettings(models_root=models),
            context=JobContext(device, _ProgressBar()),
        )
        emit(as_json, str(path), **run_fields(path))


def resimulate(run: Path = RUN_ARG, out: Path = OUT_OPT, device: str = DEVICE_OPT, as_json: bool = JSON_OPT) -> None:
    """Re-run the simulator from the reconstructed first frame over the observed window."""
    from fluidcore.jobs import JobContext
    from fluidcore.predict.job import run_resimulate

    with user_errors():
        check_device(device)
        path = run_resimulate(run, out, context=JobContext(device, _ProgressBar()))
        emit(as_json, str(path), **run_fields(path))


def interact(
    run: Path = RUN_ARG,
    frames: int = typer.Option(..., "--frames", min=1, help="How many frames to simulate after the branch frame."),
    out: Path = OUT_OPT,
    wind: str | None = typer.Option(
        None,
        "--wind",
        help='Wind as JSON: {"direction": [x, y, z], "strength": s (units/s^2), "growth": g (per unit height), '
        '"profile": "exponential|linear|uniform", "start_frame": f, "end_frame": null, "base_height": null '
        '(world height where the strength holds; default: the source centre)}',
    ),
    ball: str | None = typer.Option(
        None,
        "--ball",
        help='Ball as JSON: {"center": [x, y, z], "radius": r, "start_frame": f, "velocity": [vx, vy, vz]}',
    ),
    from_frame: int | None = FROM_OPT,
    device: str = DEVICE_OPT,
    as_json: bool = JSON_OPT,
) -> None:
    """Ask what if: a wind, a ball in the plume's way, or both, from any frame of RUN (default: after its last)."""
    from fluidcore.spec.controls import Intervention, parse_interaction
    from fluidcore.jobs import JobContext

    with user_errors():
        params = parse_interaction(wind, ball, Intervention)  # the edge: bad JSON or values fail here, before torch loads
        from fluidcore.predict.job import run_interact

        check_device(device)
        context = JobContext(device, _ProgressBar())
        path = run_interact(run, out, params, frames=frames, from_frame=from_frame, context=context)
        emit(as_json, str(path), **run_fields(path))


class _ProgressBar:
    """A tqdm bar on stderr fed by (fraction, stage) reports, so stdout carries only the run's path;
    a new stage (a prediction's refinement after its simulation) starts a new bar."""

    def __init__(self) -> None:
        self._bar = None
        self._stage: str | None = None

    def __call__(self, fraction: float, stage: str) -> None:
        if stage != self._stage and self._bar is not None:
            self._bar.close()
            self._bar = None
        self._stage = stage
        if self._bar is None:
            from tqdm import tqdm

            self._bar = tqdm(total=1.0, desc=stage, file=sys.stderr, dynamic_ncols=True,
                             bar_format="{desc}: {percentage:3.0f}%|{bar}| {elapsed}<{remaining}")
        self._bar.n = fraction
        self._bar.refresh()
        if fraction >= 1.0:
            self._bar.close()
