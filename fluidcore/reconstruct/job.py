"""The reconstruction job (Algorithm S1) as the CLI, the worker and the benchmark run it.

`run_reconstruct` reads the cameras and ONLY the videos it is handed (a `file_path` in the
cameras file never pulls in another view), checks each video fits its camera
(`fluidcore.cameras.check_video_size`, the rule the API applies to uploads), reconstructs frame
by frame into a run folder and resumes when that folder already holds the same run. Progress,
cancellation (its `JobContext`) and input errors follow `fluidcore.jobs`.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from fluidcore.jobs import BatchProgress, Cancelled, JobContext, JobInputError
from fluidcore.reconstruct.source_hint import SourceHint
from fluidcore.spec.reconstruct import DEFAULT_QUALITY, ReconstructConfig, get
from fluidcore.spec.simulation import DEFAULT_PHYSICS, SimulationConfig

if TYPE_CHECKING:
    import torch

    from fluidcore.cameras import Camera
    from fluidcore.generative.stages import GenerativeSettings
    from fluidcore.reconstruct.loop import InputViews, Reconstruction
    from fluidcore.reconstruct.views import ViewTarget
    from fluidcore.runs import FrameState, Run


def _frame_range(infos: Mapping[str, object], frames: tuple[int, int] | None) -> tuple[int, int]:
    available = min(info.n_frames for info in infos.values())
    if frames is None:
        return 0, available
    if frames[1] > available:
        raise JobInputError(f"frames: {frames[0]}:{frames[1]} asked, but the shortest input video has {available} frames")
    return frames


def run_reconstruct(
    cameras_path: str | os.PathLike[str],
    videos: Mapping[str, str | os.PathLike[str]],
    out_dir: str | os.PathLike[str],
    *,
    quality: str | ReconstructConfig = DEFAULT_QUALITY,
    frames: tuple[int, int] | None = None,
    source: SourceHint | None = None,
    physics: str = DEFAULT_PHYSICS,
    simulation: SimulationConfig | None = None,
    progress_bar: bool = False,
    generative: GenerativeSettings | None = None,
    context: JobContext = JobContext(),
) -> Path:
    """Reconstruct `videos` (camera name -> path) seen by the cameras of `cameras_path`.

    `quality` is a preset name or a `ReconstructConfig` (a preset with overrides, as the benchmark
    uses); `simulation`, when given, replaces its air and spreading settings (the user's
    `SimulationConfig`, or a request model that extends it). `physics` is "auto" (identified from the input view) or a preset name ("scalarflow",
    "fluidnexus"; fluidcore.reconstruct.identify). `source`: where the user knows the smoke's
    source to be (otherwise estimated; one view leaves its depth to a guess). Returns the run folder. `progress_bar` draws a
    tqdm bar on stderr (the CLI's).
    With one input view, the generative priors (`generative`, default: the weights of
    `fluidcore.weights.weights_dir()`) replace the symmetry pseudo-views when their weights
    exist; the manifest's "novel_views" and "view_refinement" say what ran or why not.
    """
    from fluidcore import cameras as camera_io
    from fluidcore import video
    from fluidcore.generative.stages import GENERATED_DIR, GenerativeSettings, save_generated_views
    from fluidcore.reconstruct.loop import prepare, read_inputs
    from fluidcore.scene_info import WORLD_UP

    preset = quality if isinstance(quality, ReconstructConfig) else get(quality)
    if simulation is not None:
        preset = preset.with_simulation(simulation)
    cameras_path = Path(cameras_path)
    cameras = camera_io.load(cameras_path)
    if not videos:
        raise JobInputError("videos: give at least one VIEW=path.mp4")
    unknown = sorted(set(videos) - set(cameras))
    if unknown:
        raise JobInputError(f"videos: no camera named {', '.join(unknown)} in {cameras_path.name} (have {', '.join(cameras)})")
    infos = {name: video.probe(path) for name, path in videos.items()}
    for name, info in infos.items():
        try:
            camera_io.check_video_size(cameras[name], Path(videos[name]).name, info.width, info.height)
        except camera_io.CameraError as exc:
            raise JobInputError(str(exc)) from None
    frame_range = _frame_range(infos, frames)
    fps = infos[next(iter(videos))].fps
    decoded = {  # undistorted: from here on every camera is the pinhole the renderer models
        name: camera_io.undistort_frames(
            cameras[name],
            video.read_frames(
                path, frame_range[0], frame_range[1], size=camera_io.render_size(cameras[name].width, cameras[name].height, preset.fit.long_side)
            ),
        )
        for name, path in videos.items()
    }
    cameras = {name: camera.pinhole() for name, camera in cameras.items()}
    context.progress(0.0, "prepare")
    inputs = read_inputs(cameras, decoded, frame_range=frame_range, quality=preset, device=context.device)
    del decoded
    box = camera_io.capture_box(cameras_path, cameras)
    settings = generative or GenerativeSettings()
    on_batch = context.batch_progress(f"reconstruction in {out_dir}")
    novel = novel_views(inputs, cameras, box, WORLD_UP, preset, settings, context.device, on_batch, stored=Path(out_dir) / GENERATED_DIR)
    rec = prepare(
        cameras, inputs, fps=fps, quality=preset, box=box, up=WORLD_UP, source=source, physics=physics, extra_views=novel.views,
        device=context.device,
    )
    return fit(
        rec, out_dir, context=context, progress_bar=progress_bar, status=novel.status,
        on_open=lambda run: save_generated_views(novel.frames, novel.key, novel.status, run.path / GENERATED_DIR),
    )


@dataclass(frozen=True)
class NovelViews:
    """What the generative stage gave a single-view reconstruction: the views to fit in place of
    the symmetry pseudo-views (none when it was skipped), the manifest's status lines, and the
    frames with what they were made from (`saved_key`) for keeping them in the run folder."""

    views: list[ViewTarget]
    status: dict[str, str]
    frames: dict[str, torch.Tensor]
    key: dict


def novel_views(
    inputs: InputViews,
    cameras: Mapping[str, Camera],
    box: tuple[np.ndarray, np.ndarray],
    up: Sequence[float],
    quality: ReconstructConfig,
    settings: GenerativeSettings,
    device: str = "cpu",
    on_batch: BatchProgress | None = None,
    stored: Path | None = None,
) -> NovelViews:
    """Generated views of a single-view reconstruction (same total weight as the symmetry prior,
    `priors.symmetry_weight`) when the novel-view weights exist. The generated cameras are the
    scene's other cameras (their poses only), else as many turned copies of the input camera as
    the symmetry prior uses. Views saved in `stored` from the same inputs and settings are read
    back instead of sampled again."""
    from fluidcore.generative.stages import generated_views, read_generated_views, saved_key, target_cameras
    from fluidcore.reconstruct.views import generated_targets

    if len(inputs.targets) != 1:
        reason = "skipped: more than one input view (real views constrain the depth)"
        return NovelViews([], {"novel_views": reason, "view_refinement": reason}, {}, {})
    priors = quality.priors
    if priors.symmetry_views < 1 or priors.symmetry_weight <= 0:
        reason = "skipped: pseudo-views are off in this quality (symmetry_views or symmetry_weight is 0)"
        return NovelViews([], {"novel_views": reason, "view_refinement": reason}, {}, {})
    source = inputs.targets[0]
    center = 0.5 * (np.asarray(box[0]) + np.asarray(box[1]))
    up_v = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    targets = target_cameras(cameras, source.camera, center, up_v, min(priors.symmetry_views, settings.max_views))
    key = saved_key(source.camera.name, inputs.frame_range, targets, settings)
    saved = read_generated_views(stored, key) if stored is not None else None
    frames, status = saved if saved is not None else generated_views(
        source.camera, source.frames, targets, center, up_v, settings, device, on_batch
    )
    views = generated_targets(source, targets, frames, priors.symmetry_weight) if frames else []
    return NovelViews(views, status, frames, key)


def fit(
    rec: Reconstruction,
    out_dir: str | os.PathLike[str],
    *,
    context: JobContext = JobContext(),
    progress_bar: bool = False,
    status: Mapping[str, str] | None = None,
    first_state: FrameState | None = None,
    stage: str = "reconstruct",
    on_open: Callable[[Run], None] | None = None,
) -> Path:
    """Fit a prepared reconstruction frame by frame into `out_dir` (resuming what is there).

    `status` lines go into the manifest. `first_state`, when given, is written as the first
    frame instead of fitting it, and the fit continues from it: Algorithm S2 reconstructs
    refined futures starting from the predicted state, not from a freshly seeded source.
    `on_open(run)` runs once the run folder exists, before the first frame (it keeps the
    generated views there).
    """
    from fluidcore.reconstruct.loop import Reconstructor

    reconstructor = Reconstructor(rec, device=context.device)
    run = reconstructor.open_run(out_dir)
    if status:
        run.update(**status)
    if on_open is not None:
        on_open(run)
    frame_range = rec.frame_range
    if first_state is not None and not run.frames():
        run.write_frame(frame_range[0], first_state, {}, 0.0)
    total = frame_range[1] - frame_range[0]
    bar = _bar(total, len(run.frames()), progress_bar)
    cancelled = False

    def on_frame(t: int, losses: Mapping[str, float]) -> None:
        done = t + 1 - frame_range[0]
        context.progress(done / total, stage)
        if bar is not None:
            bar.set_postfix(psnr=f"{losses['input_psnr']:.1f}", refresh=False)
            bar.update(1)

    def should_stop() -> bool:
        nonlocal cancelled
        cancelled = context.should_cancel()
        return cancelled

    run = reconstructor.run(out_dir, on_frame=on_frame, should_stop=should_stop)
    if bar is not None:
        bar.close()
    if cancelled:
        raise Cancelled(f"reconstruction cancelled; {out_dir} resumes from frame {run.next_frame()}")
    return Path(out_dir)


def _bar(total: int, done: int, enabled: bool):  # noqa: ANN202 - tqdm or None
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, initial=done, unit="frame", desc="reconstruct", file=sys.stderr, dynamic_ncols=True)
