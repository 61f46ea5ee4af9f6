"""Commands registered by this module (filled in by its owner)."""

from __future__ import annotations

import typer


def register(app: typer.Typer, bench: typer.Typer) -> None:
    """Add this module's commands to the top-level app and the bench group."""
