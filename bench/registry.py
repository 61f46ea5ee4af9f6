"""The benchmarks, declared once: each name is `bench/NAME.py`, whose `command` function is both
`python bench/NAME.py` and `fluidnexus bench NAME`, with the one-line description both show.

The CLI builds its `bench` sub-commands from `BENCHMARKS`; a benchmark module imports nothing of
the CLI (its reporting helpers are in `fluidnexus.reporting`), so loading one never loads the
other. Add a benchmark by writing `bench/NAME.py` with a `command` and adding its line here."""

from __future__ import annotations

import importlib
from collections.abc import Callable

import typer

BENCHMARKS: dict[str, str] = {
    "reconstruct": "Reconstruct from the input view(s), then PSNR/SSIM on every other camera with ground truth.",
    "predict": "Reconstruct the observed frames, predict the future ones, score them per view and horizon.",
    "generalise": "Novel views, input-view fit, future, velocity, what-ifs and rise on one scene, with baselines.",
    "source": "The source's radius and centre as estimated from one view, against the truth.",
    "metrics": "Time SSIM/PSNR (loss and scoring) and video decode/encode.",
    "frame_rate": "One plume simulated at several frame rates: its rise, substeps and the speed limit's hold.",
    "physics": "Benchmark the PBF simulator: steps/s and density error vs particles and iterations.",
    "render": "Time fluidcore.render forward + backward on a smoke plume.",
    "generative": "Seconds per frame and peak memory of novel-view generation and video refinement.",
    "load": "Requests/s and p50/p99 per route under concurrent polling, listing and uploads.",
    "upload_attacks": "Peak API memory and time to refuse four concurrent hostile uploads.",
    "whatif_render": "Simulate and render `--repeats` what-ifs of RUN, by function and as jobs; print the medians.",
}


def load_command(name: str) -> Callable[..., None]:
    """The `command` function of `bench/NAME.py` (importing the module: its options are its signature)."""
    return importlib.import_module(f"bench.{name}").command


def run_script(name: str, command: Callable[..., None]) -> None:
    """`python bench/NAME.py`: the module's own `command` (not a second import of it) as a one-command
    program with the registered description, what `typer.run` would make of it with that help."""
    app = typer.Typer(add_completion=False)
    app.command(help=BENCHMARKS[name])(command)
    app()
