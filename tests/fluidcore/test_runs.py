"""The run folder: written frame by frame, read back exactly, resumed, and refused when it is another run."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from fluidcore.physics import PBFConfig, Source
from fluidcore.runs import (
    FORMAT_VERSION,
    ContinuationSettings,
    FrameState,
    PhysicsRecord,
    ReconstructSettings,
    Run,
    RunError,
    RunKind,
    RunRecord,
    state_file,
)
from fluidcore.spec.reconstruct import ReconstructConfig, get
from fluidcore.spec.scene import Air
from fluidcore.spec.simulation import SimulationConfig
from tests.support.run_folder import _camera, _create, _scene, _state

OLD_RUNS = Path(__file__).parent / "fixtures" / "runs_v1"  # written by format version 1 (see its README.md)
V2_RUNS = Path(__file__).parent / "fixtures" / "runs_v2"  # written by format version 2 (see its README.md)


def test_frames_round_trip_and_manifest_records_losses(tmp_path):
    run = _create(tmp_path / "run")
    written = [_state(1), _state(2)]
    for t, state in enumerate(written):
        run.write_frame(t, state, {"visual": 0.5 + t}, seconds=1.5)
    reopened = Run.open(tmp_path / "run")
    assert reopened.frames() == [0, 1]
    assert reopened.next_frame() == 2
    assert not reopened.manifest["complete"]
    assert reopened.frame_log(1)["losses"] == {"visual": 1.5}
    back = reopened.read_frame(1)
    np.testing.assert_array_equal(back.positions, written[1].positions)
    np.testing.assert_array_equal(back.alive, written[1].alive)
    np.testing.assert_array_equal(back.extra["rng"], written[1].extra["rng"])
    np.testing.assert_allclose(back.gaussians["quats"], written[1].gaussians["quats"].astype(np.float32))
    assert reopened.cameras()["cam"] == _camera()
    assert reopened.scene == _scene()
    manifest = json.loads((tmp_path / "run" / "manifest.json").read_text())
    assert manifest["frames"][0]["file"] == "states/frame_000000.npz"
    assert {"fluidnexus", "numpy", "python"} <= manifest["versions"].keys()


def test_reopening_the_same_run_resumes_and_a_different_one_is_refused(tmp_path):
    run = _create(tmp_path / "run")
    run.write_frame(0, _state(1), {"visual": 1.0}, seconds=1.0)
    again = _create(tmp_path / "run")
    assert again.next_frame() == 1
    with pytest.raises(RunError, match="settings"):
        _create(tmp_path / "run", settings=ReconstructSettings(quality=get("paper")))
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    with pytest.raises(RunError, match="not a run folder"):
        _create(tmp_path / "other")
    assert (tmp_path / "other" / "notes.txt").read_text() == "mine"


def test_completion_and_out_of_order_frames(tmp_path):
    run = _create(tmp_path / "run", frame_range=(5, 7))
    with pytest.raises(RunError, match="expects 5"):
        run.write_frame(6, _state(1), {}, seconds=0.0)
    run.write_frame(5, _state(1), {}, seconds=0.0)
    run.write_frame(6, _state(2), {}, seconds=0.0)
    assert run.manifest["complete"]
    with pytest.raises(RunError, match="not in this run"):
        run.read_frame(7)


def test_bad_states_and_losses_are_refused(tmp_path):
    run = _create(tmp_path / "run")
    bad = _state(1)
    bad.positions[0, 0] = np.nan
    with pytest.raises(RunError, match="positions"):
        FrameState(bad.positions, bad.velocities, bad.alive, bad.time, bad.gaussians)
    with pytest.raises(RunError, match="not finite"):
        run.write_frame(0, _state(1), {"visual": float("nan")}, seconds=0.0)
    with pytest.raises(RunError, match="lack"):
        FrameState(bad.velocities, bad.velocities, bad.alive, 0.0, {"means": np.zeros((1, 3))})


def test_export_keeps_live_particles_and_background_round_trips(tmp_path):
    run = _create(tmp_path / "run")
    state = _state(3)
    exported = state.export()
    assert len(exported["positions"]) == int(state.alive.sum())
    np.testing.assert_array_equal(exported["velocities"], state.velocities[state.alive])
    assert exported["gaussian_colors"].shape == (4, 1)
    image = np.random.default_rng(0).random((24, 32, 1)).astype(np.float32)
    run.write_background({"cam": image})
    np.testing.assert_array_equal(Run.open(tmp_path / "run").background_images()["cam"], image)


def test_open_rejects_folders_that_are_not_runs(tmp_path):
    with pytest.raises(RunError, match="no manifest.json"):
        Run.open(tmp_path)
    (tmp_path / "manifest.json").write_text("{not json")
    with pytest.raises(RunError, match="not valid JSON"):
        Run.open(tmp_path)


def test_runs_written_before_the_typed_record_are_read_migrated(tmp_path):
    """Version-1 folders from main (kept in tests/fluidcore/fixtures/runs_v1) read as typed records of their
    kind; reading never rewrites them."""
    rec = Run.open(OLD_RUNS / "reconstruct")
    assert rec.kind is RunKind.RECONSTRUCT and rec.manifest["format_version"] == FORMAT_VERSION
    assert isinstance(rec.settings, ReconstructSettings) and rec.settings.physics.mode == "auto"
    assert rec.visual_settings().per_physical == 2 and [v.kind for v in rec.settings.views][:2] == ["input", "symmetry"]
    assert rec.settings.quality.visual.opacity_concentration is False  # version 1 ran before the concentration tie
    assert isinstance(rec.scene.physics, PBFConfig) and rec.scene.physics.h == pytest.approx(0.021333, rel=1e-4)
    assert isinstance(rec.scene.source, Source) and rec.scene.source.rate == 27
    interact = Run.open(OLD_RUNS / "interact")
    assert interact.kind is RunKind.INTERACT and interact.parent.path == OLD_RUNS / "interact" / ".." / "reconstruct"
    assert isinstance(interact.settings, ContinuationSettings) and interact.settings.branch_frame == 2
    assert interact.settings.wind.strength == 0.5 and interact.settings.ball.radius == 0.05
    assert Run.open(OLD_RUNS / "predict").settings.wind is None
    assert json.loads((OLD_RUNS / "interact" / "manifest.json").read_text())["format_version"] == 1
    stored = (OLD_RUNS / "interact" / "manifest.json").read_bytes()  # as the API fetches it from storage
    assert RunRecord.from_bytes(stored, "interact").manifest == interact.manifest
    assert interact.read_frame(3).positions.shape[1] == 3 and state_file(3) == "states/frame_000003.npz"


def test_version_1_settings_missing_later_fields_get_their_defaults_and_strangers_are_refused(tmp_path):
    """Version 1 before --physics had no physics record, before --from-frame no branch frame;
    keys it wrote that no model knows are dropped. Another kind or version is refused."""
    old = json.loads((OLD_RUNS / "predict" / "manifest.json").read_text())
    early = {**old, "settings": {k: v for k, v in old["settings"].items() if k != "branch_frame"} | {"retired": 1}}
    assert RunRecord.from_bytes(json.dumps(early).encode(), "early").settings.branch_frame == 2  # first frame - 1
    rec = json.loads((OLD_RUNS / "reconstruct" / "manifest.json").read_text())
    del rec["settings"]["physics"]
    assert RunRecord.from_bytes(json.dumps(rec).encode(), "rec").settings.physics == PhysicsRecord(mode="scalarflow")
    with pytest.raises(RunError, match="kind 'guess'"):
        RunRecord.from_bytes(json.dumps({**old, "kind": "guess"}).encode(), "guess")
    with pytest.raises(RunError, match=f"format_version {FORMAT_VERSION + 1}"):
        RunRecord.from_bytes(json.dumps({**old, "format_version": FORMAT_VERSION + 1}).encode(), "future")
    with pytest.raises(RunError, match="settings do not fit"):
        RunRecord.from_bytes(json.dumps({**old, "format_version": 2, "settings": {"visual": None}}).encode(), "broken")


def test_a_version_1_reconstruction_is_continued_into_a_current_run(tmp_path):
    from fluidcore.spec.controls import BallParams, InteractionParams
    from fluidcore.predict import run_interact

    shutil.copytree(OLD_RUNS / "reconstruct", tmp_path / "reconstruct")
    ball = InteractionParams(ball=BallParams(center=(0.0, 0.3, 0.0), radius=0.05))
    out = run_interact(tmp_path / "reconstruct", tmp_path / "what-if", ball, frames=1)
    run = Run.open(out)
    assert json.loads((out / "manifest.json").read_text())["format_version"] == FORMAT_VERSION
    assert run.frames() == [3] and run.settings.branch_frame == 2 and run.settings.ball.radius == 0.05
    assert run.scene.physics == Run.open(tmp_path / "reconstruct").scene.physics  # auto physics: used as identified


def test_version_2_runs_read_with_their_quality_nested_and_their_records_typed():
    """Version-2 folders from main before the nested config (fixtures/runs_v2): the flat quality
    reads as the `ReconstructConfig` it was (the preview preset; the air run with its air and
    spreading), the physics and symmetry records as models, the visual settings off the quality."""
    rec = Run.open(V2_RUNS / "reconstruct")
    flat = json.loads((V2_RUNS / "reconstruct" / "manifest.json").read_text())["settings"]
    assert flat["quality"]["visual_per_physical"] == 2 and rec.manifest["format_version"] == FORMAT_VERSION
    # written before the carrier: the paper model, whose still air its air_cells 0 meant
    assert rec.settings.quality == get("preview").with_overrides(motion="paper", air_cells=0)
    assert rec.visual_settings().model_dump() == flat["visual"]
    assert rec.settings.physics.model_dump(mode="json", exclude_none=True) == flat["physics"]
    assert rec.settings.symmetry.model_dump() == flat["symmetry"]
    airy = Run.open(V2_RUNS / "recair").settings.quality
    assert airy.simulation == SimulationConfig(motion="paper", air_cells=16, air_vorticity=0.1, entrainment=True)
    assert airy.model_copy(update={"simulation": SimulationConfig()}) == get("preview")
    assert Run.open(V2_RUNS / "predict").visual_settings() == rec.visual_settings()
    stored = (V2_RUNS / "reconstruct" / "manifest.json").read_bytes()  # as the API fetches it from storage
    assert RunRecord.from_bytes(stored, "reconstruct").manifest == rec.manifest


def test_the_air_of_versions_1_and_2_moves_into_the_scene_record():
    """Versions 1 and 2 kept the air a run simulates in its settings (a reconstruction's flat
    quality, a continuation's `air_cells`, `air_vorticity`); read, it is the scene record's, as
    version 3 writes it, and a reconstruction's quality still says what was asked for."""
    recair = Run.open(V2_RUNS / "recair")
    assert json.loads((V2_RUNS / "recair" / "manifest.json").read_text())["settings"]["quality"]["air_cells"] == 16
    assert recair.manifest["scene"]["air"] == {"cells": 16, "vorticity": 0.1} and recair.scene.air == Air(16, 0.1)
    assert (recair.settings.quality.simulation.air_cells, recair.settings.quality.simulation.air_vorticity) == (16, 0.1)
    for old in (OLD_RUNS / "reconstruct", OLD_RUNS / "interact", V2_RUNS / "reconstruct", V2_RUNS / "predict"):
        assert Run.open(old).manifest["scene"]["air"] == {"cells": 0, "vorticity": 0.0}  # still air, recorded
    predict = json.loads((V2_RUNS / "predict" / "manifest.json").read_text())
    assert predict["settings"]["air_cells"] == 0 and "air" not in predict["scene"]
    for version in (1, 2):
        airy = {**predict, "format_version": version,
                "settings": {**predict["settings"], "air_cells": 24, "air_vorticity": 0.2}}
        record = RunRecord.from_bytes(json.dumps(airy).encode(), "airy")
        assert record.scene.air == Air(24, 0.2) and record.manifest["scene"]["air"] == {"cells": 24, "vorticity": 0.2}
        assert not {"air_cells", "air_vorticity"} & record.manifest["settings"].keys()
        assert record.scene.physics == Run.open(V2_RUNS / "predict").scene.physics  # the rest of the record as it was
    coarse = {**predict, "settings": {**predict["settings"], "air_cells": 4}}
    with pytest.raises(RunError, match="air.cells must be 0"):
        RunRecord.from_bytes(json.dumps(coarse).encode(), "coarse").scene


def test_a_current_record_reads_back_as_it_was_written(tmp_path):
    run = _create(tmp_path / "run", settings=ReconstructSettings(quality=get("standard").with_overrides(air_cells=32)))
    assert json.loads((tmp_path / "run" / "manifest.json").read_text())["format_version"] == FORMAT_VERSION
    again = Run.open(tmp_path / "run").settings.quality
    assert isinstance(again, ReconstructConfig) and again == get("standard").with_overrides(air_cells=32)


def test_a_version_2_reconstruction_is_predicted_as_main_predicted_it(tmp_path):
    """Continuing the migrated reconstruction writes the frames the version-2 code wrote from it
    (fixtures/runs_v2/predict): the settings read back are the ones it ran with."""
    from fluidcore.predict import run_predict

    shutil.copytree(V2_RUNS / "reconstruct", tmp_path / "reconstruct")
    out = Run.open(run_predict(tmp_path / "reconstruct", tmp_path / "predict", frames=2))
    then = Run.open(V2_RUNS / "predict")
    assert out.settings == then.settings and out.frames() == then.frames() == [3, 4]
    for t in out.frames():
        now, before = out.read_frame(t), then.read_frame(t)
        np.testing.assert_allclose(now.positions, before.positions, atol=1e-5)
        np.testing.assert_allclose(now.gaussians["opacity_logits"], before.gaussians["opacity_logits"], atol=1e-5)
