"""One reconstruction from its footage (Algorithm S1 end to end): read the input videos, make
the generated views of a single input view, prepare, fit.

The reconstruct job (`fluidcore.reconstruct.job.run_reconstruct`, which decodes the video files
it is handed), Algorithm S2's refinement (`fluidcore.predict.priors.refine_future`, which
reconstructs refined frames in memory) and the source benchmark (`bench/source.py`, which stops
after `prepare`: `prepared`) run these steps through here, in this order.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from fluidcore.cameras import Camera
from fluidcore.jobs import BatchProgress, Cancelled, JobContext, StepProgress
from fluidcore.reconstruct.loop import InputViews, Plate, Reconstruction, Reconstructor, prepare, read_inputs
from fluidcore.spec.source_hint import SourceHint
from fluidcore.reconstruct.views import ViewTarget, generated_targets
from fluidcore.runs import CaptureRecord, FrameState, Run
from fluidcore.scene_info import WORLD_UP
from fluidcore.spec.reconstruct import ReconstructConfig
from fluidcore.spec.scene import SourcePlace
from fluidcore.spec.simulation import DEFAULT_PHYSICS
from fluidcore.spec.solids import SolidBall

if TYPE_CHECKING:
    from fluidcore.generative.stages import GenerativeSettings

# The share of a reconstruction's progress its prepare stage reports (the identification's trial
# simulations, about 50 s of FluidNexus-Smoke's preview on 2 cores); its frames fill the rest.
PREPARE_SHARE = 0.1
IDENTIFY_STAGE = "prepare: identifying the physics"


@dataclass(frozen=True)
class Footage:
    """What a reconstruction is given, decoded: the input videos, the cameras they and the other
    views of the scene were taken with, and the scene's box, up axis and solids."""

    cameras: Mapping[str, Camera]  # every camera of the scene by name, pinhole (undistorted)
    videos: Mapping[str, np.ndarray]  # input camera -> uint8 (T, H, W, 3): the frames of frame_range
    frame_range: tuple[int, int]
    fps: float
    box: tuple[np.ndarray, np.ndarray]  # the scene box (lo, hi), world units
    up: Sequence[float] = WORLD_UP
    source: SourceHint | SourcePlace | None = None  # where the source is known to be; None: estimated
    plate: Plate | None = None  # frames without smoke; None: the background is estimated from the videos
    capture: CaptureRecord | None = None  # how up was found, the camera file's fps; None: a refinement's
    solids: tuple[SolidBall, ...] = ()  # static balls in the scene (world units, in the box)


def prepared(footage: Footage, quality: ReconstructConfig, *, physics: str = DEFAULT_PHYSICS,
             device: str | torch.device = "cpu") -> Reconstruction:
    """The reconstruction of `footage` as `prepare` leaves it, before any fit and without
    generated views: its source and physics (what the source benchmark compares with the truth)."""
    inputs = read_inputs(footage.cameras, footage.videos, frame_range=footage.frame_range, quality=quality,
                         plate=footage.plate, device=device)
    return _prepare(footage, inputs, quality, physics, (), True, device)


def reconstruct(
    footage: Footage,
    quality: ReconstructConfig,
    out_dir: str | os.PathLike[str],
    *,
    physics: str = DEFAULT_PHYSICS,
    generative: GenerativeSettings | None = None,
    pseudo_views: bool = True,
    first_state: FrameState | None = None,
    status: Mapping[str, str] | None = None,
    stage: str = "reconstruct",
    context: JobContext = JobContext(),
    progress_bar: bool = False,
) -> Path:
    """Reconstruct `footage` into the run folder `out_dir` (resuming what is there).

    `physics`: "auto" (identified from the first input view) or a preset name. `generative`: the
    novel-view model's settings, whose views replace the symmetry pseudo-views of a single input
    view when its weights exist (None: no generated views, nor their status lines); `pseudo_views=False`
    fits the input views alone. `first_state`, `status` and `stage` are `fit`'s. The prepare stage
    reports the first PREPARE_SHARE of the progress (each of the identification's trial
    simulations), the frames the rest.
    """
    inputs = read_inputs(footage.cameras, footage.videos, frame_range=footage.frame_range, quality=quality,
                         plate=footage.plate, device=context.device)
    footage = replace(footage, videos={}, plate=None)  # the targets hold the frames now: a job's decoded ones can go
    novel = None
    if generative is not None:
        from fluidcore.generative.stages import GENERATED_DIR, save_generated_views

        novel = novel_views(inputs, footage.cameras, footage.box, footage.up, quality, generative, context.device,
                            context.batch_progress(f"reconstruction in {out_dir}"), stored=Path(out_dir) / GENERATED_DIR)
    identifying = context.share(0.0, PREPARE_SHARE).step_progress(f"reconstruction in {out_dir}", IDENTIFY_STAGE)
    rec = _prepare(footage, inputs, quality, physics, () if novel is None else novel.views, pseudo_views, context.device,
                   identifying)
    return fit(
        rec, out_dir, context=context.share(PREPARE_SHARE, 1.0), progress_bar=progress_bar, first_state=first_state, stage=stage,
        status={**(status or {}), **({} if novel is None else novel.status)},
        on_open=None if novel is None else lambda run: save_generated_views(novel.frames, novel.key, novel.status, run.path / GENERATED_DIR),
    )


def _prepare(footage: Footage, inputs: InputViews, quality: ReconstructConfig, physics: str, extra_views: Sequence[ViewTarget],
             pseudo_views: bool, device: str | torch.device, on_evaluation: StepProgress | None = None) -> Reconstruction:
    rec = prepare(footage.cameras, inputs, fps=footage.fps, quality=quality, box=footage.box, up=footage.up,
                  source=footage.source, physics=physics, solids=footage.solids, extra_views=extra_views, pseudo_views=pseudo_views,
                  device=device, on_evaluation=on_evaluation)
    return replace(rec, capture=footage.capture)


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
