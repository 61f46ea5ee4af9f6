"""`fluidnexus synth | reconstruct | render | export`: from videos to particles and back to videos.

`reconstruct` reads only the videos named with --video (a file_path in the cameras file never
pulls in another view), shows a progress bar on stderr and resumes an unfinished run in --out.
`render` and `export` work on any run folder (reconstruct, predict, interact, resimulate).
"""

from __future__ import annotations

from pathlib import Path

import typer

from fluidcore.names import check_name
from fluidcore.spec.jobs import ReconstructParams
from fluidcore.spec.reconstruct import DEFAULT_QUALITY, QUALITY_HELP
from fluidcore.spec.simulation import DEFAULT_PHYSICS, PHYSICS_MODES
from fluidcore.spec.solids import MAX_SOLIDS
from fluidnexus.reporting import UserError, check_device, emit, emit_run, user_errors
from fluidnexus.cli.generative import ModelsDir
from fluidnexus.cli.options import spec_option

RUN_ARG = typer.Argument(..., help="Run folder (from reconstruct, predict, interact or resimulate).")
JSON_OPT = typer.Option(False, "--json", help="Print one JSON object on stdout (logs and progress stay on stderr).")


def register(app: typer.Typer, bench: typer.Typer) -> None:
    """Add synth, reconstruct, render and export to the top-level app."""
    app.command("synth")(synth)
    app.command("reconstruct")(reconstruct)
    app.command("render")(render)
    app.command("export")(export)


def _set_threads(threads: int | None) -> None:
    import torch

    if threads is not None:
        torch.set_num_threads(threads)


def parse_videos(items: list[str]) -> dict[str, Path]:
    videos: dict[str, Path] = {}
    for item in items:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise UserError(f"--video must look like VIEW=path.mp4, got {item!r}")
        check_name(name, "--video: VIEW")
        if name in videos:
            raise UserError(f"--video: view {name!r} given twice")
        if not Path(path).is_file():
            raise UserError(f"--video {name}: no such file {path}")
        videos[name] = Path(path)
    return videos


def synth(
    out: Path = typer.Option(..., "--out", help="Folder for the scene (transforms.json, videos/, truth/)."),
    frames: int = typer.Option(30, "--frames", min=1, help="Frames to simulate."),
    width: int = typer.Option(96, "--width", min=16),
    height: int = typer.Option(128, "--height", min=16),
    views: int = typer.Option(5, "--views", min=1, help="Cameras on a half circle around the plume."),
    seed: int = typer.Option(0, "--seed"),
) -> None:
    """Simulate and render a small synthetic plume with known ground truth (try the pipeline without data)."""
    from fluidcore import synth as synth_module

    with user_errors():
        spec = synth_module.SynthSpec(frames=frames, width=width, height=height, views=views, seed=seed)
        path = synth_module.write(synth_module.generate(spec), out)
    typer.echo(str(path))


def reconstruct(
    cameras: Path = typer.Option(..., "--cameras", exists=True, help="transforms.json, info.json or a COLMAP model."),
    video: list[str] = typer.Option(..., "--video", help="VIEW=path.mp4; repeat for several input views."),
    frames: str | None = typer.Option(None, "--frames", help="START:END (end exclusive); default: every frame."),
    quality: str = typer.Option(DEFAULT_QUALITY, "--quality", help=QUALITY_HELP),
    physics: str = typer.Option(DEFAULT_PHYSICS, "--physics", help=" | ".join(PHYSICS_MODES) + ": identified from the video, or a preset"),
    source: str | None = typer.Option(
        None, "--source", help="X,Y,Z[,R]: the smoke source's centre (and radius) in world units, when known; one view "
        "cannot tell its depth. Kept as given (a radius left out is measured around the centre).",
    ),
    refine_source: bool = typer.Option(
        False, "--refine-source", help="Let the identification move and resize the --source, as it does an estimated one."
    ),
    background_frames: str | None = typer.Option(
        None, "--background-frames",
        help="START:END (end exclusive): frames of the same videos without smoke, the background plate. Give it when the "
        "smoke never leaves part of the view (a steady stem): estimated from the smoke's frames otherwise.",
    ),
    world_up: str | None = typer.Option(
        None, "--world-up", help="+x|-x|+y|-y|+z|-z: the axis the world's up points along (+z in Blender's files); default: "
        "the camera file's `up`, else the cameras' mean image up, else +y.",
    ),
    motion: str = spec_option(ReconstructParams, "motion", "--motion"),
    air_cells: int | None = spec_option(ReconstructParams, "air_cells", "--air-cells"),
    air_vorticity: float = spec_option(ReconstructParams, "air_vorticity", "--air-vorticity"),
    entrainment: bool = spec_option(ReconstructParams, "entrainment", "--entrainment"),
    ball: list[str] = typer.Option(
        [], "--ball", help='\'{"center": [x, y, z], "radius": r}\': a static ball in the scene the smoke flows around '
        f"(world units, inside the scene box; repeat for up to {MAX_SOLIDS}; the n-th is solids[n-1] in messages), "
        "simulated by the reconstruction and every prediction and what-if from it.",
    ),
    out: Path = typer.Option(..., "--out", help="Run folder; an unfinished run there is resumed."),
    device: str = typer.Option("cpu", "--device", help="torch device: cpu, cuda, ..."),
    threads: int | None = typer.Option(None, "--threads", min=1, help="torch CPU threads (default: all cores)."),
    models: ModelsDir = None,
    as_json: bool = JSON_OPT,
) -> None:
    """Reconstruct physical particles and visual Gaussians from one video or a few (Algorithm S1).

    With one video and novel-view weights in the models folder, generated views of the other
    cameras join the fit (see `fluidnexus models`)."""
    from fluidcore.generative.stages import GenerativeSettings
    from fluidcore.jobs import JobContext, parse_frames
    from fluidcore.reconstruct.job import run_reconstruct
    from fluidcore.spec.controls import json_object
    from fluidcore.spec.source_hint import parse_source
    from fluidcore.spec.jobs import job_params

    with user_errors():
        if refine_source and source is None:
            raise UserError("--refine-source refines a --source: give one")
        params = job_params(  # the API's reconstruct params: one check, one message naming the field
            ReconstructParams, quality=quality, physics=physics, frames=parse_frames(frames),
            source=None if source is None else parse_source(source, refine_source), motion=motion, air_cells=air_cells,
            air_vorticity=air_vorticity,
            entrainment=entrainment, background_frames=parse_frames(background_frames, "--background-frames"),
            world_up=world_up, solids=[json_object(text, "--ball") for text in ball],
        )
        check_device(device)
        _set_threads(threads)
        path = run_reconstruct(
            cameras, parse_videos(video), out, quality=params.quality, physics=params.physics, frames=params.frames,
            source=params.source, background_frames=params.background_frames, world_up=params.world_up, simulation=params,  # a ReconstructParams is its SimulationConfig
            solids=params.solids,
            progress_bar=True, generative=GenerativeSettings(models_root=models), context=JobContext(device),
        )
        emit_run(as_json, path)


def render(
    run: Path = RUN_ARG,
    camera: str | None = typer.Option(None, "--camera", help="Camera name (see the run's manifest), or 'orbit'."),
    cameras: Path | None = typer.Option(None, "--cameras", exists=True, help="Take CAMERA from this file instead."),
    frames: str | None = typer.Option(None, "--frames", help="START:END of the run's frames; default: all."),
    out: Path | None = typer.Option(None, "--out", help="MP4 to write."),
    png_dir: Path | None = typer.Option(None, "--png-dir", help="Also (or instead) write one PNG per frame here."),
    device: str = typer.Option("cpu", "--device"),
    interventions: bool | None = typer.Option(
        None, "--interventions/--no-interventions", help="Draw the ball and the wind arrow (default: on for interact runs)."
    ),
    as_json: bool = JSON_OPT,
) -> None:
    """Render a run's frames from one of its cameras, a camera of another file, or an orbit around the scene."""
    from fluidcore import cameras as camera_io
    from fluidcore.artifacts import render_orbit
    from fluidcore.run_frames import render_frames
    from fluidcore.jobs import parse_frames
    from fluidcore.runs import Run, RunKind
    from fluidcore.video import write_mp4

    with user_errors():
        if out is None and png_dir is None:
            raise UserError("give --out video.mp4 and/or --png-dir DIR")
        if camera is None:
            raise UserError("--camera NAME is required (or --camera orbit)")
        check_device(device)
        the_run = Run.open(run)
        draw = the_run.kind is RunKind.INTERACT if interventions is None else interventions
        selected = _select_frames(the_run.frames(), parse_frames(frames))
        if camera == "orbit" and cameras is None:
            video = render_orbit(the_run, selected, device, draw)
        else:
            available = camera_io.load(cameras) if cameras is not None else the_run.cameras()
            if camera not in available:
                raise UserError(f"--camera: no camera {camera!r}; have {', '.join(available)} (or 'orbit')")
            video = render_frames(the_run, available[camera], selected, device, draw)
        if out is not None:
            write_mp4(out, video, fps=the_run.fps)
        if png_dir is not None:
            _write_pngs(png_dir, video, selected)
    written = [str(p) for p in (out, png_dir) if p is not None]
    emit(as_json, "\n".join(written), run=str(run), camera=camera, frames=[selected[0], selected[-1]],
         mp4=None if out is None else str(out), png_dir=None if png_dir is None else str(png_dir))


def _select_frames(available: list[int], wanted: tuple[int, int] | None) -> list[int]:
    if not available:
        raise UserError("the run has no finished frames yet")
    if wanted is None:
        return available
    selected = [t for t in available if wanted[0] <= t < wanted[1]]
    if not selected:
        raise UserError(f"--frames {wanted[0]}:{wanted[1]} holds none of the run's frames ({available[0]}..{available[-1]})")
    return selected


def _write_pngs(folder: Path, video, frames: list[int]) -> None:  # noqa: ANN001 - uint8 array
    import av

    folder.mkdir(parents=True, exist_ok=True)
    for image, t in zip(video, frames, strict=True):
        av.VideoFrame.from_ndarray(image, format="rgb24").to_image().save(folder / f"frame_{t:06d}.png")


def export(
    run: Path = RUN_ARG,
    frame: int | None = typer.Option(None, "--frame", help="Frame number (as in the run's manifest); default: the last."),
    frames: str | None = typer.Option(
        None, "--frames", help="START:END (end excluded): a numbered sequence of these frames into the folder --out "
        "(with --bundle: into the zip; default: every frame)."
    ),
    fmt: str = typer.Option("npz", "--format", help="npz | ply | density | nrrd | velocity | vdb (docs/exports.md)."),
    out: Path = typer.Option(..., "--out", help="File to write; with --frames, the folder for the sequence; with --bundle, the zip."),
    voxel_size: float | None = typer.Option(
        None, "--voxel-size", help="Voxel size of the grid formats (density, nrrd, velocity, vdb), world units, at most "
        "the kernel radius h; default h/2, a bundle's h/4. Halving it costs 8x the voxels (docs/exports.md)."
    ),
    bundle: bool = typer.Option(False, "--bundle", help="One zip of a vdb, ply or density sequence, with bundle.json."),
    as_json: bool = JSON_OPT,
) -> None:
    """Write a frame or a sequence: particles (npz), 3D Gaussian splats (ply), a density volume (density, nrrd, vdb) or its velocity (velocity)."""
    from fluidcore.exports import export_bundle, export_frame, export_sequence, last_frame, plan_bundle
    from fluidcore.jobs import parse_frames
    from fluidcore.runs import Run

    with user_errors():
        if frame is not None and frames is not None:
            raise UserError("give --frame (one file) or --frames START:END (a sequence), not both")
        if frame is not None and bundle:
            raise UserError("a bundle holds a sequence: give --frames START:END (or nothing: every frame), not --frame")
        wanted = parse_frames(frames)
        if bundle:
            plan = plan_bundle(Run.open(run), fmt, wanted, voxel_size, str(run))
            path = export_bundle(run, plan, out)
            emit(as_json, str(path), run=str(run), frames=list(plan.frames), format=fmt, voxel_size=plan.voxel_size,
                 out=str(path), bytes=path.stat().st_size)
        elif wanted is None:
            frame = last_frame(run) if frame is None else frame
            path = export_frame(run, frame, fmt, out, voxel_size)
            emit(as_json, str(path), run=str(run), frame=frame, format=fmt, out=str(path))
        else:
            paths = export_sequence(run, wanted, fmt, out, voxel_size)
            emit(as_json, "\n".join(map(str, paths)), run=str(run), frames=list(wanted), format=fmt, out=str(out),
                 files=[p.name for p in paths])
