"""The reconstruction job (Algorithm S1) as the CLI, the worker and the benchmark run it.

`run_reconstruct` reads the cameras and ONLY the videos it is handed (a `file_path` in the
cameras file never pulls in another view), checks each video fits its camera
(`fluidcore.cameras.check_video_size`, the rule the API applies to uploads), reconstructs frame
by frame into a run folder (`fluidcore.reconstruct.pipeline.reconstruct`) and resumes when that
folder already holds the same run. Progress, cancellation (its `JobContext`) and input errors
follow `fluidcore.jobs`.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from fluidcore.jobs import JobContext, JobInputError
from fluidcore.spec.source_hint import SourceHint
from fluidcore.spec.reconstruct import DEFAULT_QUALITY, ReconstructConfig, get
from fluidcore.spec.simulation import DEFAULT_PHYSICS, SimulationConfig
from fluidcore.spec.solids import SolidBall, check_solids

if TYPE_CHECKING:
    import numpy as np

    from fluidcore.cameras import Camera
    from fluidcore.generative.stages import GenerativeSettings


def _frame_range(infos: Mapping[str, object], frames: tuple[int, int] | None, field: str = "frames") -> tuple[int, int]:
    available = min(info.n_frames for info in infos.values())
    if frames is None:
        return 0, available
    if frames[1] > available:
        raise JobInputError(f"{field}: {frames[0]}:{frames[1]} asked, but the shortest input video has {available} frames")
    return frames


def run_reconstruct(
    cameras_path: str | os.PathLike[str],
    videos: Mapping[str, str | os.PathLike[str]],
    out_dir: str | os.PathLike[str],
    *,
    quality: str | ReconstructConfig = DEFAULT_QUALITY,
    frames: tuple[int, int] | None = None,
    source: SourceHint | None = None,
    background_frames: tuple[int, int] | None = None,
    world_up: str | None = None,
    physics: str = DEFAULT_PHYSICS,
    simulation: SimulationConfig | None = None,
    solids: Sequence[SolidBall] = (),
    progress_bar: bool = False,
    generative: GenerativeSettings | None = None,
    context: JobContext = JobContext(),
) -> Path:
    """Reconstruct `videos` (camera name -> path) seen by the cameras of `cameras_path`.

    `quality` is a preset name or a `ReconstructConfig` (a preset with overrides, as the benchmark
    uses); `simulation`, when given, replaces its air and spreading settings (the user's
    `SimulationConfig`, or a request model that extends it). `physics` is "auto" (identified from the input view) or a preset name ("scalarflow",
    "fluidnexus"; fluidcore.reconstruct.identify). `source`: where the user knows the smoke's
    source to be (otherwise estimated; one view leaves its depth to a guess). `background_frames`:
    frames of the same videos that show no smoke, the background plate (otherwise the background
    is estimated from the smoke's frames). `world_up`: the axis up points along ("+z"); otherwise
    read from the camera file or the cameras (`fluidcore.cameras.world_up`). `solids`: static balls
    in the scene (`fluidcore.spec.solids`), checked against the scene box before any video is
    decoded, then simulated by the reconstruction and every prediction from it. The videos' frame rate
    is the run's; one the camera file states differently is recorded, and the health report warns.
    Returns the run folder. `progress_bar` draws a
    tqdm bar on stderr (the CLI's).
    With one input view, the generative priors (`generative`, default: the weights of
    `fluidcore.weights.weights_dir()`) replace the symmetry pseudo-views when their weights
    exist; the manifest's "novel_views" and "view_refinement" say what ran or why not.
    """
    from fluidcore import cameras as camera_io
    from fluidcore import video
    from fluidcore.generative.stages import GenerativeSettings
    from fluidcore.reconstruct.loop import Plate
    from fluidcore.cameras.world_up import world_up as world_up_of
    from fluidcore.reconstruct.pipeline import Footage, reconstruct
    from fluidcore.runs import CaptureRecord

    preset = quality if isinstance(quality, ReconstructConfig) else get(quality)
    if simulation is not None:
        preset = preset.with_simulation(simulation)
    cameras_path = Path(cameras_path)
    cameras = camera_io.load(cameras_path)
    if not videos:
        raise JobInputError("videos: give at least one VIEW=path.mp4")
    unknown = sorted(set(videos) - set(cameras))
    if unknown:
        raise JobInputError(f"videos: no camera named {', '.join(unknown)} in {cameras_path.name} (have {', '.join(cameras)})")
    infos = {name: video.probe(path) for name, path in videos.items()}
    for name, info in infos.items():
        try:
            camera_io.check_video_size(cameras[name], Path(videos[name]).name, info.width, info.height)
        except camera_io.CameraError as exc:
            raise JobInputError(str(exc)) from None
    frame_range = _frame_range(infos, frames)
    pinholes = {name: camera.pinhole() for name, camera in cameras.items()}
    box = camera_io.capture_box(cameras_path, pinholes)
    check_solids(solids, *box)
    plate = None
    if background_frames is not None:
        plate_range = _frame_range(infos, background_frames, "background_frames")
        plate = Plate(plate_range, _decoded(cameras, videos, plate_range, preset.fit.long_side))
    try:
        fps = video.common_rate({Path(videos[name]).name: info.fps for name, info in infos.items()})
        up = world_up_of(cameras_path, cameras, world_up)
        capture = CaptureRecord(up_axis=up.axis, up_found=up.found, declared_fps=camera_io.declared_fps(cameras_path))
    except (video.VideoError, camera_io.CameraError) as exc:
        raise JobInputError(str(exc)) from None
    context.progress(0.0, "prepare")
    # handed over, not kept: the pipeline lets the decoded frames go once they are its targets
    return reconstruct(
        Footage(pinholes, _decoded(cameras, videos, frame_range, preset.fit.long_side), frame_range, fps, box,
                up=up.vector, source=source, plate=plate, capture=capture, solids=tuple(solids)),
        preset, out_dir, physics=physics, generative=generative or GenerativeSettings(), context=context,
        progress_bar=progress_bar,
    )


def _decoded(cameras: Mapping[str, Camera], videos: Mapping[str, str | os.PathLike[str]], frame_range: tuple[int, int],
             long_side: int) -> dict[str, np.ndarray]:
    """The frames of `frame_range` of each video at the working size, undistorted: from here on
    every camera is the pinhole the renderer models."""
    from fluidcore import cameras as camera_io
    from fluidcore import video

    return {
        name: camera_io.undistort_frames(
            cameras[name],
            video.read_frames(
                path, frame_range[0], frame_range[1], size=camera_io.render_size(cameras[name].width, cameras[name].height, long_side)
            ),
        )
        for name, path in videos.items()
    }


