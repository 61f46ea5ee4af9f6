"""The generative stages as the jobs run them, each either run or skipped with its reason.

    generated_views   single-view reconstruction (Algorithm S1): the novel-view model draws the
                      other cameras' views of every frame from the INPUT view alone, the video
                      model refines each generated video (strength 0.5), and they become
                      ViewTargets of kind "generated", weighted below the real view;
                      `with_generated_views` puts them into a prepared reconstruction in place
                      of the plume-symmetry pseudo-views
    refine_frames     prediction (Algorithm S2): rough future frames rendered from the input
                      camera are refined by the video model (strength 0.75)

Generated frames are rounded to 8 bits, and a reconstruction keeps them in its run folder
(`generated/`: one `NAME.npz` per camera plus `views.json`, what they were made from): a resumed
or retried job reads them back instead of sampling again, and fits exactly the same targets.

A stage whose weights are absent (or incomplete) does not run; its status line says so and
why, e.g. "skipped: no cogvideox weights in ./models", and the caller keeps its weight-free
prior. Models are loaded for one stage and released after it, so the novel-view model and the
video model are never in memory together. Work goes in batches (`on_batch(stage, done,
total)` after each; an exception it raises, e.g. a job's Cancelled, stops the work there).
"""

from __future__ import annotations

import gc
import json
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from fluidcore.cameras import Camera
from fluidcore.generative import models
from fluidcore.jobs import BatchProgress
from fluidcore.generative.novel_view import SamplingOptions, generate_views
from fluidcore.generative.refine import STRENGTH_FUTURES, STRENGTH_NOVEL_VIEWS, RefineOptions, refine_video, window_starts
from fluidcore.names import safe_join
from fluidcore.reconstruct.views import ViewTarget, rotate_about_axis

if TYPE_CHECKING:
    from fluidcore.reconstruct.loop import Reconstruction

GENERATED_DIR = "generated"  # in a reconstruction's run folder
NOVEL_VIEWS = "novel views"
REFINE_VIEWS = "refine views"
REFINE_FUTURES = "refine futures"


@dataclass(frozen=True)
class GenerativeSettings:
    """How the generative stages run; the defaults are the paper's sampling settings."""

    models_root: Path | None = None  # None: fluidcore.weights.weights_dir()
    novel_view_steps: int = 50
    refine_steps: int = 50
    max_views: int = 8  # generated cameras at most
    novel_view_batch: int | None = None  # items per UNet batch; None: 16 on CUDA, 2 on CPU
    refine_batch: int = 1  # windows per transformer batch
    seed: int = 0

    def dtype(self, device: str | torch.device) -> torch.dtype:
        """float32 on CPU; bfloat16 on CUDA where supported (CogVideoX-5b needs it), else float16."""
        if torch.device(device).type != "cuda":
            return torch.float32
        return torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16

    def batch(self, device: str | torch.device) -> int:
        if self.novel_view_batch is not None:
            return self.novel_view_batch
        return 16 if torch.device(device).type == "cuda" else 2


def target_cameras(
    cameras: Mapping[str, Camera], source: Camera, center: np.ndarray, up: np.ndarray, count: int
) -> list[Camera]:
    """Cameras to generate views for, at the source's working size (long side): the scene's other
    cameras (only their poses are used), else `count` copies of the source turned about the
    vertical axis through `center` (the poses the symmetry prior would use)."""
    long_side = max(source.width, source.height)
    others = [c for name, c in sorted(cameras.items()) if name != source.name][:count]
    if not others:
        turns = [2.0 * np.pi * i / (count + 1) for i in range(1, count + 1)]
        return [rotate_about_axis(source, center, up, turn, f"{source.name}~gen{i}") for i, turn in enumerate(turns, 1)]
    scaled = []
    for camera in others:
        factor = long_side / max(camera.width, camera.height)
        scaled.append(camera.scaled(max(8, round(camera.width * factor)), max(8, round(camera.height * factor))))
    return scaled


def generated_views(
    source: ViewTarget,
    targets: Sequence[Camera],
    center: np.ndarray,
    up: np.ndarray,
    weight: float,
    settings: GenerativeSettings,
    device: str | torch.device = "cpu",
    on_batch: BatchProgress | None = None,
) -> tuple[list[ViewTarget], dict[str, str]]:
    """Generated ViewTargets (total loss weight `weight`, split evenly) and the status of both
    steps: {"novel_views": ..., "view_refinement": ...}. Only `source.frames` reach a model."""
    skipped = models.skip_reason(models.NOVEL_VIEW, settings.models_root)
    if skipped is not None:
        return [], {"novel_views": skipped, "view_refinement": "skipped: no generated views to refine"}
    dtype = settings.dtype(device)
    model = models.load_novel_view(settings.models_root, device, dtype)
    options = SamplingOptions(steps=settings.novel_view_steps, batch_size=settings.batch(device), seed=settings.seed)
    report = _stage(on_batch, NOVEL_VIEWS)
    frames = generate_views(model, source.frames, source.camera, targets, center, up, options, report)
    del model
    _free_memory()
    status = {"novel_views": f"generated {len(targets)} views x {len(source.frames)} frames from {source.camera.name} "
                             f"({options.steps} DDIM steps, {_adapter_note(models.NOVEL_VIEW, settings)})"}
    frames, status["view_refinement"] = _refine_all(frames, STRENGTH_NOVEL_VIEWS, REFINE_VIEWS, settings, device, on_batch)
    eight_bit = {name: torch.round(video.clamp(0.0, 1.0) * 255.0) / 255.0 for name, video in frames.items()}
    return _as_targets(source, targets, eight_bit, weight), status


def _as_targets(
    source: ViewTarget, targets: Sequence[Camera], frames: Mapping[str, torch.Tensor], weight: float
) -> list[ViewTarget]:
    """Generated frames as fitting targets: the input's background colour, `weight` split evenly."""
    background = _colour(source.background)
    per_view = weight / max(len(targets), 1)
    return [
        ViewTarget(camera, frames[camera.name].to(source.frames.device), background, weight=per_view, kind="generated")
        for camera in targets
    ]


def with_generated_views(
    rec: Reconstruction,
    settings: GenerativeSettings,
    device: str | torch.device = "cpu",
    on_batch: BatchProgress | None = None,
    stored: Path | None = None,
) -> dict[str, str]:
    """Replace the symmetry pseudo-views of a single-view reconstruction by generated views
    (same total weight, `Quality.symmetry_weight`) when the novel-view weights exist; returns
    the manifest's status lines. The generated cameras are the scene's other cameras (their
    poses only), else as many turned copies of the input camera as the symmetry prior uses.
    Views saved in `stored` (`save_generated_views`) from the same inputs and settings are read
    back instead of sampled again."""
    if len(rec.input_views) != 1:
        reason = "skipped: more than one input view (real views constrain the depth)"
        return {"novel_views": reason, "view_refinement": reason}
    quality = rec.quality
    if quality.symmetry_views < 1 or quality.symmetry_weight <= 0:
        reason = "skipped: pseudo-views are off in this quality (symmetry_views or symmetry_weight is 0)"
        return {"novel_views": reason, "view_refinement": reason}
    source = rec.views[0]
    center = 0.5 * (np.asarray(rec.box.lo) + np.asarray(rec.box.hi))
    count = min(quality.symmetry_views, settings.max_views)
    targets = target_cameras(rec.cameras, source.camera, center, rec.up, count)
    saved = _read_saved(stored, _saved_key(rec, targets, settings)) if stored is not None else None
    if saved is not None:
        frames, status = saved
        views = _as_targets(source, targets, frames, quality.symmetry_weight)
        status = {name: f"{line} (read back from {GENERATED_DIR}/)" for name, line in status.items()}
    else:
        views, status = generated_views(source, targets, center, rec.up, quality.symmetry_weight, settings, device, on_batch)
    if views:
        rec.views = [v for v in rec.views if v.kind != "symmetry"] + views
    return status


def save_generated_views(rec: Reconstruction, settings: GenerativeSettings, status: Mapping[str, str], folder: Path) -> None:
    """Keep the generated views of `rec` in `folder` (a run's GENERATED_DIR) for a resume; the
    index (views.json) is written last, so a half-written folder is never read back."""
    from fluidcore.files import atomic_output

    generated = [v for v in rec.views if v.kind == "generated"]
    key = _saved_key(rec, [v.camera for v in generated], settings)
    index = folder / "views.json"
    if not generated or (index.is_file() and json.loads(index.read_text()).get("key") == json.loads(json.dumps(key))):
        return
    folder.mkdir(parents=True, exist_ok=True)
    for view in generated:
        frames = torch.round(view.frames.cpu() * 255.0).to(torch.uint8).numpy()
        with atomic_output(safe_join(folder, f"{view.camera.name}.npz"), suffix=".npz") as tmp:
            np.savez_compressed(tmp, frames=frames)
    with atomic_output(index) as tmp:
        tmp.write_text(json.dumps({"key": key, "status": dict(status)}, indent=1))


def _saved_key(rec: Reconstruction, targets: Sequence[Camera], settings: GenerativeSettings) -> dict:
    """What saved views were made from: reading them back is only right when all of it agrees."""
    return {
        "input": rec.input_views[0],
        "frame_range": list(rec.frame_range),
        "targets": [[c.name, c.width, c.height] for c in targets],
        "novel_view_steps": settings.novel_view_steps,
        "refine_steps": settings.refine_steps,
        "seed": settings.seed,
        "models": {e.name: {"present": e.present, "adapter": str(e.adapter)} for e in models.inventory(settings.models_root)},
    }


def _read_saved(folder: Path, key: dict) -> tuple[dict[str, torch.Tensor], dict[str, str]] | None:
    index = folder / "views.json"
    if not index.is_file():
        return None
    saved = json.loads(index.read_text())
    if saved.get("key") != json.loads(json.dumps(key)):
        return None
    frames = {}
    for name, _width, _height in key["targets"]:
        with np.load(safe_join(folder, f"{name}.npz")) as data:
            frames[name] = torch.from_numpy(data["frames"]).float() / 255.0
    return frames, saved["status"]


def refine_frames(
    videos: Mapping[str, torch.Tensor],
    settings: GenerativeSettings,
    device: str | torch.device = "cpu",
    on_batch: BatchProgress | None = None,
) -> tuple[dict[str, torch.Tensor], str]:
    """Algorithm S2's refinement of rough futures ({camera: (T, H, W, C) in [0, 1]}): the refined
    videos and the status line (the inputs unchanged when the video model is absent)."""
    return _refine_all(dict(videos), STRENGTH_FUTURES, REFINE_FUTURES, settings, device, on_batch)


def _refine_all(
    videos: dict[str, torch.Tensor], strength: float, stage: str, settings: GenerativeSettings, device: str | torch.device,
    on_batch: BatchProgress | None,
) -> tuple[dict[str, torch.Tensor], str]:
    skipped = models.skip_reason(models.VIDEO, settings.models_root)
    if skipped is not None:
        return videos, skipped
    model = models.load_video(settings.models_root, device, settings.dtype(device))
    options = RefineOptions(strength=strength, steps=settings.refine_steps, batch_size=settings.refine_batch, seed=settings.seed)
    windows = {name: len(window_starts(len(v), model.window, options.overlap)) for name, v in videos.items()}
    total, done = sum(windows.values()), 0
    refined = {}
    for name, video in videos.items():
        def report(finished: int, _count: int, base: int = done) -> None:
            if on_batch is not None:
                on_batch(stage, base + finished, total)

        refined[name] = refine_video(model, video, options, report)
        done += windows[name]
    del model
    _free_memory()
    steps = int(options.steps * strength)
    return refined, (f"refined {len(videos)} videos with cogvideox (strength {strength}, {steps} of {options.steps} steps, "
                     f"{_adapter_note(models.VIDEO, settings)})")


def _adapter_note(name: str, settings: GenerativeSettings) -> str:
    adapter = models.entry(name, settings.models_root).adapter
    return f"LoRA {adapter}" if adapter is not None else "base weights, no LoRA adapter"


def _stage(on_batch: BatchProgress | None, stage: str) -> Callable[[int, int], None] | None:
    if on_batch is None:
        return None
    return lambda done, total: on_batch(stage, done, total)


def _colour(background: torch.Tensor) -> torch.Tensor:
    """A generated view's background: the input's background colour (its background image
    belongs to the input camera's viewpoint)."""
    if background.ndim == 1:
        return background
    return background.reshape(-1, background.shape[-1]).median(dim=0).values


def _free_memory() -> None:
    """After a stage dropped its model: free it before the next loads (one model at a time)."""
    gc.collect()
    if torch.cuda.is_available():
        torch.cuda.empty_cache()
