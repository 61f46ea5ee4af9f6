"""`fluidnexus bench NAME`: one sub-command per benchmark declared in `bench.registry`, the same
`command` function that `python bench/NAME.py` runs, with the same description."""

from __future__ import annotations

import typer

from bench.registry import BENCHMARKS, load_command


def register(app: typer.Typer, bench: typer.Typer) -> None:
    """Add one `bench` sub-command per registered benchmark."""
    for name, description in BENCHMARKS.items():
        bench.command(name, help=description)(load_command(name))
