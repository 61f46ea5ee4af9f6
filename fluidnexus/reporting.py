"""How a command line reports: bad input as one clear line on stderr and exit code 2 (no
traceback), a bug as its traceback and `error: internal error (id ...)` on stderr and exit code 1,
results on stdout as text or, with --json, as one JSON object (logs go to stderr).

Both the `fluidnexus` commands and the benchmarks (`python bench/NAME.py`) report this way. It
lives outside `fluidnexus.cli` because the CLI loads every benchmark: a benchmark that imported
the CLI package for these helpers would load the CLI, and the benchmarks again, from inside itself."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import typer

from fluidcore.errors import InputError, internal_error

log = logging.getLogger("fluidnexus.cli")
# A command's own ways out (typer.Exit is a RuntimeError): never taken for bugs.
COMMAND_EXITS = (typer.Exit, typer.Abort, typer.TyperException)


class UserError(InputError):
    """An option the command line itself refuses; its message is shown as is."""


@contextmanager
def user_errors(*kinds: type[BaseException]) -> Iterator[None]:
    """Turn an `InputError` (and the given exception types) into `error: message` and exit 2.

    Anything else is a bug, whatever its type (a ValueError from deep inside numpy too): its
    traceback goes to the log (stderr) under an id, and the command exits 1 naming that id."""
    try:
        yield
    except (InputError, *kinds) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(code=2) from None
    except COMMAND_EXITS:
        raise
    except Exception as exc:
        reported = internal_error(log, exc, "a fluidnexus command")
        typer.echo(f"error: {reported}: not a problem with the input; the traceback above shows where", err=True)
        raise typer.Exit(code=1) from None


def check_device(device: str) -> None:
    """Refuse a torch device this machine does not have (a CPU-only torch asked for cuda) with
    one line, before any work, instead of a traceback from deep inside the first kernel."""
    import torch

    try:
        parsed = torch.device(device)
    except (RuntimeError, ValueError):
        raise UserError(f"--device {device!r} is not a torch device (cpu, cuda, cuda:1, ...)") from None
    if parsed.type != "cuda":
        return
    if not torch.cuda.is_available():
        raise UserError(f"--device {device}: no CUDA device available to this torch ({torch.__version__}); use --device cpu")
    if parsed.index is not None and parsed.index >= torch.cuda.device_count():
        raise UserError(f"--device {device}: only {torch.cuda.device_count()} CUDA device(s) here")


def emit(as_json: bool, text: str, **fields: object) -> None:
    """A command's result on stdout: `text` for people, or the fields as one JSON object (--json)."""
    if as_json:
        echo_json(fields)
    else:
        typer.echo(text)


def run_fields(path: object) -> dict[str, object]:
    """What --json reports about a run folder a command wrote: path, kind, frames, parent, and a
    reconstruction's health report (`fluidcore.health`)."""
    from fluidcore.health import report
    from fluidcore.runs import Run

    run = Run.open(path)
    frames = run.frames()
    health = report(run, audience="cli")
    return {
        "run": str(path),
        "kind": run.kind,
        "frames": [frames[0], frames[-1]] if frames else [],
        "parent": None if run.parent is None else str(run.parent.path),
        "settings": run.settings.model_dump(mode="json", include={"branch_frame", "wind", "ball"}),
        **({} if health is None else {"health": health}),
    }


def emit_run(as_json: bool, path: object) -> None:
    """A command's run folder on stdout (`emit` of `run_fields`); without --json, a
    reconstruction's health warnings and notes follow on stderr, one per line."""
    fields = run_fields(path)
    emit(as_json, str(path), **fields)
    health = fields.get("health")
    if not as_json and health:
        for level in ("warnings", "notes"):
            for message in health[level]:
                typer.echo(f"{level[:-1]}: {message}", err=True)


def echo_json(obj: object) -> None:
    """Print one JSON object on stdout (the `--json` convention: nothing else goes to stdout)."""
    import json

    typer.echo(json.dumps(obj, indent=2, sort_keys=True, default=_jsonable))


def _jsonable(value: object) -> object:
    tolist: Callable[[], object] | None = getattr(value, "tolist", None)
    if tolist is not None:
        return tolist()
    return str(value)
