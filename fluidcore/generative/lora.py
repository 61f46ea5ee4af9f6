"""LoRA adapters in peft's folder layout: `adapter_config.json` + `adapter_model.safetensors`.

The same two files are written by `fluidnexus finetune` and read when a model is loaded, for
the Zero123 UNet and the CogVideoX transformer alike (both are diffusers models with peft
support). Adapters go on the attention projections, as in the paper's fine-tuning.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from fluidcore.errors import InputError

if TYPE_CHECKING:
    import torch

ADAPTER_NAME = "smoke"
CONFIG_FILE = "adapter_config.json"
WEIGHTS_FILE = "adapter_model.safetensors"
TARGET_MODULES = ("to_q", "to_k", "to_v", "to_out.0")


def is_adapter(folder: Path) -> bool:
    return (folder / CONFIG_FILE).is_file() and (folder / WEIGHTS_FILE).is_file()


def add_new(module: torch.nn.Module, rank: int = 16, seed: int = 0) -> None:
    """A fresh adapter on `module` (B = 0, so the model's output is unchanged until trained);
    every base weight is frozen, only the adapter trains."""
    import torch
    from peft import LoraConfig

    if rank < 1:
        raise InputError(f"rank must be >= 1, got {rank}")
    for parameter in module.parameters():
        parameter.requires_grad_(False)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        module.add_adapter(LoraConfig(r=rank, lora_alpha=rank, target_modules=list(TARGET_MODULES)), adapter_name=ADAPTER_NAME)


def load(module: torch.nn.Module, folder: Path) -> None:
    """Attach the adapter saved in `folder` to `module` (the module's own weights untouched)."""
    from peft import LoraConfig, set_peft_model_state_dict
    from safetensors.torch import load_file

    if not is_adapter(folder):
        raise InputError(f"{folder}: not a LoRA adapter (needs {CONFIG_FILE} and {WEIGHTS_FILE})")
    module.add_adapter(LoraConfig.from_pretrained(str(folder)), adapter_name=ADAPTER_NAME)
    result = set_peft_model_state_dict(module, load_file(str(folder / WEIGHTS_FILE)), adapter_name=ADAPTER_NAME)
    unexpected = getattr(result, "unexpected_keys", [])
    if unexpected:
        raise InputError(f"{folder}: adapter does not fit this model ({len(unexpected)} unknown weights, e.g. {unexpected[0]})")
    module.to(next(iter(module.parameters())).dtype)


def state(module: torch.nn.Module) -> dict[str, torch.Tensor]:
    """The adapter's weights only, under peft's key names."""
    from peft import get_peft_model_state_dict

    return {k: v.detach().cpu().contiguous() for k, v in get_peft_model_state_dict(module, adapter_name=ADAPTER_NAME).items()}


def save(module: torch.nn.Module, folder: Path) -> Path:
    """Write the module's adapter to `folder` in peft's layout; returns the folder."""
    from safetensors.torch import save_file

    from fluidcore.files import atomic_output

    folder.mkdir(parents=True, exist_ok=True)
    module.peft_config[ADAPTER_NAME].save_pretrained(str(folder))
    with atomic_output(folder / WEIGHTS_FILE) as tmp:
        save_file(state(module), str(tmp))
    return folder
