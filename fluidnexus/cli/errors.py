"""How the command line reports bad input: one clear line on stderr and exit code 2, no traceback."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager

import typer


class UserError(Exception):
    """An input problem the user can fix; its message is shown as is."""


@contextmanager
def user_errors(*kinds: type[BaseException]) -> Iterator[None]:
    """Turn UserError (and the given exception types) into `error: message` and exit 2."""
    try:
        yield
    except (UserError, *kinds) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(code=2) from None


def echo_json(obj: object) -> None:
    """Print one JSON object on stdout (the `--json` convention: nothing else goes to stdout)."""
    import json

    typer.echo(json.dumps(obj, indent=2, sort_keys=True, default=_jsonable))


def _jsonable(value: object) -> object:
    tolist: Callable[[], object] | None = getattr(value, "tolist", None)
    if tolist is not None:
        return tolist()
    return str(value)
