"""What every fluidcore job shares with its caller (the CLI, the worker, the benchmarks).

A job (`fluidcore.reconstruct.job.run_reconstruct`, `fluidcore.predict.job.run_predict`, ...)
writes a run folder frame by frame under a `JobContext`: it computes on the context's device,
reports progress to it as (fraction, stage), asks it `should_cancel()` between frames and raises
`Cancelled` after its last checkpoint, so starting it again resumes; inputs it cannot run on
raise `JobInputError`, a `fluidcore.errors.InputError` whose message names the field.

Torch-free, so the worker and the API can name these without loading the science.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

from fluidcore.errors import InputError

Progress = Callable[[float, str], None]
ShouldCancel = Callable[[], bool]
BatchProgress = Callable[[str, int, int], None]  # (stage, batches done, batches in the stage)
StepProgress = Callable[[int, int], None]  # (steps done, steps in the stage) of a stage that knows no stage names


class Cancelled(Exception):
    """Raised when should_cancel() said so; the run folder holds every frame finished before."""


class JobInputError(InputError):
    """Inputs a job cannot run on; the message names the field."""


def no_progress(fraction: float, stage: str) -> None:
    """The progress callback of a caller that does not listen."""


def never_cancel() -> bool:
    """The cancellation check of a caller that never cancels."""
    return False


@dataclass(frozen=True)
class JobContext:
    """Where a job computes and who watches it: the one thing every job entry takes besides its
    inputs, so the CLI, the worker and the benchmarks hand the same three over the same way."""

    device: str = "cpu"  # torch device of every tensor the job makes
    progress: Progress = no_progress
    should_cancel: ShouldCancel = never_cancel

    def share(self, start: float, end: float) -> JobContext:
        """This context for one part of a job that spans `start`..`end` of the job's progress: the
        part reports its own 0..1 (a reconstruction's prepare stage, then its frames)."""
        return replace(self, progress=lambda fraction, stage: self.progress(start + (end - start) * fraction, stage))

    def step_progress(self, job: str, stage: str) -> StepProgress:
        """For a stage of counted steps that names no stage itself (the identification's trial
        simulations): each step reported under `stage` as the stage's fraction done, and
        cancelling takes effect after it (`batch_progress`)."""
        on_batch = self.batch_progress(job)
        return lambda done, total: on_batch(stage, done, total)

    def batch_progress(self, job: str) -> BatchProgress:
        """For a stage that works in batches (the generative models): each finished batch is
        reported as the stage's fraction done, and cancelling takes effect after it."""

        def on_batch(stage: str, done: int, total: int) -> None:
            self.progress(done / max(total, 1), stage)
            if self.should_cancel():
                raise Cancelled(f"{job} cancelled during {stage}; starting it again resumes where it stopped")

        return on_batch


def parse_frames(text: str | None, field: str = "frames") -> tuple[int, int] | None:
    """'A:B' -> (A, B), the half-open frame range [A, B); None passes through. `field` names the
    option in the messages."""
    if text is None:
        return None
    try:
        start, stop = (int(x) for x in text.split(":"))
    except ValueError:
        raise JobInputError(f"{field} must look like START:END (e.g. 0:60), got {text!r}") from None
    if start < 0 or stop <= start:
        raise JobInputError(f"{field} must satisfy 0 <= START < END, got {text!r}")
    return start, stop
