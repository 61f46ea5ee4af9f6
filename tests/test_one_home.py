"""Each concept has one home: these tests fail when a second copy of a rule grows back, or when
a torch-free caller (the API) can no longer read what it needs without loading torch."""

from __future__ import annotations

import inspect
import subprocess
import sys
from pathlib import Path

import pytest
from tests.support.service import write_transforms, write_video
from typer.testing import CliRunner

from fluidcore.spec.reconstruct import DEFAULT_QUALITY

TORCH_FREE = (
    "fluidcore.spec.reconstruct",
    "fluidcore.spec.simulation",
    "fluidcore.reconstruct",
    "fluidcore.spec.physics",
    "fluidcore.spec.scene",
    "fluidcore.physics",
    "fluidcore.predict",
    "fluidcore.spec.controls",
    "fluidcore.jobs",
    "fluidcore.runs",
    "fluidcore.artifacts",
    "fluidcore.cameras",
)


def test_package_faces_import_without_torch() -> None:
    """What the API reads (presets, physics configuration, interaction models, run manifests)
    loads in a fresh interpreter without torch; the torch-backed names still resolve on use."""
    code = (
        "import sys\n"
        f"for name in {TORCH_FREE!r}: __import__(name)\n"
        "from fluidcore.spec.reconstruct import DEFAULT_QUALITY, PRESETS\n"
        "from fluidcore.physics import PRESETS as PHYSICS, PBFConfig\n"
        "from fluidcore.spec.controls import InteractionParams\n"
        "assert PHYSICS['scalarflow'].terminal_speed > 0 and DEFAULT_QUALITY in PRESETS\n"
        "loaded = [m for m in ('torch', 'worker', 'api') if m in sys.modules]\n"
        "assert not loaded, loaded\n"
        "import fluidcore.physics, fluidcore.predict\n"
        "assert fluidcore.physics.Simulator and fluidcore.predict.run_predict and 'torch' in sys.modules\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr


def test_the_quality_default_is_the_presets_everywhere() -> None:
    from bench.predict import command as bench_predict
    from bench.reconstruct import command as bench_reconstruct
    from fluidcore.reconstruct.job import run_reconstruct
    from fluidcore.spec.jobs import ReconstructParams
    from fluidcore.spec.reconstruct import PRESETS
    from fluidnexus.cli.scenes import reconstruct as cli_reconstruct

    assert DEFAULT_QUALITY in PRESETS
    assert inspect.signature(run_reconstruct).parameters["quality"].default == DEFAULT_QUALITY
    assert ReconstructParams().quality == DEFAULT_QUALITY  # what the API queues when a request says nothing
    for command in (cli_reconstruct, bench_reconstruct, bench_predict):
        assert inspect.signature(command).parameters["quality"].default.default == DEFAULT_QUALITY, command


def test_the_terminal_rise_speed_is_the_physics_configs() -> None:
    from fluidcore.physics import PRESETS
    from fluidcore.synth import SynthSpec

    config = PRESETS["scalarflow"]
    assert config.terminal_speed == pytest.approx(abs(config.alpha) * 9.8 / config.length_scale / config.drag)
    spec = SynthSpec()
    assert spec.source().velocity == (0.0, spec.config().terminal_speed, 0.0)


def test_a_video_that_does_not_fit_its_camera_is_refused_alike_by_the_cli_and_the_api(tmp_path: Path) -> None:
    """Same bad input, both call sites, one message: a 64x48 video for a 32x24 camera (the same
    aspect ratio, which the CLI used to accept by rescaling the camera)."""
    from service.settings import Settings
    from api.uploads import UploadRejected, validate_scene
    from fluidnexus.cli import app

    write_transforms(tmp_path / "transforms.json", ["cam0"], width=32, height=24)
    video = write_video(tmp_path / "cam0.mp4", width=64, height=48)
    with pytest.raises(UploadRejected) as refused:
        validate_scene(tmp_path, "transforms.json", {"cam0.mp4": video.stat().st_size}, Settings())
    message = str(refused.value)
    assert message.startswith("video: cam0.mp4 is 64x48 but camera 'cam0' is 32x24"), message
    result = CliRunner().invoke(
        app, ["reconstruct", "--cameras", str(tmp_path / "transforms.json"), "--video", f"cam0={video}",
              "--out", str(tmp_path / "run")],
    )
    assert result.exit_code == 2 and f"error: {message}" in " ".join(result.output.split()), result.output
    assert not (tmp_path / "run").exists()


def test_the_smoke_state_round_trips_through_a_run_file(tmp_path: Path) -> None:
    """The one conversion between the live two-layer state and a run's frame file is exact."""
    import torch

    from fluidcore.physics import ParticleState
    from fluidcore.runs import FrameState
    from fluidcore.smoke import Appearance, SmokeState

    g = torch.Generator().manual_seed(0)
    particles = ParticleState.from_positions(torch.rand(5, 3, generator=g), torch.randn(5, 3, generator=g), time=0.5)
    particles.alive[2], particles.step = False, 7
    appearance = Appearance(torch.randn(4, 3, generator=g), torch.randn(4, 4, generator=g),
                            torch.randn(4, generator=g), torch.rand(4, 1, generator=g))
    smoke = SmokeState(particles, torch.rand(4, 3, generator=g), appearance)
    smoke.to_frame().save(tmp_path / "frame.npz")
    back = SmokeState.from_frame(FrameState.load(tmp_path / "frame.npz"), "cpu")
    assert (back.particles.time, back.particles.step) == (0.5, 7)
    for name in ("positions", "velocities", "alive"):
        assert torch.equal(getattr(back.particles, name), getattr(particles, name)), name
    assert torch.equal(back.means, smoke.means)
    for name in ("log_scales", "quats", "opacity_logits", "colors"):
        assert torch.equal(getattr(back.appearance, name), getattr(appearance, name)), name
    cropped = smoke.cropped((0.0, 0.0, 0.0), (0.5, 1.0, 1.0))
    inside = smoke.means[:, 0] <= 0.5
    assert torch.equal(cropped.means, smoke.means[inside])
    assert torch.equal(cropped.appearance.colors, appearance.colors[inside])


def _sources(*roots: str) -> dict[str, str]:
    """Python sources of the service and fluidcore packages, by path relative to the repository."""
    top = Path(__file__).resolve().parents[1]
    return {str(path.relative_to(top)): path.read_text() for root in roots for path in sorted((top / root).rglob("*.py"))}


def test_a_runs_file_names_are_known_to_fluidcore_runs_alone() -> None:
    """The API, the worker and the CLI read a run through fluidcore.runs: no other module spells
    its manifest or state file names (`fluidcore.runs.layout` does; the package's docstring
    describes the layout)."""
    for path, text in _sources("api", "worker", "service", "fluidnexus", "fluidcore", "bench").items():
        if path not in ("fluidcore/runs/layout.py", "fluidcore/runs/__init__.py"):
            assert "manifest.json" not in text and "states/" not in text, path


def test_every_job_type_writes_the_run_kind_of_its_name() -> None:
    from fluidcore.runs import RunKind
    from service.job_types import JobType

    writers = [job for job in JobType if job.writes_run]
    assert {job.run_kind for job in writers} == set(RunKind)
    assert all(job.run_kind.value == job.value for job in writers)
    assert [job.run_kind for job in JobType if not job.writes_run] == [None, None]  # a render and a bundle write none


def test_the_smoke_mask_has_one_home() -> None:
    """Source estimate, physics identification, mirror agreement and flow confidence all take
    the smoke where `images.smoke_mask` (or, with the contrast in hand, `images.is_smoke`) says."""
    import torch

    from fluidcore.reconstruct import flow, images, loop, scene_physics, views

    for function in (loop.prepare, scene_physics.scene_physics, views.mirror_agreement, flow.input_flow):
        text = inspect.getsource(function)
        assert "smoke_mask(" in text or "is_smoke(" in text, function.__name__
        assert "THRESHOLD" not in text and "threshold" not in inspect.signature(function).parameters, function.__name__
    frames = torch.tensor([[[[0.5, 0.5, 0.5], [0.5, 0.54, 0.5]], [[0.3, 0.9, 0.5], [0.51, 0.51, 0.51]]]])  # (1, 2, 2, 3)
    background, noise = torch.tensor([0.5, 0.5, 0.5]), torch.tensor([0.01, 0.01, 0.001])
    assert images.smoke_mask(frames, background, noise).tolist() == [[[False, False], [True, True]]]  # 4 noise units are not smoke, 10 are (in the quietest channel)


def test_the_wind_speed_limit_is_the_physics_configs() -> None:
    """`check_scene` asks PBFConfig for the speed limit instead of re-deriving it from h and dt."""
    from fluidcore.spec.controls import InteractionError, InteractionParams, WindParams
    from fluidcore.spec.physics import PBFConfig, Source
    from fluidcore.spec.scene import Scene

    assert "max_speed" not in inspect.getsource(InteractionParams.check_scene)
    for config in (PBFConfig(h=0.1, dt=0.05), PBFConfig(h=0.1, dt=0.05, max_speed=0.5)):
        scene = Scene((-1.0, 0.0, -1.0), (1.0, 2.0, 1.0), (0.0, 1.0, 0.0), config, Source((0.0, 0.0, 0.0), 0.1, 1))
        limit = config.speed_limit / config.dt  # the largest acceleration the scene resolves
        InteractionParams(wind=WindParams(direction=(1, 0, 0), strength=0.99 * limit)).check_scene(scene, 10)
        with pytest.raises(InteractionError, match="wind.strength"):
            InteractionParams(wind=WindParams(direction=(1, 0, 0), strength=1.01 * limit)).check_scene(scene, 10)


def test_a_what_if_needs_a_wind_or_a_ball_alike_at_the_api_and_in_the_job(tmp_path: Path) -> None:
    from pydantic import ValidationError

    from fluidcore.spec.controls import InteractionError, InteractionParams
    from fluidcore.predict import run_interact
    from fluidcore.spec.jobs import InteractParams

    with pytest.raises(InteractionError) as job:
        run_interact(tmp_path / "no-parent-needed", tmp_path / "out", InteractionParams(), frames=3)
    with pytest.raises(ValidationError) as api:
        InteractParams(frames=3)
    assert str(job.value) in str(api.value)
    assert not (tmp_path / "out").exists()


def test_the_physics_mode_is_checked_where_it_is_interpreted() -> None:
    """One check of the physics mode on the way from a request to the simulator: `scene_prior`."""
    calls = [path for path, text in _sources("fluidcore").items() if "check_mode(" in text.replace("def check_mode(", "")]
    assert calls == ["fluidcore/reconstruct/scene_physics.py"]
    from fluidcore.reconstruct import scene_physics

    assert inspect.getsource(scene_physics).count("check_mode(") == 2  # its definition and its one call


def test_the_scene_box_falls_back_to_the_cameras_in_one_place() -> None:
    """A reconstruction and the scene geometry the API shows take the same box:
    `cameras.capture_box` (declared box, else the cameras' shared view)."""
    users = [path for path, text in _sources("fluidcore", "api", "service").items() if "scene_box(" in text and "frusta_box(" in text]
    assert users == ["fluidcore/cameras/boxes.py"]
    from fluidcore import scene_info
    from fluidcore.reconstruct import job

    assert "capture_box(" in inspect.getsource(job.run_reconstruct) and "capture_box(" in inspect.getsource(scene_info.from_cameras_file)
