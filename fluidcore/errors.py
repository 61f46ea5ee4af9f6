"""How every caller of fluidcore tells a user's mistake from a bug.

`InputError` is the one base of what a user can fix (a field out of range, a file that is not a
video, a frame a run never reached): its message names the field and is shown as it is, by the
CLI (`error: ...`, exit code 2), the API (422) and the worker (the job's error). Every other
exception is a bug, even a `ValueError` from deep inside numpy: `internal_error` logs it with its
traceback under a fresh id and returns the only text a user sees, so no stack, SQL or path text
ever reaches a job's error or a terminal's last line.

Torch-free and importing nothing of fluidcore, so every module (and the API) can name these.
"""

from __future__ import annotations

import logging
import uuid
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from pydantic import ValidationError


class InputError(ValueError):
    """Input a user can fix; the message names the field. A `ValueError` too, for the callers
    that caught that before this base existed."""


def internal_error(log: logging.Logger, exc: BaseException, during: str) -> str:
    """Log `exc` with its traceback under a new id (and what was `during`, e.g. "job 3f2a");
    return "internal error (id ...)", which finds that log entry and says nothing else."""
    incident = uuid.uuid4().hex[:12]
    log.error("internal error (id %s) in %s: %s: %s", incident, during, type(exc).__name__, exc, exc_info=exc)
    return f"internal error (id {incident})"


def describe_validation(exc: ValidationError) -> str:
    """One line for a pydantic `ValidationError` that names each offending field (`wind.strength`,
    `ball.center[2]`, `air_cells`), for an `InputError`: pydantic's own message spans several lines
    with documentation links. A model-level check's message is shown as it was raised
    (after the name of the part it checks, when it checks a nested one)."""
    parts = []
    for error in exc.errors(include_url=False):
        location = ""
        for key in error["loc"]:
            location += f"[{key}]" if isinstance(key, int) else (f".{key}" if location else str(key))
        message = str(error["msg"]).removeprefix("Value error, ")
        parts.append(f"{location}: {message}" if location else message)
    return "; ".join(parts)
