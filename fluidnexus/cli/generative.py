"""`fluidnexus models` (what the models folder enables) and `fluidnexus finetune novel-view | refine`
(LoRA adapters for the generative priors, fluidcore.generative)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from fluidnexus.reporting import echo_json, user_errors

ModelsDir = Annotated[
    Path | None, typer.Option("--models", help="models folder (default: $FLUIDNEXUS_MODELS or ./models)")
]


def register(app: typer.Typer, bench: typer.Typer) -> None:
    """Add `models` and the `finetune` group."""
    app.command("models")(models)
    finetune = typer.Typer(help="LoRA fine-tuning of the generative priors on multi-view captures.", no_args_is_help=True)
    for kind in FINETUNE_HELP:
        finetune.command(kind)(finetune_command(kind))
    app.add_typer(finetune, name="finetune")


def models(
    models_dir: ModelsDir = None,
    as_json: Annotated[bool, typer.Option("--json", help="one JSON object instead of the table")] = False,
) -> None:
    """List the generative models found in the models folder, what each enables and what is missing."""
    from fluidcore import weights
    from fluidcore.generative import models as registry

    root = models_dir or weights.weights_dir()
    entries = registry.inventory(root)
    if as_json:
        echo_json({"models_dir": str(root), "models": [e.to_json() for e in entries]})
        return
    typer.echo(f"models folder: {root.resolve()}")
    for e in entries:
        state = "present" if e.present else "missing: " + ", ".join(e.missing)
        typer.echo(f"\n{e.name:<10} {state}")
        typer.echo(f"{'':<10} folder: {e.path}")
        typer.echo(f"{'':<10} LoRA adapter: {e.adapter or 'none (base weights)'}")
        for note in e.notes:
            typer.echo(f"{'':<10} {note}")
        verb = "enables" if e.present else "would enable"
        for stage in e.stages:
            typer.echo(f"{'':<10} {verb} {stage}")


def _finetune(kind: str, data: Path, out: Path, steps: int, models_dir: Path | None, options: dict) -> None:
    from fluidcore.generative import finetune

    with user_errors():
        result = finetune.run(
            kind, data, out, steps=steps, models_root=models_dir, progress=lambda line: typer.echo(line, err=True), **options
        )
    typer.echo(str(result))


Data = Annotated[Path, typer.Option("--data", help="a scene folder (transforms.json + videos) or a folder of them")]
Out = Annotated[Path, typer.Option("--out", help="adapter folder; a checkpoint there is resumed")]
Steps = Annotated[
    int, typer.Option("--steps", min=1, max=100_000, help="optimiser steps in total (a resumed run counts its earlier ones)")
]
Rank = Annotated[int, typer.Option("--rank", min=1, max=256, help="LoRA rank")]
LearningRate = Annotated[float, typer.Option("--lr", min=1e-7, max=1e-1, help="Adam learning rate")]
Device = Annotated[str, typer.Option("--device", help="torch device: cpu, cuda, ...")]
Seed = Annotated[int, typer.Option("--seed")]
Exclude = Annotated[
    list[str], typer.Option("--exclude", help="camera held out for measuring (never trained on); repeat for several")
]


FINETUNE_HELP = {
    "novel-view": "Fit a LoRA adapter of the Zero123 UNet to pairs of views of the same frame.",
    "refine": "Fit a LoRA adapter of the CogVideoX transformer to clips of the captured videos.",
}


def finetune_command(kind: str):  # noqa: ANN201 - a typer command function
    """The `fluidnexus finetune KIND` command: both kinds take the same options."""

    def command(
        data: Data, out: Out, steps: Steps = 500, rank: Rank = 16, lr: LearningRate = 1e-4, device: Device = "cpu",
        seed: Seed = 0, models_dir: ModelsDir = None, exclude: Exclude = [],  # noqa: B006 - typer only reads it
    ) -> None:
        options = {"rank": rank, "learning_rate": lr, "device": device, "seed": seed, "exclude": exclude}
        _finetune(kind, data, out, steps, models_dir, options)

    command.__doc__ = FINETUNE_HELP[kind]
    return command
