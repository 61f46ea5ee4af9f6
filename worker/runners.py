"""Job runners: the only place the worker calls fluidcore's jobs (the "Jobs" contract in
docs/architecture.md). The science and torch are imported inside the runner bodies, so the
Celery app, the API and the tests of the service logic load without them; only the torch-free
`fluidcore.jobs` (the progress, cancellation and context types) is imported here.

A runner gets a `RunInputs` (folders, parameters, callbacks) and returns the rendered
files to publish besides the run folder itself (a reconstruction's input-view MP4s, the last frame in
every `fluidcore.exports` format, every frame as VDB; a render job: the one video asked for; a
bundle job: the one zip).
Each reads its parameters through its type's model in `service.job_types`, so defaults live
there only.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from fluidcore.jobs import JobContext, Progress, ShouldCancel
from fluidcore.spec.jobs import BundleParams, InteractParams, PredictParams, ReconstructParams, RenderParams
from service.bundles import params_plan
from service.job_types import JobType


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
    parent_run: Path | None = None  # predict / interact / resimulate / render

    @property
    def context(self) -> JobContext:
        """The device and callbacks as the fluidcore job entries take them."""
        return JobContext(self.device, self.progress, self.should_cancel)


Runner = Callable[[RunInputs], list[Path]]


RENDER_SHARE = 0.25  # of a job's progress bar: a 62 s ScalarFlow reconstruction spent 15.7 s rendering (issue 24)


def _render(inputs: RunInputs) -> list[Path]:
    """The videos a finished job renders before it ends (a reconstruction's input views,
    `eager_videos`; any other is a render job away) at the size the run's reconstruction was fit at, the last frame
    in every export format and the run's frames as a VDB sequence
    (fluidcore.exports.export_artifacts); progress moves per rendered frame."""
    from fluidcore.artifacts import eager_videos, fit_long_side, render_artifacts
    from fluidcore.exports import export_artifacts
    from fluidcore.runs import Run

    def progress(fraction: float, stage: str) -> None:
        inputs.progress(1.0 - RENDER_SHARE + RENDER_SHARE * fraction, stage)

    progress(0.0, "render")  # the run itself is complete; rendering fills the rest
    videos = render_artifacts(inputs.run_dir, inputs.render_dir, eager_videos(Run.open(inputs.run_dir)), progress,
                              fit_long_side(inputs.run_dir), inputs.device)
    progress(1.0, "export")  # a stage of its own, so the job's timings tell rendering from writing files
    return [*videos, *export_artifacts(inputs.run_dir, inputs.render_dir)]


def render(inputs: RunInputs) -> list[Path]:
    """One video of the parent job's run, asked for by a client (`JobType.RENDER`), as the
    parent's own videos are made: at its reconstruction's fit size, progress per rendered frame."""
    from fluidcore.artifacts import fit_long_side, render_artifacts

    video = RenderParams.model_validate(inputs.params).video
    assert inputs.parent_run is not None
    return render_artifacts(inputs.parent_run, inputs.render_dir, [video], inputs.progress, fit_long_side(inputs.parent_run),
                            inputs.device)


def bundle(inputs: RunInputs) -> list[Path]:
    """A sequence of the parent job's run as one zip (`JobType.BUNDLE`), progress per frame;
    named after what it holds, so the parent's artifacts list it under that name."""
    from fluidcore.exports import export_bundle

    plan = params_plan(BundleParams.model_validate(inputs.params))
    assert inputs.parent_run is not None

    def progress(done: int, total: int) -> None:
        inputs.progress(done / total, "bundle")

    return [export_bundle(inputs.parent_run, plan, inputs.render_dir / plan.name, progress)]


def _rendered(run: Callable[[RunInputs], None]) -> Runner:
    """Run a fluidcore job, then render it; its Cancelled and InputError reach the executor as raised."""

    def runner(inputs: RunInputs) -> list[Path]:
        def job_progress(fraction: float, stage: str) -> None:
            inputs.progress((1.0 - RENDER_SHARE) * fraction, stage)

        run(replace(inputs, progress=job_progress))
        return _render(inputs)

    runner.__name__ = run.__name__
    runner.__doc__ = run.__doc__
    return runner


@_rendered
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
        background_frames=params.background_frames,
        world_up=params.world_up,
        simulation=params,  # a ReconstructParams is its SimulationConfig
        solids=params.solids,
        context=inputs.context,
    )


@_rendered
def predict(inputs: RunInputs) -> None:
    from fluidcore.predict.job import run_predict

    params = PredictParams.model_validate(inputs.params)
    run_predict(inputs.parent_run, inputs.run_dir, frames=params.frames, context=inputs.context)


@_rendered
def interact(inputs: RunInputs) -> None:
    from fluidcore.spec.controls import InteractionParams
    from fluidcore.predict.job import run_interact

    params = InteractParams.model_validate(inputs.params)
    run_interact(
        inputs.parent_run,
        inputs.run_dir,
        InteractionParams(wind=params.wind, ball=params.ball),
        frames=params.frames,
        from_frame=params.from_frame,
        context=inputs.context,
    )


@_rendered
def resimulate(inputs: RunInputs) -> None:
    from fluidcore.predict.job import run_resimulate

    run_resimulate(inputs.parent_run, inputs.run_dir, context=inputs.context)


FLUIDCORE_RUNNERS: dict[JobType, Runner] = {
    JobType.RECONSTRUCT: reconstruct,
    JobType.PREDICT: predict,
    JobType.INTERACT: interact,
    JobType.RESIMULATE: resimulate,
    JobType.RENDER: render,
    JobType.BUNDLE: bundle,
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
