"""Where local model weights live. Nothing is ever downloaded: a stage whose weights are absent
is skipped and says so (for example, LPIPS is reported as null).

The folder is `$FLUIDNEXUS_MODELS`, or `./models` relative to the working directory. Each model
documents its own layout below that folder (fluidcore.metrics: `lpips/alex.pth` + `lpips/alexnet.pth`;
fluidcore.generative.models: `zero123/`, `cogvideox/`, `lora/<model>/` in the public diffusers and
peft layouts; `fluidnexus models` lists what is there).
"""

from __future__ import annotations

import os
from pathlib import Path, PurePath

from fluidcore.errors import InputError

ENV_VAR = "FLUIDNEXUS_MODELS"
DEFAULT_DIR = "models"


def weights_dir() -> Path:
    """The models folder ($FLUIDNEXUS_MODELS, default ./models); it need not exist."""
    return Path(os.environ.get(ENV_VAR) or DEFAULT_DIR).expanduser()


def find(name: str, root: str | Path | None = None) -> Path | None:
    """`root / name` (root defaults to `weights_dir()`) if that file or folder exists, else None.

    `name` is a relative path inside the models folder; absolute names and `..` are refused
    (InputError) so a configured name can never point outside it.
    """
    relative = PurePath(name)
    if not name or relative.is_absolute() or ".." in relative.parts:
        raise InputError(f"weights name must be a relative path inside the models folder, got {name!r}")
    path = Path(root if root is not None else weights_dir()) / relative
    return path if path.exists() else None
