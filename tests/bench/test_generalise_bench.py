"""bench/generalise.py and its scene readers (bench/gt_scenes.py) on tiny scenes.

The baselines are checked against values computed here independently (numpy PSNR and
scikit-image SSIM on frames decoded from the files), the readers against hand-made folders of
each layout, and the whole protocol end to end on a tiny `fluidcore.synth` scene.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from skimage.metrics import structural_similarity

from bench.generalise import SMOKE_LEVEL, Protocol, plume_widths
from bench.gt_scenes import PhiFlowScene, ScalarFlowScene, SynthScene, open_scene
from fluidcore import synth, video

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def synth_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("synth")
    synth.write(synth.generate(synth.SynthSpec(frames=6, width=48, height=64, views=3, fps=10.0)), folder)
    return folder


def _psnr(pred: np.ndarray, truth: np.ndarray) -> float:
    """Mean over frames of 10 log10(1 / MSE), images in [0, 1]."""
    p, t = pred.astype(np.float64) / 255.0, truth.astype(np.float64) / 255.0
    return float(np.mean([10 * np.log10(1.0 / np.mean((a - b) ** 2)) for a, b in zip(p, t, strict=True)]))


def _ssim(pred: np.ndarray, truth: np.ndarray) -> float:
    return float(np.mean([
        structural_similarity(b.astype(np.float64) / 255.0, a.astype(np.float64) / 255.0, channel_axis=-1, data_range=1.0)
        for a, b in zip(pred, truth, strict=True)
    ]))


def test_baselines_equal_independent_values(synth_dir: Path, tmp_path: Path) -> None:
    gt = open_scene(synth_dir)
    assert isinstance(gt, SynthScene)
    protocol = Protocol(gt, "view_01", gt.input_path("view_01"), (0, 4), 1, None, tmp_path)
    colour = [0.5, 0.25, 0.75]  # a background colour far from the scene's white
    run = SimpleNamespace(background_color=colour)
    frames = [0, 1, 2, 3]
    scored = protocol.score(gt, ["view_00", "view_02"], frames, {
        "copy_input": protocol._copy_input(), "blank": protocol._blank(run), "freeze": protocol._freeze(3),
    })
    source = video.read_frames(synth_dir / "videos" / "view_01.mp4", 0, 4)
    blank = np.broadcast_to(np.round(np.array(colour) * 255).astype(np.uint8), source.shape)
    for view in ("view_00", "view_02"):
        truth = video.read_frames(synth_dir / "videos" / f"{view}.mp4", 0, 4)
        expected = {"copy_input": source, "blank": blank, "freeze": np.broadcast_to(source[3], source.shape)}
        for name, pred in expected.items():
            got = scored["views"][view][name]
            assert got["psnr"] == pytest.approx(_psnr(pred, truth), abs=1e-4), (view, name)
            assert got["ssim"] == pytest.approx(_ssim(pred, truth), abs=1e-4), (view, name)
            assert got["per_frame_psnr"][0] == pytest.approx(_psnr(pred[:1], truth[:1]), abs=1e-4)
    for name in ("copy_input", "blank", "freeze"):
        mean = np.mean([scored["views"][v][name]["psnr"] for v in ("view_00", "view_02")])
        assert scored["mean"][name]["psnr"] == pytest.approx(mean)


def test_score_every_and_long_side_score_the_same_frames_for_every_predictor(synth_dir: Path, tmp_path: Path) -> None:
    gt = open_scene(synth_dir)
    protocol = Protocol(gt, "view_01", gt.input_path("view_01"), (0, 6), 2, 32, tmp_path)
    frames = protocol._frames(0, 6)
    assert frames == [0, 2, 4]
    scored = protocol.score(gt, ["view_00"], frames, {"copy_input": protocol._copy_input()})
    source = video.read_frames(synth_dir / "videos" / "view_01.mp4", 0, 6, size=(24, 32))[frames]
    truth = video.read_frames(synth_dir / "videos" / "view_00.mp4", 0, 6, size=(24, 32))[frames]
    assert scored["views"]["view_00"]["copy_input"]["psnr"] == pytest.approx(_psnr(source, truth), abs=1e-4)


def _tiny_video(path: Path, values: list[int], size: tuple[int, int] = (16, 24)) -> None:
    frames = np.stack([np.full((size[1], size[0], 3), v, np.uint8) for v in values])
    video.write_mp4(path, frames)


def _cameras(folder: Path, names: list[str], file_paths: dict[str, str]) -> None:
    from fluidcore.cameras import Camera, look_at, write_transforms

    like = Camera("like", 20.0, 20.0, 8.0, 12.0, 16, 24, np.eye(4))
    cameras = {}
    for k, name in enumerate(names):
        cam = look_at(np.array([np.sin(k), 0.3, np.cos(k)]) * 2, np.zeros(3), (0.0, 1.0, 0.0), like, name)
        cameras[name] = cam.__class__(**{**cam.__dict__, "file_path": file_paths.get(name)})
    write_transforms(folder / "transforms.json", cameras, fps=30)


def test_scalarflow_reader_takes_predicted_frames_from_the_future_clip(tmp_path: Path) -> None:
    (tmp_path / "gt").mkdir()
    (tmp_path / "videos").mkdir()
    _cameras(tmp_path, ["view_00", "view_02"], {"view_02": "videos/input_view_02.mp4"})
    _tiny_video(tmp_path / "videos" / "input_view_02.mp4", [10 * k for k in range(8)])
    _tiny_video(tmp_path / "gt" / "nvs_view_00.mp4", [10 * k for k in range(8)])
    _tiny_video(tmp_path / "gt" / "future_view_00.mp4", [200, 210, 220, 230])  # clip frame i = t 4 + i
    windows = {"nvs": {"n_frames": 8}, "future": {"prediction_t": [6, 7], "prediction_clip_frames": [2, 3]}}
    (tmp_path / "windows.json").write_text(json.dumps(windows))
    gt = open_scene(tmp_path)
    assert isinstance(gt, ScalarFlowScene)
    assert gt.n_frames == 8 and gt.views() == ["view_00"]
    values = gt.truth("view_00", [1, 5, 6, 7])[:, 0, 0, 0].astype(int)
    assert np.abs(values - [10, 50, 220, 230]).max() <= 2  # t 6, 7 come from the future clip's frames 2, 3


def test_phiflow_reader_finds_variants_and_samples_velocity_where_smoke_is(tmp_path: Path) -> None:
    meta = {
        "saved_frames": [0], "grid_resolution": [2, 2, 2], "voxel_size": [0.5, 0.5, 0.5], "domain_world_min": [0, 0, 0],
        "source": {"center_world": [0.5, 0.1, 0.5]}, "forces": {"wind": None}, "obstacle": None, "counterfactual_of": None,
    }
    wind = {"start_frame": 5, "direction_world": [1, 0, 0], "strength": 0.1, "growth": 2.0, "source_height_world": 0.1}
    ball = {"shape": "sphere", "center_world": [0.5, 0.5, 0.5], "radius": 0.1, "static": True, "present_from_frame": 0}
    for name, extra in (("S", {}), ("S_wind", {"forces": {"wind": wind}, "counterfactual_of": "S"}),
                        ("S_ball", {"obstacle": ball, "counterfactual_of": "S"}), ("T", {"counterfactual_of": "X"})):
        folder = tmp_path / name
        (folder / "gt").mkdir(parents=True)
        (folder / "videos").mkdir()
        _cameras(folder, ["view_00"], {"view_00": "videos/view_00.mp4"})
        _tiny_video(folder / "videos" / "view_00.mp4", [0] * 12)
        (folder / "gt" / "meta.json").write_text(json.dumps({**meta, **extra}))
    density = np.zeros((2, 2, 2), np.float16)
    density[1, 0, 1] = 1.0
    velocity = np.zeros((2, 2, 2, 3), np.float16)
    velocity[1, 0, 1] = (0.0, 0.5, 0.0)
    np.savez(tmp_path / "S" / "gt" / "density_0000.npz", density=density)
    np.savez(tmp_path / "S" / "gt" / "velocity_0000.npz", velocity=velocity)
    (tmp_path / "anchors.json").write_text(json.dumps({"tasks": {"counterfactual": "S_wind: frames 5..11, late 8..11; S_ball: frames 0..11, late 6..11"}}))
    gt = open_scene(tmp_path / "S")
    assert isinstance(gt, PhiFlowScene)
    points, values = gt.velocity(0)
    np.testing.assert_allclose(points, [[0.75, 0.25, 0.75]])
    np.testing.assert_allclose(values, [[0.0, 0.5, 0.0]])
    variants = {v.name: v for v in gt.variants()}
    assert sorted(variants) == ["S_ball", "S_wind"]
    w, b = variants["S_wind"], variants["S_ball"]
    assert (w.branch_frame, w.first_frame, w.late_start, w.wind["start_frame"], w.wind["base_height"]) == (4, 5, 8, 0, 0.1)
    assert (b.branch_frame, b.first_frame, b.late_start, b.ball["start_frame"]) == (0, 0, 6, 0)


def test_a_protocol_json_gives_the_input_view_windows_and_what_ifs_in_world_units(tmp_path: Path) -> None:
    """A scene folder with a protocol.json (the dev scene F's layout) is run from it: its wind,
    a linear ramp from zero at world height y0 to acc_top at y_top, becomes a WindParams that
    pushes exactly that much at every height, whatever source the reconstruction estimates."""
    import torch

    from bench.generalise import _protocol_defaults
    from fluidcore.spec.controls import WindParams
    from fluidcore.physics.forces import wind_acceleration

    meta = {"saved_frames": [0], "source": {"center_world": [0.26, 0.065, -0.2]}, "forces": {"wind": None}, "obstacle": None}
    for name in ("F", "F_wind", "F_ball"):
        folder = tmp_path / name
        (folder / "gt").mkdir(parents=True)
        _cameras(folder, ["view_02"], {"view_02": "videos/view_02.mp4"})
        (folder / "videos").mkdir()
        _tiny_video(folder / "videos" / "view_02.mp4", [0] * 12)
        (folder / "gt" / "meta.json").write_text(json.dumps({**meta, "counterfactual_of": None if name == "F" else "F"}))
    protocol = {
        "input_view": "view_02", "observed": [0, 8], "future": [8, 12],
        "wind": {"start_frame": 5, "direction": [0, 0, -1], "acc_top": 0.2, "y0_world": 0.065, "y_top_world": 0.765, "late": [9, 12]},
        "ball": {"center": [0.26, 0.265, -0.2], "radius": 0.045, "start_frame": 0, "late": [6, 12]},
        "scenes": {"factual": "F", "wind": "F_wind", "ball": "F_ball"},
    }
    (tmp_path / "protocol.json").write_text(json.dumps(protocol))
    gt = open_scene(tmp_path / "F")
    assert _protocol_defaults(gt, None, None) == ("view_02", "0:8")
    assert _protocol_defaults(gt, "view_00", "0:4") == ("view_00", "0:4")
    assert open_scene(tmp_path / "F_wind").protocol is None  # it names F as the factual scene, not F_wind
    variants = {v.name: v for v in gt.variants()}
    w, b = variants["F_wind"], variants["F_ball"]
    assert (w.branch_frame, w.first_frame, w.late_start) == (4, 5, 9)
    assert (b.branch_frame, b.first_frame, b.late_start, b.ball["center"], b.ball["radius"]) == (0, 0, 6, (0.26, 0.265, -0.2), 0.045)
    heights = np.array([0.0, 0.065, 0.2, 0.5, 0.765])
    points = torch.tensor([[0.3, y, -0.2] for y in heights], dtype=torch.float32)
    pushed = wind_acceleration(WindParams(**w.wind), points, WindParams(**w.wind).reference_height(0.5), (0.0, 1.0, 0.0))
    truth = 0.2 * np.clip((heights - 0.065) / 0.7, 0.0, 1.0)  # F_wind/gt/meta.json's law
    np.testing.assert_allclose(-pushed[:, 2].numpy(), truth, atol=1e-6)
    np.testing.assert_allclose(pushed[:, :2].numpy(), 0.0, atol=1e-7)


def test_a_scene_without_protocol_needs_its_input_view_and_window(tmp_path: Path) -> None:
    from bench.generalise import _protocol_defaults
    from fluidnexus.reporting import UserError

    (tmp_path / "videos").mkdir()
    _cameras(tmp_path, ["view_00"], {"view_00": "videos/view_00.mp4"})
    _tiny_video(tmp_path / "videos" / "view_00.mp4", [0] * 4)
    with pytest.raises(UserError, match="--input-view and --observed"):
        _protocol_defaults(open_scene(tmp_path), None, "0:4")


@pytest.mark.slow
def test_bench_runs_end_to_end_on_a_synth_scene(synth_dir: Path, tmp_path: Path) -> None:
    figure = tmp_path / "per_frame.png"
    out = subprocess.run(
        [sys.executable, str(ROOT / "bench" / "generalise.py"), str(synth_dir), "--input-view", "view_01", "--observed", "0:4",
         "--future", "2", "--set", "long_side=48", "--set", "position_iterations=4", "--set", "appearance_iterations=2",
         "--tasks", "nvs,input,future,velocity", "--figure", str(figure), "--threads", "1", "--json"],
        capture_output=True, text=True, check=True, cwd=ROOT,
    )
    result = json.loads(out.stdout)
    assert set(result["tasks"]) == {"nvs", "input", "future", "velocity"}
    assert result["tasks"]["future"]["frames"] == [4, 5]
    assert result["tasks"]["future"]["plume_width"]["frame"] == 5  # B + 30 clipped to the last predicted frame
    assert set(result["tasks"]["nvs"]["views"]) == {"view_00", "view_02"}
    observed = result["tasks"]["velocity"]["summary"]["observed"]
    assert observed["zero_epe"] > 0
    assert 0 <= observed["axisymmetric_epe"] < observed["zero_epe"]  # a ring mean is never worse than zero
    assert set(result["tasks"]["input"]["reconstruction"]) == {"fit", "forecast"}
    assert figure.stat().st_size > 1000


def test_the_effect_score_is_the_cosine_of_predicted_and_true_effects_over_the_late_window(tmp_path: Path) -> None:
    """Protocol.effect on hand-made frames: a what-if that changes the images as the truth does
    (at any strength) scores 1, the opposite change -1, no change None; frames before the late
    window do not count, and the frames the PSNR rendered are not rendered again."""
    rng = np.random.default_rng(0)
    frames, late_start, shape = [3, 4, 5, 6], 5, (4, 6, 8, 3)
    factual_truth = rng.integers(60, 200, shape).astype(np.uint8)
    change = rng.integers(-40, 40, shape)
    variant_truth = (factual_truth + change).astype(np.uint8)
    own_factual = rng.integers(60, 200, shape).astype(np.uint8)
    camera = SimpleNamespace(name="cam", width=8, height=6)

    def truth_of(video: np.ndarray):  # noqa: ANN202 - a GroundTruth.truth stand-in over `frames`
        return lambda view, wanted, size: video[[frames.index(t) for t in wanted]]

    def scene(video: np.ndarray) -> SimpleNamespace:
        return SimpleNamespace(views=lambda: ["cam"], cameras={"cam": camera}, truth=truth_of(video))

    protocol = Protocol(scene(factual_truth), "cam", Path("in.mp4"), (0, 3), 1, None, tmp_path)
    variant = SimpleNamespace(scene=scene(variant_truth), late_start=late_start)
    calls = []

    def predictor(images: np.ndarray):  # noqa: ANN202
        def predict(camera, wanted, size):  # noqa: ANN001, ANN202
            calls.append(1)
            return images
        return predict

    from bench.generalise import _kept

    for strength, expected in ((0.5, 1.0), (-1.0, -1.0)):
        whatif = (own_factual + strength * change).clip(0, 255).astype(np.uint8)
        early_noise = whatif.copy()
        early_noise[:2] = rng.integers(0, 255, (2, *shape[1:]))  # before the late window: ignored
        method, factual = _kept(predictor(early_noise)), _kept(predictor(own_factual))
        method(camera, frames, (8, 6)), factual(camera, frames, (8, 6))  # what the PSNR renders
        calls.clear()
        score = protocol.effect(variant, frames, method, factual)
        assert calls == [] and score["frames"] == [5, 6]
        late_change = (whatif.astype(float) - own_factual)[2:], change[2:]
        cosine = np.vdot(*late_change) / np.linalg.norm(late_change[0]) / np.linalg.norm(late_change[1])
        assert score["cosine"] == pytest.approx(cosine) and score["views"]["cam"] == pytest.approx(cosine)
        assert score["cosine"] == pytest.approx(expected, abs=0.1)  # clipping to 0..255 bends it a little
    nothing = protocol.effect(variant, frames, _kept(predictor(own_factual)), _kept(predictor(own_factual)))
    assert nothing["cosine"] is None


def test_plume_width_is_the_smoke_extent_in_the_row_at_the_truth_plumes_mid_height() -> None:
    """Hand-made frames: a truth plume of 11 columns over rows 10..30 (mid-height row 20); a
    narrower prediction with a stray wisp in that row is measured from its leftmost to its
    rightmost smoke pixel; faint differences below SMOKE_LEVEL are background."""
    background = np.array([10, 20, 30], np.uint8)
    truth = np.broadcast_to(background, (40, 50, 3)).copy()
    truth[10:31, 20:31] = 200
    truth[0:40, 0:5] = background + SMOKE_LEVEL  # not smoke: does not move the mid-height
    method = np.broadcast_to(background, (40, 50, 3)).copy()
    method[15:25, 22:27] = 200
    assert plume_widths(method, truth, background) == {"row": 20, "method": 5, "truth": 11, "ratio": 5 / 11}
    method[20, 40] = 255
    assert plume_widths(method, truth, background)["method"] == 19
    empty = np.broadcast_to(background, (40, 50, 3)).copy()
    assert plume_widths(method, empty, background)["ratio"] is None
    assert plume_widths(empty, truth, background)["ratio"] == 0.0


def test_bench_source_identifies_once_per_seed_and_refuses_bad_seeds(synth_dir: Path) -> None:
    """`bench source --seeds`: the image estimate once, the identified source per seed (the
    issue's tables are means over seeds); malformed seeds are a usage error (exit code 2)."""
    from typer.testing import CliRunner

    from fluidnexus.cli import app

    runner = CliRunner()
    base = ["bench", "source", str(synth_dir), "--input-view", "view_01", "--observed", "0:6", "--threads", "1"]
    result = runner.invoke(app, [*base, "--seeds", "0,1", "--json"])
    assert result.exit_code == 0, result.output
    row = json.loads(result.stdout)["scenes"][0]
    assert set(row["seeds"]) == {"0", "1"} and row["auto"] == row["seeds"]["0"]
    for estimate in (row["image"], *row["seeds"].values()):
        assert np.isfinite(estimate["radius_ratio"]) and estimate["radius_ratio"] > 0
    assert all(e["physics"]["mode"] == "auto" for e in row["seeds"].values())
    for bad in ("0,0", "x", "-1", ",".join(map(str, range(11)))):
        refused = runner.invoke(app, [*base, "--seeds", bad])
        assert refused.exit_code == 2 and "--seeds" in refused.output, (bad, refused.output)


def test_bench_gives_the_reconstruction_a_source_when_asked_and_refuses_what_it_cannot_use(synth_dir: Path, tmp_path: Path) -> None:
    """`--source X,Y,Z,R` (the issue's "with the true source given" diagnostic): the reconstruction
    starts from that source, kept as given, and the JSON
    says what was given; a malformed source, or one with --reconstruction (which has its own), is
    a usage error (exit code 2)."""
    from typer.testing import CliRunner

    from fluidnexus.cli import app

    center = (0.03, 0.05, -0.04)  # inside the synth box, off its axis
    runner = CliRunner()
    base = ["bench", "generalise", str(synth_dir), "--input-view", "view_01", "--observed", "0:3", "--threads", "1",
            "--set", "long_side=48", "--set", "position_iterations=2", "--set", "appearance_iterations=1", "--tasks", "input"]
    result = runner.invoke(app, [*base, "--source", ",".join(map(str, (*center, 0.05))), "--out", str(tmp_path / "runs"), "--json"])
    assert result.exit_code == 0, result.output
    out = json.loads(result.stdout)
    assert out["source_given"] == {"center": list(center), "radius": 0.05, "refine": False}
    assert out["source"]["center"] == pytest.approx(list(center)) and out["source"]["radius"] == pytest.approx(0.05)
    for bad in (["--source", "1,2"], ["--source", "0,0,0,-1"], ["--source", "0,0,0", "--reconstruction", str(tmp_path / "runs" / "reconstruct")]):
        refused = runner.invoke(app, [*base, *bad])
        assert refused.exit_code == 2 and "source" in refused.output, (bad, refused.output)
    refused = runner.invoke(app, [*base, "--set", "air_cells=4"])  # a quality override is checked as the API's params are
    assert refused.exit_code == 2 and "air_cells must be 0 (still air) or 8..128" in refused.output, refused.output
    refused = runner.invoke(app, [*base, "--set", "seed=[1"])  # not JSON: a usage error, not a traceback
    assert refused.exit_code == 2 and "--set seed" in refused.output and "not a JSON value" in refused.output, refused.output
