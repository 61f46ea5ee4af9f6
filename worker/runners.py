"""Job runners: the only place the worker calls fluidcore (the "Jobs" contract in
docs/architecture.md). fluidcore and torch are imported inside the runner bodies, so
the Celery app, the API and the tests of the service logic load without them.

A runner gets a `RunInputs` (folders, parameters, callbacks) and returns the rendered
files to publish besides the run folder itself (MP4 per camera, orbit video, a what-if's
side-by-side, and the last frame in every `fluidcore.exports` format). Each reads its
parameters through its type's model in `service.job_types`, so defaults live there only.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from service.job_types import InteractParams, JobType, PredictParams, ReconstructParams

Progress = Callable[[float, str], None]
ShouldCancel = Callable[[], bool]


class JobCancelled(Exception):
    """The runner stopped because should_cancel() said so (fluidcore's Cancelled, translated)."""


@dataclass(frozen=True)
class RunInputs:
    job_id: str
    job_type: JobType
    params: dict[str, Any]  # as stored by the API; parse with the type's parameter model
    run_dir: Path  # the job's run folder: checkpointed to storage, resumed from on a retry
    render_dir: Path  # where the videos go
    device: str
    progress: Progress
    should_cancel: ShouldCancel
    cameras_path: Path | None = None  # reconstruct
    videos: Mapping[str, Path] | None = None  # reconstruct: camera name -> video
    parent_run: Path | None = None  # predict / interact / resimulate


Runner = Callable[[RunInputs], list[Path]]


def _callbacks(inputs: RunInputs) -> dict[str, Any]:
    return {"device": inputs.device, "progress": inputs.progress, "should_cancel": inputs.should_cancel}


RENDER_SHARE = 0.25  # of a job's progress bar: a 62 s ScalarFlow reconstruction spent 15.7 s rendering (issue 24)


def _render(inputs: RunInputs) -> list[Path]:
    """The videos (a what-if adds its side-by-side), at the size the run's reconstruction was
    fit at, and the last frame in every export format; progress moves per rendered frame."""
    from fluidcore.artifacts import fit_long_side, render_artifacts
    from fluidcore.exports import export_artifacts

    def progress(fraction: float, stage: str) -> None:
        inputs.progress(1.0 - RENDER_SHARE + RENDER_SHARE * fraction, stage)

    progress(0.0, "render")  # the run itself is complete; rendering fills the rest
    videos = render_artifacts(inputs.run_dir, inputs.render_dir, progress=progress, long_side=fit_long_side(inputs.run_dir))
    return [*videos, *export_artifacts(inputs.run_dir, inputs.render_dir)]


def _translating_cancel(run: Callable[[RunInputs], None]) -> Runner:
    """Run a fluidcore job, then render it; fluidcore's Cancelled becomes JobCancelled."""

    def runner(inputs: RunInputs) -> list[Path]:
        from fluidcore.jobs import Cancelled

        def job_progress(fraction: float, stage: str) -> None:
            inputs.progress((1.0 - RENDER_SHARE) * fraction, stage)

        try:
            run(replace(inputs, progress=job_progress))
        except Cancelled as exc:
            raise JobCancelled(str(exc)) from exc
        return _render(inputs)

    runner.__name__ = run.__name__
    runner.__doc__ = run.__doc__
    return runner


@_translating_cancel
def reconstruct(inputs: RunInputs) -> None:
    from fluidcore.reconstruct.job import run_reconstruct

    params = ReconstructParams.model_validate(inputs.params)
    assert inputs.cameras_path is not None and inputs.videos is not None
    run_reconstruct(
        inputs.cameras_path,
        dict(inputs.videos),
        inputs.run_dir,
        quality=params.quality,
        physics=params.physics,
        frames=params.frames,
        source=params.source,
        **_callbacks(inputs),
    )


@_translating_cancel
def predict(inputs: RunInputs) -> None:
    from fluidcore.predict.job import run_predict

    params = PredictParams.model_validate(inputs.params)
    run_predict(inputs.parent_run, inputs.run_dir, frames=params.frames, **_callbacks(inputs))


@_translating_cancel
def interact(inputs: RunInputs) -> None:
    from fluidcore.predict.job import run_interact

    params = InteractParams.model_validate(inputs.params)
    run_interact(
        inputs.parent_run,
        inputs.run_dir,
        frames=params.frames,
        wind=params.wind,
        ball=params.ball,
        from_frame=params.from_frame,
        **_callbacks(inputs),
    )


@_translating_cancel
def resimulate(inputs: RunInputs) -> None:
    from fluidcore.predict.job import run_resimulate

    run_resimulate(inputs.parent_run, inputs.run_dir, **_callbacks(inputs))


FLUIDCORE_RUNNERS: dict[JobType, Runner] = {
    JobType.RECONSTRUCT: reconstruct,
    JobType.PREDICT: predict,
    JobType.INTERACT: interact,
    JobType.RESIMULATE: resimulate,
}


def load_runners(spec: str | None) -> Mapping[str, Runner]:
    """fluidcore's runners, or the dict named by `spec` ('module:attribute'), the seam for test
    doubles; either must have a runner for every `JobType`, so a worker never takes a job it cannot run."""
    runners = FLUIDCORE_RUNNERS
    if spec is not None:
        module_name, _, attribute = spec.partition(":")
        runners = getattr(importlib.import_module(module_name), attribute)
    missing = sorted(job_type.value for job_type in set(JobType) - set(runners))
    if missing:
        raise ValueError(f"runners {spec or 'FLUIDCORE_RUNNERS'}: no runner for {missing}")
    return runners
