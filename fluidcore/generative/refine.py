"""Video refinement with CogVideoX: noise a video part of the way and denoise it again.

diffusers' `CogVideoXVideoToVideoPipeline` does the sampling: it encodes the video, adds noise
for the first `strength` of the schedule and runs only those int(steps x strength) steps, so a
low strength keeps the layout and removes flicker (the paper: 0.5 for generated novel views),
a higher one also repairs shapes (0.75 for predicted futures).

The model works on windows of a fixed size and length: 720x480 and 49 frames for CogVideoX-2b
and -5b (the transformer's sample size times the VAE's spatial factor; the length must be
4k + 1 for the temporal VAE). Frames are resized to that size and back; a longer video is cut
into windows that overlap by `overlap` frames, and each output frame is the average of the
windows covering it, weighted by a ramp that falls to zero toward each window's cut ends, so no
seam shows where one window hands over to the next. A short video is padded with its last frame.

Text conditioning comes from precomputed T5 embeddings (`prompt_embeds`), so the 4.7B-parameter
T5 encoder never has to be loaded.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from fluidcore.errors import InputError

BatchCallback = Callable[[int, int], None]  # (windows done, windows total); may raise to cancel
STRENGTH_NOVEL_VIEWS = 0.5
STRENGTH_FUTURES = 0.75


class RefineError(InputError):
    """Inputs refinement cannot use; the message names the argument."""


@dataclass
class VideoModel:
    """A CogVideoX video-to-video pipeline with its text conditioning already encoded."""

    pipeline: object  # diffusers CogVideoXVideoToVideoPipeline (tokenizer and text encoder may be None)
    prompt_embeds: torch.Tensor  # (1, L, D)
    negative_prompt_embeds: torch.Tensor  # (1, L, D)

    def __post_init__(self) -> None:
        """On CUDA the VAE encodes and decodes in overlapping spatial tiles: a 49-frame 720x480
        window decoded whole needs tens of GB, and the memory a job needs should be bounded by
        its batch size, not by the frame size (tiles are blended, as diffusers recommends)."""
        if self.transformer.device.type == "cuda":
            self.pipeline.vae.enable_tiling()

    @property
    def transformer(self) -> torch.nn.Module:
        return self.pipeline.transformer

    @property
    def device(self) -> torch.device:
        return self.transformer.device

    @property
    def dtype(self) -> torch.dtype:
        return self.transformer.dtype

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of the frames the model works on (720x480 for CogVideoX-2b/5b)."""
        config, factor = self.transformer.config, self.pipeline.vae_scale_factor_spatial
        return int(config.sample_width) * factor, int(config.sample_height) * factor

    @property
    def window(self) -> int:
        """Frames per window (49 for CogVideoX-2b/5b)."""
        return int(self.transformer.config.sample_frames)

    def modules(self) -> list[torch.nn.Module]:
        return [self.transformer, self.pipeline.vae]


@dataclass(frozen=True)
class RefineOptions:
    strength: float = STRENGTH_NOVEL_VIEWS
    steps: int = 50
    guidance_scale: float = 6.0  # CogVideoX's default
    overlap: int = 8  # frames shared by neighbouring windows
    batch_size: int = 1  # windows per transformer batch; bounds memory
    seed: int = 0

    def __post_init__(self) -> None:
        if not 0.0 < self.strength <= 1.0:
            raise RefineError(f"strength must be in (0, 1], got {self.strength}")
        if not 1 <= self.steps <= 1000:
            raise RefineError(f"steps must be in [1, 1000], got {self.steps}")
        if int(self.steps * self.strength) < 1:
            raise RefineError(f"steps x strength must leave at least one step, got {self.steps} x {self.strength}")
        if self.overlap < 0:
            raise RefineError(f"overlap must be >= 0, got {self.overlap}")
        if self.batch_size < 1:
            raise RefineError(f"batch_size must be >= 1, got {self.batch_size}")


def window_starts(n_frames: int, window: int, overlap: int) -> list[int]:
    """First frame of each window: stride window - overlap, the last one flush with the end."""
    if overlap >= window:
        raise RefineError(f"overlap must be smaller than the model's window of {window} frames, got {overlap}")
    if n_frames <= window:
        return [0]
    stride = window - overlap
    starts = list(range(0, n_frames - window, stride))
    return [*starts, n_frames - window]


def blend_weights(window: int, overlap: int, cut_start: bool, cut_end: bool) -> torch.Tensor:
    """(window,) weights: 1 inside, rising over `overlap + 1` steps from a cut start and falling
    toward a cut end; video ends are not cuts and keep weight 1."""
    index = torch.arange(window, dtype=torch.float32)
    weight = torch.ones(window)
    if overlap > 0 and cut_start:
        weight = torch.minimum(weight, (index + 1) / (overlap + 1))
    if overlap > 0 and cut_end:
        weight = torch.minimum(weight, (window - index) / (overlap + 1))
    return weight


def refine_video(
    model: VideoModel, video: torch.Tensor, options: RefineOptions = RefineOptions(), on_batch: BatchCallback | None = None
) -> torch.Tensor:
    """Refined copy of `video` ((T, H, W, C) float in [0, 1], C in (1, 3)), same shape, float32,
    on the video's device. `on_batch(done, total)` runs after each batch of windows."""
    if video.ndim != 4 or video.shape[-1] not in (1, 3) or len(video) == 0:
        raise RefineError(f"video must be (T, H, W, C) with T > 0 and C in (1, 3), got shape {tuple(video.shape)}")
    n_frames, height, width, channels = video.shape
    window = model.window
    starts = window_starts(n_frames, window, options.overlap)
    work_width, work_height = model.size
    total = torch.zeros(n_frames, 3, height, width)
    weight_sum = torch.zeros(n_frames)
    for first in range(0, len(starts), options.batch_size):
        batch = starts[first : first + options.batch_size]
        clips = torch.stack([window_frames(video, s, window) for s in batch])  # (B, L, H, W, C)
        seeds = [options.seed + first + i for i in range(len(batch))]  # one per window, whatever the batching
        refined = _run(model, to_model_frames(clips, work_width, work_height), seeds, options)
        back = F.interpolate(refined.flatten(0, 1), size=(height, width), mode="bilinear", antialias=True, align_corners=False)
        back = back.view(len(batch), window, 3, height, width)
        for i, start in enumerate(batch):
            count = min(window, n_frames - start)
            weight = blend_weights(window, options.overlap, cut_start=start > 0, cut_end=start + window < n_frames)[:count]
            total[start : start + count] += weight[:, None, None, None] * back[i, :count]
            weight_sum[start : start + count] += weight
        if on_batch is not None:
            on_batch(first + len(batch), len(starts))
    out = (total / weight_sum[:, None, None, None]).permute(0, 2, 3, 1)
    if channels == 1:
        out = out.mean(dim=-1, keepdim=True)
    return out.clamp(0.0, 1.0).to(video.device)


def window_frames(video: torch.Tensor, start: int, window: int) -> torch.Tensor:
    """`window` frames from `start`, padded with the last frame when the video is shorter."""
    clip = video[start : start + window].float().cpu()
    if len(clip) < window:
        clip = torch.cat([clip, clip[-1:].expand(window - len(clip), -1, -1, -1)])
    return clip


def to_model_frames(clips: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """(B, L, H, W, C) in [0, 1] -> (B, L, 3, height, width) in [0, 1] at the model's size."""
    batch, length, _, _, channels = clips.shape
    frames = clips.flatten(0, 1).permute(0, 3, 1, 2)
    if channels == 1:
        frames = frames.expand(-1, 3, -1, -1)
    frames = F.interpolate(frames, size=(height, width), mode="bilinear", antialias=True, align_corners=False)
    return frames.clamp(0.0, 1.0).view(batch, length, 3, height, width)


@torch.no_grad()
def _run(model: VideoModel, clips: torch.Tensor, seeds: list[int], options: RefineOptions) -> torch.Tensor:
    """The diffusers pipeline on a batch of windows: (B, L, 3, h, w) in [0, 1] -> same, float32 CPU."""
    batch = len(clips)
    width, height = model.size
    generators = [torch.Generator().manual_seed(seed) for seed in seeds]
    result = model.pipeline(
        video=clips.to(model.device, model.dtype),
        prompt_embeds=model.prompt_embeds.to(model.device, model.dtype).expand(batch, -1, -1),
        negative_prompt_embeds=model.negative_prompt_embeds.to(model.device, model.dtype).expand(batch, -1, -1),
        height=height,
        width=width,
        num_inference_steps=options.steps,
        strength=options.strength,
        guidance_scale=options.guidance_scale,
        generator=generators,
        output_type="pt",
    )
    frames = result.frames.float().cpu()  # (B, L, 3, h, w) in [0, 1]
    if not torch.isfinite(frames).all():
        raise FloatingPointError("video refinement produced non-finite pixels (try float32 or bfloat16)")
    return frames
