"""Rendering a run's artifacts: any run folder (reconstruct, predict, interact, resimulate) to
videos. The CLI's `render`, the worker's runners and the benchmarks all render here; single
frames come from `fluidcore.run_frames` (which Algorithm S2's refinement uses too).

    render_orbit      one turn around the scene while the run plays
    render_artifacts  one MP4 per camera plus `orbit.mp4` (and for a what-if `side_by_side.mp4`,
                      factual | what-if): what a finished job publishes, at the size its
                      reconstruction was fit at, reporting progress per rendered frame
    render_side_by_side  the factual | what-if picture, the what-if's ball and wind drawn
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np

from fluidcore.jobs import JobContext, JobInputError, Progress, no_progress
from fluidcore.run_frames import FrameDone, render_frames

SCENE_VIDEOS = ("orbit", "side_by_side")  # render_artifacts' videos that belong to no camera
REFINED_PREFIX = "refined_"


def check_camera_names(names: Sequence[str]) -> None:
    """Raise JobInputError when a camera's video would take the file name of another video of
    `render_artifacts` (a camera named `orbit`, or `refined_x` beside `x`): two artifacts under
    one name would make the job's publication fail. The API applies it to uploads, before any work."""
    for name in names:
        if name in SCENE_VIDEOS or (name.startswith(REFINED_PREFIX) and name[len(REFINED_PREFIX):] in names):
            raise JobInputError(
                f"camera {name!r}: its video would have the name of another video of the job "
                f"({', '.join(SCENE_VIDEOS)}, {REFINED_PREFIX}<camera>); rename the camera"
            )


def orbit_cameras(run, n: int) -> list:  # noqa: ANN001
    """`n` cameras on a turn around the scene box's vertical axis, at the first input camera's
    distance and height, starting from it."""
    from fluidcore.cameras import orbit

    scene = run.scene
    cameras = run.cameras()
    like = cameras[run.input_views[0]] if run.input_views else next(iter(cameras.values()))
    center = 0.5 * (np.asarray(scene.box_lo) + np.asarray(scene.box_hi))
    up = np.asarray(scene.up)
    offset = like.center() - center
    height = float(offset @ up)
    radius = float(np.linalg.norm(offset - height * up))
    return orbit(center, radius, height, n, like, up=up)


def render_orbit(
    run, frames: Sequence[int] | None = None, device: str = "cpu", interventions: bool = False,  # noqa: ANN001
    on_frame: FrameDone | None = None, size: Callable[[object], object] | None = None,
) -> np.ndarray:
    """One full turn around the scene while `frames` (default: all) play, one frame per step of
    the turn: as long as the camera videos, so players of both stay in step. `size` maps each
    orbit camera to the one rendered (`published_camera`)."""
    frames = run.frames() if frames is None else list(frames)
    cameras = orbit_cameras(run, len(frames))
    return np.concatenate([
        render_frames(run, cam if size is None else size(cam), [t], device, interventions, on_frame)
        for cam, t in zip(cameras, frames, strict=True)
    ])


def fit_long_side(run_dir: str | os.PathLike[str]) -> int | None:
    """The long side, in pixels, that the reconstruction behind the run was fit at (preview:
    480); None for a run with no reconstruction among its ancestors."""
    from fluidcore.reconstruct.presets import reconstruction_quality
    from fluidcore.runs import Run

    quality = reconstruction_quality(Run.open(run_dir))
    return None if quality is None else quality.long_side


def published_camera(camera, long_side: int | None):  # noqa: ANN001, ANN201 - Camera
    """`camera` scaled to `long_side` pixels on its long side (never up): a job's videos are
    rendered at the size its reconstruction was fit at (preview: 480 px), which holds all the
    detail the fit has; ScalarFlow's full 1160 px cost 5.8x the pixels for the same picture."""
    from fluidcore.cameras import render_size

    return camera if long_side is None else camera.scaled(*render_size(camera.width, camera.height, long_side))


def render_artifacts(
    run_dir: str | os.PathLike[str], out_dir: str | os.PathLike[str], cameras: Mapping[str, object] | None = None,
    progress: Progress = no_progress, long_side: int | None = None,
) -> list[Path]:
    """MP4 per camera (the run's own, or `cameras`) plus `orbit.mp4`; returns the files. A
    what-if renders only its input views of the run's own cameras (its side-by-side shows the
    input view; `fluidnexus render` draws any other camera), since rendering every camera took
    most of its time (docs/bench_render.md, "What-if artifacts"). A prediction refined by
    Algorithm S2 adds `refined_CAMERA.mp4` per camera: its `refined/` sub-run, the future
    reconstructed on the refined frames. Videos are `long_side` pixels on their long side
    (never upscaled; None: each camera's own size). `progress(fraction, "render")` after every
    rendered frame."""
    from fluidcore.names import safe_join
    from fluidcore.runs import Run, RunKind
    from fluidcore.video import write_mp4

    run = Run.open(run_dir)
    if not run.frames():
        raise JobInputError(f"run: {run_dir} has no finished frames to render")
    check_camera_names(list(cameras or run.cameras()))
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    what_if = run.kind is RunKind.INTERACT
    own = dict(cameras or published_cameras(run))
    refined = run.refined()
    refined_cameras = dict(cameras or refined.cameras()) if refined is not None else {}
    n = len(run.frames())
    side = int(what_if) * (1 + int(cameras is not None))  # the factual side, and the what-if's unless already rendered
    total = n * (len(own) + 1 + side) + (len(refined.frames()) * len(refined_cameras) if refined else 0)
    done = 0

    def on_frame() -> None:
        nonlocal done
        done += 1
        progress(done / total, "render")

    def size(camera):  # noqa: ANN001, ANN202
        return published_camera(camera, long_side)

    written, videos = [], {}
    for name, camera in own.items():
        videos[name] = render_frames(run, size(camera), interventions=what_if, on_frame=on_frame)
        written.append(write_mp4(safe_join(out, f"{name}.mp4"), videos[name], fps=run.fps))
    orbit = render_orbit(run, interventions=what_if, on_frame=on_frame, size=size)
    written.append(write_mp4(out / "orbit.mp4", orbit, fps=run.fps))
    for name, camera in refined_cameras.items():
        written.append(write_mp4(safe_join(out, f"{REFINED_PREFIX}{name}.mp4"), render_frames(refined, size(camera), on_frame=on_frame), fps=refined.fps))
    if what_if:
        name = run.input_views[0]
        camera = size(run.cameras()[name])
        both = render_side_by_side(run, camera, what_if=videos.get(name) if cameras is None else None, on_frame=on_frame)
        written.append(write_mp4(out / "side_by_side.mp4", both, fps=run.fps))
    return written


def published_cameras(run) -> dict[str, object]:  # noqa: ANN001 - Run
    """The cameras whose videos a finished job publishes: all of the run's, a what-if's input views."""
    cameras = run.cameras()
    from fluidcore.runs import RunKind

    if run.kind is RunKind.INTERACT:
        return {name: cameras[name] for name in run.input_views}
    return cameras


def render_side_by_side(
    run, camera, device: str = "cpu", what_if: np.ndarray | None = None, on_frame: FrameDone | None = None,  # noqa: ANN001
) -> np.ndarray:
    """factual | what-if over the what-if run's frames, from `camera`: both start from the same
    branch frame of the parent, the what-if with its ball and wind drawn (`what_if`: those
    frames when already rendered, uint8 (T, H, W, 3))."""
    from fluidcore.overlay import side_by_side

    if what_if is None:
        what_if = render_frames(run, camera, device=device, interventions=True, on_frame=on_frame)
    return side_by_side(factual_frames(run, camera, device, on_frame), what_if)


def factual_frames(run, camera, device: str = "cpu", on_frame: FrameDone | None = None) -> np.ndarray:  # noqa: ANN001 - Run, Camera
    """What the parent shows over `run`'s frames without the intervention: its own frames when it
    holds them all (a what-if branched inside a reconstruction), else a prediction from the same
    branch frame without intervention (the branch goes past the parent's last frame)."""
    import tempfile

    from fluidcore.predict import run_predict
    from fluidcore.runs import Run

    parent, frames = run.parent, run.frames()
    if set(frames) <= set(parent.frames()):
        return render_frames(parent, camera, frames, device, on_frame=on_frame)
    with tempfile.TemporaryDirectory(prefix="fluidnexus-factual-") as tmp:
        branch = run.settings.branch_frame
        factual = Run.open(run_predict(parent.path, Path(tmp) / "factual", frames=frames[-1] - branch, from_frame=branch,
                                      context=JobContext(device=device)))
        return render_frames(factual, camera, frames, device, on_frame=on_frame)
