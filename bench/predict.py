"""Future prediction and re-simulation on a scene with ground truth (the paper's Algorithm S2 task).

    python bench/predict.py --scene ../shared/realdata/scalarflow --input-view view_02 \
        --observed 0:90 --future 90:120 --gt view_00=gt/nvs_view_00.mp4 ... [--json]

1. Reconstruct the observed window from the input view only (`fluidcore.reconstruct.job.run_reconstruct`;
   `--reconstruction RUN` reuses a finished one of exactly that window and view).
2. Predict the future window from the last reconstructed frame (`fluidcore.predict.job.run_predict`)
   and re-simulate the observed window from the first (`run_resimulate`).
3. Score every camera with ground truth (held-out views from `--gt`, paths relative to --scene;
   the input view against its own video's future frames, which never reach step 1): PSNR and
   SSIM (scikit-image's 7x7 uniform window, as the shared anchors) per view and per horizon,
   at each camera's full resolution, next to two baselines at every horizon:
     copy_input   the last observed input frame, held, on every view (the anchors' definition);
     freeze       the last reconstructed frame rendered from the view, held (what a user has
                  without prediction: for a held-out view no observed frame exists).
   Re-simulation is scored over the observed window the same way.
4. Time: seconds per predicted frame = simulation (with visual advection and checkpoint) plus
   one render per scored view, measured separately.

With `anchors.json` in the scene folder, its future-prediction rows are printed alongside.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import typer

if __package__ in (None, ""):  # `python bench/predict.py`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.scene_args import SET_HELP, load_scene, quality_overrides, view_paths  # noqa: E402 - shared option parsing
from fluidcore.spec.reconstruct import DEFAULT_QUALITY, QUALITY_HELP  # noqa: E402
from fluidnexus.reporting import UserError, echo_json, user_errors  # noqa: E402

ANCHOR_ROWS = {"all_views": "future_prediction_frames_all_views", "held_out": "future_prediction_frames_novel_views_0134"}


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def command(
    scene: Path = typer.Option(..., "--scene", exists=True, file_okay=False, help="Scene folder with transforms.json."),
    input_view: str = typer.Option(..., "--input-view", help="NAME[=path] of the one input view."),
    observed: str = typer.Option(..., "--observed", help="A:B, the observed (reconstructed) frames."),
    future: str = typer.Option(..., "--future", help="B:C, the frames to predict and score."),
    gt: list[str] = typer.Option([], "--gt", help="VIEW=path (relative to --scene): ground truth of a camera."),
    quality: str = typer.Option(DEFAULT_QUALITY, "--quality", help=f"Reconstruction quality: {QUALITY_HELP}."),
    set_: list[str] = typer.Option([], "--set", help=SET_HELP),
    reconstruction: Path | None = typer.Option(None, "--reconstruction", help="Reuse this finished reconstruction run."),
    out: Path | None = typer.Option(None, "--out", help="Keep the runs here (default: a temporary folder)."),
    threads: int | None = typer.Option(None, "--threads", min=1, help="torch threads (default: all cores)."),
    json_out: bool = typer.Option(False, "--json", help="Print one JSON object on stdout."),
) -> None:
    import torch

    from fluidcore.jobs import parse_frames
    from fluidcore.predict.job import run_predict, run_resimulate
    from fluidcore.spec.reconstruct import get
    from fluidcore.reconstruct.job import run_reconstruct
    from fluidcore.runs import Run

    with user_errors():
        cameras_path, cameras = load_scene(scene, threads)
        (name, given), = view_paths([input_view], "--input-view", scene).items()
        if name not in cameras:
            raise UserError(f"--input-view: no camera {name!r} in {cameras_path.name} (have {', '.join(cameras)})")
        input_path = given or (scene / cameras[name].file_path if cameras[name].file_path else None)
        if input_path is None:
            raise UserError(f"--input-view {name}: its camera names no video; give {name}=path")
        truths = {view: path for view, path in view_paths(gt, "--gt", scene).items() if path is not None}
        unknown = sorted(set(truths) - set(cameras))
        if unknown:
            raise UserError(f"--gt: no camera named {', '.join(unknown)}")
        truths.setdefault(name, input_path)
        window, horizon = parse_frames(observed), parse_frames(future)
        if horizon[0] != window[1]:
            raise UserError(f"--future must start where --observed ends ({window[1]}), got {future}")

        folder = out or Path(tempfile.mkdtemp(prefix="bench-predict-"))
        seconds: dict[str, float] = {}
        if reconstruction is None:
            preset = get(quality).with_overrides(**quality_overrides(set_))
            reconstruction = folder / "reconstruct"
            _log(f"reconstructing {name} frames {observed} at quality {preset.name} with {torch.get_num_threads()} threads")
            started = time.perf_counter()
            run_reconstruct(cameras_path, {name: input_path}, reconstruction, quality=preset, frames=window,
                            progress_bar=not json_out)
            seconds["reconstruct"] = time.perf_counter() - started
        _check_reconstruction(reconstruction, name, window)

        n_future = horizon[1] - horizon[0]
        _log(f"predicting {n_future} frames")
        started = time.perf_counter()
        predicted = run_predict(reconstruction, folder / "predict", frames=n_future)
        seconds["predict"] = time.perf_counter() - started
        started = time.perf_counter()
        resimulated = run_resimulate(reconstruction, folder / "resimulate")
        seconds["resimulate"] = time.perf_counter() - started

        views, render_seconds = _score(cameras, truths, name, input_path, reconstruction, predicted, resimulated, window, horizon)
        result = _summary(views, name)
        seconds["render_future_all_views"] = render_seconds
        result.update(
            {
                "scene": str(scene),
                "input_view": name,
                "observed": list(window),
                "future": list(horizon),
                "reconstruction": str(reconstruction),
                "runs": {"predict": str(predicted), "resimulate": str(resimulated)},
                "refinement": Run.open(predicted).manifest.get("refinement"),
                "seconds": seconds,
                "seconds_per_predicted_frame": (seconds["predict"] + render_seconds) / n_future,
                "seconds_per_predicted_frame_simulation": seconds["predict"] / n_future,
                "seconds_per_predicted_frame_render_per_view": render_seconds / n_future / len(views),
                "threads": torch.get_num_threads(),
                "load_average": list(os.getloadavg()),
                "anchors": _anchors(scene),
            }
        )
    if json_out:
        echo_json(result)
    else:
        _print_table(result)


def _check_reconstruction(path: Path, input_view: str, window: tuple[int, int]) -> None:
    """A reused reconstruction must have seen exactly the input view over exactly the observed window."""
    from fluidcore.runs import Run

    run = Run.open(path)
    if run.manifest["input_views"] != [input_view]:
        raise UserError(f"--reconstruction: {path} was fitted to {run.manifest['input_views']}, not [{input_view!r}]")
    if run.frames() != list(range(*window)):
        raise UserError(f"--reconstruction: {path} holds frames {run.frames()[:1]}..{run.frames()[-1:]}, not {window[0]}:{window[1]}")


def _score(cameras, truths, input_view, input_path, reconstruction, predicted, resimulated, window, horizon):  # noqa: ANN001, ANN202, PLR0913
    """Per view: future PSNR/SSIM per horizon for the prediction and both baselines, re-simulation
    PSNR/SSIM over the observed window. Returns (views, seconds spent rendering the future)."""
    import numpy as np

    from fluidcore import video
    from fluidcore.run_frames import render_frames, to_uint8_rgb
    from fluidcore.reconstruct.images import resize_image
    from fluidcore.runs import Run

    recon, pred_run, resim_run = Run.open(reconstruction), Run.open(predicted), Run.open(resimulated)
    last_input = video.read_frames(input_path, window[1] - 1, window[1])[0]
    views: dict[str, Any] = {}
    render_seconds = 0.0
    for name, path in sorted(truths.items()):
        camera = cameras[name]
        size = (camera.width, camera.height)
        truth = video.read_frames(path, horizon[0], horizon[1], size=size)
        started = time.perf_counter()
        pred = render_frames(pred_run, camera)
        render_seconds += time.perf_counter() - started
        freeze = render_frames(recon, camera, [window[1] - 1])
        copy = resize_image(last_input.astype(np.float32) / 255.0, *size)
        scores = {
            "prediction": per_frame(pred, truth),
            "copy_input": per_frame(np.broadcast_to(to_uint8_rgb(copy), truth.shape), truth),
            "freeze": per_frame(np.broadcast_to(freeze, truth.shape), truth),
        }
        resim = per_frame(render_frames(resim_run, camera), video.read_frames(path, window[0], window[1], size=size))
        views[name] = {
            "role": "input" if name == input_view else "held-out",
            **{f"{k}_psnr": float(np.mean(v["psnr"])) for k, v in scores.items()},
            **{f"{k}_ssim": float(np.mean(v["ssim"])) for k, v in scores.items()},
            "resimulation_psnr": float(np.mean(resim["psnr"])),
            "resimulation_ssim": float(np.mean(resim["ssim"])),
            "per_horizon": {f"{k}_{m}": v[m] for k, v in scores.items() for m in ("psnr", "ssim")},
        }
        _log(f"scored {name}: prediction {views[name]['prediction_psnr']:.2f} dB, freeze {views[name]['freeze_psnr']:.2f}, "
             f"copy {views[name]['copy_input_psnr']:.2f}, re-simulation {views[name]['resimulation_psnr']:.2f}")
    return views, render_seconds


def per_frame(pred, truth) -> dict[str, list[float]]:  # noqa: ANN001 - uint8 (T, H, W, 3) arrays
    """PSNR and SSIM of each frame (the anchors average these over frames)."""
    import numpy as np
    import torch

    from fluidcore import metrics

    as_float = lambda a: torch.from_numpy(np.array(a, dtype=np.float32)) / 255.0  # noqa: E731 - copies read-only views
    out: dict[str, list[float]] = {"psnr": [], "ssim": []}
    for p, t in zip(pred, truth, strict=True):
        out["psnr"].append(metrics.psnr(as_float(p), as_float(t)))
        out["ssim"].append(metrics.ssim(as_float(p), as_float(t), window="uniform"))
    return out


def _summary(views: dict[str, Any], input_view: str) -> dict[str, Any]:
    """Means over all scored views and over the held-out ones, and the per-horizon comparison."""
    import numpy as np

    keys = [k for k in next(iter(views.values())) if k.endswith(("_psnr", "_ssim"))]
    groups = {"all_views": list(views), "held_out": [v for v in views if v != input_view]}
    means = {group: {k: float(np.mean([views[v][k] for v in names])) for k in keys} for group, names in groups.items() if names}
    horizon = {
        k: np.mean([views[v]["per_horizon"][k] for v in views], axis=0).tolist() for k in next(iter(views.values()))["per_horizon"]
    }
    beats = {
        baseline: bool(all(p > b for p, b in zip(horizon["prediction_psnr"], horizon[f"{baseline}_psnr"])))
        for baseline in ("freeze", "copy_input")
    }
    return {"views": views, "mean": means, "per_horizon_mean_all_views": horizon, "beats_at_every_horizon": beats}


def _anchors(scene: Path) -> dict[str, Any] | None:
    path = scene / "anchors.json"
    if not path.is_file():
        return None
    data = json.loads(path.read_text())
    return {group: data[row] for group, row in ANCHOR_ROWS.items() if row in data}


def _print_table(result: dict[str, Any]) -> None:
    print(f"{'view':<9} {'role':<9} {'pred PSNR':>9} {'SSIM':>6} {'freeze':>7} {'copy':>7} {'resim PSNR':>10}")
    for name, v in result["views"].items():
        print(f"{name:<9} {v['role']:<9} {v['prediction_psnr']:9.2f} {v['prediction_ssim']:6.3f} {v['freeze_psnr']:7.2f} "
              f"{v['copy_input_psnr']:7.2f} {v['resimulation_psnr']:10.2f}")
    for group, m in result["mean"].items():
        print(f"{'mean':<9} {group:<9} {m['prediction_psnr']:9.2f} {m['prediction_ssim']:6.3f} {m['freeze_psnr']:7.2f} "
              f"{m['copy_input_psnr']:7.2f} {m['resimulation_psnr']:10.2f}")
    for group, rows in (result["anchors"] or {}).items():
        print(f"anchors ({group}): " + ", ".join(f"{k} {v['psnr']:.2f}" for k, v in rows.items()))
    h = result["per_horizon_mean_all_views"]
    print("horizon  pred  freeze  copy   (PSNR, mean over views)")
    for k, (p, f, c) in enumerate(zip(h["prediction_psnr"], h["freeze_psnr"], h["copy_input_psnr"]), start=1):
        print(f"{k:7d} {p:5.2f} {f:7.2f} {c:5.2f}")
    print(f"beats at every horizon: {result['beats_at_every_horizon']}; refinement: {result['refinement']}")
    print(
        f"{result['seconds_per_predicted_frame']:.2f} s per predicted frame "
        f"({result['seconds_per_predicted_frame_simulation']:.2f} s simulation, "
        f"{result['seconds_per_predicted_frame_render_per_view']:.2f} s render per view), "
        f"{result['threads']} threads, load {result['load_average'][0]:.2f}"
    )


if __name__ == "__main__":
    from bench.registry import run_script

    run_script("predict", command)
