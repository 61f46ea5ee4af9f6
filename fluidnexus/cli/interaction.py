"""`fluidnexus predict | resimulate | interact`: continue a reconstruction with the simulator.

Each command writes a new run folder (the shared run format, with the parent recorded), so
`fluidnexus render RUN2` renders its new frames like any other run. Counterfactual parameters
are validated before any work starts; a bad value prints `error: ...` and exits with code 2.
"""

from __future__ import annotations

import sys
from pathlib import Path

import typer

from fluidcore.spec.controls import BallParams, WindParams
from fluidcore.spec.jobs import InteractParams, PredictParams
from fluidnexus.reporting import check_device, emit_run, user_errors
from fluidnexus.cli.generative import ModelsDir
from fluidnexus.cli.options import json_help, spec_option

RUN_ARG = typer.Argument(..., help="Run folder to continue (a reconstruction, or a prediction).")
OUT_OPT = typer.Option(..., "--out", help="Folder for the new run; an unfinished run there is resumed.")
DEVICE_OPT = typer.Option("cpu", "--device", help="torch device: cpu, cuda, cuda:1, ...")
JSON_OPT = typer.Option(False, "--json", help="Print one JSON object (run, kind, frames, parent) on stdout.")
FROM_OPT = spec_option(InteractParams, "from_frame", "--from-frame")


def register(app: typer.Typer, bench: typer.Typer) -> None:
    """Add predict, resimulate and interact to the top-level app."""
    app.command("predict")(predict)
    app.command("resimulate")(resimulate)
    app.command("interact")(interact)


def predict(
    run: Path = RUN_ARG,
    frames: int = spec_option(PredictParams, "frames", "--frames", default=...),
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
    from fluidcore.spec.jobs import job_params

    with user_errors():
        params = job_params(PredictParams, frames=frames)
        check_device(device)
        path = run_predict(
            run, out, frames=params.frames, from_frame=from_frame, generative=GenerativeSettings(models_root=models),
            context=JobContext(device, _ProgressBar()),
        )
        emit_run(as_json, path)


def resimulate(run: Path = RUN_ARG, out: Path = OUT_OPT, device: str = DEVICE_OPT, as_json: bool = JSON_OPT) -> None:
    """Re-run the simulator from the reconstructed first frame over the observed window."""
    from fluidcore.jobs import JobContext
    from fluidcore.predict.job import run_resimulate

    with user_errors():
        check_device(device)
        path = run_resimulate(run, out, context=JobContext(device, _ProgressBar()))
        emit_run(as_json, path)


def interact(
    run: Path = RUN_ARG,
    frames: int = spec_option(InteractParams, "frames", "--frames", default=...),
    out: Path = OUT_OPT,
    wind: str | None = typer.Option(None, "--wind", help=f"Wind as JSON: {json_help(WindParams)}"),
    ball: str | None = typer.Option(None, "--ball", help=f"Ball as JSON: {json_help(BallParams)}"),
    from_frame: int | None = FROM_OPT,
    device: str = DEVICE_OPT,
    as_json: bool = JSON_OPT,
) -> None:
    """Ask what if: a wind, a ball in the plume's way, or both, from any frame of RUN (default: after its last)."""
    from fluidcore.jobs import JobContext
    from fluidcore.spec.controls import parse_interaction

    with user_errors():
        # the edge: the API's interact params, so bad JSON or values fail here, before torch loads
        params = parse_interaction(wind, ball, InteractParams, frames=frames, from_frame=from_frame)
        from fluidcore.predict.job import run_interact

        check_device(device)
        context = JobContext(device, _ProgressBar())
        path = run_interact(run, out, params, frames=params.frames, from_frame=params.from_frame, context=context)
        emit_run(as_json, path)


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
