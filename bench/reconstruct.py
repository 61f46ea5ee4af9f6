"""Reconstruct a scene from its input view(s) and score every other camera that has ground truth.

    python bench/reconstruct.py --scene ../shared/realdata/scalarflow --input-view view_02 \
        --frames 0:60 --quality preview --gt view_00=gt/nvs_view_00.mp4 ... [--json]

Input videos: `--input-view NAME[=path]`; the path defaults to the camera's `file_path`, then to
its `--gt` file (the paper's multi-view setting feeds the other views' videos in). Only the
input views' videos reach the reconstruction; the held-out views' frames are read afterwards,
for scoring only. Scores are PSNR and SSIM (scikit-image's 7x7 uniform window, as the shared
anchors) per view over the frame range, at the camera's full resolution, next to the "blank"
baseline (the run's background colour everywhere). Paths in --gt are relative to --scene.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

import typer

if __package__ in (None, ""):  # `python bench/reconstruct.py`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.scene_args import SET_HELP, load_scene, quality_overrides, view_paths  # noqa: E402 - shared option parsing
from fluidcore.spec.reconstruct import DEFAULT_QUALITY, QUALITY_HELP  # noqa: E402
from fluidnexus.reporting import UserError, echo_json, user_errors  # noqa: E402


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def command(
    scene: Path = typer.Option(..., "--scene", exists=True, file_okay=False, help="Scene folder with transforms.json."),
    input_view: list[str] = typer.Option(..., "--input-view", help="NAME[=path]; repeat for several input views."),
    frames: str = typer.Option("0:10", "--frames", help="START:END (end exclusive)."),
    quality: str = typer.Option(DEFAULT_QUALITY, "--quality", help=QUALITY_HELP),
    gt: list[str] = typer.Option([], "--gt", help="VIEW=path (relative to --scene): ground truth of a camera."),
    set_: list[str] = typer.Option([], "--set", help=SET_HELP),
    out: Path | None = typer.Option(None, "--out", help="Keep the run folder here (default: a temporary folder)."),
    threads: int | None = typer.Option(None, "--threads", min=1, help="torch threads (default: all cores)."),
    json_out: bool = typer.Option(False, "--json", help="Print one JSON object on stdout."),
) -> None:
    import torch

    from fluidcore.jobs import parse_frames
    from fluidcore.spec.reconstruct import get
    from fluidcore.reconstruct.job import run_reconstruct

    with user_errors():
        cameras_path, cameras = load_scene(scene, threads)
        truths = view_paths(gt, "--gt", scene)
        if any(path is None for path in truths.values()):
            raise UserError("--gt must look like VIEW=path")
        for name, camera in cameras.items():
            if name not in truths and camera.file_path:
                truths[name] = scene / camera.file_path
        inputs = {}
        for name, path in view_paths(input_view, "--input-view", scene).items():
            path = path or (scene / cameras[name].file_path if name in cameras and cameras[name].file_path else truths.get(name))
            if path is None:
                raise UserError(f"--input-view {name}: no video (give {name}=path, or --gt {name}=path)")
            inputs[name] = path
        scored = {name: path for name, path in truths.items() if name not in inputs}
        if not scored:
            raise UserError("no camera besides the input views has ground truth (give --gt VIEW=path)")
        frame_range = parse_frames(frames)
        preset = get(quality).with_overrides(**quality_overrides(set_))
        run_dir = out or Path(tempfile.mkdtemp(prefix="bench-reconstruct-"))
        _log(f"reconstructing {sorted(inputs)} frames {frames} at quality {preset.name} with {torch.get_num_threads()} threads")
        started = time.perf_counter()
        run_reconstruct(cameras_path, inputs, run_dir, quality=preset, frames=frame_range, progress_bar=not json_out)
        seconds = time.perf_counter() - started
        result = _score(run_dir, cameras, scored, inputs, frame_range)
        result["anchors_same_frames"] = _anchors(scene / "anchors.json", sorted(inputs), sorted(scored), frame_range)
        result.update(
            {
                "scene": str(scene),
                "input_views": sorted(inputs),
                "frames": list(frame_range),
                "quality": preset.model_dump(mode="json"),
                "threads": torch.get_num_threads(),
                "load_average": list(os.getloadavg()),
                "seconds_total": seconds,
                "seconds_per_frame": seconds / (frame_range[1] - frame_range[0]),
                "peak_rss_mib": _peak_rss_mib(),
                "run_dir": str(run_dir),
            }
        )
    if json_out:
        echo_json(result)
    else:
        _print_table(result)


def _peak_rss_mib() -> float:
    """The process's peak resident memory so far (the reconstruction's, scoring reads little more)."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux reports KiB


def _score(run_dir: Path, cameras: dict, scored: dict[str, Path], inputs: dict[str, Path], frame_range: tuple[int, int]) -> dict:
    """PSNR / SSIM of the run against each scored view, the blank baseline, and the input fit."""
    import numpy as np
    import torch

    from fluidcore import metrics, video
    from fluidcore.run_frames import render_frames, to_uint8_rgb
    from fluidcore.runs import Run

    run = Run.open(run_dir)
    views = {}
    for name, path in sorted({**scored, **inputs}.items()):
        camera = cameras[name]
        truth = video.read_frames(path, frame_range[0], frame_range[1], size=(camera.width, camera.height))
        pred = render_frames(run, camera, run.frames())
        blank = np.broadcast_to(to_uint8_rgb(np.asarray(run.background_color, np.float32)[None, None]), truth.shape)
        as_float = lambda a: torch.from_numpy(np.ascontiguousarray(a)).float() / 255.0  # noqa: E731
        t, p, b = as_float(truth), as_float(pred), as_float(blank)
        views[name] = {
            "role": "input" if name in inputs else "held-out",
            "psnr": metrics.psnr(p, t),
            "ssim": metrics.ssim(p, t, window="uniform"),
            "blank_psnr": metrics.psnr(b, t),
            "blank_ssim": metrics.ssim(b, t, window="uniform"),
        }
        _log(f"scored {name}: {views[name]['psnr']:.2f} dB")
    held = [v for v in views.values() if v["role"] == "held-out"]
    mean = {k: float(np.mean([v[k] for v in held])) for k in ("psnr", "ssim", "blank_psnr", "blank_ssim")}
    log = [run.frame_log(t)["seconds"] for t in run.frames()]
    return {"views": views, "mean_held_out": mean, "fit_seconds_per_frame": float(np.mean(log))}


def _view_key(name: str) -> str:
    """'view_02' -> '2', the view keys of the realdata anchors."""
    return name.rsplit("_", 1)[-1].lstrip("0") or "0"


def _anchors(
    path: Path, inputs: list[str], views: list[str], frame_range: tuple[int, int]
) -> dict[str, dict[str, float]] | None:
    """The published methods' PSNR / SSIM (realdata anchors.json, per-frame NVS lists) averaged
    over exactly the scored views and frames, so a partial run is compared like for like.
    None when the scene has no such file, when the input views are not the anchors' single
    input view (the anchors are single-view results), or the view names are not view_K."""
    if not path.is_file():
        return None
    anchors = json.loads(path.read_text())
    per_frame = anchors.get("per_frame", {}).get("nvs")
    input_view = anchors.get("frame_windows", {}).get("nvs", {}).get("input_view")
    if per_frame is None or [_view_key(n) for n in inputs] != [str(input_view)]:
        return None
    keys = [_view_key(name) for name in views]
    if any(k not in per_frame for k in keys):
        return None
    out = {}
    for method in per_frame[keys[0]]:
        rows = [per_frame[k][method][frame_range[0] : frame_range[1]] for k in keys]
        if any(len(r) != frame_range[1] - frame_range[0] for r in rows):
            return None
        out[method] = {
            "psnr": sum(sum(f[0] for f in r) / len(r) for r in rows) / len(rows),
            "ssim": sum(sum(f[1] for f in r) / len(r) for r in rows) / len(rows),
        }
    return out


def _print_table(result: dict) -> None:
    print(f"{'view':<10} {'role':<9} {'PSNR':>7} {'SSIM':>7} {'blank PSNR':>11} {'blank SSIM':>11}")
    for name, v in result["views"].items():
        print(f"{name:<10} {v['role']:<9} {v['psnr']:7.2f} {v['ssim']:7.4f} {v['blank_psnr']:11.2f} {v['blank_ssim']:11.4f}")
    m = result["mean_held_out"]
    print(f"{'mean':<10} {'held-out':<9} {m['psnr']:7.2f} {m['ssim']:7.4f} {m['blank_psnr']:11.2f} {m['blank_ssim']:11.4f}")
    for method, v in (result.get("anchors_same_frames") or {}).items():
        print(f"{'anchor':<10} {method:<9} {v['psnr']:7.2f} {v['ssim']:7.4f}")
    print(
        f"{result['seconds_per_frame']:.2f} s/frame ({result['fit_seconds_per_frame']:.2f} s fitting), "
        f"{result['seconds_total']:.1f} s total, peak memory {result['peak_rss_mib']:.0f} MiB, {result['threads']} threads, "
        f"load {result['load_average'][0]:.2f}"
    )


if __name__ == "__main__":
    from bench.registry import run_script

    run_script("reconstruct", command)
