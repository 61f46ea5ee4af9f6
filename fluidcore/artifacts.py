"""Rendering a run's artifacts: any run folder (reconstruct, predict, interact, resimulate) to
videos. The CLI's `render`, the worker's runners and the benchmarks all render here; single
frames come from `fluidcore.run_frames` (which Algorithm S2's refinement uses too).

    video_names       the videos a run can have: one per camera, `orbit`, a what-if's
                      `side_by_side` (factual | what-if), a refined prediction's `refined_CAMERA`
    eager_videos      those a finished job renders before it ends (a reconstruction's input
                      views); the worker renders any other on request (`JobType.RENDER`) and
                      storage keeps it
    render_artifacts  named videos as MP4s, at the size the run's reconstruction was fit at,
                      reporting progress per rendered frame
    render_orbit      one turn around the scene while the run plays
    render_side_by_side  the factual | what-if picture, the what-if's ball and wind drawn
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from fluidcore.jobs import JobContext, JobInputError, Progress, no_progress
from fluidcore.run_frames import FrameDone, render_frames

if TYPE_CHECKING:
    from fluidcore.runs import RunRecord

ORBIT, SIDE_BY_SIDE = "orbit", "side_by_side"
SCENE_VIDEOS = (ORBIT, SIDE_BY_SIDE)  # render_artifacts' videos that belong to no camera
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
    from fluidcore.runs import Run

    origin = Run.open(run_dir).reconstruction()
    return None if origin is None else origin.settings.quality.fit.long_side


def published_camera(camera, long_side: int | None):  # noqa: ANN001, ANN201 - Camera
    """`camera` scaled to `long_side` pixels on its long side (never up): a job's videos are
    rendered at the size its reconstruction was fit at (preview: 480 px), which holds all the
    detail the fit has; ScalarFlow's full 1160 px cost 5.8x the pixels for the same picture."""
    from fluidcore.cameras import render_size

    return camera if long_side is None else camera.scaled(*render_size(camera.width, camera.height, long_side))


def video_names(run: RunRecord) -> list[str]:
    """Every video `render_artifacts` can make of `run`: one per camera of the run, `orbit`, a
    what-if's `side_by_side`, and `refined_CAMERA` per camera of a refined prediction's sub-run
    (seen only in a run folder, `Run`; a manifest read from storage lists the rest). The names a
    client may ask for: no other string becomes a file name."""
    from fluidcore.runs import Run, RunKind

    names = [*run.manifest["cameras"], ORBIT]
    if run.kind is RunKind.INTERACT and run.input_views:  # the side-by-side is seen from the input view
        names.append(SIDE_BY_SIDE)
    refined = run.refined() if isinstance(run, Run) else None
    return names + [f"{REFINED_PREFIX}{name}" for name in (refined.manifest["cameras"] if refined else ())]


def eager_videos(run: RunRecord) -> list[str]:
    """The videos a finished job renders before it ends: a reconstruction's input views, and a
    refined prediction's `refined_CAMERA` videos (what Algorithm S2's refinement made). A
    continuation (predict, what-if, resimulate) renders none: its simulation costs about what one
    view's video does (a 30-frame preview what-if of ScalarFlow: 0.25 s CPU simulating, 0.27 s
    rendering the input view), so even that one would be over a third of its time
    (docs/bench_render.md, "What-if artifacts"). Every other name of `video_names` is rendered
    when asked for (`POST /v1/jobs/{id}/videos/{name}`, which the results page calls for the
    videos it shows; `fluidnexus render`)."""
    from fluidcore.runs import RunKind

    views = run.input_views if run.kind is RunKind.RECONSTRUCT else []
    return [*views, *(name for name in video_names(run) if name.startswith(REFINED_PREFIX))]


def check_video_names(run: RunRecord, names: Sequence[str]) -> None:
    """Raise JobInputError unless every name is one of `video_names(run)`."""
    known = video_names(run)
    for name in names:
        if name not in known:
            raise JobInputError(f"video: {name!r} is not a video of this run; have {', '.join(known)}")


def render_artifacts(
    run_dir: str | os.PathLike[str], out_dir: str | os.PathLike[str], names: Sequence[str] | None = None,
    progress: Progress = no_progress, long_side: int | None = None, device: str = "cpu",
) -> list[Path]:
    """`NAME.mp4` in `out_dir` for each of `names` (default: every one of `video_names`); returns
    the files. A what-if's videos draw its ball and wind; its side-by-side reuses the input
    view's frames when they are rendered in the same call. Videos are `long_side` pixels on
    their long side (never upscaled; None: each camera's own size). `progress(fraction,
    "render")` after every rendered frame."""
    from fluidcore.names import safe_join
    from fluidcore.runs import Run, RunKind
    from fluidcore.video import write_mp4

    run = Run.open(run_dir)
    if not run.frames():
        raise JobInputError(f"run: {run_dir} has no finished frames to render")
    names = video_names(run) if names is None else list(dict.fromkeys(names))
    check_video_names(run, names)
    check_camera_names(list(run.cameras()))
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    what_if = run.kind is RunKind.INTERACT
    input_view = run.input_views[0] if run.input_views else None
    refined = run.refined()
    cameras = run.cameras()
    n = len(run.frames())

    def cost(name: str) -> int:  # rendered frames, for the progress fraction
        if name == SIDE_BY_SIDE:
            return n * (1 + int(input_view not in names))  # the factual side, and the what-if's unless rendered here
        return n if name in cameras or name == ORBIT else len(refined.frames())

    total, done = sum(cost(name) for name in names), 0

    def on_frame() -> None:
        nonlocal done
        done += 1
        progress(done / total, "render")

    def size(camera):  # noqa: ANN001, ANN202
        return published_camera(camera, long_side)

    written, input_frames = [], None
    for name in sorted(names, key=lambda name: name == SIDE_BY_SIDE):  # the side-by-side last: it reuses the input view
        if name == ORBIT:
            video = render_orbit(run, device=device, interventions=what_if, on_frame=on_frame, size=size)
        elif name == SIDE_BY_SIDE:
            video = render_side_by_side(run, size(cameras[input_view]), device, what_if=input_frames, on_frame=on_frame)
        elif name in cameras:
            video = render_frames(run, size(cameras[name]), device=device, interventions=what_if, on_frame=on_frame)
            input_frames = video if name == input_view else input_frames
        else:  # refined_CAMERA: the refined sub-run
            video = render_frames(refined, size(refined.cameras()[name[len(REFINED_PREFIX):]]), device=device, on_frame=on_frame)
        fps = run.fps if name in cameras or name in SCENE_VIDEOS else refined.fps
        written.append(write_mp4(safe_join(out, f"{name}.mp4"), video, fps=fps))
    return written


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
