"""`fluidnexus bench NAME`: each benchmark lives in `bench/NAME.py` and exposes a typer-style
`command` function, so `python bench/NAME.py` and `fluidnexus bench NAME` are one program."""

from __future__ import annotations

import importlib

import typer

BENCHMARKS: tuple[str, ...] = (
    "reconstruct", "predict", "generalise", "source", "metrics", "physics", "render", "generative", "load", "upload_attacks",
    "whatif_render",
)


def register(app: typer.Typer, bench: typer.Typer) -> None:
    """Add one `bench` sub-command per benchmark module."""
    for name in BENCHMARKS:
        module = importlib.import_module(f"bench.{name}")
        bench.command(name)(module.command)
