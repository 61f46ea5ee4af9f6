"""The generative stages as the jobs run them, each either run or skipped with its reason.

    generated_views   single-view reconstruction (Algorithm S1): the novel-view model draws the
                      other cameras' views of every frame from the INPUT view alone and the video
                      model refines each generated video (strength 0.5); the reconstruction job
                      fits them as views of kind "generated" in place of the plume-symmetry
                      pseudo-views (fluidcore.reconstruct.job, before `prepare`)
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

import numpy as np
import torch

from fluidcore.cameras import Camera, rotate_about_axis
from fluidcore.generative import models
from fluidcore.jobs import BatchProgress
from fluidcore.names import safe_join
from fluidcore.generative.novel_view import SamplingOptions, generate_views
from fluidcore.generative.refine import STRENGTH_FUTURES, STRENGTH_NOVEL_VIEWS, RefineOptions, refine_video, window_starts

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
    source: Camera,
    frames: torch.Tensor,
    targets: Sequence[Camera],
    center: np.ndarray,
    up: np.ndarray,
    settings: GenerativeSettings,
    device: str | torch.device = "cpu",
    on_batch: BatchProgress | None = None,
) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """The views of `targets` drawn from the input view's `frames` ((T, H, W, C) in [0, 1], seen
    by `source`), rounded to 8 bits, by camera name ({} when the weights are absent), and the
    status of both steps: {"novel_views": ..., "view_refinement": ...}. Only `frames` reach a model."""
    skipped = models.skip_reason(models.NOVEL_VIEW, settings.models_root)
    if skipped is not None:
        return {}, {"novel_views": skipped, "view_refinement": "skipped: no generated views to refine"}
    dtype = settings.dtype(device)
    model = models.load_novel_view(settings.models_root, device, dtype)
    options = SamplingOptions(steps=settings.novel_view_steps, batch_size=settings.batch(device), seed=settings.seed)
    report = _stage(on_batch, NOVEL_VIEWS)
    drawn = generate_views(model, frames, source, targets, center, up, options, report)
    del model
    _free_memory()
    status = {"novel_views": f"generated {len(targets)} views x {len(frames)} frames from {source.name} "
                             f"({options.steps} DDIM steps, {_adapter_note(models.NOVEL_VIEW, settings)})"}
    drawn, status["view_refinement"] = _refine_all(drawn, STRENGTH_NOVEL_VIEWS, REFINE_VIEWS, settings, device, on_batch)
    return {name: torch.round(video.clamp(0.0, 1.0) * 255.0) / 255.0 for name, video in drawn.items()}, status


def saved_key(source: str, frame_range: tuple[int, int], targets: Sequence[Camera], settings: GenerativeSettings) -> dict:
    """What saved views were made from (the input camera's name, its frames, the generated
    cameras, the sampling settings and the weights): reading them back is only right when all of
    it agrees."""
    return {
        "input": source,
        "frame_range": list(frame_range),
        "targets": [[c.name, c.width, c.height] for c in targets],
        "novel_view_steps": settings.novel_view_steps,
        "refine_steps": settings.refine_steps,
        "seed": settings.seed,
        "models": {e.name: {"present": e.present, "adapter": str(e.adapter)} for e in models.inventory(settings.models_root)},
    }


def save_generated_views(frames: Mapping[str, torch.Tensor], key: dict, status: Mapping[str, str], folder: Path) -> None:
    """Keep generated `frames` (by camera name, made from `key`, `saved_key`) in `folder` (a run's
    GENERATED_DIR) for a resume; the index (views.json) is written last, so a half-written folder
    is never read back."""
    from fluidcore.files import atomic_output

    index = folder / "views.json"
    if not frames or (index.is_file() and json.loads(index.read_text()).get("key") == json.loads(json.dumps(key))):
        return
    folder.mkdir(parents=True, exist_ok=True)
    for name, video in frames.items():
        eight_bit = torch.round(video.cpu() * 255.0).to(torch.uint8).numpy()
        with atomic_output(safe_join(folder, f"{name}.npz"), suffix=".npz") as tmp:
            np.savez_compressed(tmp, frames=eight_bit)
    with atomic_output(index) as tmp:
        tmp.write_text(json.dumps({"key": key, "status": dict(status)}, indent=1))


def read_generated_views(folder: Path, key: dict) -> tuple[dict[str, torch.Tensor], dict[str, str]] | None:
    """The views `save_generated_views` kept in `folder` for exactly `key`, with their status
    lines (marked as read back), or None."""
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
    return frames, {name: f"{line} (read back from {GENERATED_DIR}/)" for name, line in saved["status"].items()}


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


def _free_memory() -> None:
    """After a stage dropped its model: free it before the next loads (one model at a time)."""
    gc.collect()
    if torch.cuda.is_available():
        torch.cuda.empty_cache()
