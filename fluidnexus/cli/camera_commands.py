"""`fluidnexus cameras single | colmap` and `fluidnexus scene info`: scene geometry.

`single` declares one camera from its field of view (a phone video, a clip shot with one
camera); `colmap` calibrates a rig of fixed cameras from the static background its videos
share. Both write nerfstudio's transforms.json with FluidNexus's `scene_box` (docs/cameras.md).
`scene info` prints where the box, the source, the run's solid balls and the cameras are, to place a ball.
"""

from __future__ import annotations

from pathlib import Path

import typer

from fluidnexus.reporting import emit, user_errors

OUT_OPT = typer.Option(..., "--out", help="transforms.json to write.")
DISTANCE_OPT = typer.Option(1.0, "--distance", help="Camera distance from the scene centre, in world units.")
JSON_OPT = typer.Option(False, "--json", help="Print one JSON object (out, cameras, scene_box) on stdout.")


def register(app: typer.Typer, bench: typer.Typer) -> None:
    """Add the `cameras` group to the top-level app."""
    cameras = typer.Typer(help="Write a transforms.json for uncalibrated videos.", no_args_is_help=True)
    cameras.command("single")(single)
    cameras.command("colmap")(colmap)
    app.add_typer(cameras, name="cameras")
    scene = typer.Typer(help="Scene geometry in world units.", no_args_is_help=True)
    scene.command("info")(info)
    app.add_typer(scene, name="scene")


def info(
    path: Path = typer.Argument(..., exists=True, help="A run folder (box, source, solids, cameras) or a camera file (box, cameras)."),
) -> None:
    """Print the scene box, the estimated source, the run's solid balls and the camera centres (world units) as JSON."""
    from fluidcore import scene_info
    from fluidcore.runs import MANIFEST, Run
    from fluidnexus.reporting import echo_json

    with user_errors():
        if (path / MANIFEST).is_file():
            echo_json(scene_info.from_run(Run.open(path), "cli"))
        else:
            echo_json(scene_info.from_cameras_file(path))


def single(
    video: Path = typer.Option(..., "--video", exists=True, dir_okay=False, help="The clip (its size is read from it)."),
    fov: float = typer.Option(..., "--fov", help="Horizontal field of view in degrees."),
    out: Path = OUT_OPT,
    distance: float = DISTANCE_OPT,
    up: str = typer.Option("up", "--up", help="Where world up points in the image: up | down | left | right."),
    as_json: bool = JSON_OPT,
) -> None:
    """One camera at DISTANCE looking at the scene centre, and the scene box it frames."""
    from fluidcore.cameras.single import write_single_camera

    with user_errors():
        _report(write_single_camera(out, video, fov, distance, up), as_json)


def colmap(
    video: list[str] = typer.Option(..., "--video", help="VIEW=path.mp4; one per camera of the rig."),
    out: Path = OUT_OPT,
    distance: float = DISTANCE_OPT,
    camera_model: str = typer.Option("SIMPLE_RADIAL", "--camera-model", help="COLMAP lens model (PINHOLE, SIMPLE_RADIAL, OPENCV, ...)."),
    as_json: bool = JSON_OPT,
) -> None:
    """Calibrate fixed cameras from the static background of their videos (COLMAP, CPU)."""
    from fluidcore.cameras.calibrate import write_rig
    from fluidnexus.cli.scenes import parse_videos

    with user_errors():
        _report(write_rig(out, parse_videos(video), distance=distance, camera_model=camera_model), as_json)


def _report(path: Path, as_json: bool) -> None:
    from fluidcore.cameras import load, scene_box
    from fluidcore.cameras.single import box_json

    cameras, box = load(path), scene_box(path)
    emit(
        as_json, str(path), out=str(path),
        cameras={name: {"center": camera.center().tolist(), "fx": camera.fx, "width": camera.width, "height": camera.height}
                 for name, camera in cameras.items()},
        scene_box=None if box is None else box_json(box),
    )
