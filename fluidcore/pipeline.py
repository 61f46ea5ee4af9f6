"""Jobs: what the command line and the worker call (docs/architecture.md, "Jobs").

`run_reconstruct` reads the cameras and ONLY the videos it is handed (a `file_path` in the
cameras file never pulls in another view), reconstructs frame by frame into a run folder and
resumes when that folder already holds the same run. `render_artifacts` renders a finished
run (any kind: reconstruct, predict, interact, resimulate) to one MP4 per camera plus an
orbit video.

Progress is reported as (fraction, stage); `should_cancel` is asked between frames, and a
cancelled job raises `Cancelled` after its last checkpoint, so starting it again resumes.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # torch-free at import: the worker imports this module lazily anyway
    from fluidcore.reconstruct import Quality

Progress = Callable[[float, str], None]
ShouldCancel = Callable[[], bool]
ORBIT_FRAMES = 120  # a full turn lasts at least this many frames (4 s at 30 fps)


class Cancelled(Exception):
    """Raised when should_cancel() said so; the run folder holds every frame finished before."""


class PipelineError(ValueError):
    """Inputs a job cannot run on; the message names the field."""


def parse_frames(text: str | None) -> tuple[int, int] | None:
    """'A:B' -> (A, B), the half-open frame range [A, B); None passes through."""
    if text is None:
        return None
    try:
        start, stop = (int(x) for x in text.split(":"))
    except ValueError:
        raise PipelineError(f"frames must look like START:END (e.g. 0:60), got {text!r}") from None
    if start < 0 or stop <= start:
        raise PipelineError(f"frames must satisfy 0 <= START < END, got {text!r}")
    return start, stop


def _box(cameras_path: Path, cameras: Mapping[str, object]) -> tuple[np.ndarray, np.ndarray]:
    from fluidcore.cameras import frusta_box, scene_box

    box = scene_box(cameras_path)
    return box if box is not None else frusta_box(cameras)


def _frame_range(infos: Mapping[str, object], frames: tuple[int, int] | None) -> tuple[int, int]:
    available = min(info.n_frames for info in infos.values())
    if frames is None:
        return 0, available
    if frames[1] > available:
        raise PipelineError(f"frames: {frames[0]}:{frames[1]} asked, but the shortest input video has {available} frames")
    return frames


def run_reconstruct(
    cameras_path: str | os.PathLike[str],
    videos: Mapping[str, str | os.PathLike[str]],
    out_dir: str | os.PathLike[str],
    *,
    quality: str | Quality = "preview",
    frames: tuple[int, int] | None = None,
    device: str = "cpu",
    progress: Progress | None = None,
    should_cancel: ShouldCancel | None = None,
    source: tuple[Sequence[float], float] | None = None,
    progress_bar: bool = False,
) -> Path:
    """Reconstruct `videos` (camera name -> path) seen by the cameras of `cameras_path`.

    `quality` is a preset name or a `Quality` (a preset with overrides, as the benchmark
    uses). Returns the run folder. `progress_bar` draws a tqdm bar on stderr (the CLI's).
    """
    from fluidcore import cameras as camera_io
    from fluidcore import video
    from fluidcore.reconstruct import Quality, Reconstructor, get, prepare
    from fluidcore.reconstruct.presets import render_size

    preset = quality if isinstance(quality, Quality) else get(quality)
    cameras_path = Path(cameras_path)
    cameras = camera_io.load(cameras_path)
    if not videos:
        raise PipelineError("videos: give at least one VIEW=path.mp4")
    unknown = sorted(set(videos) - set(cameras))
    if unknown:
        raise PipelineError(f"videos: no camera named {', '.join(unknown)} in {cameras_path.name} (have {', '.join(cameras)})")
    infos = {name: video.probe(path) for name, path in videos.items()}
    for name, info in infos.items():
        camera = cameras[name]
        if abs(info.width / info.height - camera.width / camera.height) > 0.01 * camera.width / camera.height:
            raise PipelineError(
                f"videos: {name} is {info.width}x{info.height} but its camera is {camera.width}x{camera.height} "
                "(another aspect ratio: wrong video or wrong camera?)"
            )
    frame_range = _frame_range(infos, frames)
    fps = infos[next(iter(videos))].fps
    decoded = {
        name: video.read_frames(
            path, frame_range[0], frame_range[1], size=render_size(cameras[name].width, cameras[name].height, preset.long_side)
        )
        for name, path in videos.items()
    }
    report = progress or (lambda fraction, stage: None)
    report(0.0, "prepare")
    rec = prepare(
        cameras, decoded, frame_range=frame_range, fps=fps, quality=preset, box=_box(cameras_path, cameras),
        source=source, device=device,
    )
    del decoded
    reconstructor = Reconstructor(rec, device=device)
    run = reconstructor.open_run(out_dir)
    total = frame_range[1] - frame_range[0]
    bar = _bar(total, len(run.frames()), progress_bar)
    cancelled = False

    def on_frame(t: int, losses: Mapping[str, float]) -> None:
        done = t + 1 - frame_range[0]
        report(done / total, "reconstruct")
        if bar is not None:
            bar.set_postfix(psnr=f"{losses['input_psnr']:.1f}", refresh=False)
            bar.update(1)

    def should_stop() -> bool:
        nonlocal cancelled
        cancelled = bool(should_cancel and should_cancel())
        return cancelled

    run = reconstructor.run(out_dir, on_frame=on_frame, should_stop=should_stop)
    if bar is not None:
        bar.close()
    if cancelled:
        raise Cancelled(f"reconstruction cancelled; {out_dir} resumes from frame {run.next_frame()}")
    return Path(out_dir)


def _bar(total: int, done: int, enabled: bool):  # noqa: ANN202 - tqdm or None
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(total=total, initial=done, unit="frame", desc="reconstruct", file=sys.stderr, dynamic_ncols=True)


# -- rendering runs -----------------------------------------------------------------------------
def run_background(run, camera) -> np.ndarray | float | list[float]:  # noqa: ANN001 - Run, Camera
    """What empty space looks like from `camera` in `run`: the static background image of that
    camera when the run (or its parent) estimated one, otherwise the background colour."""
    from fluidcore.reconstruct.init import resize_image

    current = run
    while current is not None:
        images = current.background_images()
        if camera.name in images:
            return resize_image(images[camera.name], camera.width, camera.height)
        current = current.parent
    return run.background_color


def render_frames(run, camera, frames: Sequence[int] | None = None, device: str = "cpu") -> np.ndarray:  # noqa: ANN001
    """uint8 (T, H, W, 3) renders of `frames` (default: all) of a run from `camera`."""
    import torch

    from fluidcore.reconstruct.visual import Appearance
    from fluidcore.render import render

    frames = run.frames() if frames is None else list(frames)
    background = torch.as_tensor(np.asarray(run_background(run, camera), dtype=np.float32), device=device)
    out = []
    for t in frames:
        g = run.read_frame(t).gaussians
        tensor = lambda a: torch.from_numpy(np.ascontiguousarray(a)).to(device)  # noqa: E731
        appearance = Appearance(tensor(g["log_scales"]), tensor(g["quats"]), tensor(g["opacity_logits"]), tensor(g["colors"]))
        with torch.no_grad():
            image = render(appearance.gaussians(tensor(g["means"])), camera, background, depth=False).image
        out.append(to_uint8_rgb(image.cpu().numpy()))
    return np.stack(out) if out else np.zeros((0, camera.height, camera.width, 3), np.uint8)


def to_uint8_rgb(image: np.ndarray) -> np.ndarray:
    """(..., C) float in [0, 1], C = 1 or 3 -> (..., 3) uint8."""
    image = np.repeat(image, 3, axis=-1) if image.shape[-1] == 1 else image
    return (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def orbit_cameras(run, n: int) -> list:  # noqa: ANN001
    """`n` cameras on a turn around the scene box's vertical axis, at the first input camera's
    distance and height, starting from it."""
    from fluidcore.cameras import orbit

    scene = run.scene
    cameras = run.cameras()
    like = cameras[run.manifest["input_views"][0]] if run.manifest.get("input_views") else next(iter(cameras.values()))
    center = 0.5 * (np.asarray(scene.box_lo) + np.asarray(scene.box_hi))
    up = np.asarray(scene.up)
    offset = like.center() - center
    height = float(offset @ up)
    radius = float(np.linalg.norm(offset - height * up))
    return orbit(center, radius, height, n, like, up=up)


def render_orbit(run, device: str = "cpu") -> np.ndarray:  # noqa: ANN001
    """One full turn around the scene while the run plays (frames repeat when the run is short)."""
    frames = run.frames()
    n = max(len(frames), ORBIT_FRAMES)
    cameras = orbit_cameras(run, n)
    return np.concatenate([render_frames(run, cam, [frames[i * len(frames) // n]], device) for i, cam in enumerate(cameras)])


def render_artifacts(
    run_dir: str | os.PathLike[str], out_dir: str | os.PathLike[str], cameras: Mapping[str, object] | None = None
) -> list[Path]:
    """MP4 per camera (the run's own, or `cameras`) plus `orbit.mp4`; returns the files."""
    from fluidcore.runs import Run
    from fluidcore.video import write_mp4

    run = Run.open(run_dir)
    if not run.frames():
        raise PipelineError(f"run: {run_dir} has no finished frames to render")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name, camera in (cameras or run.cameras()).items():
        written.append(write_mp4(out / f"{name}.mp4", render_frames(run, camera), fps=run.fps))
    written.append(write_mp4(out / "orbit.mp4", render_orbit(run), fps=run.fps))
    return written
