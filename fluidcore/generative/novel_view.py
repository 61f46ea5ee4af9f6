"""Zero123-style novel views: what the smoke of the input view looks like from another camera.

The model is a latent diffusion UNet with 8 input channels: 4 for the noisy latent of the
target view and 4 for the VAE latent of the input view (unscaled, as the released Zero123
checkpoints were trained). Its cross-attention context is one token: the CLIP image embedding
of the input view concatenated with the relative camera pose and mapped back to the CLIP width
by `cc_projection` (768 + 4 -> 768 for Zero123 and Zero123-XL). Classifier-free guidance uses
zeros for both the input latent and the context, which is how the model was trained to drop its
condition. Sampling is DDIM with eta = 0, so the only randomness is the starting noise.

Frames are padded to a square with their border colour (the model only knows square images),
resized to the model size (256 for the public checkpoints), generated, and resized and cropped
back to the target camera's aspect. Work items are (target camera, time step) pairs, sampled in
batches of `batch_size`; each item draws its own starting noise from (seed, camera index, time
step), so a result does not depend on the batch size or on which other items were asked for.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from fluidcore.cameras import Camera
from fluidcore.errors import InputError

BatchCallback = Callable[[int, int], None]  # (items done, items total); may raise to cancel
POSE_DIMS = 4  # [polar change, sin azimuth change, cos azimuth change, radius change]
REFERENCE_RADIUS = 1.5  # Zero123's nearest training camera distance; radii are given in these units


class NovelViewError(InputError):
    """Inputs novel-view generation cannot use; the message names the argument."""


@dataclass
class NovelViewModel:
    """The diffusers components of a Zero123 checkpoint, on one device and dtype."""

    unet: torch.nn.Module  # UNet2DConditionModel, in_channels = 2 x latent channels
    vae: torch.nn.Module  # AutoencoderKL
    image_encoder: torch.nn.Module  # transformers CLIPVisionModelWithProjection
    cc_projection: torch.nn.Linear  # (CLIP projection width + 4) -> cross-attention width
    scheduler: object  # DDIMScheduler
    clip_mean: tuple[float, float, float]
    clip_std: tuple[float, float, float]
    clip_size: int  # CLIP input side (224 for ViT-L/14)

    @property
    def device(self) -> torch.device:
        return self.unet.device

    @property
    def dtype(self) -> torch.dtype:
        return self.unet.dtype

    @property
    def size(self) -> int:
        """Side of the square images the model generates (256 for the public checkpoints)."""
        return int(self.unet.config.sample_size) * 2 ** (len(self.vae.config.block_out_channels) - 1)

    def modules(self) -> list[torch.nn.Module]:
        return [self.unet, self.vae, self.image_encoder, self.cc_projection]


# ----------------------------------------------------------------------------------------------
# Camera pose relative to the input view


def spherical(camera: Camera, center: np.ndarray, up: np.ndarray) -> tuple[float, float, float]:
    """(polar angle from `up`, azimuth about `up`, distance) of the camera centre around `center`.

    The azimuth is measured from an axis fixed by `up` alone, so differences of azimuths are
    meaningful between cameras of one scene (only differences reach the model).
    """
    axis = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    offset = camera.center() - np.asarray(center, dtype=np.float64)
    radius = float(np.linalg.norm(offset))
    if radius < 1e-9:
        raise NovelViewError(f"camera {camera.name!r} sits at the scene centre; its direction is undefined")
    reference = np.eye(3)[int(np.argmin(np.abs(axis)))]
    first = np.cross(axis, reference)
    first /= np.linalg.norm(first)
    second = np.cross(axis, first)
    polar = math.acos(float(np.clip(offset @ axis / radius, -1.0, 1.0)))
    azimuth = math.atan2(float(offset @ second), float(offset @ first))
    return polar, azimuth, radius


def relative_pose(source: Camera, target: Camera, center: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Zero123's pose condition for moving from `source` to `target`: [polar change, sin and cos
    of the azimuth change, distance change]. Distances are scaled so that the source camera is at
    REFERENCE_RADIUS, because scene units differ between captures while the model learnt one scale."""
    polar_s, azimuth_s, radius_s = spherical(source, center, up)
    polar_t, azimuth_t, radius_t = spherical(target, center, up)
    turn = azimuth_t - azimuth_s
    return np.array(
        [polar_t - polar_s, math.sin(turn), math.cos(turn), REFERENCE_RADIUS * (radius_t / radius_s - 1.0)],
        dtype=np.float32,
    )


# ----------------------------------------------------------------------------------------------
# Square padding and its inverse


@dataclass(frozen=True)
class SquarePlacement:
    """Where a (height, width) frame sits inside the square of side max(height, width)."""

    height: int
    width: int

    @property
    def side(self) -> int:
        return max(self.height, self.width)

    @property
    def top(self) -> int:
        return (self.side - self.height) // 2

    @property
    def left(self) -> int:
        return (self.side - self.width) // 2


def to_square(images: torch.Tensor, size: int) -> torch.Tensor:
    """(B, H, W, C) in [0, 1] -> (B, 3, size, size) in [-1, 1]: centred on a square filled with
    each image's median border colour (the background around the smoke), then resized."""
    batch, height, width, channels = images.shape
    place = SquarePlacement(height, width)
    border = torch.cat([images[:, 0], images[:, -1], images[:, :, 0], images[:, :, -1]], dim=1)  # (B, 2W+2H, C)
    fill = border.median(dim=1).values  # (B, C)
    square = fill[:, None, None, :].expand(batch, place.side, place.side, channels).clone()
    square[:, place.top : place.top + height, place.left : place.left + width] = images
    chw = square.permute(0, 3, 1, 2)
    if channels == 1:
        chw = chw.expand(-1, 3, -1, -1)
    resized = F.interpolate(chw, size=(size, size), mode="bilinear", antialias=True, align_corners=False)
    return resized * 2.0 - 1.0


def from_square(squares: torch.Tensor, height: int, width: int, channels: int) -> torch.Tensor:
    """Inverse of `to_square` for a (height, width) frame: (B, 3, S, S) in [0, 1] ->
    (B, height, width, channels); grey output is the mean of the three channels."""
    place = SquarePlacement(height, width)
    full = F.interpolate(squares.float(), size=(place.side, place.side), mode="bilinear", antialias=True, align_corners=False)
    crop = full[:, :, place.top : place.top + height, place.left : place.left + width]
    if channels == 1:
        crop = crop.mean(dim=1, keepdim=True)
    return crop.permute(0, 2, 3, 1).clamp(0.0, 1.0).contiguous()


# ----------------------------------------------------------------------------------------------
# Sampling


@dataclass(frozen=True)
class SamplingOptions:
    steps: int = 50
    guidance_scale: float = 3.0  # Zero123's default
    batch_size: int = 4  # (camera, time step) items per UNet batch; bounds memory
    seed: int = 0

    def __post_init__(self) -> None:
        if not 1 <= self.steps <= 1000:
            raise NovelViewError(f"steps must be in [1, 1000], got {self.steps}")
        if not self.guidance_scale >= 1.0:
            raise NovelViewError(f"guidance_scale must be >= 1, got {self.guidance_scale}")
        if self.batch_size < 1:
            raise NovelViewError(f"batch_size must be >= 1, got {self.batch_size}")


def generate_views(
    model: NovelViewModel,
    frames: torch.Tensor,
    source: Camera,
    targets: Sequence[Camera],
    center: np.ndarray,
    up: np.ndarray,
    options: SamplingOptions = SamplingOptions(),
    on_batch: BatchCallback | None = None,
) -> dict[str, torch.Tensor]:
    """Each target camera's view of every frame of `frames` ((T, H, W, C) in [0, 1], the source
    camera's video and the only image input): {target name: (T, H_t, W_t, C) float32 on the
    frames' device}, at each target camera's size.

    `on_batch(done, total)` runs after every batch; an exception it raises stops the work there.
    """
    if frames.ndim != 4 or frames.shape[-1] not in (1, 3):
        raise NovelViewError(f"frames must be (T, H, W, C) with C in (1, 3), got shape {tuple(frames.shape)}")
    if not targets:
        return {}
    names = [camera.name for camera in targets]
    if len(set(names)) != len(names):
        raise NovelViewError(f"targets: camera names repeat: {names}")
    poses = np.stack([relative_pose(source, camera, center, up) for camera in targets])
    items = [(k, t) for k in range(len(targets)) for t in range(len(frames))]
    outputs = {camera.name: [] for camera in targets}
    channels = frames.shape[-1]
    for start in range(0, len(items), options.batch_size):
        batch = items[start : start + options.batch_size]
        images = frames[[t for _, t in batch]].to(model.device, torch.float32)
        pose = torch.from_numpy(poses[[k for k, _ in batch]])
        noise_seeds = [_item_seed(options.seed, k, t) for k, t in batch]
        squares = sample(model, images, pose, noise_seeds, options)
        for (k, _), square in zip(batch, squares, strict=True):
            camera = targets[k]
            outputs[camera.name].append(from_square(square[None], camera.height, camera.width, channels)[0].to(frames.device))
        if on_batch is not None:
            on_batch(start + len(batch), len(items))
    return {name: torch.stack(views) for name, views in outputs.items()}


def _item_seed(seed: int, camera_index: int, time_step: int) -> int:
    return (seed * 1_000_003 + camera_index * 100_003 + time_step) % 2**63


@torch.no_grad()
def sample(
    model: NovelViewModel, images: torch.Tensor, poses: torch.Tensor, noise_seeds: Sequence[int], options: SamplingOptions
) -> torch.Tensor:
    """One batch: input images (B, H, W, C) in [0, 1] and poses (B, 4) -> generated squares
    (B, 3, S, S) in [0, 1]."""
    device, dtype = model.device, model.dtype
    squares = to_square(images, model.size).to(device, dtype)
    context = condition(model, squares, poses.to(device, dtype))
    input_latents = model.vae.encode(squares).latent_dist.mode()
    latents = _noise(noise_seeds, input_latents.shape[1:], device, dtype) * model.scheduler.init_noise_sigma
    guided = options.guidance_scale > 1.0
    if guided:
        context = torch.cat([torch.zeros_like(context), context])
        input_latents = torch.cat([torch.zeros_like(input_latents), input_latents])
    model.scheduler.set_timesteps(options.steps, device=device)
    for t in model.scheduler.timesteps:
        noisy = torch.cat([latents, latents]) if guided else latents
        noisy = model.scheduler.scale_model_input(noisy, t)
        prediction = model.unet(torch.cat([noisy, input_latents], dim=1), t, encoder_hidden_states=context).sample
        if guided:
            unconditional, conditional = prediction.chunk(2)
            prediction = unconditional + options.guidance_scale * (conditional - unconditional)
        latents = model.scheduler.step(prediction, t, latents, eta=0.0).prev_sample
    decoded = model.vae.decode(latents / model.vae.config.scaling_factor).sample
    out = (decoded.float() + 1.0) / 2.0
    if not torch.isfinite(out).all():
        raise FloatingPointError("novel-view sampling produced non-finite pixels (try float32 or bfloat16)")
    return out.clamp(0.0, 1.0)


def condition(model: NovelViewModel, squares: torch.Tensor, poses: torch.Tensor) -> torch.Tensor:
    """Cross-attention context (B, 1, D): CLIP embedding of the input view plus the pose, projected."""
    side = (model.clip_size, model.clip_size)
    pixels = F.interpolate(squares.float(), size=side, mode="bicubic", antialias=True, align_corners=False)
    pixels = (pixels + 1.0) / 2.0
    mean = torch.tensor(model.clip_mean, device=pixels.device).view(1, 3, 1, 1)
    std = torch.tensor(model.clip_std, device=pixels.device).view(1, 3, 1, 1)
    pixels = ((pixels - mean) / std).to(squares.dtype)
    embedding = model.image_encoder(pixel_values=pixels).image_embeds
    return model.cc_projection(torch.cat([embedding, poses.to(embedding.dtype)], dim=-1))[:, None, :]


def _noise(seeds: Sequence[int], shape: Sequence[int], device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    """One standard normal tensor per seed, drawn on the CPU so that every device gets the same."""
    draws = [torch.randn(tuple(shape), generator=torch.Generator().manual_seed(seed)) for seed in seeds]
    return torch.stack(draws).to(device, dtype)
