"""`fluidnexus bench whatif_render` (= `python bench/whatif_render.py`): where a what-if job's
time goes, simulating against rendering its published videos.

It does what the worker does for an interact job: `run_interact` on a reconstruction's run
folder, then `fluidcore.artifacts.render_artifacts` at the size the worker asks for
(`fit_long_side`), timing each (wall seconds, and CPU seconds of the process, which another
user's load on a shared machine changes far less), `--repeats` times on fresh folders.
`render_share` is the rendering's part of the two together (`render_cpu_share` in CPU time);
issue 24 asks for at most a third at preview quality on the 2-core machine. Where
`render_artifacts` takes only the two folders (the code before issue 24: every camera at full
size, a 120-frame orbit) it is called so; docs/bench_render.md's "before" row is this script at
commit b60e0d9 (whose `run_interact` still took `wind=`) on fluidcore of commit 9f10de6.
`--json` prints one JSON object.
"""

from __future__ import annotations

import inspect
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import typer

import fluidcore  # noqa: F401  first, before torch: sets OpenMP's passive wait policy (see fluidcore/__init__.py)

DEFAULT_WIND = '{"direction": [1, 0, 0], "strength": 0.5}'
KEYS = ("simulate_s", "render_s", "render_share", "simulate_cpu_s", "render_cpu_s", "render_cpu_share")  # medians


def measure(parent: Path, frames: int, wind: str, folder: Path) -> dict[str, Any]:
    """One what-if: seconds simulating, seconds rendering, and what was rendered."""
    from fluidcore import artifacts
    from fluidcore.interaction import parse_interaction
    from fluidcore.predict import run_interact
    from fluidcore.video import probe

    params = parse_interaction(json.loads(wind), None)
    start, cpu_start = time.perf_counter(), time.process_time()
    run_dir = run_interact(parent, folder / "run", params, frames=frames)
    simulated, cpu_simulated = time.perf_counter(), time.process_time()
    supported = inspect.signature(artifacts.render_artifacts).parameters
    extra = {"long_side": artifacts.fit_long_side(run_dir)} if "long_side" in supported else {}  # absent before issue 24
    files = artifacts.render_artifacts(run_dir, folder / "videos", **extra)
    rendered, cpu_rendered = time.perf_counter(), time.process_time()
    infos = [probe(f) for f in files]
    simulate_s, render_s = simulated - start, rendered - simulated
    simulate_cpu_s, render_cpu_s = cpu_simulated - cpu_start, cpu_rendered - cpu_simulated
    return {
        "simulate_s": simulate_s,
        "render_s": render_s,
        "render_share": render_s / (simulate_s + render_s),
        "simulate_cpu_s": simulate_cpu_s,
        "render_cpu_s": render_cpu_s,
        "render_cpu_share": render_cpu_s / (simulate_cpu_s + render_cpu_s),
        "videos": len(files),
        "video_frames": sum(i.n_frames for i in infos),
        "pixels_per_frame": max(i.width * i.height for i in infos),
    }


def command(
    run: Path = typer.Option(..., "--run", exists=True, file_okay=False, help="A reconstruction's run folder to branch."),
    frames: int = typer.Option(30, "--frames", min=1, max=1000, help="New frames of the what-if."),
    wind: str = typer.Option(DEFAULT_WIND, "--wind", help="The what-if's wind (JSON, as `fluidnexus interact --wind`)."),
    repeats: int = typer.Option(3, "--repeats", min=1, max=20, help="What-ifs to time (medians)."),
    threads: int | None = typer.Option(None, "--threads", min=1, help="CPU threads (default: all cores)."),
    json_output: bool = typer.Option(False, "--json", help="Print one JSON object instead of the table."),
) -> None:
    """Simulate and render `--repeats` what-ifs of RUN; print the medians."""
    import torch

    if threads is not None:
        torch.set_num_threads(threads)
    rows = []
    for i in range(repeats):
        with tempfile.TemporaryDirectory(prefix="fluidnexus-bench-whatif-") as tmp:
            rows.append(measure(run, frames, wind, Path(tmp)))
        print(f"what-if {i + 1}/{repeats}: {rows[-1]['simulate_s']:.1f} s simulate, {rows[-1]['render_s']:.1f} s render", file=sys.stderr)
    report: dict[str, Any] = {
        "run": str(run), "frames": frames, "wind": json.loads(wind), "repeats": repeats,
        "threads": torch.get_num_threads(), "cpu_count": os.cpu_count(), "load_average": [round(x, 2) for x in os.getloadavg()],
        **{key: statistics.median(r[key] for r in rows) for key in KEYS},
        **{key: rows[0][key] for key in ("videos", "video_frames", "pixels_per_frame")},
        "rows": rows,
    }
    if json_output:
        from fluidnexus.cli.errors import echo_json

        echo_json(report)
        return
    typer.echo(f"threads {report['threads']} of {report['cpu_count']} cores, load average {report['load_average']}")
    typer.echo(table(report))


def table(report: dict[str, Any]) -> str:
    """The medians as one markdown row under its header."""
    header = "| simulate s | render s | render share | simulate CPU s | render CPU s | render CPU share | videos | video frames | pixels per frame |"
    row = (f"| {report['simulate_s']:.2f} | {report['render_s']:.2f} | {report['render_share']:.2f} "
           f"| {report['simulate_cpu_s']:.2f} | {report['render_cpu_s']:.2f} | {report['render_cpu_share']:.2f} "
           f"| {report['videos']} | {report['video_frames']} | {report['pixels_per_frame']} |")
    return "\n".join([header, "|" + "---:|" * 9, row])


if __name__ == "__main__":
    typer.run(command)
