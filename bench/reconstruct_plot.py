"""Speed versus error of reconstruction settings, from `bench/reconstruct.py --json` outputs.

    python bench/reconstruct_plot.py RESULT.json [RESULT.json ...] --out docs/bench_reconstruct.png

Each result is one point: x = fitting seconds per frame, y = mean held-out PSNR, labelled with
its iterations per frame and render resolution; the blank-frame PSNR of the same frames is
drawn as a reference line, with the published HyFluid and PINF numbers on the same views and
frames when the results carry them.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import typer


def _label(result: dict) -> str:
    from fluidcore.spec.reconstruct import ReconstructConfig, quality_fields

    quality = ReconstructConfig.model_validate(quality_fields(result["quality"]))  # older results: flat
    fit = quality.fit
    return f"{fit.position_iterations}+{fit.appearance_iterations} it, {fit.long_side} px, sym {quality.priors.symmetry_views}"


def command(
    results: list[Path] = typer.Argument(..., exists=True, help="JSON files written by bench/reconstruct.py --json."),
    out: Path = typer.Option(..., "--out", help="PNG to write."),
) -> None:
    """Plot held-out PSNR against fitting seconds per frame."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    loaded = [json.loads(path.read_text()) for path in results]
    fig, ax = plt.subplots(figsize=(6.5, 4.0), dpi=120)
    for result in loaded:
        x, y = result["fit_seconds_per_frame"], result["mean_held_out"]["psnr"]
        ax.scatter([x], [y], color="tab:blue")
        ax.annotate(_label(result), (x, y), textcoords="offset points", xytext=(4, 4), fontsize=7)
    blank = sum(r["mean_held_out"]["blank_psnr"] for r in loaded) / len(loaded)
    ax.axhline(blank, color="grey", linestyle="--", linewidth=1, label=f"blank frame ({blank:.2f} dB)")
    anchors = loaded[0].get("anchors_same_frames") or {}
    for method, color in (("hyfluid", "tab:orange"), ("pinf", "tab:green")):
        if method in anchors:
            value = anchors[method]["psnr"]
            ax.axhline(value, color=color, linestyle=":", linewidth=1, label=f"{method}, same frames ({value:.2f} dB)")
    ax.margins(x=0.3)
    ax.set_xlabel("fitting seconds per frame (2-core CPU)")
    ax.set_ylabel("mean held-out PSNR (dB)")
    ax.set_title("Reconstruction: speed vs novel-view error", fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    print(out, file=sys.stderr)


if __name__ == "__main__":
    typer.run(command)
