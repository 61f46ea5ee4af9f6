"""Reconstruction on a tiny synthetic plume (fluidcore.synth) with known ground truth.

The scene: 3 cameras on a half circle, 48x64 px, 5 frames at 10 fps (so the smoke moves a
few pixels), a few hundred particles. We reconstruct from the middle camera only.

Why the thresholds are what they are:
* input view: a blank (background-only) frame scores ~14.5 dB on this scene; the rendering
  model is the one that made the scene, so a working fit reproduces the smoke closely. We
  require 25 dB on every frame, i.e. most of the smoke's energy explained (MSE under 1/30 of
  the blank's).
* held-out views: depth is unconstrained from one view, so we only require that the novel
  views beat the blank frame by a wide margin (5 dB): the smoke is in the right place in 3D.
* velocity: the mean error of the reconstructed velocity field at the true particles must be
  below that of the zero-velocity baseline (the mean true speed), frame by frame.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fluidcore import metrics, run_frames, synth
from fluidcore.physics import interpolate_velocity
from fluidcore.reconstruct import Reconstructor, ReconstructionError, prepare, read_inputs
from fluidcore.spec.source_hint import SourceHint, SourceHintError, parse_source
from fluidcore.runs import Run
from fluidcore.spec.reconstruct import get

INPUT = "view_01"
FRAMES = 5


@pytest.fixture(scope="module")
def scene() -> synth.SynthScene:
    return synth.generate(synth.SynthSpec(frames=FRAMES, width=48, height=64, views=3, fps=10.0))


def _prepare(scene: synth.SynthScene, frames: int = FRAMES, source: SourceHint | None = None, **overrides):
    """The synthetic plume's reconstruction prepared under the paper model, the model that made it
    (its velocities are the truth the tests score), unless `overrides` name another."""
    spec = scene.spec
    per_30th = max(1, round(spec.particles_per_step * spec.fps / 30))  # the budget is per 1/30 s (scene_physics.frame_budget)
    quality = get("preview").with_overrides(long_side=64, particles_per_frame=per_30th, **{"motion": "paper", **overrides})
    box = spec.box()
    return prepare(
        scene.cameras,
        read_inputs(scene.cameras, {INPUT: scene.videos[INPUT][:frames]}, frame_range=(0, frames), quality=quality),
        fps=spec.fps,
        quality=quality,
        box=(np.array(box.lo), np.array(box.hi)),
        source=source,
    )


def _as_float(video: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(video).float() / 255.0


@pytest.fixture(scope="module")
def run(scene, tmp_path_factory) -> Run:
    return Reconstructor(_prepare(scene)).run(tmp_path_factory.mktemp("run") / "run")


def test_input_view_is_reproduced_and_novel_views_beat_blank(scene, run):
    assert run.frames() == list(range(FRAMES))
    for name, camera in scene.cameras.items():
        pred = _as_float(run_frames.render_frames(run, camera))
        truth = _as_float(scene.videos[name])
        blank = metrics.psnr(torch.ones_like(truth), truth)
        if name == INPUT:
            for t in range(FRAMES):
                assert metrics.psnr(pred[t], truth[t]) > 25.0, f"frame {t}"
        else:
            assert metrics.psnr(pred, truth) > blank + 5.0, name


def test_forecast_of_each_unseen_frame_is_recorded_from_the_input_view_alone(run):
    """forecast_psnr scores the carried state on frame t before frame t is fitted; the run was
    given the input camera only, so the only views it fits or scores are that camera and its
    symmetry pseudo-views."""
    fitted_views = {v["camera"].split("~")[0] for v in run.manifest["settings"]["views"]}
    assert fitted_views == {INPUT}
    losses = [frame["losses"] for frame in run.manifest["frames"]]
    assert all(np.isfinite(entry["forecast_psnr"]) and np.isfinite(entry["input_psnr"]) for entry in losses)
    later = losses[1:]  # frame 0 forecasts from the untrained newborn look
    assert np.mean([e["input_psnr"] for e in later]) >= np.mean([e["forecast_psnr"] for e in later]) - 0.5


def test_particles_move_the_right_way(scene, run):
    radius = 2.0 * run.scene.physics.h
    for t in range(1, FRAMES):
        state = run.read_frame(t)
        alive = state.alive
        estimate = interpolate_velocity(
            torch.from_numpy(scene.positions[t]),
            torch.from_numpy(state.positions[alive]),
            torch.from_numpy(state.velocities[alive]),
            radius,
        ).numpy()
        error = np.linalg.norm(estimate - scene.velocities[t], axis=1).mean()
        zero_baseline = np.linalg.norm(scene.velocities[t], axis=1).mean()
        assert error < zero_baseline, f"frame {t}: {error:.4f} vs {zero_baseline:.4f}"
        assert np.mean(estimate[:, 1] > 0) > 0.9  # the smoke rises


def test_estimated_source_is_near_the_true_one(scene):
    rec = _prepare(scene, frames=2)
    truth = scene.spec.source()
    assert np.linalg.norm(np.subtract(rec.scene.source.center, truth.center)) < 2 * truth.radius
    assert 0.5 * truth.radius < rec.scene.source.radius < 2 * truth.radius
    assert rec.channels == 1
    np.testing.assert_allclose(rec.background_color, [1.0], atol=0.02)


def test_a_known_source_keeps_its_depth_and_its_radius_is_measured_there(scene):
    """One view cannot tell depth: a user's source centre is kept where they put it, off the
    estimate's axis (identification chooses the measured radius around it, and moves nothing),
    and recorded in the manifest's settings."""
    truth = scene.spec.source()
    forward = scene.cameras[INPUT].forward()
    hint = SourceHint(center=tuple(np.asarray(truth.center) - 0.1 * forward))  # 10 cm nearer the camera
    rec, guessed = _prepare(scene, frames=2, source=hint), _prepare(scene, frames=2)
    up = np.asarray(rec.scene.up)

    def across(point) -> np.ndarray:
        offset = np.subtract(point, hint.center)
        return offset - (offset @ up) * up

    np.testing.assert_allclose(rec.scene.source.center, hint.center, atol=1e-6)
    assert np.linalg.norm(across(guessed.scene.source.center)) > 0.05
    assert 0.3 * truth.radius < rec.scene.source.radius < 3 * truth.radius
    assert rec.settings().source_hint == hint
    assert guessed.settings().source_hint is None


def test_a_source_hint_outside_the_box_or_malformed_is_refused(scene):
    with pytest.raises(SourceHintError, match="outside the scene box"):
        _prepare(scene, frames=2, source=SourceHint(center=(9.0, 0.0, 0.0)))
    for text in ("1,2", "a,b,c", "0,0,0,-1", "0,nan,0"):
        with pytest.raises(SourceHintError, match="--source"):
            parse_source(text)
    assert parse_source("0.1,0.2,0.3,0.05") == SourceHint(center=(0.1, 0.2, 0.3), radius=0.05)


def test_interrupted_run_resumes_to_the_same_result(scene, tmp_path):
    quick = dict(position_iterations=3, appearance_iterations=2, first_frame_factor=1)
    straight = Reconstructor(_prepare(scene, frames=3, **quick)).run(tmp_path / "straight")
    calls = iter([False, False, True])
    partial = Reconstructor(_prepare(scene, frames=3, **quick)).run(tmp_path / "resumed", should_stop=lambda: next(calls))
    assert partial.frames() == [0, 1]
    resumed = Reconstructor(_prepare(scene, frames=3, **quick)).run(tmp_path / "resumed")
    assert resumed.frames() == [0, 1, 2]
    a, b = straight.read_frame(2), resumed.read_frame(2)
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_array_equal(a.velocities, b.velocities)
    for key in a.gaussians:
        np.testing.assert_array_equal(a.gaussians[key], b.gaussians[key])


def test_bad_inputs_name_the_field(scene):
    with pytest.raises(ReconstructionError, match="videos"):
        read_inputs(scene.cameras, {"nope": scene.videos[INPUT]}, frame_range=(0, FRAMES), quality=get("preview"))
    with pytest.raises(ReconstructionError, match="frames"):
        read_inputs(scene.cameras, {INPUT: scene.videos[INPUT][:2]}, frame_range=(0, FRAMES), quality=get("preview"))
    with pytest.raises(ValueError, match="quality"):
        get("ultra")


def test_prepare_fits_the_views_it_is_given_and_the_reconstruction_is_frozen(scene):
    """Views made before `prepare` (the generated ones) take the place of the symmetry
    pseudo-views; a refinement fits its inputs alone; nobody rewrites the views afterwards."""
    from dataclasses import FrozenInstanceError

    from fluidcore.reconstruct.views import generated_targets

    spec = scene.spec
    quality = get("preview").with_overrides(long_side=64, particles_per_frame=spec.particles_per_step)
    inputs = read_inputs(scene.cameras, {INPUT: scene.videos[INPUT][:2]}, frame_range=(0, 2), quality=quality)
    box = spec.box()
    common = dict(fps=spec.fps, quality=quality, box=(np.array(box.lo), np.array(box.hi)), physics="scalarflow")
    plain = prepare(scene.cameras, inputs, **common)
    source = inputs.targets[0]
    other = scene.cameras["view_00"].scaled(source.camera.width, source.camera.height)
    drawn = generated_targets(source, [other], {"view_00": source.frames.clone()}, quality.priors.symmetry_weight)
    generated = prepare(scene.cameras, inputs, extra_views=drawn, **common)
    alone = prepare(scene.cameras, inputs, pseudo_views=False, **common)
    assert [v.kind for v in plain.views] == ["input"] + ["symmetry"] * quality.priors.symmetry_views
    assert [v.kind for v in generated.views] == ["input", "generated"] and generated.views[1].weight == quality.priors.symmetry_weight
    assert [v.kind for v in alone.views] == ["input"]
    assert plain.symmetry == generated.symmetry == alone.symmetry  # the prior's record stays in the manifest
    with pytest.raises(FrozenInstanceError):
        plain.views = ()


def test_the_source_estimate_and_the_depth_range_of_one_view_are_in_the_manifest_and_scene_info(run):
    """One view: the manifest says how the source's depth was found, and scene info gives the
    stretch of the input ray inside the box on which the estimated centre lies."""
    from fluidcore import scene_info

    reopened = Run.open(run.path)
    estimate = reopened.settings.source_estimate
    assert estimate is not None and estimate.depth_cue in ("floor", "box axis")
    assert set(estimate.pixels) == {INPUT}
    depth = scene_info.from_run(reopened, "cli")["source"]["depth"]
    near, far = (np.asarray(p) for p in depth["range"])
    lo, hi = np.asarray(reopened.scene.box_lo), np.asarray(reopened.scene.box_hi)
    assert np.all(near >= lo - 1e-9) and np.all(far <= hi + 1e-9) and np.linalg.norm(far - near) > 0.1
    camera = reopened.cameras()[INPUT]
    ray = (far - near) / np.linalg.norm(far - near)
    assert np.allclose(ray, (near - camera.center()) / np.linalg.norm(near - camera.center()), atol=1e-6)  # the input ray


def test_a_symmetry_long_side_that_is_not_a_whole_number_of_pixels_from_8_is_refused():
    from fluidcore.spec.reconstruct import PresetError

    for bad in (0, 7, -120, 12.5, True, "120"):
        with pytest.raises(PresetError, match="symmetry_long_side"):
            get("preview").with_overrides(symmetry_long_side=bad)
    assert get("preview").with_overrides(symmetry_long_side=8).priors.symmetry_long_side == 8


def test_symmetry_pseudo_views_are_fitted_at_their_own_long_side(scene, monkeypatch):
    """`priors.symmetry_long_side`: every symmetry pseudo-view is rendered at that long side,
    whatever the coarse-to-fine stage, while the input view keeps the stages; at or above the
    working size, and with None (runs made before the field), the pseudo-views follow the stages."""
    import random

    from fluidcore.reconstruct import loop
    from fluidcore.render import Gaussians

    original, sizes = loop.render, []

    def recording(gaussians, camera, background, depth):
        sizes.append((camera.name, max(camera.width, camera.height)))
        return original(gaussians, camera, background, depth=depth)

    monkeypatch.setattr(loop, "render", recording)
    for side in (24, 64, None):  # the scene is fitted at a long side of 64
        rec = _prepare(scene, frames=2, symmetry_long_side=side)
        working = {v.camera.name: max(v.camera.width, v.camera.height) for v in rec.views}
        stages = lambda name: {max(loop.MIN_FIT_SIDE, round(working[name] * f)) for f in rec.quality.fit.coarse_to_fine}  # noqa: E731
        n = 4
        center = torch.tensor(rec.scene.source.center, dtype=torch.float32)
        gaussians = Gaussians(center + 0.01 * torch.randn(n, 3), torch.full((n, 3), -4.0), torch.tensor([[1.0, 0, 0, 0]] * n),
                              torch.zeros(n), torch.full((n, 1), 0.5))
        loss = Reconstructor(rec)._image_loss(0, iterations=40, chooser=random.Random(1))
        sizes.clear()
        for k in range(40):
            loss(gaussians, k)
        pseudo = [(name, long) for name, long in sizes if "~sym" in name]
        real = [(name, long) for name, long in sizes if "~sym" not in name]
        assert pseudo and real, sizes
        assert all(long in stages(name) for name, long in real)
        if side == 24:
            assert all(long == 24 for _, long in pseudo), pseudo
        else:
            assert {long for _, long in pseudo} == stages(pseudo[0][0]), pseudo
