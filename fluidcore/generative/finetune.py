"""LoRA fine-tuning of the generative priors on multi-view smoke captures.

Data: a scene folder in the transforms.json layout (cameras plus one video per camera, as
`fluidnexus synth` writes and the dev scene ships) or a folder of such scenes. Two kinds:

    novel-view  Zero123 UNet: input view i and target view j of the same frame, noise the
                target's latent and learn to predict the noise given the input view and the
                pose from i to j (10% of the samples drop the condition, as Zero123 trains
                for classifier-free guidance)
    refine      CogVideoX transformer: a window of one camera's video, noised at a random
                step, denoised toward CogVideoX's v-prediction target

Only the adapter trains (peft LoRA on the attention projections; every base weight is frozen).
Randomness of step k is a function of (seed, k) alone, and every `checkpoint_every` steps the
adapter and the optimiser state are written to OUT/checkpoint.pt, so a run that is stopped and
started again computes the same adapter as one that was not. OUT/loss.jsonl holds one line per
step and OUT/loss.png its plot; OUT itself is the adapter in peft's layout, ready to be copied
to MODELS/lora/<model>/.
"""

from __future__ import annotations

import json
import math
import random
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from fluidcore.errors import InputError
from fluidcore.files import atomic_output
from fluidcore.generative import lora, models
from fluidcore.generative.novel_view import NovelViewModel, condition, relative_pose, to_square
from fluidcore.generative.refine import VideoModel, to_model_frames, window_frames

KINDS = ("novel-view", "refine")
MAX_SCENES = 200
MAX_FRAMES_PER_VIDEO = 300  # frames kept per video: bounds the memory of the decoded data
CONDITION_DROP = 0.1
CHECKPOINT = "checkpoint.pt"
LOSS_LOG = "loss.jsonl"
LOSS_PLOT = "loss.png"
Progress = Callable[[str], None]


class FinetuneError(InputError):
    """Data or settings fine-tuning cannot use; the message names the option."""


@dataclass(frozen=True)
class Settings:
    kind: str
    rank: int
    learning_rate: float
    seed: int
    exclude: tuple[str, ...]


@dataclass
class Scene:
    """One capture: cameras with their videos at the model's working size, (T, H, W, 3) in [0, 1]."""

    cameras: dict  # name -> Camera (scaled to the frames)
    videos: dict[str, torch.Tensor]
    center: np.ndarray
    up: np.ndarray


def find_scenes(data: Path) -> list[Path]:
    """`data` itself when it holds transforms.json, else its sub-folders that do (sorted)."""
    if not data.is_dir():
        raise FinetuneError(f"--data: no such folder {data}")
    if (data / "transforms.json").is_file():
        return [data]
    scenes = sorted(p.parent for p in data.glob("*/transforms.json"))
    if not scenes:
        raise FinetuneError(f"--data: no transforms.json in {data} or its sub-folders")
    if len(scenes) > MAX_SCENES:
        raise FinetuneError(f"--data: {len(scenes)} scenes, at most {MAX_SCENES} per run")
    return scenes


def load_scene(folder: Path, long_side: int, exclude: Sequence[str] = ()) -> Scene:
    """Cameras and videos of one scene folder: the cameras with a video (their file_path), less
    those named in `exclude` (views held out for measuring: never trained on)."""
    from fluidcore import cameras as camera_io
    from fluidcore.cameras import render_size
    from fluidcore.video import probe, read_frames

    cameras = camera_io.load(folder / "transforms.json")
    scaled, videos = {}, {}
    for name, camera in cameras.items():
        if name in exclude or camera.file_path is None or not (folder / camera.file_path).is_file():
            continue
        width, height = render_size(camera.width, camera.height, long_side)
        path = folder / camera.file_path
        frames = read_frames(path, 0, min(probe(path).n_frames, MAX_FRAMES_PER_VIDEO), size=(width, height))
        videos[name] = torch.from_numpy(frames).float() / 255.0
        scaled[name] = camera.scaled(width, height)
    if len(videos) < 2:
        raise FinetuneError(f"--data: {folder} has {len(videos)} camera(s) with a video; fine-tuning needs at least 2")
    box = camera_io.capture_box(folder / "transforms.json", cameras)
    return Scene(scaled, videos, camera_io.box_center(box), np.array([0.0, 1.0, 0.0]))


def run(
    kind: str,
    data: Path,
    out: Path,
    *,
    steps: int,
    models_root: Path | None = None,
    rank: int = 16,
    learning_rate: float = 1e-4,
    device: str = "cpu",
    seed: int = 0,
    checkpoint_every: int = 50,
    exclude: Sequence[str] = (),
    progress: Progress | None = None,
) -> Path:
    """Train (or resume) the adapter of `kind` for `steps` steps in total; returns `out`.
    Cameras named in `exclude` are left out of every scene."""
    if kind not in KINDS:
        raise FinetuneError(f"kind must be one of {KINDS}, got {kind!r}")
    if steps < 1 or checkpoint_every < 1:
        raise FinetuneError("steps and checkpoint_every must be >= 1")
    settings = Settings(kind, rank, learning_rate, seed, tuple(sorted(exclude)))
    report = progress or (lambda line: None)
    if kind == "novel-view":
        model = models.load_novel_view(models_root, device=device, use_adapter=False)
        module, long_side = model.unet, model.size
    else:
        model = models.load_video(models_root, device=device, use_adapter=False)
        module, long_side = model.transformer, max(model.size)
    scenes = [load_scene(folder, long_side, exclude) for folder in find_scenes(Path(data))]
    lora.add_new(module, rank=rank, seed=seed)
    module.train()
    parameters = [p for p in module.parameters() if p.requires_grad]
    optimizer = torch.optim.Adam(parameters, lr=learning_rate)
    start = _resume(out, settings, module, optimizer)
    if start:
        report(f"resuming at step {start} from {out / CHECKPOINT}")
    loss_of = novel_view_loss if kind == "novel-view" else refine_loss
    log = _LossLog(out / LOSS_LOG, start)
    for step in range(start, steps):
        began = time.perf_counter()
        rng = random.Random(seed * 1_000_003 + step)
        generator = torch.Generator().manual_seed(seed * 1_000_003 + step)
        loss = loss_of(model, scenes[rng.randrange(len(scenes))], rng, generator)
        if not torch.isfinite(loss):
            raise FloatingPointError(f"fine-tuning loss is {loss.item()} at step {step} (lower --lr?)")
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        value = loss.item()
        log.append(step + 1, value, time.perf_counter() - began)
        if (step + 1) % checkpoint_every == 0 or step + 1 == steps:
            _checkpoint(out, settings, step + 1, module, optimizer)
            report(f"step {step + 1}/{steps}: loss {value:.4f} (checkpoint)")
    plot_losses(out / LOSS_LOG, out / LOSS_PLOT)
    return out


# ---------------------------------------------------------------- losses


def _diffusion_target(scheduler, latents: torch.Tensor, noise: torch.Tensor, timesteps: torch.Tensor) -> torch.Tensor:
    if scheduler.config.prediction_type == "v_prediction":
        return scheduler.get_velocity(latents, noise, timesteps)
    return noise


def novel_view_loss(model: NovelViewModel, scene: Scene, rng: random.Random, generator: torch.Generator) -> torch.Tensor:
    """Denoising loss of one (input view, target view, frame) triple of `scene`."""
    source, target = rng.sample(sorted(scene.videos), 2)
    frame = rng.randrange(min(len(scene.videos[source]), len(scene.videos[target])))
    device, dtype = model.device, model.dtype
    with torch.no_grad():
        inputs = to_square(scene.videos[source][frame][None], model.size).to(device, dtype)
        targets = to_square(scene.videos[target][frame][None], model.size).to(device, dtype)
        pose = torch.from_numpy(relative_pose(scene.cameras[source], scene.cameras[target], scene.center, scene.up))[None]
        context = condition(model, inputs, pose.to(device, dtype))
        input_latents = model.vae.encode(inputs).latent_dist.mode()
        latents = model.vae.encode(targets).latent_dist.mode() * model.vae.config.scaling_factor
        if rng.random() < CONDITION_DROP:
            context, input_latents = torch.zeros_like(context), torch.zeros_like(input_latents)
    noise = torch.randn(latents.shape, generator=generator).to(device, dtype)
    timesteps = torch.tensor([rng.randrange(model.scheduler.config.num_train_timesteps)], device=device)
    noisy = model.scheduler.add_noise(latents, noise, timesteps)
    prediction = model.unet(torch.cat([noisy, input_latents], dim=1), timesteps, encoder_hidden_states=context).sample
    return F.mse_loss(prediction.float(), _diffusion_target(model.scheduler, latents, noise, timesteps).float())


def refine_loss(model: VideoModel, scene: Scene, rng: random.Random, generator: torch.Generator) -> torch.Tensor:
    """Denoising loss of one window of one camera's video."""
    video = scene.videos[rng.choice(sorted(scene.videos))]
    start = rng.randrange(max(len(video) - model.window, 0) + 1)
    width, height = model.size
    device, dtype = model.device, model.dtype
    pipeline = model.pipeline
    with torch.no_grad():
        clip = to_model_frames(window_frames(video, start, model.window)[None], width, height)  # (1, L, 3, h, w)
        pixels = (clip * 2.0 - 1.0).permute(0, 2, 1, 3, 4).to(device, dtype)  # (1, 3, L, h, w)
        latents = pipeline.vae.encode(pixels).latent_dist.mode() * pipeline.vae_scaling_factor_image
        latents = latents.permute(0, 2, 1, 3, 4)  # (1, F, C, h', w')
    noise = torch.randn(latents.shape, generator=generator).to(device, dtype)
    timesteps = torch.tensor([rng.randrange(pipeline.scheduler.config.num_train_timesteps)], device=device)
    noisy = pipeline.scheduler.add_noise(latents, noise, timesteps)
    rotary = None
    if model.transformer.config.use_rotary_positional_embeddings:  # CogVideoX-5b
        rotary = pipeline._prepare_rotary_positional_embeddings(height, width, latents.shape[1], device)
    prediction = model.transformer(
        hidden_states=noisy,
        encoder_hidden_states=model.prompt_embeds.to(device, dtype),
        timestep=timesteps,
        image_rotary_emb=rotary,
    ).sample
    return F.mse_loss(prediction.float(), _diffusion_target(pipeline.scheduler, latents, noise, timesteps).float())


# ---------------------------------------------------------------- checkpoints and the loss log


def _checkpoint(out: Path, settings: Settings, step: int, module: torch.nn.Module, optimizer: torch.optim.Optimizer) -> None:
    """The adapter (peft layout, usable as is) and what resuming needs, each written atomically."""
    lora.save(module, out)
    with atomic_output(out / CHECKPOINT) as tmp:
        torch.save({"step": step, "settings": asdict(settings), "optimizer": optimizer.state_dict()}, tmp)


def _resume(out: Path, settings: Settings, module: torch.nn.Module, optimizer: torch.optim.Optimizer) -> int:
    """The step to continue from: 0 for a fresh folder, else the checkpoint's (adapter loaded)."""
    path = out / CHECKPOINT
    if not path.is_file():
        return 0
    saved = torch.load(path, map_location="cpu", weights_only=True)
    if saved["settings"] != asdict(settings):
        raise FinetuneError(f"--out {out} holds a run with other settings {saved['settings']}; use another folder")
    from peft import set_peft_model_state_dict
    from safetensors.torch import load_file

    set_peft_model_state_dict(module, load_file(str(out / lora.WEIGHTS_FILE)), adapter_name=lora.ADAPTER_NAME)
    optimizer.load_state_dict(saved["optimizer"])
    return int(saved["step"])


class _LossLog:
    """JSON lines {step, loss, seconds}; on resume, lines after the checkpoint are dropped
    (those steps run again)."""

    def __init__(self, path: Path, start: int) -> None:
        self.path = path
        path.parent.mkdir(parents=True, exist_ok=True)
        kept = [line for line in read_losses(path) if line["step"] <= start] if path.is_file() else []
        path.write_text("".join(json.dumps(line) + "\n" for line in kept))

    def append(self, step: int, loss: float, seconds: float) -> None:
        with self.path.open("a") as handle:
            handle.write(json.dumps({"step": step, "loss": loss, "seconds": round(seconds, 4)}) + "\n")


def read_losses(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def plot_losses(log: Path, png: Path) -> Path:
    """Loss per step and its running mean over ~5% of the steps, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lines = read_losses(log)
    steps = np.array([line["step"] for line in lines])
    losses = np.array([line["loss"] for line in lines])
    width = max(1, math.ceil(len(losses) / 20))
    smooth = np.convolve(losses, np.ones(width) / width, mode="valid")
    figure, axes = plt.subplots(figsize=(6, 3.5))
    axes.plot(steps, losses, lw=0.8, alpha=0.5, label="loss")
    axes.plot(steps[width - 1 :], smooth, lw=1.5, label=f"mean of {width}")
    axes.set_xlabel("step")
    axes.set_ylabel("denoising loss (MSE)")
    axes.set_yscale("log")
    axes.legend()
    figure.tight_layout()
    with atomic_output(png, suffix=".png") as tmp:
        figure.savefig(tmp, dpi=100, format="png")
    plt.close(figure)
    return png
