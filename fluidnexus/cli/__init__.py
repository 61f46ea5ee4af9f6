"""The `fluidnexus` command line.

Each module of this package owns one group of commands and exposes
`register(app, bench)`. Modules import torch and fluidcore inside the command
bodies only, so `fluidnexus --help` and `fluidnexus serve` start without torch.
"""

from __future__ import annotations

import fluidcore  # noqa: F401  first, before any command imports torch: sets OpenMP's wait policy
import typer

from fluidnexus.cli import benchmarks, camera_commands, generative, interaction, scenes, service

app = typer.Typer(
    name="fluidnexus",
    help="Reconstruct smoke from video, predict it, and ask what-if questions.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
)
bench = typer.Typer(help="Benchmarks: print a table, or one JSON object with --json.", no_args_is_help=True)
app.add_typer(bench, name="bench")



def _print_version(value: bool) -> None:
    if value:
        from fluidcore import __version__

        typer.echo(f"fluidnexus {__version__}")
        raise typer.Exit()


@app.callback()
def _options(
    version: bool = typer.Option(False, "--version", callback=_print_version, is_eager=True, help="Print the version and exit."),
) -> None:
    """Reconstruct smoke from video, predict it, and ask what-if questions."""


for module in (scenes, camera_commands, interaction, generative, service, benchmarks):
    module.register(app, bench)


def main() -> None:
    """Console-script entry point."""
    app()
