"""Prediction and re-simulation runs: what they write, what they cost, and that they are
reproducible, resumable, continuable and finite over long horizons."""

from __future__ import annotations

import json
import shutil
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from tests.support.predict_scenes import SPEC, horizontal_distance, live, plume_run
from tests.support.simulators import paper, run
from typer.testing import CliRunner

from fluidcore import run_frames
from fluidcore.spec.controls import InteractionParams, WindParams
from fluidcore.jobs import Cancelled, JobContext, JobInputError
from fluidcore.physics import ParticleState, Simulator
from fluidcore.physics.motion import NO_CONTROLS
from fluidcore.predict import identification, job, priors, rollout
from fluidcore.runs import AppearanceProfile, Run, RunError
from fluidcore.smoke import Appearance, SmokeState

FRAMES = 6


@pytest.fixture(scope="module")
def parent(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return plume_run(tmp_path_factory.mktemp("plume") / "parent", frames=3, warmup=25)


def states(run: Run) -> list[dict[str, np.ndarray]]:
    """Every frame's arrays, for exact comparison of two runs."""
    out = []
    for t in run.frames():
        saved = run.read_frame(t)
        out.append({"positions": saved.positions, "alive": saved.alive, **saved.gaussians})
    return out


def assert_same_states(a: Run, b: Run) -> None:
    assert a.frames() == b.frames()
    for x, y in zip(states(a), states(b), strict=True):
        assert x.keys() == y.keys()
        for key in x:
            np.testing.assert_array_equal(x[key], y[key], err_msg=key)


def test_prediction_continues_after_the_last_frame_and_records_its_parent(
    parent: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("FLUIDNEXUS_MODELS", str(tmp_path / "models"))  # no video model: refinement says so
    run = Run.open(job.run_predict(parent, tmp_path / "pred", frames=FRAMES))
    assert run.kind == "predict" and run.manifest["complete"]
    assert run.frames() == list(range(3, 3 + FRAMES))
    assert not Path(run.manifest["parent"]).is_absolute()  # relative to the run folder: a chain moves as one
    assert run.parent is not None and run.parent.path.resolve() == parent.resolve()
    assert run.manifest["refinement"] == f"skipped: no cogvideox weights in {tmp_path / 'models'}"
    first = run.read_frame(3)
    last_parent = Run.open(parent).read_frame(2)
    assert first.time == pytest.approx(last_parent.time + 1 / 30)
    # The smoke keeps rising and the source keeps seeding.
    assert live(first)[:, 1].mean() > live(last_parent)[:, 1].mean()
    assert first.alive.sum() > last_parent.alive.sum()


def test_rendering_a_prediction_gives_its_new_frames(parent: Path, tmp_path: Path) -> None:
    run = Run.open(job.run_predict(parent, tmp_path / "pred", frames=FRAMES))
    camera = run.cameras()["view_01"]
    video = run_frames.render_frames(run, camera)
    assert video.shape == (FRAMES, camera.height, camera.width, 3)
    assert video.min() < 200  # smoke is visible on the white background


def test_cost_per_frame_is_one_step_plus_one_render_per_view(parent: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import fluidcore.render as render_module

    calls = {"step": 0, "render": 0}
    step, original_render = Simulator.step, render_module.render

    def counting_step(self: Simulator, state, controls=NO_CONTROLS):  # noqa: ANN001, ANN202
        calls["step"] += 1
        return step(self, state, controls)

    def counting_render(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        calls["render"] += 1
        return original_render(*args, **kwargs)

    monkeypatch.setattr(Simulator, "step", counting_step)
    monkeypatch.setattr(render_module, "render", counting_render)
    reconstruction = Run.open(parent)
    identification.calibrate_buoyancy(reconstruction, reconstruction.scene, reconstruction.frames()[-1], "cpu")
    once = calls["step"]  # the one-off identification of the buoyancy, not a per-frame cost
    assert 0 < once <= len(identification.BUOYANCY_SCALES) * reconstruction.scene.physics.frames_in(identification.CALIBRATION_SECONDS)
    calls["step"] = 0
    run = Run.open(job.run_predict(parent, tmp_path / "pred", frames=FRAMES))
    assert calls == {"step": once + FRAMES, "render": 0}  # refinement is off: rendering is left to render_artifacts
    for camera in run.cameras().values():
        run_frames.render_frames(run, camera)
    assert calls == {"step": once + FRAMES, "render": FRAMES * len(run.cameras())}


def test_prediction_without_forces_is_deterministic(parent: Path, tmp_path: Path) -> None:
    a = Run.open(job.run_predict(parent, tmp_path / "a", frames=FRAMES))
    b = Run.open(job.run_predict(parent, tmp_path / "b", frames=FRAMES))
    assert_same_states(a, b)


def test_a_cancelled_prediction_resumes_to_the_same_result(parent: Path, tmp_path: Path) -> None:
    asked = []
    reported: list[float] = []

    def cancel_after_three() -> bool:
        asked.append(True)
        return len(asked) > 3

    with pytest.raises(Cancelled, match="resumes from frame 6"):
        job.run_predict(parent, tmp_path / "resumed", frames=FRAMES, context=JobContext(should_cancel=cancel_after_three))
    assert Run.open(tmp_path / "resumed").frames() == [3, 4, 5]
    job.run_predict(parent, tmp_path / "resumed", frames=FRAMES, context=JobContext(progress=lambda f, stage: reported.append(f)))
    assert reported == pytest.approx([(k + 1) / FRAMES for k in range(3, FRAMES)])
    whole = Run.open(job.run_predict(parent, tmp_path / "whole", frames=FRAMES))
    assert_same_states(Run.open(tmp_path / "resumed"), whole)


def test_another_run_in_the_same_folder_is_refused(parent: Path, tmp_path: Path) -> None:
    job.run_predict(parent, tmp_path / "out", frames=2)
    with pytest.raises(RunError, match="different run"):
        job.run_interact(parent, tmp_path / "out", InteractionParams(wind=WindParams(direction=(1, 0, 0), strength=0.1)), frames=2)


@pytest.mark.parametrize("frames", [0, -3, 2.5, True])
def test_a_bad_horizon_is_refused(parent: Path, tmp_path: Path, frames: object) -> None:
    with pytest.raises(JobInputError, match="frames"):
        job.run_predict(parent, tmp_path / "out", frames=frames)  # type: ignore[arg-type]


def test_a_prediction_can_be_continued_by_another(parent: Path, tmp_path: Path) -> None:
    first = job.run_predict(parent, tmp_path / "first", frames=3)
    second = Run.open(job.run_predict(first, tmp_path / "second", frames=3))
    whole = Run.open(job.run_predict(parent, tmp_path / "whole", frames=6))
    assert second.frames() == whole.frames()[3:]
    for t in second.frames():
        np.testing.assert_array_equal(live(second.read_frame(t)), live(whole.read_frame(t)))


def test_newborn_smoke_looks_like_the_reconstructed_smoke_at_the_source(parent: Path, tmp_path: Path) -> None:
    """Births copy the fitted appearance near the source, not some default look."""
    recoloured = tmp_path / "recoloured"
    source = Run.open(parent)
    Run.create(
        recoloured, kind="reconstruct", cameras=source.cameras(), input_views=["view_00"], frame_range=(0, 1),
        fps=30.0, channels=1, background_color=[1.0], scene=source.scene, settings=source.settings,
    ).write_frame(0, _recoloured(source.read_frame(2), source.scene.source.center), {}, 0.0)
    run = Run.open(job.run_predict(recoloured, tmp_path / "pred", frames=1))
    colors = run.read_frame(1).gaussians["colors"]
    born = run.scene.source.rate * run.manifest["settings"]["visual"]["per_physical"]
    # Births are appended last. The height profile then nudges every band's mean colour back to
    # the parent's, so newborns end near, not exactly at, the 0.9 they copied.
    assert (colors[-born:] > 0.6).all()
    assert np.mean(np.abs(colors[:-born] - 0.25) < 0.1) > 0.9


def test_a_prediction_follows_the_concentration_only_where_the_reconstruction_asked(tmp_path: Path) -> None:
    """A parent recorded with opacity_concentration is continued with each Gaussian following its
    smoke's concentration; one recorded without (every run before it) keeps each Gaussian's look.
    Identified ("auto") physics: no appearance prior moves the look besides."""
    fixed = plume_run(tmp_path / "fixed", frames=3, warmup=25, physics="auto")
    following = plume_run(tmp_path / "following", frames=3, warmup=25, quality={"opacity_concentration": True}, physics="auto")
    looks = {}
    for name, source in (("fixed", fixed), ("following", following)):
        run = Run.open(job.run_predict(source, tmp_path / f"predicted_{name}", frames=4))
        assert run.settings.visual.opacity_concentration is (name == "following")
        first, last = run.read_frame(3).gaussians, run.read_frame(6).gaussians
        n = len(first["opacity_logits"])  # the Gaussians alive at both ends come first, in order
        looks[name] = (last["opacity_logits"][:n] - first["opacity_logits"][:n], last["log_scales"][:n] - first["log_scales"][:n])
        assert np.isfinite(last["opacity_logits"]).all() and np.isfinite(last["log_scales"]).all()
    assert not looks["fixed"][0].any() and not looks["fixed"][1].any()
    opacity, extent = looks["following"]
    assert np.abs(opacity).max() > 1e-3
    # a parcel of fixed mass: where it grew it got lighter, and the other way round
    changed = np.abs(extent[:, 0]) > 1e-4
    assert changed.any() and (np.sign(opacity[changed]) == -np.sign(extent[changed, 0])).all()


def _recoloured(saved, center):  # noqa: ANN001, ANN202
    """The frame with every Gaussian grey 0.25 except those nearest the source, grey 0.9."""
    means = saved.gaussians["means"]
    near = np.argsort(np.linalg.norm(means - np.asarray(center), axis=1))[: rollout.TEMPLATE_SIZE]
    colors = np.full_like(saved.gaussians["colors"], 0.25)
    colors[near] = 0.9
    return replace(saved, gaussians={**saved.gaussians, "colors": colors})


def test_resimulating_a_pure_physics_run_reproduces_it(parent: Path, tmp_path: Path) -> None:
    run = Run.open(job.run_resimulate(parent, tmp_path / "resim"))
    original = Run.open(parent)
    assert run.kind == "resimulate" and run.frames() == original.frames()
    first = run.read_frame(0)
    np.testing.assert_array_equal(first.gaussians["means"], original.read_frame(0).gaussians["means"])
    for t in run.frames():
        ours, theirs = run.read_frame(t), original.read_frame(t)
        np.testing.assert_array_equal(ours.alive, theirs.alive)
        np.testing.assert_allclose(ours.positions[ours.alive], theirs.positions[theirs.alive], atol=1e-6)


def test_a_300_frame_horizon_stays_finite_and_bounded(tmp_path: Path) -> None:
    parent = plume_run(tmp_path / "parent", frames=1, warmup=10, spec=replace(SPEC, particles_per_step=4))
    run = Run.open(job.run_predict(parent, tmp_path / "long", frames=300))
    counts = []
    for t in run.frames()[::25] + run.frames()[-1:]:
        saved = run.read_frame(t)  # loading checks every array is finite
        counts.append(int(saved.alive.sum()))
        lo, hi = np.asarray(run.scene.box_lo), np.asarray(run.scene.box_hi)
        assert ((saved.gaussians["means"] >= lo) & (saved.gaussians["means"] <= hi)).all()
    # Smoke leaves through the top as fast as the source feeds it: the count levels off.
    assert counts[-1] < 4 * 320 and abs(counts[-1] - counts[-3]) < 0.2 * counts[-1]


def test_cli_predict_interact_resimulate(parent: Path, tmp_path: Path) -> None:
    from fluidnexus.cli import app

    runner = CliRunner()
    out = runner.invoke(app, ["predict", str(parent), "--frames", "2", "--out", str(tmp_path / "p")])
    assert out.exit_code == 0, out.output
    assert Run.open(tmp_path / "p").frames() == [3, 4]
    wind = json.dumps({"direction": [1, 0, 0], "strength": 0.1})
    ball = json.dumps({"center": [0, 0.2, 0], "radius": 0.05})
    out = runner.invoke(app, ["interact", str(parent), "--wind", wind, "--ball", ball, "--frames", "2", "--out", str(tmp_path / "i")])
    assert out.exit_code == 0, out.output
    assert Run.open(tmp_path / "i").manifest["settings"]["ball"]["radius"] == 0.05
    out = runner.invoke(app, ["resimulate", str(parent), "--out", str(tmp_path / "r")])
    assert out.exit_code == 0, out.output
    assert Run.open(tmp_path / "r").frames() == [0, 1, 2]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--wind", "{not json"], "error: wind is not valid JSON"),
        (["--ball", '{"center": [0, 0.2, 0], "radius": -1}'], "error: ball.radius"),
        (["--ball", '{"center": [0, 9, 0], "radius": 0.1}'], "error: ball.center"),
        ([], "error: interact needs"),
    ],
)
def test_cli_interact_reports_bad_parameters(parent: Path, tmp_path: Path, args: list[str], message: str) -> None:
    from fluidnexus.cli import app

    out = CliRunner().invoke(app, ["interact", str(parent), *args, "--frames", "2", "--out", str(tmp_path / "i")])
    assert out.exit_code == 2
    assert message in out.output and "Traceback" not in out.output
    assert not (tmp_path / "i").exists()


def test_cli_predict_on_a_folder_that_is_not_a_run(tmp_path: Path) -> None:
    from fluidnexus.cli import app

    out = CliRunner().invoke(app, ["predict", str(tmp_path), "--frames", "2", "--out", str(tmp_path / "p")])
    assert out.exit_code == 2 and "not a run folder" in out.output



def test_an_overfilled_source_is_capped_to_what_its_inlet_carries_at_rest_density() -> None:
    config, source = SPEC.config(), SPEC.source()
    speed = max(math.hypot(*source.velocity), math.hypot(*config.body_acceleration) / config.drag)
    capacity = 8 * config.rho0 / config.h**3 * math.pi * source.radius**2 * speed * config.dt
    assert rollout.inlet_source(source, config) == source  # the test plume seeds below capacity
    flooded = replace(source, rate=round(4 * capacity))
    assert rollout.inlet_source(flooded, config).rate == round(capacity)
    # Physically: the flooded inlet piles particles up and pushes them sideways; the capped one
    # keeps the plume's base as narrow as an inlet at rest density allows.
    widths = []
    for seeded in (flooded, rollout.inlet_source(flooded, config)):
        simulator = paper(config, SPEC.box(), seeded)
        state, _ = run(simulator, simulator.new_state(), 30)
        x = state.positions[state.alive]
        base = x[(x[:, 1] > source.center[1]) & (x[:, 1] < source.center[1] + 2 * source.radius)]
        widths.append(float(horizontal_distance(base, source.center).mean()))
    assert widths[1] < 0.8 * widths[0], widths


def test_a_prediction_records_the_inlet_rate_it_used(tmp_path: Path) -> None:
    config, source = SPEC.config(), SPEC.source()
    flooded = replace(SPEC, particles_per_step=10 * source.rate)
    parent = plume_run(tmp_path / "parent", frames=1, warmup=2, spec=flooded)
    run = Run.open(job.run_predict(parent, tmp_path / "pred", frames=2))
    assert run.manifest["settings"]["parent_source_rate"] == 10 * source.rate
    assert run.scene.source.rate == rollout.inlet_source(flooded.source(), config).rate < 10 * source.rate
    continued = Run.open(job.run_predict(run.path, tmp_path / "again", frames=1))
    assert continued.scene.source.rate == run.scene.source.rate


@pytest.mark.parametrize("preset_factor", [0.5, 1.0, 2.0, 4.0])
def test_the_buoyancy_is_identified_from_the_reconstructed_motion(tmp_path: Path, preset_factor: float) -> None:
    # A "reconstruction" that is pure physics under the true alpha, continued under a preset that
    # misstates the buoyancy: replaying its last frames finds the factor that undoes the preset.
    parent = Run.open(plume_run(tmp_path / "parent", frames=6, warmup=20))
    truth = parent.scene
    preset = truth.with_buoyancy_scaled(preset_factor)
    scale, errors = identification.calibrate_buoyancy(parent, preset, parent.frames()[-1], "cpu")
    assert scale == 1.0 / preset_factor
    assert errors[f"{scale:g}"] < min(e for k, e in errors.items() if k != f"{scale:g}")


def test_a_prediction_from_a_reconstruction_records_its_calibration_and_profile(parent: Path, tmp_path: Path) -> None:
    run = Run.open(job.run_predict(parent, tmp_path / "pred", frames=2))
    settings = run.manifest["settings"]
    assert settings["buoyancy_scale"] == 1.0  # the test plume is pure physics under its own alpha
    assert run.scene.physics.alpha == Run.open(parent).scene.physics.alpha
    assert set(settings["buoyancy_calibration_error"]) == {f"{s:g}" for s in identification.BUOYANCY_SCALES}
    chained = Run.open(job.run_predict(run.path, tmp_path / "again", frames=1))
    assert chained.manifest["settings"]["buoyancy_calibration_error"] == {}  # physics is not re-identified on itself
    assert chained.manifest["settings"]["appearance_profile"] == settings["appearance_profile"] is not None
    assert any("appearance height profile" in prior for prior in settings["priors"])  # named as a prior


def _visual(heights: torch.Tensor, colors: torch.Tensor) -> SmokeState:
    n = len(heights)
    means = torch.stack([torch.zeros(n), heights, torch.zeros(n)], dim=1)
    appearance = Appearance(torch.full((n, 3), -4.0), torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                            torch.zeros(n), colors[:, None])
    return SmokeState(ParticleState.empty(), means, appearance)


def test_the_height_profile_pulls_each_bands_mean_colour_back_and_keeps_the_spread_within_it() -> None:
    generator = torch.Generator().manual_seed(0)
    heights = torch.rand(400, generator=generator)
    observed = _visual(heights, 0.2 + 0.6 * heights)  # smoke lightens as it rises
    profile = priors.HeightProfile.observe(observed, (0.0, 1.0, 0.0), bands=4)
    # The simulation carried dark smoke up: every Gaussian 0.1 darker than its height's colour.
    risen = _visual(heights, 0.1 + 0.6 * heights + 0.01 * torch.randn(400, generator=generator))
    held = profile.hold(risen, 1 / 30)
    band = torch.bucketize(heights, torch.tensor(profile.edges[1:-1], dtype=heights.dtype))
    for b in range(4):
        inside = band == b
        before = risen.appearance.colors[inside].mean() - observed.appearance.colors[inside].mean()
        after = held.appearance.colors[inside].mean() - observed.appearance.colors[inside].mean()
        assert before < -0.05 and torch.isclose(after, (1 - priors.HOLD_RATE) * before, atol=1e-5)
        spread = held.appearance.colors[inside, 0] - risen.appearance.colors[inside, 0]
        assert torch.allclose(spread, spread[0].expand_as(spread), atol=1e-6)  # one shift per band
    for _ in range(60):  # held frame after frame, the band means converge to the profile's
        held = profile.hold(held, 1 / 30)
    # in seconds: two frames at 60 fps hold as much as one at 30
    twice = profile.hold(profile.hold(risen, 1 / 60), 1 / 60)
    torch.testing.assert_close(twice.appearance.colors, profile.hold(risen, 1 / 30).appearance.colors, atol=1e-5, rtol=0)
    for b in range(4):
        inside = band == b
        assert torch.isclose(held.appearance.colors[inside].mean(), observed.appearance.colors[inside].mean(), atol=1e-4)
    assert torch.equal(held.means, risen.means) and torch.equal(held.appearance.log_scales, risen.appearance.log_scales)
    recorded = AppearanceProfile.model_validate_json(profile.model_dump_json())  # as a chained prediction reads it
    assert priors.HeightProfile.of(recorded) == profile


def test_a_run_chain_moved_to_another_folder_continues(parent: Path, tmp_path: Path) -> None:
    """reconstruct -> predict -> predict, moved as one folder (another work dir, another worker):
    the parents are found relative to each run, an interrupted link resumes, and the chain grows."""
    first = tmp_path / "here"
    shutil.copytree(parent, first / "reconstruct")
    job.run_predict(first / "reconstruct", first / "p1", frames=2)
    with pytest.raises(Cancelled):
        job.run_predict(first / "p1", first / "p2", frames=3, context=JobContext(should_cancel=iter([False, True]).__next__))
    moved = tmp_path / "elsewhere" / "chain"
    shutil.move(first, moved)
    job.run_predict(moved / "p1", moved / "p2", frames=3)  # resumes: same run, its parent found again
    grown = Run.open(job.run_predict(moved / "p2", moved / "p3", frames=2))
    assert grown.parent.parent.parent.path.resolve() == (moved / "reconstruct").resolve()
    assert len(run_frames.render_frames(grown, grown.cameras()["view_00"])) == 2
    uninterrupted = tmp_path / "whole"
    job.run_predict(parent, uninterrupted / "p1", frames=2)
    job.run_predict(uninterrupted / "p1", uninterrupted / "p2", frames=3)
    assert_same_states(Run.open(moved / "p2"), Run.open(uninterrupted / "p2"))


def test_a_parent_recorded_by_absolute_path_is_still_read(parent: Path, tmp_path: Path) -> None:
    run = Run.open(job.run_predict(parent, tmp_path / "pred", frames=1))
    manifest = json.loads((run.path / "manifest.json").read_text())
    manifest["parent"] = str(parent.resolve())  # as runs were written before parents became relative
    (run.path / "manifest.json").write_text(json.dumps(manifest))
    assert Run.open(run.path).parent.path == parent.resolve()


def test_identified_physics_is_predicted_with_as_it_is_and_calibration_never_zeroes_buoyancy(parent: Path, tmp_path: Path) -> None:
    """A reconstruction whose physics was identified from the video (settings physics mode
    "auto") is continued under exactly that physics and without the appearance prior (it lost
    on ScalarFlow, docs/bench_generalise.md); preset physics is still calibrated, over
    candidate multiples that are all positive (rising smoke never loses its buoyancy)."""
    assert min(identification.BUOYANCY_SCALES) > 0.0
    identified = tmp_path / "identified"
    shutil.copytree(parent, identified)
    manifest = json.loads((identified / "manifest.json").read_text())
    manifest["settings"]["physics"] = {"mode": "auto"}
    (identified / "manifest.json").write_text(json.dumps(manifest))
    run = Run.open(job.run_predict(identified, tmp_path / "pred", frames=1))
    assert run.manifest["settings"]["buoyancy_calibration_error"] == {}
    assert run.scene.physics.alpha == Run.open(parent).scene.physics.alpha
    assert run.manifest["settings"]["priors"] == [] and run.manifest["settings"]["appearance_profile"] is None
