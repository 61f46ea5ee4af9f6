"""Speed of the image metrics and of video I/O: what scoring and the reconstruction loss cost.

    python bench/metrics.py [--threads N] [--repeats R] [--json]

Rows: the SSIM loss (`ssim_tensor`, float32, forward + backward) at render sizes, the scoring
metrics (`ssim` in float64 and `psnr`) per frame at the shared benchmark's 648x1160 size, and
`read_frames` / `write_mp4` frames per second on a generated clip of that size. Times are
medians of R runs after one warm-up, in milliseconds. Logs go to stderr; `--json` prints one
JSON object on stdout.
"""

from __future__ import annotations

import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Callable, Optional

import typer

if __package__ in (None, ""):  # `python bench/metrics.py`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fluidnexus.reporting import echo_json  # noqa: E402

LOSS_SIZES = ((480, 270), (960, 540))  # (width, height) render sizes of the reconstruction loop
SCORE_SIZE = (648, 1160)  # the ScalarFlow benchmark files
VIDEO_FRAMES = 30


def _median_ms(run: Callable[[], object], repeats: int) -> float:
    run()  # warm-up (allocations, lazy imports)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        times.append((time.perf_counter() - start) * 1000.0)
    return statistics.median(times)


def _loss_rows(repeats: int, device: str) -> list[dict[str, Any]]:
    import torch

    from fluidcore.metrics import ssim_tensor

    rows = []
    for (width, height) in LOSS_SIZES:
        for channels in (1, 3):
            pred = torch.rand(height, width, channels, device=device, requires_grad=True)
            target = torch.rand(height, width, channels, device=device)

            def step() -> None:
                ssim_tensor(pred, target).backward()
                if device == "cuda":
                    torch.cuda.synchronize()

            ms = _median_ms(step, repeats)
            rows.append({"what": "ssim_tensor fwd+bwd f32", "device": device, "size": f"{width}x{height}", "channels": channels, "ms": ms})
    return rows


def _score_rows(repeats: int) -> list[dict[str, Any]]:
    import torch

    from fluidcore.metrics import psnr, ssim

    width, height = SCORE_SIZE
    pred, target = torch.rand(2, height, width, 3).unbind(0)
    rows = []
    for name, run in (
        ("ssim gaussian f64", lambda: ssim(pred, target)),
        ("ssim uniform f64", lambda: ssim(pred, target, window="uniform")),
        ("psnr", lambda: psnr(pred, target)),
    ):
        rows.append({"what": name, "device": "cpu", "size": f"{width}x{height}", "channels": 3, "ms": _median_ms(run, repeats)})
    return rows


def _video_rows(repeats: int) -> list[dict[str, Any]]:
    import numpy as np

    from fluidcore.video import read_frames, write_mp4

    width, height = SCORE_SIZE
    y, x = np.mgrid[0:height, 0:width] / width
    frames = np.stack([np.repeat((0.5 + 0.4 * np.sin(8 * x + t / 5) * np.cos(5 * y))[..., None], 3, -1) for t in range(VIDEO_FRAMES)])
    frames = np.round(frames * 255).astype(np.uint8)
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "clip.mp4"
        write_ms = _median_ms(lambda: write_mp4(path, frames), repeats)
        read_ms = _median_ms(lambda: read_frames(path), repeats)
    size = f"{width}x{height}"
    return [
        {"what": "write_mp4 (x264 crf 18)", "device": "cpu", "size": size, "channels": 3, "ms": write_ms, "fps": VIDEO_FRAMES / write_ms * 1000},
        {"what": "read_frames", "device": "cpu", "size": size, "channels": 3, "ms": read_ms, "fps": VIDEO_FRAMES / read_ms * 1000},
    ]


def command(
    repeats: int = typer.Option(3, "--repeats", min=1, help="Timed runs per row (median), after one warm-up."),
    threads: Optional[int] = typer.Option(None, "--threads", min=1, help="CPU threads for torch (default: all cores)."),
    json_output: bool = typer.Option(False, "--json", help="Print one JSON object instead of the table."),
) -> None:
    import torch

    torch.set_num_threads(threads or os.cpu_count() or 1)
    load_before = [round(x, 2) for x in os.getloadavg()]
    print("metrics bench: SSIM loss ...", file=sys.stderr, flush=True)
    rows = _loss_rows(repeats, "cpu")
    if torch.cuda.is_available():
        rows += _loss_rows(repeats, "cuda")
    print("metrics bench: scoring metrics ...", file=sys.stderr, flush=True)
    rows += _score_rows(repeats)
    print("metrics bench: video I/O ...", file=sys.stderr, flush=True)
    rows += _video_rows(repeats)
    report = {"benchmark": "metrics", "threads": torch.get_num_threads(), "cpu_count": os.cpu_count(), "load_average": load_before, "rows": rows}
    if json_output:
        echo_json(report)
        return
    print(f"threads {report['threads']} of {report['cpu_count']} cores, load average before {load_before}")
    print(f"{'what':<26} {'device':<6} {'size':<9} {'C':>2} {'ms':>9} {'fps':>7}")
    for row in rows:
        fps = f"{row['fps']:7.1f}" if "fps" in row else ""
        print(f"{row['what']:<26} {row['device']:<6} {row['size']:<9} {row['channels']:>2} {row['ms']:9.1f} {fps}")


if __name__ == "__main__":
    from bench.registry import run_script

    run_script("metrics", command)
