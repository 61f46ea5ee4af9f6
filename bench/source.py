"""Where the smoke comes from: the source a reconstruction starts from, against the truth (issue 22).

    fluidnexus bench source SCENE_DIR [SCENE_DIR ...] [--input-view view_02] [--observed 0:90]
        [--quality preview] [--physics auto] [--seeds 0,1,2] [--threads 1] [--json]

For each scene, only the input view's video is read (as a reconstruction reads it), and
`fluidcore.reconstruct.loop.prepare` runs twice: with a preset's physics, which keeps the image
estimate of the source (`fluidcore.reconstruct.source_estimate.estimate_source`), and with `--physics`
(default auto), whose identification may move and resize it, once per `--seeds` seed (the
source's particle seeding, which the identification's rollouts start from). Both are compared
with the truth:

    radius ratio     estimated radius / true radius
    across, height   centre error perpendicular to the input ray, split into the part along the
                     scene's up axis (height) and the horizontal rest (across), world units
    depth            centre error along the input ray (what one view cannot see)

The truth is the scene's own record (PhiFlow meta.json, synth.json) or, for ScalarFlow, the
source triangulated by the same estimator from all five cameras of the published rig: its
held-out clips are read here for that measurement only, never by the reconstruction.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any

import numpy as np
import typer

if __package__ in (None, ""):  # `python bench/source.py`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.gt_scenes import GroundTruth, ScalarFlowScene, open_scene  # noqa: E402
from fluidcore.spec.reconstruct import DEFAULT_QUALITY, QUALITY_HELP  # noqa: E402
from fluidcore.spec.scene import SourcePlace  # noqa: E402
from fluidnexus.reporting import UserError, echo_json, user_errors  # noqa: E402

IMAGE_ESTIMATE_PHYSICS = "scalarflow"  # any preset: presets keep the image estimate of the source
DEFAULT_OBSERVED = (0, 90)  # frames read when the scene has no protocol.json


def command(
    scene_dirs: list[Path] = typer.Argument(..., exists=True, file_okay=False, help="Scene folders with transforms.json and a known source."),
    input_view: str | None = typer.Option(None, "--input-view", help="The camera whose video is read (default: protocol.json, else view_02)."),
    observed: str | None = typer.Option(None, "--observed", help="A:B, frames read (default: protocol.json, else 0:90)."),
    quality: str = typer.Option(DEFAULT_QUALITY, "--quality", help=f"Reconstruction quality: {QUALITY_HELP}."),
    physics: str = typer.Option("auto", "--physics", help="Physics mode of the second estimate (auto identifies it)."),
    seeds: str = typer.Option("0", "--seeds", help="Comma-separated seeds of the second estimate, e.g. 0,1,2."),
    threads: int | None = typer.Option(None, "--threads", min=1, help="torch threads (default: all cores)."),
    json_out: bool = typer.Option(False, "--json", help="Print one JSON object on stdout."),
) -> None:
    import torch

    from fluidcore.jobs import parse_frames

    with user_errors(ValueError):
        if threads is not None:
            torch.set_num_threads(threads)
        seed_list = parse_seeds(seeds)
        rows = []
        for scene_dir in scene_dirs:
            gt = open_scene(scene_dir)
            protocol = gt.protocol or {}
            view = input_view or protocol.get("input_view", "view_02")
            window = parse_frames(observed) if observed else tuple(protocol.get("observed", DEFAULT_OBSERVED))
            rows.append(scene_row(gt, view, (window[0], min(window[1], gt.n_frames)), quality, physics, seed_list))
        result = {"quality": quality, "physics": physics, "seeds": seed_list, "threads": torch.get_num_threads(),
                  "load_average": list(os.getloadavg()), "scenes": rows}
    if json_out:
        echo_json(result)
    else:
        print_table(result)


MAX_SEEDS = 10  # seeds one call may ask for: each is a `prepare` per scene


def parse_seeds(text: str) -> list[int]:
    """'0,1,2' -> [0, 1, 2]: distinct non-negative integers, at most MAX_SEEDS."""
    try:
        seeds = [int(part) for part in text.split(",")]
    except ValueError:
        raise UserError(f"--seeds: comma-separated integers, got {text!r}") from None
    if not seeds or len(seeds) > MAX_SEEDS or len(set(seeds)) != len(seeds) or min(seeds) < 0:
        raise UserError(f"--seeds: 1 to {MAX_SEEDS} distinct non-negative integers, got {text!r}")
    return seeds


def scene_row(gt: GroundTruth, view: str, window: tuple[int, int], quality: str, physics: str,
              seeds: list[int]) -> dict[str, Any]:
    """The image estimate and the `physics` estimate of one scene's source (one per seed, under
    "seeds"; the first seed's also under the mode's name), with their errors."""
    camera = gt.cameras.get(view)
    if camera is None:
        raise UserError(f"--input-view: no camera {view!r} in {gt.cameras_path}")
    truth = gt.source_truth()
    truth_kind = "recorded"
    if truth is None and isinstance(gt, ScalarFlowScene):
        truth, truth_kind = rig_source(gt, view, window, quality), "rig triangulation"
    if truth is None:
        raise UserError(f"{gt.root}: no recorded source to compare with")
    row: dict[str, Any] = {"scene": str(gt.root), "view": view, "frames": list(window), "truth_kind": truth_kind,
                           "truth": truth.to_json()}
    def estimate(mode: str, seed: int) -> dict[str, Any]:
        place, chosen = prepared_source(gt, {view: gt.input_path(view)}, window, quality, mode, seed)
        return {**place.to_json(), **errors(camera, place, truth), "physics": chosen}

    row["image"] = estimate(IMAGE_ESTIMATE_PHYSICS, seeds[0])  # a preset keeps the image estimate: no seed enters it
    row["seeds"] = {str(seed): estimate(physics, seed) for seed in seeds}
    row[physics] = row["seeds"][str(seeds[0])]
    return row


def prepared_source(gt: GroundTruth, videos: dict[str, Path], window: tuple[int, int], quality: str,
                    physics: str, seed: int = 0) -> tuple[SourcePlace, dict[str, Any]]:
    """The place of the source `prepare` starts a reconstruction of `videos` from (world units),
    and the manifest's record of the physics it chose (what identification found)."""
    from fluidcore import video
    from fluidcore.cameras import capture_box, render_size
    from fluidcore.reconstruct.pipeline import Footage, prepared
    from fluidcore.spec.reconstruct import get

    preset = get(quality).with_overrides(seed=seed)
    cameras = {name: camera.pinhole() for name, camera in gt.cameras.items()}
    decoded = {name: video.read_frames(path, window[0], window[1], size=render_size(cameras[name].width, cameras[name].height, preset.fit.long_side))
               for name, path in videos.items()}
    rec = prepared(Footage(cameras, decoded, window, gt.fps, capture_box(gt.cameras_path, cameras)), preset, physics=physics)
    return SourcePlace.of(rec.scene.source), rec.physics.model_dump(mode="json")


def rig_source(gt: ScalarFlowScene, view: str, window: tuple[int, int], quality: str) -> SourcePlace:
    """ScalarFlow's source triangulated from every camera of the rig (input video + held-out clips)."""
    videos = {name: gt.input_path(view) if name == view else gt.truth_path(name) for name in [view, *gt.views()]}
    return prepared_source(gt, videos, window, quality, IMAGE_ESTIMATE_PHYSICS)[0]


def errors(camera: Any, estimate: SourcePlace, truth: SourcePlace) -> dict[str, float]:
    """Radius ratio and the centre's error split along the input ray (depth), along up (height)
    and across (the horizontal rest), world units."""
    offset = np.asarray(estimate.center) - np.asarray(truth.center)
    ray = np.asarray(truth.center) - camera.center()
    ray = ray / np.linalg.norm(ray)
    depth = float(offset @ ray)
    rest = offset - depth * ray
    up = np.array([0.0, 1.0, 0.0])  # every benchmark scene's world is y-up
    height = float(rest @ up)
    return {"radius_ratio": estimate.radius / truth.radius, "depth": depth, "height": height,
            "across": float(np.linalg.norm(rest - height * up)), "distance": float(np.linalg.norm(offset))}


def print_table(result: dict) -> None:
    print(f"source estimate vs truth ({result['quality']}, threads {result['threads']})")
    print(f"{'scene':<28} {'estimate':<10} {'radius':>8} {'ratio':>6} {'across':>7} {'height':>7} {'depth':>7}")
    for row in result["scenes"]:
        name = Path(row["scene"]).name
        print(f"{name:<28} {'truth':<10} {row['truth']['radius']:8.4f}   ({row['truth_kind']})")
        estimates = [("image", row["image"]), *((f"{result['physics']} s{seed}", e) for seed, e in row["seeds"].items())]
        for key, e in estimates:
            print(f"{'':<28} {key:<10} {e['radius']:8.4f} {e['radius_ratio']:6.2f} {e['across']:7.3f} {e['height']:7.3f} {e['depth']:7.3f}")


if __name__ == "__main__":
    from bench.registry import run_script

    run_script("source", command)
