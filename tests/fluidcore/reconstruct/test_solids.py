"""A reconstruction with solids in its scene (issue 48): the static balls the user placed are in
the way of every step and of the image fit, recorded in the run's scene, and the health report
notes one the smoke never came near.

The scene: the tiny synthetic plume of test_reconstruct (its smoke rises from y 0.05 to 0.42 over
x, z within 0.05 of the axis by frame 3), reconstructed from one view over 4 frames at few
iterations. One ball sits on the plume's axis at y 0.25, where the smoke of the same run without
it passes (the control below), one in a top corner of the box, which no smoke reaches.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fluidcore import synth
from fluidcore.health import report
from fluidcore.reconstruct import Reconstructor, prepare, read_inputs
from fluidcore.runs import Run
from fluidcore.spec.reconstruct import get
from fluidcore.spec.solids import SolidBall, SolidError, gap_record

INPUT = "view_01"
FRAMES = 4
IN_THE_PLUME = SolidBall(center=(0.0, 0.25, 0.0), radius=0.04)
IN_A_CORNER = SolidBall(center=(0.2, 0.7, 0.2), radius=0.03)
QUICK = dict(position_iterations=4, appearance_iterations=3, first_frame_factor=1)


@pytest.fixture(scope="module")
def scene() -> synth.SynthScene:
    return synth.generate(synth.SynthSpec(frames=FRAMES, width=48, height=64, views=3, fps=10.0))


def _reconstruct(scene: synth.SynthScene, out, solids=()) -> Run:  # noqa: ANN001 - a path
    spec = scene.spec
    per_30th = max(1, round(spec.particles_per_step * spec.fps / 30))
    quality = get("preview").with_overrides(long_side=64, particles_per_frame=per_30th, motion="paper", **QUICK)
    box = spec.box()
    rec = prepare(scene.cameras, read_inputs(scene.cameras, {INPUT: scene.videos[INPUT]}, frame_range=(0, FRAMES), quality=quality),
                  fps=spec.fps, quality=quality, box=(np.array(box.lo), np.array(box.hi)), solids=solids)
    return Reconstructor(rec).run(out)


@pytest.fixture(scope="module")
def with_balls(scene, tmp_path_factory) -> Run:
    return _reconstruct(scene, tmp_path_factory.mktemp("solids") / "run", (IN_THE_PLUME, IN_A_CORNER))


def _nearest(run: Run, ball: SolidBall, layer: str) -> float:
    """The closest any live particle (`layer` "particles") or visual Gaussian ("gaussians") of the
    run's frames came to the ball's centre."""
    nearest = np.inf
    for t in run.frames():
        frame = run.read_frame(t)
        points = frame.positions[frame.alive] if layer == "particles" else frame.gaussians["means"]
        if len(points):
            nearest = min(nearest, float(np.linalg.norm(points - np.asarray(ball.center), axis=1).min()))
    return nearest


def test_the_smoke_keeps_out_of_a_ball_in_its_way_and_passes_there_without_it(scene, with_balls, tmp_path):
    radius = IN_THE_PLUME.radius
    for layer in ("particles", "gaussians"):
        assert _nearest(with_balls, IN_THE_PLUME, layer) >= radius * (1 - 1e-5), layer
    without = _reconstruct(scene, tmp_path / "without")
    assert _nearest(without, IN_THE_PLUME, "particles") < 0.5 * radius  # the ball is where the smoke goes


def test_the_run_records_its_solids_and_how_near_the_smoke_came(with_balls):
    assert with_balls.scene.solids == (IN_THE_PLUME, IN_A_CORNER)
    assert Run.open(with_balls.path).scene.solids == (IN_THE_PLUME, IN_A_CORNER)
    h = with_balls.scene.physics.h
    losses = [entry["losses"] for entry in with_balls.manifest["frames"]]
    assert min(frame[gap_record(0)] for frame in losses) < h  # touched: the smoke is pushed onto its surface
    assert min(frame[gap_record(1)] for frame in losses) > 0.1


def test_the_health_report_notes_the_ball_the_smoke_never_touched_and_not_the_other(with_balls):
    for audience, flag in (("cli", "--ball"), ("api", "params.solids")):
        checks = [c for c in report(with_balls, audience=audience)["checks"] if c["name"] == "solids"]
        assert len(checks) == 1, checks
        (check,) = checks
        assert check["level"] == "note"
        assert "solids[1]" in check["finding"] and "solids[0]" not in check["finding"]
        assert flag in check["message"]


def test_a_ball_outside_the_box_is_refused_by_name(scene, tmp_path):
    with pytest.raises(SolidError, match=r"solids\[0\].center .* is outside the scene box"):
        _reconstruct(scene, tmp_path / "refused", (SolidBall(center=(0.0, 2.0, 0.0), radius=0.1),))
    assert not (tmp_path / "refused").exists()
