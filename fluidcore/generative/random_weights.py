"""Randomly initialised Zero123 and CogVideoX models, in memory or written in the public layouts.

Real weights cannot be fetched on the machines this project is tested on, so the tests write
`tiny` models with exactly the folder layout of the public releases and load them back through
`fluidcore.generative.models`, the same code that loads real weights. `full` builds the real
architectures (Zero123-XL: Stable Diffusion 1.x UNet with 8 input channels, CLIP ViT-L/14;
CogVideoX-2b) for timing and memory on a GPU; random weights cost what trained ones cost.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

import torch

from fluidcore.generative.models import NOVEL_VIEW, PROMPT_FILE, VIDEO, quiet_libraries
from fluidcore.generative.novel_view import POSE_DIMS, NovelViewModel
from fluidcore.generative.refine import VideoModel

Size = Literal["tiny", "full"]
CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)  # OpenAI CLIP's normalisation
CLIP_STD = (0.26862954, 0.26130258, 0.27577711)

UNET = {
    "tiny": dict(
        sample_size=16, block_out_channels=(32, 64), layers_per_block=1, cross_attention_dim=32, attention_head_dim=4,
        down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"), up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"),
    ),
    "full": dict(sample_size=32, cross_attention_dim=768, attention_head_dim=8),  # SD 1.x blocks are the class defaults
}
VAE = {
    "tiny": dict(
        block_out_channels=(32, 64), layers_per_block=1, sample_size=32,
        down_block_types=("DownEncoderBlock2D",) * 2, up_block_types=("UpDecoderBlock2D",) * 2,
    ),
    "full": dict(
        block_out_channels=(128, 256, 512, 512), layers_per_block=2, sample_size=256,
        down_block_types=("DownEncoderBlock2D",) * 4, up_block_types=("UpDecoderBlock2D",) * 4,
    ),
}
CLIP = {
    "tiny": dict(
        hidden_size=32, intermediate_size=64, num_hidden_layers=2, num_attention_heads=4, image_size=32, patch_size=8,
        projection_dim=28,
    ),
    "full": dict(
        hidden_size=1024, intermediate_size=4096, num_hidden_layers=24, num_attention_heads=16, image_size=224, patch_size=14,
        projection_dim=768,
    ),
}
# Stable Diffusion's training schedule, which Zero123 kept
DDIM = dict(
    num_train_timesteps=1000, beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear", clip_sample=False,
    set_alpha_to_one=False, steps_offset=1,
)
TRANSFORMER = {
    "tiny": dict(
        num_attention_heads=2, attention_head_dim=8, in_channels=4, out_channels=4, time_embed_dim=8, text_embed_dim=16,
        num_layers=1, sample_width=8, sample_height=6, sample_frames=9, max_text_seq_length=8,
    ),
    "full": {},  # CogVideoX-2b is the class default
}
VIDEO_VAE = {
    "tiny": dict(
        block_out_channels=(8, 8, 8, 8), latent_channels=4, layers_per_block=1, norm_num_groups=2, sample_height=48,
        sample_width=64,
    ),
    "full": {},
}
# CogVideoX-2b's scheduler_config.json
COGVIDEOX_DDIM = dict(
    num_train_timesteps=1000, beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear", clip_sample=False,
    prediction_type="v_prediction", rescale_betas_zero_snr=True, set_alpha_to_one=True, snr_shift_scale=3.0,
    steps_offset=0, timestep_spacing="trailing",
)


def build_novel_view(
    size: Size = "tiny", device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32, seed: int = 0
) -> NovelViewModel:
    from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
    from transformers import CLIPVisionConfig, CLIPVisionModelWithProjection

    quiet_libraries()
    torch.manual_seed(seed)
    with torch.device(device):
        unet = UNet2DConditionModel(in_channels=8, out_channels=4, **UNET[size])
        vae = AutoencoderKL(latent_channels=4, scaling_factor=0.18215, **VAE[size])
        clip_config = CLIPVisionConfig(**CLIP[size])
        encoder = CLIPVisionModelWithProjection(clip_config)
        projection = torch.nn.Linear(clip_config.projection_dim + POSE_DIMS, unet.config.cross_attention_dim)
    model = NovelViewModel(unet, vae, encoder, projection, DDIMScheduler(**DDIM), CLIP_MEAN, CLIP_STD, clip_config.image_size)
    for module in model.modules():
        module.to(dtype).eval().requires_grad_(False)
    return model


def save_novel_view(model: NovelViewModel, root: Path) -> Path:
    """Write `model` as `root/zero123/` in the diffusers conversion's layout; returns that folder."""
    from safetensors.torch import save_file
    from transformers import CLIPImageProcessor

    folder = root / NOVEL_VIEW
    model.unet.save_pretrained(folder / "unet")
    model.vae.save_pretrained(folder / "vae")
    model.image_encoder.save_pretrained(folder / "image_encoder")
    model.scheduler.save_pretrained(folder / "scheduler")
    side = {"height": model.clip_size, "width": model.clip_size}
    processor = CLIPImageProcessor(
        size={"shortest_edge": model.clip_size}, crop_size=side, image_mean=list(model.clip_mean), image_std=list(model.clip_std)
    )
    processor.save_pretrained(folder / "feature_extractor")
    projection = folder / "cc_projection"
    projection.mkdir(parents=True, exist_ok=True)
    layer = model.cc_projection
    config = {"_class_name": "CCProjection", "in_channel": layer.in_features, "out_channel": layer.out_features}
    (projection / "config.json").write_text(json.dumps(config))
    weights = {"projection.weight": layer.weight, "projection.bias": layer.bias}
    tensors = {k: v.detach().cpu().contiguous() for k, v in weights.items()}
    save_file(tensors, str(projection / "diffusion_pytorch_model.safetensors"))
    _model_index(folder, "Zero1to3StableDiffusionPipeline", {
        "unet": ["diffusers", "UNet2DConditionModel"],
        "vae": ["diffusers", "AutoencoderKL"],
        "image_encoder": ["transformers", "CLIPVisionModelWithProjection"],
        "feature_extractor": ["transformers", "CLIPImageProcessor"],
        "cc_projection": ["diffusers_modules.local.pipeline_zero1to3", "CCProjection"],
        "scheduler": ["diffusers", "DDIMScheduler"],
    })
    return folder


def build_video(
    size: Size = "tiny", device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32, seed: int = 0
) -> VideoModel:
    from diffusers import (
        AutoencoderKLCogVideoX,
        CogVideoXDDIMScheduler,
        CogVideoXTransformer3DModel,
        CogVideoXVideoToVideoPipeline,
    )

    quiet_libraries()
    torch.manual_seed(seed)
    with torch.device(device):
        transformer = CogVideoXTransformer3DModel(**TRANSFORMER[size])
        vae = AutoencoderKLCogVideoX(**VIDEO_VAE[size])
    scheduler = CogVideoXDDIMScheduler(**COGVIDEOX_DDIM)
    pipeline = CogVideoXVideoToVideoPipeline(
        tokenizer=None, text_encoder=None, vae=vae, transformer=transformer, scheduler=scheduler
    )
    pipeline.set_progress_bar_config(disable=True)
    pipeline.to(device, dtype)
    for module in (transformer, vae):
        module.eval().requires_grad_(False)
    config = transformer.config
    generator = torch.Generator().manual_seed(seed + 1)
    shape = (1, config.max_text_seq_length, config.text_embed_dim)
    prompt, negative = (torch.randn(shape, generator=generator).to(device, dtype) for _ in range(2))
    return VideoModel(pipeline, prompt, negative)


def save_video(model: VideoModel, root: Path) -> Path:
    """Write `model` as `root/cogvideox/` in CogVideoX's layout with its prompt embedding file;
    returns that folder."""
    from safetensors.torch import save_file

    folder = root / VIDEO
    model.transformer.save_pretrained(folder / "transformer")
    model.pipeline.vae.save_pretrained(folder / "vae")
    model.pipeline.scheduler.save_pretrained(folder / "scheduler")
    embeddings = {"prompt_embeds": model.prompt_embeds, "negative_prompt_embeds": model.negative_prompt_embeds}
    save_file({k: v.cpu().contiguous() for k, v in embeddings.items()}, str(folder / PROMPT_FILE))
    _model_index(folder, "CogVideoXPipeline", {
        "transformer": ["diffusers", "CogVideoXTransformer3DModel"],
        "vae": ["diffusers", "AutoencoderKLCogVideoX"],
        "scheduler": ["diffusers", "CogVideoXDDIMScheduler"],
        "text_encoder": ["transformers", "T5EncoderModel"],
        "tokenizer": ["transformers", "T5Tokenizer"],
    })
    return folder


def _model_index(folder: Path, class_name: str, components: dict[str, list[str]]) -> None:
    import diffusers

    index = {"_class_name": class_name, "_diffusers_version": diffusers.__version__, **components}
    (folder / "model_index.json").write_text(json.dumps(index, indent=2))
