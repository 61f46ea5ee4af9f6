"""What every fluidcore job shares with its caller (the CLI, the worker, the benchmarks).

A job (`fluidcore.reconstruct.job.run_reconstruct`, `fluidcore.predict.job.run_predict`, ...)
writes a run folder frame by frame. It reports progress as (fraction, stage), asks
`should_cancel()` between frames and raises `Cancelled` after its last checkpoint, so starting
it again resumes; inputs it cannot run on raise `JobInputError`, whose message names the field.

Torch-free, so the worker and the API can name these without loading the science.
"""

from __future__ import annotations

from collections.abc import Callable

Progress = Callable[[float, str], None]
ShouldCancel = Callable[[], bool]
BatchProgress = Callable[[str, int, int], None]  # (stage, batches done, batches in the stage)


class Cancelled(Exception):
    """Raised when should_cancel() said so; the run folder holds every frame finished before."""


class JobInputError(ValueError):
    """Inputs a job cannot run on; the message names the field."""


def no_progress(fraction: float, stage: str) -> None:
    """The progress callback of a caller that does not listen."""


def batch_progress(report: Progress, should_cancel: ShouldCancel | None, job: str) -> BatchProgress:
    """For a stage that works in batches (the generative models): each finished batch is
    reported as the stage's fraction done, and cancelling takes effect after it."""

    def on_batch(stage: str, done: int, total: int) -> None:
        report(done / max(total, 1), stage)
        if should_cancel is not None and should_cancel():
            raise Cancelled(f"{job} cancelled during {stage}; starting it again resumes where it stopped")

    return on_batch


def parse_frames(text: str | None) -> tuple[int, int] | None:
    """'A:B' -> (A, B), the half-open frame range [A, B); None passes through."""
    if text is None:
        return None
    try:
        start, stop = (int(x) for x in text.split(":"))
    except ValueError:
        raise JobInputError(f"frames must look like START:END (e.g. 0:60), got {text!r}") from None
    if start < 0 or stop <= start:
        raise JobInputError(f"frames must satisfy 0 <= START < END, got {text!r}")
    return start, stop
