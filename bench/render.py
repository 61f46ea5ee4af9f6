"""`fluidnexus bench render` (= `python bench/render.py`): forward + backward time of fluidcore.render.

The scene is what reconstruction renders: a rising smoke plume of many small, semi-transparent
Gaussians (about 12 % peak opacity; standard deviation half the mean particle spacing, so that
neighbours overlap into a smooth density and coverage does not depend on N), seen by a portrait
camera that frames the plume like the ScalarFlow views. Images of the
same camera at other sizes scale its intrinsics, so the pixel footprint of every Gaussian grows
with the resolution as it would in a real run.

Each row times `render` (projection + tile binning + compositing, forward) and the backward pass
of an image loss, and separately the compositing stage alone (forward + backward), which is where
the channel count matters. Like reconstruction, it renders image and alpha without the depth map
unless `--depth` asks for it (depth is one more composited channel). The default sweep covers
{10k, 100k} Gaussians x {270x480, 540x960, 1080x1920} x {1, 3} channels on every available
backend and device, plus the 20k / 270x480 / 1 channel target row and the torch-reference
compositor at the smallest size (to show what the fused kernel buys). `--json` prints one JSON
object; with a single configuration its fields are also at the top level (`ms_forward_backward`,
...). Progress goes to stderr.

Columns: `coverage` is the fraction of pixels with alpha > 0.01, `pairs` the number of (tile,
Gaussian) pairs after binning, `ms_*` medians of wall-clock time (`_min`: the fastest run, the
least disturbed by other work on a shared machine), `cpu_ms_forward_backward` the CPU time of all
threads (with one thread, the compute cost itself; with more, it includes OpenMP spin-waiting),
`ms_composite` / `cpu_ms_composite` the compositing stage alone (forward + backward).
"""

from __future__ import annotations

import itertools
import math
import os
import statistics
import sys
import time
from typing import Any, Optional

import typer

import fluidcore  # noqa: F401  first, before torch: sets OpenMP's passive wait policy (see fluidcore/__init__.py)
from fluidnexus.reporting import echo_json

SIZES = ((270, 480), (540, 960), (1080, 1920))
COUNTS = (10_000, 100_000)
CHANNELS = (1, 3)
BACKENDS = ("torch", "torch-reference", "gsplat")
TARGET = {"gaussians": 20_000, "size": (270, 480), "channels": 1, "ms": 150.0}
PLUME_HEIGHT = 1.0  # world units; the camera frames it at 80 % of the image height
PEAK_OPACITY_LOGIT = -2.0  # sigmoid(-2) = 0.12


def plume(n: int, channels: int, seed: int = 0, device: str = "cpu"):
    """A smoke plume: a column widening with height, denser near the source, twisted by a swirl."""
    import torch

    from fluidcore.render import Gaussians

    gen = torch.Generator().manual_seed(seed)
    height = PLUME_HEIGHT * torch.rand(n, generator=gen) ** 1.5
    radius = (0.06 + 0.2 * height) * torch.sqrt(torch.rand(n, generator=gen))
    angle = 2 * math.pi * torch.rand(n, generator=gen) + 3.0 * height
    means = torch.stack([radius * torch.cos(angle) + 0.05 * torch.sin(6 * height), height, radius * torch.sin(angle)], 1)
    volume = math.pi * 0.16**2 * PLUME_HEIGHT
    spacing = (volume / n) ** (1 / 3)
    g = Gaussians(
        means=means,
        log_scales=math.log(0.5 * spacing) + 0.3 * torch.randn(n, 3, generator=gen),
        quats=torch.randn(n, 4, generator=gen),
        opacity_logits=PEAK_OPACITY_LOGIT + 0.5 * torch.randn(n, generator=gen),
        colors=(0.8 + 0.1 * torch.randn(n, channels, generator=gen)).clamp(0, 1),
    )
    return Gaussians(*(t.to(device).requires_grad_(True) for t in (g.means, g.log_scales, g.quats, g.opacity_logits, g.colors)))


def plume_camera(width: int, height: int):
    """A camera 1.6 units from the plume axis, slightly above its middle, framing it at 80 %."""
    import numpy as np

    from fluidcore.cameras import Camera, look_at

    distance = 1.6
    focal = 0.8 * height * distance / PLUME_HEIGHT
    like = Camera("bench", focal, focal, width / 2, height / 2, width, height, np.eye(4))
    return look_at([0.0, 0.6, distance], [0.0, 0.5 * PLUME_HEIGHT, 0.0], [0.0, 1.0, 0.0], like, "bench")


def measure(
    gaussians: int, size: tuple[int, int], channels: int, backend: str, device: str, repeats: int, depth: bool
) -> dict[str, Any]:
    """Median timings (ms) of one configuration, after one warm-up run."""
    import torch

    from fluidcore.render import render

    g = plume(gaussians, channels, device=device)
    camera = plume_camera(*size)
    forward, backward, cpu = [], [], []
    for i in range(repeats + 1):
        _sync(device)
        start, cpu_start = time.perf_counter(), time.process_time()
        out = render(g, camera, background=0.0, backend=backend, depth=depth)
        _sync(device)
        middle = time.perf_counter()
        (out.image.mean() + 0.1 * out.alpha.mean()).backward()
        _sync(device)
        end, cpu_end = time.perf_counter(), time.process_time()
        if i > 0:
            forward.append(1e3 * (middle - start))
            backward.append(1e3 * (end - middle))
            cpu.append(1e3 * (cpu_end - cpu_start))
        for tensor in (g.means, g.log_scales, g.quats, g.opacity_logits, g.colors):
            tensor.grad = None
    row: dict[str, Any] = {
        "backend": backend,
        "device": device,
        "threads": torch.get_num_threads() if device == "cpu" else None,
        "gaussians": gaussians,
        "size": f"{size[0]}x{size[1]}",
        "channels": channels,
        "depth": depth,
        "coverage": round(float((out.alpha > 0.01).float().mean()), 3),
        "ms_forward": statistics.median(forward),
        "ms_backward": statistics.median(backward),
        "ms_forward_backward": statistics.median(f + b for f, b in zip(forward, backward)),
        "ms_forward_backward_min": min(f + b for f, b in zip(forward, backward)),  # least disturbed run
        # CPU time of all threads: on a shared machine wall time grows with other people's load,
        # CPU time much less; wall time >= cpu_ms / threads.
        "cpu_ms_forward_backward": statistics.median(cpu),
    }
    if backend == "gsplat":  # gsplat's compositor is not separable from its own pipeline
        row.update({"ms_composite": None, "cpu_ms_composite": None, "pairs": None})
    else:
        row.update(_composite_stage(g, camera, backend, repeats, depth))
    return row


def _composite_stage(g, camera, backend: str, repeats: int, depth: bool) -> dict[str, Any]:
    """Forward + backward of the compositor alone, on the projection and bins of the real scene."""
    import torch

    from fluidcore.render.projection import covariance_3d, project
    from fluidcore.render.rasterize import composite, fused_available
    from fluidcore.render.tiles import bin_gaussians

    with torch.no_grad():
        covariances = covariance_3d(g.scales(), g.unit_quats())
        p = project(g.means, covariances, g.opacities(), camera.viewmat(g.device), camera.intrinsics(g.device), camera.width, camera.height)
        bins = bin_gaussians(p.bboxes, p.depths, p.visible, camera.width, camera.height)
    for tensor in (p.means2d, p.conics, p.opacities):
        tensor.requires_grad_(True)
    features = (torch.cat([g.colors.detach(), p.depths[:, None]], 1) if depth else g.colors.detach()).requires_grad_(True)
    fused = backend == "torch" and fused_available(features)
    times, cpu = [], []
    for i in range(repeats + 1):
        _sync(g.device.type)
        start, cpu_start = time.perf_counter(), time.process_time()
        image, transmittance = composite(p, features, bins, fused)
        (image.mean() + transmittance.mean()).backward()
        _sync(g.device.type)
        if i > 0:
            times.append(1e3 * (time.perf_counter() - start))
            cpu.append(1e3 * (time.process_time() - cpu_start))
    return {
        "ms_composite": statistics.median(times),
        "cpu_ms_composite": statistics.median(cpu),
        "pairs": int(bins.ids.shape[0]),
    }


def _sync(device: str) -> None:
    if device == "cuda":
        import torch

        torch.cuda.synchronize()


def configurations(
    gaussians: Optional[int], size: Optional[str], channels: Optional[int], backend: Optional[str], device: Optional[str]
) -> list[tuple[int, tuple[int, int], int, str, str]]:
    """The sweep: every unspecified dimension takes its default values."""
    import torch

    devices = [device] if device else ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    counts = [gaussians] if gaussians else list(COUNTS)
    sizes = [parse_size(size)] if size else list(SIZES)
    channel_list = [channels] if channels else list(CHANNELS)
    rows = []
    for dev in devices:
        backends = [backend] if backend else (["gsplat"] if dev == "cuda" else ["torch"])
        rows += [(n, s, c, b, dev) for b, n, s, c in itertools.product(backends, counts, sizes, channel_list)]
    full_sweep = not any((gaussians, size, channels, backend, device))
    if full_sweep:
        rows.insert(0, (TARGET["gaussians"], TARGET["size"], TARGET["channels"], "torch", "cpu"))
        rows += [(COUNTS[0], SIZES[0], c, "torch-reference", "cpu") for c in CHANNELS]
    return rows


def parse_size(text: str) -> tuple[int, int]:
    try:
        width, height = (int(part) for part in text.lower().split("x"))
    except ValueError:
        raise typer.BadParameter(f"size must look like WIDTHxHEIGHT (e.g. 270x480), got {text!r}") from None
    if width <= 0 or height <= 0:
        raise typer.BadParameter(f"size must be positive, got {text!r}")
    return width, height


def _check_choices(channels: Optional[int], backend: Optional[str], device: Optional[str]) -> None:
    """Reject what cannot run here before any timing starts (typer shows it as a usage error)."""
    import torch

    if channels is not None and channels not in CHANNELS:
        raise typer.BadParameter(f"--channels must be 1 or 3, got {channels}")
    if backend is not None and backend not in BACKENDS:
        raise typer.BadParameter(f"--backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    if device is not None and device not in ("cpu", "cuda"):
        raise typer.BadParameter(f"--device must be cpu or cuda, got {device!r}")
    if device == "cuda" and not torch.cuda.is_available():
        raise typer.BadParameter("--device cuda: no CUDA device on this machine")
    if backend == "gsplat" and device != "cuda" and not torch.cuda.is_available():
        raise typer.BadParameter("--backend gsplat needs a CUDA device")
    if backend == "gsplat" and device == "cpu":
        raise typer.BadParameter("--backend gsplat runs on CUDA only; use --device cuda")


def table(rows: list[dict[str, Any]]) -> str:
    """A markdown table, then the 1-channel / 3-channel cost ratios of the compositing stage
    (in CPU time, which other load on the machine disturbs less than wall time)."""
    columns = ["backend", "device", "threads", "gaussians", "size", "channels", "depth", "coverage", "pairs",
               "ms_forward", "ms_backward", "ms_forward_backward", "ms_forward_backward_min", "cpu_ms_forward_backward",
               "ms_composite", "cpu_ms_composite"]  # fmt: skip
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for row in rows:
        lines.append("| " + " | ".join(_cell(row[c]) for c in columns) + " |")
    grey = {(r["backend"], r["device"], r["gaussians"], r["size"]): r for r in rows if r["channels"] == 1}
    for r in rows:
        one = grey.get((r["backend"], r["device"], r["gaussians"], r["size"]))
        if r["channels"] == 3 and one is not None and r["cpu_ms_composite"] and one["cpu_ms_composite"]:
            lines.append(
                f"\ncompositing 1 ch / 3 ch, {r['backend']} {r['device']} {r['gaussians']} x {r['size']}: "
                f"{one['cpu_ms_composite'] / r['cpu_ms_composite']:.2f} "
                f"(whole forward + backward {one['cpu_ms_forward_backward'] / r['cpu_ms_forward_backward']:.2f})"
            )
    return "\n".join(lines)


def _cell(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.1f}" if value >= 1 else f"{value:.3f}"
    return str(value)


def command(
    gaussians: Optional[int] = typer.Option(None, "--gaussians", min=1, help="Number of Gaussians (default: sweep 10k, 100k)."),
    size: Optional[str] = typer.Option(None, "--size", help="Image WIDTHxHEIGHT (default: sweep 270x480, 540x960, 1080x1920)."),
    channels: Optional[int] = typer.Option(None, "--channels", min=1, max=3, help="1 (grey) or 3 (default: both)."),
    backend: Optional[str] = typer.Option(None, "--backend", help="torch, torch-reference or gsplat (default: per device)."),
    device: Optional[str] = typer.Option(None, "--device", help="cpu or cuda (default: cpu, and cuda when present)."),
    repeats: int = typer.Option(3, "--repeats", min=1, help="Timed runs per row (median), after one warm-up."),
    threads: Optional[int] = typer.Option(None, "--threads", min=1, help="CPU threads (default: all cores)."),
    depth: bool = typer.Option(False, "--depth/--no-depth", help="Also render the depth map (reconstruction does not)."),
    json_output: bool = typer.Option(False, "--json", help="Print one JSON object instead of the table."),
) -> None:
    import torch

    _check_choices(channels, backend, device)
    torch.set_num_threads(threads or os.cpu_count() or 1)
    load_before = [round(x, 2) for x in os.getloadavg()]  # other work on the machine, before ours
    rows = []
    for n, s, c, b, dev in configurations(gaussians, size, channels, backend, device):
        print(f"render bench: {b} {dev} {n} Gaussians {s[0]}x{s[1]} C={c} ...", file=sys.stderr, flush=True)
        rows.append(measure(n, s, c, b, dev, repeats, depth))
    report: dict[str, Any] = {
        "benchmark": "render",
        "threads": torch.get_num_threads(),
        "cpu_count": os.cpu_count(),
        "load_average": load_before,
        "rows": rows,
    }
    if len(rows) == 1:
        report.update(rows[0])
    if json_output:
        echo_json(report)
        return
    typer.echo(f"threads {report['threads']} of {report['cpu_count']} cores, load average {report['load_average']}")
    typer.echo(table(rows))


if __name__ == "__main__":
    from bench.registry import run_script

    run_script("render", command)
