"""`fluidnexus bench generative` (= `python bench/generative.py`): time and memory of the generative priors.

Two rows, one per pipeline of `fluidcore.generative`:

    novel_view  Zero123-style generation of VIEWS target cameras x FRAMES time steps from one input
                view (DDIM, --steps, classifier-free guidance), in batches of --batch-size items
    refine      CogVideoX video-to-video refinement of one window of the model's length
                (--strength x --steps denoising steps actually run, classifier-free guidance)

`seconds_per_frame` is the timed call's wall-clock time divided by the frames it produced (one
generated view of one time step, or one refined frame). Each pipeline runs once untimed with one
step first (the first call pays for kernel selection and allocator growth). `peak_memory_mb`: on
CUDA, torch's peak allocated memory during the timed call; on CPU, the peak resident set size of
the process during the call minus the resident size before it (sampled every 5 ms).

Models: `--size tiny` (default) builds small random models (a smoke test of the whole path on
CPU: the numbers say nothing about real models); `--size full` builds the real architectures with
random weights (Zero123-XL: SD 1.x UNet + CLIP ViT-L/14 at 256x256; CogVideoX-2b at 720x480 x 49
frames), which costs what trained weights cost; `--models DIR` loads the weights of a models folder
instead. float16 on CUDA and float32 on CPU unless --dtype says otherwise.
"""

from __future__ import annotations

import math
import os
import sys
import threading
import time
from pathlib import Path
from typing import Any, Optional

import typer

import fluidcore  # noqa: F401  first, before torch: sets OpenMP's passive wait policy (see fluidcore/__init__.py)
from fluidnexus.reporting import UserError, echo_json, user_errors

if __package__ in (None, ""):  # `python bench/generative.py`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

DTYPES = ("float32", "float16", "bfloat16")


class PeakMemory:
    """Peak memory (MB) of the work inside the `with` block: CUDA allocator peak, or sampled RSS."""

    def __init__(self, device: str) -> None:
        self.device = device
        self.peak_mb = 0.0
        self._stop = threading.Event()

    def __enter__(self) -> PeakMemory:
        import torch

        if self.device.startswith("cuda"):
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
            self._base = torch.cuda.memory_allocated()
        else:
            self._base = _rss()
            self._high = self._base
            self._thread = threading.Thread(target=self._sample, daemon=True)
            self._thread.start()
        return self

    def _sample(self) -> None:
        while not self._stop.wait(0.005):
            self._high = max(self._high, _rss())

    def __exit__(self, *exc: object) -> None:
        import torch

        if self.device.startswith("cuda"):
            torch.cuda.synchronize()
            self.peak_mb = torch.cuda.max_memory_allocated() / 2**20
        else:
            self._stop.set()
            self._thread.join()
            self.peak_mb = (max(self._high, _rss()) - self._base) / 2**20


def _rss() -> int:
    with open("/proc/self/statm") as handle:
        return int(handle.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def load_models(size: str, models_dir: Path | None, device: str, dtype) -> tuple[Any, Any]:  # noqa: ANN001 - torch.dtype
    from fluidcore.generative import models, random_weights

    if models_dir is not None:
        return models.load_novel_view(models_dir, device, dtype), models.load_video(models_dir, device, dtype)
    return random_weights.build_novel_view(size, device, dtype), random_weights.build_video(size, device, dtype)


def ring_cameras(n: int, width: int, height: int) -> list:
    """`n + 1` cameras on a circle around the origin; the first is the input view."""
    import numpy as np

    from fluidcore.cameras import Camera, look_at

    like = Camera("like", 1.2 * width, 1.2 * width, width / 2, height / 2, width, height, np.eye(4))
    return [look_at((2 * math.sin(a), 0.3, -2 * math.cos(a)), (0, 0, 0), (0, 1, 0), like, f"view_{i}")
            for i, a in enumerate(np.linspace(0, 2 * math.pi, n + 1, endpoint=False))]


def time_novel_view(model: Any, views: int, frames: int, steps: int, batch_size: int, device: str) -> dict[str, Any]:
    import numpy as np
    import torch

    from fluidcore.generative.novel_view import SamplingOptions, generate_views

    cameras = ring_cameras(views, model.size, model.size)
    video = torch.rand(frames, model.size, model.size, 3, generator=torch.Generator().manual_seed(0))
    center, up = np.zeros(3), np.array([0.0, 1.0, 0.0])
    generate_views(model, video[:1], cameras[0], cameras[1:2], center, up, SamplingOptions(steps=1, batch_size=1))
    with PeakMemory(device) as memory:
        began = time.perf_counter()
        generate_views(model, video, cameras[0], cameras[1:], center, up, SamplingOptions(steps=steps, batch_size=batch_size))
        _sync(device)
        seconds = time.perf_counter() - began
    items = views * frames
    return {"pipeline": "novel_view", "frames_out": items, "size": f"{model.size}x{model.size}", "steps": steps,
            "batch_size": batch_size, "seconds": round(seconds, 3), "seconds_per_frame": round(seconds / items, 4),
            "peak_memory_mb": round(memory.peak_mb, 1)}


def time_refine(model: Any, steps: int, strength: float, device: str) -> dict[str, Any]:
    import torch

    from fluidcore.generative.refine import RefineOptions, refine_video

    width, height = model.size
    video = torch.rand(model.window, height, width, 3, generator=torch.Generator().manual_seed(0))
    refine_video(model, video, RefineOptions(strength=1.0, steps=1))
    with PeakMemory(device) as memory:
        began = time.perf_counter()
        refine_video(model, video, RefineOptions(strength=strength, steps=steps))
        _sync(device)
        seconds = time.perf_counter() - began
    return {"pipeline": "refine", "frames_out": model.window, "size": f"{width}x{height}", "steps": int(steps * strength),
            "batch_size": 1, "seconds": round(seconds, 3), "seconds_per_frame": round(seconds / model.window, 4),
            "peak_memory_mb": round(memory.peak_mb, 1)}


def _sync(device: str) -> None:
    import torch

    if device.startswith("cuda"):
        torch.cuda.synchronize()


def command(
    size: str = typer.Option("tiny", "--size", help="tiny (CPU smoke test) or full (real architectures, random weights)."),
    models_dir: Optional[Path] = typer.Option(None, "--models", help="Time the weights of this models folder instead."),
    device: str = typer.Option("cpu", "--device", help="cpu or cuda."),
    dtype: Optional[str] = typer.Option(
        None, "--dtype", help="float32, float16 or bfloat16 (default: float16 on CUDA, float32 on CPU)."
    ),
    steps: int = typer.Option(50, "--steps", min=1, max=1000, help="Denoising steps (refinement runs steps x strength)."),
    strength: float = typer.Option(
        0.75, "--strength", min=0.01, max=1.0, help="Refinement strength (0.75: futures, 0.5: views)."
    ),
    views: int = typer.Option(4, "--views", min=1, max=64, help="Target cameras for novel views."),
    frames: int = typer.Option(2, "--frames", min=1, max=64, help="Time steps per target camera."),
    batch_size: int = typer.Option(8, "--batch-size", min=1, max=256, help="Novel-view items per batch."),
    threads: Optional[int] = typer.Option(None, "--threads", min=1, help="CPU threads (default: all cores)."),
    json_output: bool = typer.Option(False, "--json", help="Print one JSON object instead of the table."),
) -> None:
    import torch

    with user_errors():
        if size not in ("tiny", "full"):
            raise UserError(f"--size must be tiny or full, got {size!r}")
        if dtype is not None and dtype not in DTYPES:
            raise UserError(f"--dtype must be one of {', '.join(DTYPES)}, got {dtype!r}")
        if device.startswith("cuda") and not torch.cuda.is_available():
            raise UserError("--device cuda: no CUDA device here")
        torch.set_num_threads(threads or os.cpu_count() or 1)
        load_before = [round(x, 2) for x in os.getloadavg()]  # other work on the machine, before ours
        chosen = getattr(torch, dtype or ("float16" if device.startswith("cuda") else "float32"))
        _log(f"generative bench: building {size if models_dir is None else models_dir} models on {device} ({chosen}) ...")
        began = time.perf_counter()
        novel, video = load_models(size, models_dir, device, chosen)
        load_seconds = time.perf_counter() - began
        _log("generative bench: novel views ...")
        rows = [time_novel_view(novel, views, frames, steps, batch_size, device)]
        del novel
        _log("generative bench: refinement ...")
        rows.append(time_refine(video, steps, strength, device))
    report: dict[str, Any] = {
        "benchmark": "generative",
        "models": str(models_dir) if models_dir is not None else f"random {size}",
        "device": torch.cuda.get_device_name() if device.startswith("cuda") else "cpu",
        "dtype": str(chosen).removeprefix("torch."),
        "threads": torch.get_num_threads(),
        "cpu_count": os.cpu_count(),
        "load_average": load_before,
        "load_seconds": round(load_seconds, 2),
        "rows": rows,
    }
    if json_output:
        echo_json(report)
        return
    typer.echo(f"{report['models']} models on {report['device']} ({report['dtype']}), threads {report['threads']} of "
               f"{report['cpu_count']} cores, built/loaded in {report['load_seconds']} s")
    columns = ("pipeline", "size", "frames_out", "steps", "batch_size", "seconds", "seconds_per_frame", "peak_memory_mb")
    typer.echo("  ".join(f"{c:>17}" for c in columns))
    for row in rows:
        typer.echo("  ".join(f"{row[c]!s:>17}" for c in columns))


if __name__ == "__main__":
    from bench.registry import run_script

    run_script("generative", command)
