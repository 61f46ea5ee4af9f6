"""`fluidnexus synth | reconstruct | render | export` end to end on a tiny synthetic scene, and
their answers to bad input (one `error:` line, exit code 2, nothing already stored lost)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from fluidcore import video
from fluidcore.runs import Run
from fluidnexus.cli import app

runner = CliRunner()


def _ok(args: list[str]) -> str:
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    return result.output


def _fails(args: list[str], message: str) -> None:
    result = runner.invoke(app, args)
    assert result.exit_code == 2, result.output
    assert "error:" in result.output and message in result.output, result.output


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    folder = tmp_path_factory.mktemp("scene")
    _ok(["synth", "--out", str(folder), "--frames", "2", "--width", "32", "--height", "48", "--views", "3"])
    return folder


@pytest.fixture(scope="module")
def run_dir(scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("runs") / "run"
    _ok(
        [
            "reconstruct", "--cameras", str(scene / "transforms.json"),
            "--video", f"view_01={scene / 'videos' / 'view_01.mp4'}",
            "--frames", "0:2", "--out", str(out), "--threads", "1",
        ]
    )
    return out


def test_reconstruct_reads_only_the_named_view(run_dir):
    manifest = json.loads((run_dir / "manifest.json").read_text())
    assert manifest["input_views"] == ["view_01"]
    assert manifest["complete"] and [f["t"] for f in manifest["frames"]] == [0, 1]
    assert sorted(manifest["cameras"]) == ["view_00", "view_01", "view_02"]
    assert all(view["camera"].startswith("view_01") for view in manifest["settings"]["views"])


def test_render_video_pngs_and_orbit(run_dir, tmp_path):
    _ok(["render", str(run_dir), "--camera", "view_00", "--out", str(tmp_path / "v.mp4"), "--png-dir", str(tmp_path / "png")])
    frames = video.read_frames(tmp_path / "v.mp4")
    assert frames.shape[:3] == (2, 48, 32)
    assert frames.min() < 220  # the smoke is drawn, not just the background
    assert sorted(p.name for p in (tmp_path / "png").iterdir()) == ["frame_000000.png", "frame_000001.png"]
    _ok(["render", str(run_dir), "--camera", "orbit", "--frames", "1:2", "--out", str(tmp_path / "o.mp4")])
    assert video.probe(tmp_path / "o.mp4").n_frames == 1


def test_export_writes_world_space_particles(run_dir, tmp_path):
    _ok(["export", str(run_dir), "--frame", "1", "--out", str(tmp_path / "s.npz")])
    with np.load(tmp_path / "s.npz") as data:
        assert data["positions"].shape == data["velocities"].shape
        assert data["positions"].shape[0] > 0
        assert {"gaussian_means", "gaussian_colors", "gaussian_opacity_logits"} <= set(data.files)
        assert np.median(data["velocities"][:, 1]) > 0


@pytest.mark.parametrize("motion", ["paper", "carrier"])
def test_reconstruct_with_the_simulated_air_saves_it_and_exports_its_velocity(scene, tmp_path, motion):
    """Either motion model: the paper's particles in an air grid with their spreading, or the
    carrier, whose air is its motion; the run records the choice and exports the air's velocity."""
    out = tmp_path / "airy"
    spreading = ["--entrainment"] if motion == "paper" else []
    _ok(["reconstruct", "--cameras", str(scene / "transforms.json"), "--video", f"view_01={scene / 'videos' / 'view_01.mp4'}",
         "--frames", "0:2", "--motion", motion, "--air-cells", "8", "--air-vorticity", "0.3", *spreading, "--out", str(out),
         "--threads", "1"])
    run = Run.open(out)
    simulation = run.settings.quality.simulation
    assert (simulation.motion, simulation.air_cells, simulation.air_vorticity, simulation.entrainment) == (motion, 8, 0.3, bool(spreading))
    assert run.scene.motion == motion and run.scene.air.cells == 8
    _ok(["export", str(out), "--frame", "1", "--format", "density", "--out", str(tmp_path / "d.npz")])
    with np.load(tmp_path / "d.npz") as data:
        assert str(data["velocity_source"]) == "air"
        assert data["velocity"].shape == (*data["density"].shape, 3)
        assert np.abs(data["velocity"]).max() > 0  # the smoke's buoyancy has set the air moving


def test_bad_input_is_one_clear_error(scene, run_dir, tmp_path):
    cams = str(scene / "transforms.json")
    _fails(["reconstruct", "--cameras", cams, "--video", "view_01", "--out", str(tmp_path / "r")], "VIEW=path")
    _fails(["reconstruct", "--cameras", cams, "--video", f"view_09={scene / 'videos' / 'view_01.mp4'}", "--out", str(tmp_path / "r")], "view_09")
    _fails(["reconstruct", "--cameras", cams, "--video", f"view_01={scene / 'videos' / 'view_01.mp4'}", "--frames", "3:1", "--out", str(tmp_path / "r")], "frames")
    _fails(["reconstruct", "--cameras", cams, "--video", f"view_01={scene / 'videos' / 'view_01.mp4'}", "--quality", "ultra", "--out", str(tmp_path / "r")], "quality")
    _fails(["reconstruct", "--cameras", cams, "--video", f"view_01={scene / 'videos' / 'view_01.mp4'}", "--source", "0,1", "--out", str(tmp_path / "r")], "--source")
    _fails(["reconstruct", "--cameras", cams, "--video", f"view_01={scene / 'videos' / 'view_01.mp4'}", "--source", "9,9,9", "--out", str(tmp_path / "r")], "outside the scene box")
    _fails(["reconstruct", "--cameras", cams, "--video", f"view_01={scene / 'videos' / 'view_01.mp4'}", "--refine-source", "--out", str(tmp_path / "r")], "give one")
    _fails(["reconstruct", "--cameras", cams, "--video", f"view_01={scene / 'videos' / 'view_01.mp4'}", "--air-cells", "4", "--out", str(tmp_path / "r")], "air_cells must be 0")
    _fails(["reconstruct", "--cameras", cams, "--video", f"view_01={scene / 'videos' / 'view_01.mp4'}", "--motion", "paper", "--air-vorticity", "0.5", "--out", str(tmp_path / "r")], "needs the simulated air")
    _fails(["reconstruct", "--cameras", cams, "--video", f"view_01={scene / 'videos' / 'view_01.mp4'}", "--motion", "carrier", "--air-cells", "0", "--out", str(tmp_path / "r")], "cannot carry the smoke")
    _fails(["reconstruct", "--cameras", cams, "--video", f"view_01={scene / 'videos' / 'view_01.mp4'}", "--motion", "eulerian", "--out", str(tmp_path / "r")], "motion")
    assert not (tmp_path / "r").exists()
    _fails(["synth", "--out", str(tmp_path / "odd"), "--width", "135"], "width must be even")
    assert not (tmp_path / "odd").exists()
    _fails(["render", str(run_dir), "--camera", "nope", "--out", str(tmp_path / "x.mp4")], "nope")
    _fails(["render", str(tmp_path), "--camera", "view_00", "--out", str(tmp_path / "x.mp4")], "not a run folder")
    _fails(["export", str(run_dir), "--frame", "7", "--out", str(tmp_path / "x.npz")], "frame")
    # a folder holding another run is refused, and what it holds survives
    before = (run_dir / "manifest.json").read_text()
    _fails(["reconstruct", "--cameras", cams, "--video", f"view_00={scene / 'videos' / 'view_00.mp4'}", "--frames", "0:2", "--out", str(run_dir)], "different run")
    assert (run_dir / "manifest.json").read_text() == before


BALL = {"center": [0.0, 0.3, 0.0], "radius": 0.05}  # on the plume's axis, above its source


def test_reconstruct_with_a_ball_records_it_and_scene_info_shows_it(scene, tmp_path):
    out = tmp_path / "ball"
    _ok(["reconstruct", "--cameras", str(scene / "transforms.json"), "--video", f"view_01={scene / 'videos' / 'view_01.mp4'}",
         "--frames", "0:2", "--ball", json.dumps(BALL), "--physics", "fluidnexus", "--out", str(out), "--threads", "1"])
    assert Run.open(out).manifest["scene"]["solids"] == [BALL]
    info = json.loads(_ok(["scene", "info", str(out)]))
    assert info["solids"] == [BALL]


@pytest.mark.parametrize(("ball", "message"), [
    ({"center": [0.0, 3.0, 0.0], "radius": 0.05}, "error: solids[0].center [0.0, 3.0, 0.0] is outside the scene box"),
    ({"center": [0.0, 0.3, 0.0], "radius": -1}, "error: solids[0].radius: Input should be greater than 0"),
    ({"center": [0.0, 0.3], "radius": 0.1}, "error: solids[0].center[2]: Field required"),
    ("{not json", "error: --ball is not valid JSON"),
])
def test_a_bad_ball_exits_2_naming_the_field_and_writes_nothing(scene, tmp_path, ball, message):
    out = tmp_path / "refused"
    _fails(["reconstruct", "--cameras", str(scene / "transforms.json"), "--video", f"view_01={scene / 'videos' / 'view_01.mp4'}",
            "--frames", "0:2", "--ball", ball if isinstance(ball, str) else json.dumps(ball), "--out", str(out)], message)
    assert not out.exists()
