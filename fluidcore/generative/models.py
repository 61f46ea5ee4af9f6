"""Which generative weights are in the models folder, and loading them. Nothing is downloaded.

Layout below the models folder (`fluidcore.weights.weights_dir()`: $FLUIDNEXUS_MODELS or ./models),
each model folder exactly as its public diffusers release or conversion ships it:

    zero123/          Zero123 or Zero123-XL, diffusers conversion: unet/ vae/ image_encoder/
                      feature_extractor/ cc_projection/ scheduler/ (model_index.json is not needed)
    cogvideox/        CogVideoX-2b or -5b: transformer/ vae/ scheduler/, and for the text condition
                      either prompt_embeds.safetensors (precomputed T5 output: `prompt_embeds` and
                      `negative_prompt_embeds`, each (1, L, 4096)) or text_encoder/ + tokenizer/
    lora/zero123/     optional LoRA adapters in peft's layout (adapter_config.json +
    lora/cogvideox/   adapter_model.safetensors), as `fluidnexus finetune` writes them

What each enables (STAGES): Zero123 gives the single-view reconstruction its generated views;
CogVideoX refines those views (with Zero123) and the predicted futures (Algorithm S2).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from fluidcore import weights
from fluidcore.errors import InputError
from fluidcore.generative import lora

if TYPE_CHECKING:  # torch and the model libraries load only when a model does: listing is instant
    import torch

    from fluidcore.generative.novel_view import NovelViewModel
    from fluidcore.generative.refine import VideoModel

NOVEL_VIEW = "zero123"
VIDEO = "cogvideox"
PROMPT_FILE = "prompt_embeds.safetensors"
# The scene description the text encoder path encodes (the embedding file replaces it).
DEFAULT_PROMPT = "Thin smoke rising from a source in front of a plain background, static camera, no other motion."

# part -> file that marks it (a config) ; parts with weights also need *.safetensors or *.bin
PARTS: dict[str, dict[str, str]] = {
    NOVEL_VIEW: {
        "unet": "config.json",
        "vae": "config.json",
        "image_encoder": "config.json",
        "feature_extractor": "preprocessor_config.json",
        "cc_projection": "config.json",
        "scheduler": "scheduler_config.json",
    },
    VIDEO: {"transformer": "config.json", "vae": "config.json", "scheduler": "scheduler_config.json"},
}
WEIGHTLESS_PARTS = ("feature_extractor", "scheduler", "tokenizer")
STAGES: dict[str, tuple[str, ...]] = {
    NOVEL_VIEW: ("novel-view: generated views for single-view reconstruction",),
    VIDEO: (
        "refine-views: refinement of generated views (needs zero123 too)",
        "refine-futures: refinement of predicted futures (Algorithm S2)",
    ),
}


class MissingWeights(InputError, FileNotFoundError):
    """The weights a stage needs are not in the models folder; the message says what is missing."""


@dataclass
class ModelEntry:
    """What the models folder holds for one model."""

    name: str
    path: Path
    missing: list[str] = field(default_factory=list)  # parts absent or without weights
    adapter: Path | None = None  # LoRA adapter found for it
    notes: list[str] = field(default_factory=list)

    @property
    def present(self) -> bool:
        return not self.missing

    @property
    def stages(self) -> tuple[str, ...]:
        return STAGES[self.name]

    def to_json(self) -> dict:
        return {
            "name": self.name,
            "path": str(self.path),
            "present": self.present,
            "missing": self.missing,
            "adapter": str(self.adapter) if self.adapter else None,
            "stages": list(self.stages),
            "notes": self.notes,
        }


def quiet_libraries() -> None:
    """diffusers and transformers print progress bars and dtype notes on every load; a job's log
    and the CLI's stderr show our own progress instead."""
    import diffusers
    import transformers

    for library in (diffusers, transformers):
        library.utils.logging.set_verbosity_error()
        library.utils.logging.disable_progress_bar()


def _has_weights(folder: Path) -> bool:
    return any(folder.glob("*.safetensors")) or any(folder.glob("*.bin"))


def _missing_parts(folder: Path, parts: dict[str, str]) -> list[str]:
    missing = []
    for part, marker in parts.items():
        if not (folder / part / marker).is_file():
            missing.append(f"{part}/{marker}")
        elif part not in WEIGHTLESS_PARTS and not _has_weights(folder / part):
            missing.append(f"{part}/ weights (*.safetensors or *.bin)")
    return missing


def _adapter(root: Path, name: str) -> Path | None:
    folder = root / "lora" / name
    return folder if lora.is_adapter(folder) else None


def inventory(root: str | Path | None = None) -> list[ModelEntry]:
    """One entry per generative model, whether or not it is present."""
    root = Path(root) if root is not None else weights.weights_dir()
    entries = []
    for name, parts in PARTS.items():
        folder = root / name
        entry = ModelEntry(name, folder, _missing_parts(folder, parts), _adapter(root, name))
        if name == VIDEO:
            _check_text_condition(entry)
        entries.append(entry)
    return entries


def _check_text_condition(entry: ModelEntry) -> None:
    if (entry.path / PROMPT_FILE).is_file():
        entry.notes.append(f"text condition: {PROMPT_FILE}")
    elif (entry.path / "text_encoder" / "config.json").is_file() and (entry.path / "tokenizer").is_dir():
        entry.notes.append(f"text condition: text_encoder/ encodes {DEFAULT_PROMPT!r} once per load")
    else:
        entry.missing.append(f"{PROMPT_FILE} (or text_encoder/ + tokenizer/)")


def entry(name: str, root: str | Path | None = None) -> ModelEntry:
    return next(e for e in inventory(root) if e.name == name)


def skip_reason(name: str, root: str | Path | None = None) -> str | None:
    """None when `name` can be loaded, else the manifest's 'skipped: ...' line."""
    found = entry(name, root)
    if found.present:
        return None
    if not found.path.exists():
        return f"skipped: no {name} weights in {found.path.parent}"
    return f"skipped: {name} weights in {found.path} are incomplete (missing {', '.join(found.missing)})"


def _require(name: str, root: str | Path | None) -> ModelEntry:
    reason = skip_reason(name, root)
    if reason is not None:
        raise MissingWeights(reason.removeprefix("skipped: "))
    return entry(name, root)


def _loading(name: str, root: str | Path | None, dtype: torch.dtype | None) -> tuple[ModelEntry, dict]:
    """The model's entry (MissingWeights when it cannot load) and the from_pretrained options:
    the dtype (None: float32) and local files only, so nothing is ever fetched."""
    import torch

    found = _require(name, root)
    quiet_libraries()
    return found, {"torch_dtype": dtype or torch.float32, "local_files_only": True}


def _denoiser(model_class: type, found: ModelEntry, part: str, options: dict, use_adapter: bool) -> torch.nn.Module:
    """The model's denoising network, with the LoRA adapter of the models folder when asked."""
    module = model_class.from_pretrained(found.path / part, **options)
    if use_adapter and found.adapter is not None:
        lora.load(module, found.adapter)
    return module


def load_novel_view(
    root: str | Path | None = None, device: str | torch.device = "cpu", dtype: torch.dtype | None = None, use_adapter: bool = True
) -> NovelViewModel:
    """The Zero123 model of the models folder (with its LoRA adapter when there is one);
    dtype None is float32."""
    from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
    from transformers import CLIPVisionModelWithProjection

    from fluidcore.generative.novel_view import NovelViewModel

    found, options = _loading(NOVEL_VIEW, root, dtype)
    path, dtype = found.path, options["torch_dtype"]
    unet = _denoiser(UNet2DConditionModel, found, "unet", options, use_adapter)
    processor = json.loads((path / "feature_extractor" / "preprocessor_config.json").read_text())
    model = NovelViewModel(
        unet=unet,
        vae=AutoencoderKL.from_pretrained(path / "vae", **options),
        image_encoder=CLIPVisionModelWithProjection.from_pretrained(path / "image_encoder", **options),
        cc_projection=load_cc_projection(path / "cc_projection", dtype),
        scheduler=DDIMScheduler.from_pretrained(path / "scheduler", local_files_only=True),
        clip_mean=tuple(processor["image_mean"]),
        clip_std=tuple(processor["image_std"]),
        clip_size=_crop_side(processor),
    )
    for module in model.modules():
        module.to(device).eval().requires_grad_(False)
    return model


def _crop_side(processor: dict) -> int:
    crop = processor.get("crop_size", processor.get("size"))
    if isinstance(crop, dict):
        crop = crop.get("height", crop.get("shortest_edge"))
    return int(crop)


def load_cc_projection(folder: Path, dtype: torch.dtype) -> torch.nn.Linear:
    """The pose projection as the conversion stores it: config.json (in_channel, out_channel)
    and a `projection` Linear's weight and bias (safetensors, or the older .bin)."""
    import torch

    config = json.loads((folder / "config.json").read_text())
    layer = torch.nn.Linear(int(config["in_channel"]), int(config["out_channel"]))
    safetensors_file = folder / "diffusion_pytorch_model.safetensors"
    if safetensors_file.is_file():
        from safetensors.torch import load_file

        state = load_file(str(safetensors_file))
    else:
        state = torch.load(folder / "diffusion_pytorch_model.bin", map_location="cpu", weights_only=True)
    layer.load_state_dict({key.removeprefix("projection."): value for key, value in state.items()})
    return layer.to(dtype)


def load_video(
    root: str | Path | None = None, device: str | torch.device = "cpu", dtype: torch.dtype | None = None, use_adapter: bool = True
) -> VideoModel:
    """The CogVideoX video-to-video model of the models folder, text condition encoded; dtype
    None is float32."""
    from diffusers import (
        AutoencoderKLCogVideoX,
        CogVideoXDDIMScheduler,
        CogVideoXTransformer3DModel,
        CogVideoXVideoToVideoPipeline,
    )

    from fluidcore.generative.refine import VideoModel

    found, options = _loading(VIDEO, root, dtype)
    path, dtype = found.path, options["torch_dtype"]
    transformer = _denoiser(CogVideoXTransformer3DModel, found, "transformer", options, use_adapter)
    pipeline = CogVideoXVideoToVideoPipeline(
        tokenizer=None,
        text_encoder=None,
        vae=AutoencoderKLCogVideoX.from_pretrained(path / "vae", **options),
        transformer=transformer,
        scheduler=CogVideoXDDIMScheduler.from_pretrained(path / "scheduler", local_files_only=True),
    )
    pipeline.set_progress_bar_config(disable=True)
    pipeline.to(device)
    for module in (pipeline.transformer, pipeline.vae):
        module.eval().requires_grad_(False)
    prompt, negative = _text_condition(path, int(transformer.config.max_text_seq_length), device, dtype)
    return VideoModel(pipeline, prompt, negative)


def _text_condition(path: Path, length: int, device: str | torch.device, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """(prompt, negative prompt) embeddings: from the file, else from T5 run once (then dropped),
    padded to the transformer's text length (226 tokens for CogVideoX)."""
    embeddings = path / PROMPT_FILE
    if embeddings.is_file():
        from safetensors.torch import load_file

        tensors = load_file(str(embeddings))
        for key in ("prompt_embeds", "negative_prompt_embeds"):
            if key not in tensors or tensors[key].ndim != 3 or tensors[key].shape[0] != 1:
                raise MissingWeights(f"{embeddings}: needs a (1, L, D) tensor named {key!r}")
        return tensors["prompt_embeds"].to(device, dtype), tensors["negative_prompt_embeds"].to(device, dtype)
    import torch
    from transformers import AutoTokenizer, T5EncoderModel

    tokenizer = AutoTokenizer.from_pretrained(path / "tokenizer", local_files_only=True)
    encoder = T5EncoderModel.from_pretrained(path / "text_encoder", torch_dtype=dtype, local_files_only=True).to(device)
    with torch.no_grad():
        embeds = [_encode(tokenizer, encoder, text, length, device) for text in (DEFAULT_PROMPT, "")]
    del encoder
    return embeds[0].to(dtype), embeds[1].to(dtype)


def _encode(tokenizer, encoder, text: str, length: int, device: str | torch.device) -> torch.Tensor:
    """T5 hidden states of `text`, padded to `length` tokens as CogVideoX's pipeline does."""
    ids = tokenizer(text, padding="max_length", max_length=length, truncation=True, add_special_tokens=True, return_tensors="pt")
    return encoder(ids.input_ids.to(device))[0]

