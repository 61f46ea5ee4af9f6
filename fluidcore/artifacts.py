"""Rendering a run's artifacts: any run folder (reconstruct, predict, interact, resimulate) to
images and videos. The CLI's `render`, the worker's runners and the benchmarks all render here.

    render_frames     uint8 frames of a run from one camera (the run's own, or any other)
    render_orbit      one turn around the scene while the run plays
    render_artifacts  one MP4 per camera plus `orbit.mp4` (and for a what-if `side_by_side.mp4`,
                      factual | what-if): what a finished job publishes
    render_side_by_side  the factual | what-if picture, the what-if's ball and wind drawn
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from fluidcore.jobs import JobContext, JobInputError

ORBIT_FRAMES = 120  # a full turn lasts at least this many frames (4 s at 30 fps)
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


def render_frames(
    run, camera, frames: Sequence[int] | None = None, device: str = "cpu", interventions: bool = False  # noqa: ANN001
) -> np.ndarray:
    """uint8 (T, H, W, 3) renders of `frames` (default: all) of a run from `camera`.

    `interventions` draws the run's ball and wind over the smoke (fluidcore.overlay): on in the
    videos made for people (`render_artifacts`, `fluidnexus render` of an interact run), off
    where renders are scored against footage, in which the ball is invisible."""
    import torch

    from fluidcore.overlay import draw_run_interventions

    from fluidcore.render import render
    from fluidcore.smoke import visual_layer

    frames = run.frames() if frames is None else list(frames)
    background = torch.as_tensor(np.asarray(run_background(run, camera), dtype=np.float32), device=device)
    out = []
    for t in frames:
        means, appearance = visual_layer(run.read_frame(t), device)
        with torch.no_grad():
            image = render(appearance.gaussians(means), camera, background, depth=False).image
        out.append(to_uint8_rgb(image.cpu().numpy()))
    video = np.stack(out) if out else np.zeros((0, camera.height, camera.width, 3), np.uint8)
    if interventions:
        video = draw_run_interventions(run, camera, frames, video)
    return video


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
    like = cameras[run.input_views[0]] if run.input_views else next(iter(cameras.values()))
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
    """MP4 per camera (the run's own, or `cameras`) plus `orbit.mp4`; returns the files. A
    prediction refined by Algorithm S2 adds `refined_CAMERA.mp4` per camera: its `refined/`
    sub-run, the future reconstructed on the refined frames."""
    from fluidcore.names import safe_join
    from fluidcore.runs import Run, RunKind
    from fluidcore.video import write_mp4

    run = Run.open(run_dir)
    if not run.frames():
        raise JobInputError(f"run: {run_dir} has no finished frames to render")
    check_camera_names(list(cameras or run.cameras()))
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    what_if = run.kind is RunKind.INTERACT
    for name, camera in (cameras or run.cameras()).items():
        written.append(write_mp4(safe_join(out, f"{name}.mp4"), render_frames(run, camera, interventions=what_if), fps=run.fps))
    written.append(write_mp4(out / "orbit.mp4", render_orbit(run), fps=run.fps))
    refined = run.refined()
    if refined is not None:
        for name, camera in (cameras or refined.cameras()).items():
            written.append(write_mp4(safe_join(out, f"refined_{name}.mp4"), render_frames(refined, camera), fps=refined.fps))
    if what_if:
        camera = run.cameras()[run.input_views[0]]
        written.append(write_mp4(out / "side_by_side.mp4", render_side_by_side(run, camera), fps=run.fps))
    return written


def render_side_by_side(run, camera, device: str = "cpu") -> np.ndarray:  # noqa: ANN001 - Run, Camera
    """factual | what-if over the what-if run's frames, from `camera`: both start from the same
    branch frame of the parent, the what-if with its ball and wind drawn."""
    from fluidcore.overlay import side_by_side

    return side_by_side(factual_frames(run, camera, device), render_frames(run, camera, device=device, interventions=True))


def factual_frames(run, camera, device: str = "cpu") -> np.ndarray:  # noqa: ANN001 - Run, Camera
    """What the parent shows over `run`'s frames without the intervention: its own frames when it
    holds them all (a what-if branched inside a reconstruction), else a prediction from the same
    branch frame without intervention (the branch goes past the parent's last frame)."""
    import tempfile

    from fluidcore.predict import run_predict
    from fluidcore.runs import Run

    parent, frames = run.parent, run.frames()
    if set(frames) <= set(parent.frames()):
        return render_frames(parent, camera, frames, device)
    with tempfile.TemporaryDirectory(prefix="fluidnexus-factual-") as tmp:
        branch = run.settings.branch_frame
        factual = Run.open(run_predict(parent.path, Path(tmp) / "factual", frames=frames[-1] - branch, from_frame=branch,
                                      context=JobContext(device=device)))
        return render_frames(factual, camera, frames, device)
