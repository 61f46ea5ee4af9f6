"""The one pipeline entry of a reconstruction (`fluidcore.reconstruct.pipeline`): footage in memory
-> read_inputs -> prepare -> fit, which the reconstruct job, Algorithm S2's refinement and the
source benchmark share."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from fluidcore import synth
from fluidcore.reconstruct import prepare, read_inputs
from fluidcore.reconstruct.loop import Plate
from fluidcore.reconstruct.pipeline import Footage, prepared, reconstruct
from fluidcore.spec.source_hint import SourceHint
from fluidcore.runs import Run
from fluidcore.spec.reconstruct import get
from fluidcore.spec.scene import SourcePlace

INPUT = "view_01"
QUICK = get("preview").with_overrides(position_iterations=2, appearance_iterations=2, first_frame_factor=1)


@pytest.fixture(scope="module")
def plume() -> synth.SynthScene:
    return synth.generate(synth.SynthSpec(frames=2, width=32, height=48, views=3))


def _footage(plume: synth.SynthScene, source: SourceHint | SourcePlace | None = None) -> Footage:
    box = plume.spec.box()
    return Footage(plume.cameras, {INPUT: plume.videos[INPUT]}, (0, 2), plume.spec.fps, (np.array(box.lo), np.array(box.hi)),
                   source=source)


def test_prepared_is_read_inputs_then_prepare(plume: synth.SynthScene) -> None:
    footage = _footage(plume)
    rec = prepared(footage, QUICK, physics="scalarflow")
    inputs = read_inputs(footage.cameras, footage.videos, frame_range=(0, 2), quality=QUICK)
    by_hand = prepare(footage.cameras, inputs, fps=footage.fps, quality=QUICK, box=footage.box, physics="scalarflow")
    assert rec.scene == by_hand.scene and rec.physics == by_hand.physics
    assert [v.kind for v in rec.views] == [v.kind for v in by_hand.views] and rec.views[0].kind == "input"


def test_reconstruct_fits_the_footage_into_a_run(plume: synth.SynthScene, tmp_path) -> None:
    """A known source's place is kept and recorded; without generative settings no generated
    views are made nor reported; `pseudo_views=False` fits the input view alone."""
    place = SourcePlace((0.0, 0.075, 0.0), 0.05)
    out = reconstruct(_footage(plume, place), QUICK, tmp_path / "run", physics="scalarflow", pseudo_views=False,
                      status={"note": "from memory"})
    run = Run.open(out)
    assert run.frames() == [0, 1] and run.manifest["complete"] and run.manifest["note"] == "from memory"
    assert "novel_views" not in run.manifest
    assert [v.kind for v in run.settings.views] == ["input"]
    assert run.scene.source.center == place.center and run.scene.source.radius == place.radius
    assert run.settings.source_hint == SourceHint(center=place.center, radius=place.radius) and run.settings.source_estimate is None
    hinted = prepared(_footage(plume, SourceHint(center=place.center)), QUICK, physics="scalarflow")
    assert hinted.scene.source.center == place.center and hinted.source_estimate.depth_cue == "given"


def test_a_plate_replaces_the_estimated_background_and_is_recorded(plume: synth.SynthScene) -> None:
    """The background of each input view comes from the plate when one is given (the record says
    which frames); without one it is estimated, and the record says so."""
    empty = np.full_like(plume.videos[INPUT][:1], 0)  # a plate of the synthetic scene's black background
    plated = prepared(replace(_footage(plume), plate=Plate((0, 1), {INPUT: empty})), QUICK, physics="scalarflow")
    assert plated.backgrounds[INPUT].plate_frames == (0, 1) and plated.backgrounds[INPUT].textured
    assert plated.settings().backgrounds[INPUT].plate_frames == (0, 1)
    estimated = prepared(_footage(plume), QUICK, physics="scalarflow")
    assert estimated.backgrounds[INPUT].plate_frames is None
