"""Scene options shared by the benchmarks that read a scene folder (bench/reconstruct.py,
bench/predict.py): one camera-file lookup and one parser for VIEW[=path] and FIELD=JSON, so
both accept the same command lines and report the same errors."""

from __future__ import annotations

import json
from pathlib import Path
from fluidcore.cameras import Camera
from fluidnexus.reporting import UserError

CAMERA_FILES = ("transforms.json", "info.json")


def load_scene(scene: Path, threads: int | None) -> tuple[Path, dict[str, Camera]]:
    """Set the torch thread count (None keeps torch's default), then load the scene's cameras
    from the first of CAMERA_FILES it holds; returns (camera file, cameras by name)."""
    import torch

    from fluidcore import cameras as camera_io

    if threads is not None:
        torch.set_num_threads(threads)
    cameras_path = next((scene / f for f in CAMERA_FILES if (scene / f).is_file()), None)
    if cameras_path is None:
        raise UserError(f"--scene: {scene} holds no {' or '.join(CAMERA_FILES)}")
    return cameras_path, camera_io.load(cameras_path)


def view_paths(items: list[str], option: str, base: Path) -> dict[str, Path | None]:
    """Parse repeated `VIEW` / `VIEW=path` options; paths are relative to `base`, None when absent."""
    out: dict[str, Path | None] = {}
    for item in items:
        name, sep, path = item.partition("=")
        if not name:
            raise UserError(f"{option} must look like VIEW or VIEW=path, got {item!r}")
        out[name] = (base / path) if sep else None
    return out


SET_HELP = ("Quality override FIELD=JSON, repeatable: FIELD a dotted path (fit.long_side) or a field's own name "
            "(long_side, seed, air_cells), checked against the config")


def quality_overrides(items: list[str]) -> dict[str, object]:
    """Parse repeated `--set FIELD=JSON` options into keyword overrides for a quality preset
    (`ReconstructConfig.with_overrides` checks them: FIELD is a dotted path, `fit.long_side`, or a
    field's own name, `long_side`)."""
    values: dict[str, object] = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep:
            raise UserError(f"--set must look like FIELD=VALUE, got {item!r}")
        try:
            values[key] = json.loads(text)
        except ValueError:
            raise UserError(f"--set {key}: {text!r} is not a JSON value") from None
    return values
