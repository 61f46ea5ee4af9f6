"""The health report of a reconstruction (fluidcore.health): each warning fires on a run that
earns it and stays silent on a healthy one; notes say what one view or the identification could
not tell; every reader (scene info, the API's geometry, the CLI) gets the same report."""

from __future__ import annotations

from pathlib import Path

import pytest

from fluidcore import health, scene_info
from fluidcore.cameras import Camera, look_at
from fluidcore.runs import (BackgroundRecord, CaptureRecord, IdentificationPrior, IdentifiedRecord, PhysicsRecord, ReconstructSettings, Run,
                            RunRecord, SourceEstimateRecord)
from fluidcore.spec.physics import PBFConfig, Source
from fluidcore.spec.reconstruct import get
from fluidcore.spec.scene import Scene, SourcePlace

BOX = ((-0.25, 0.0, -0.25), (0.25, 0.8, 0.25))  # 0.5 wide across up (+y)


def _identified(misfit: float, buoyancy: float, floor: float, tried: dict | None = None, bounds: dict | None = None) -> IdentifiedRecord:
    prior = IdentificationPrior(preset="scalarflow", buoyancy=1.0, drag=1.0, rho0=1.0, held_from_prior=("drag",),
                                inflow_speed="buoyancy / drag", budget=30, source=SourcePlace((0.0, 0.05, 0.0), 0.03))
    return IdentifiedRecord(buoyancy=buoyancy, inflow_speed=0.2, rate=10, age=0, misfit=misfit, rise_speed=0.2, floor=floor,
                            evaluations=10, source_center=(0.0, 0.05, 0.0), source_radius=0.03, prior=prior, tried=tried,
                            bounds=bounds)


def _run(tmp_path: Path, *, psnr: float = 35.0, radius: float = 0.03, misfit: float = 0.3, buoyancy: float = 1.0,
         floor: float = 0.5, covered: float = 0.0, depth_range=None, capture: CaptureRecord | None = None,  # noqa: ANN001
         spreading: tuple[bool, float] = (False, 0.0), tried: dict | None = None, bounds: dict | None = None) -> RunRecord:
    like = Camera("like", 60.0, 60.0, 24.0, 32.0, 48, 64, [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    camera = look_at((0.0, 0.4, 1.6), (0.0, 0.4, 0.0), (0.0, 1.0, 0.0), like, "view_02")
    estimate = SourceEstimateRecord(depth_cue="box axis", depth_range=depth_range)
    quality = get("preview").with_overrides(motion="paper", entrainment=spreading[0])  # the spreading is the paper model's
    settings = ReconstructSettings(
        quality=quality, capture=capture, physics=PhysicsRecord(mode="auto", identified=_identified(misfit, buoyancy, floor, tried, bounds)),
        source_estimate=estimate, backgrounds={"view_02": BackgroundRecord(textured=covered > 0, covered=covered)},
    )
    run = Run.create(tmp_path / f"run{len(list(tmp_path.iterdir()))}", kind="reconstruct", cameras={"view_02": camera},
                     input_views=["view_02"], frame_range=(0, 2), fps=30.0, channels=1, background_color=[0.0],
                     settings=settings,
                     scene=Scene(BOX[0], BOX[1], (0.0, 1.0, 0.0), PBFConfig(h=0.05, entrainment=spreading[1]), Source((0.0, 0.05, 0.0), radius, 1)))
    frames = [{"t": t, "losses": {"input_psnr": psnr}} for t in (0, 1)]
    return RunRecord({**run.manifest, "frames": frames})


def test_a_healthy_run_warns_of_nothing(tmp_path: Path) -> None:
    report = health.report(_run(tmp_path))
    assert report["warnings"] == [] and report["notes"] == []
    assert {c["name"] for c in report["checks"]} == {"input fit", "source size", "identification"}


@pytest.mark.parametrize(
    ("fields", "check", "words"),
    [
        ({"psnr": 26.1}, "input fit", "fits its own input view at only 26.1 dB"),
        ({"radius": 0.1}, "source size", "0.40 of the box's width"),  # a 0.2-wide source in a 0.5-wide box
        ({"misfit": 0.79}, "identification", "misfit 0.79"),
    ],
)
def test_each_warning_fires_and_says_what_to_do(tmp_path: Path, fields: dict, check: str, words: str) -> None:
    report = health.report(_run(tmp_path, **fields))
    (warning,) = report["warnings"]
    assert words in warning and ("--source" in warning or "--background-frames" in warning)
    assert [c["name"] for c in report["checks"] if c["level"] == "warning"] == [check]


def test_notes_say_what_was_not_fitted(tmp_path: Path) -> None:
    report = health.report(_run(tmp_path, buoyancy=0.5, floor=0.5, covered=0.05,
                                depth_range=((0.0, 0.05, 0.25), (0.0, 0.05, -0.25))))
    assert report["warnings"] == []
    notes = " | ".join(report["notes"])
    assert "sits on its floor" in notes and "never left 5.0% of view view_02" in notes and "0.5-unit stretch" in notes


def test_parameters_on_an_end_of_the_searched_range_are_named(tmp_path: Path) -> None:
    """Each identified value at an end of what the search tried is named with that range; values
    inside their ranges are not. A run that searched nothing at its ends has no such note."""
    tried = {"buoyancy": (0.5, 4.0), "source_radius": (0.03, 0.05), "source_height": (0.04, 0.06), "age": (0.0, 45.0)}
    (note,) = health.report(_run(tmp_path, buoyancy=0.5, floor=0.5, tried=tried))["notes"]
    assert "buoyancy 0.5 (the lowest searched of 0.5-4)" in note and "sits on its floor" in note
    assert "source radius 0.03 (the lowest searched of 0.03-0.05)" in note
    assert "source height" not in note and "plume age" not in note  # a plume that starts in frame 0 is an answer
    inside = {"buoyancy": (0.5, 4.0), "source_radius": (0.02, 0.05), "age": (-1.0, 45.0)}
    assert health.report(_run(tmp_path, buoyancy=1.0, floor=0.5, tried=inside))["notes"] == []


def test_the_search_bounds_are_shown_and_a_value_on_one_named(tmp_path: Path) -> None:
    """A run that recorded its search's bounds shows each identified value with them in the
    identification's check, and names one that sits on a bound; the bounds, not the range tried,
    decide (the tried range's ends are inside them)."""
    bounds = {"buoyancy": (0.05, 20.0), "source_radius": (0.015, 0.06), "source_height": (0.0, 0.1), "age": (0.0, 45.0)}
    tried = {"buoyancy": (1.0, 4.0), "source_radius": (0.03, 0.05)}
    report = health.report(_run(tmp_path, buoyancy=1.0, floor=0.05, tried=tried, bounds=bounds))
    assert report["notes"] == []
    (check,) = [c for c in report["checks"] if c["name"] == "identification"]
    assert "buoyancy 1 (searched 0.05-20)" in check["message"] and "source radius 0.03 (searched 0.015-0.06)" in check["message"]
    (note,) = health.report(_run(tmp_path, buoyancy=20.0, floor=0.05, bounds=bounds))["notes"]
    assert "buoyancy 20 (the highest searched of 0.05-20)" in note and "source radius" not in note


def test_scene_info_carries_the_same_report(tmp_path: Path) -> None:
    run = _run(tmp_path, psnr=20.0)
    assert scene_info.from_run(run)["health"] == health.report(run)


def test_what_the_capture_and_the_simulation_left_unsaid_is_reported(tmp_path: Path) -> None:
    """A camera file's fps the videos do not play at warns; an up read off the cameras other than
    +y, or assumed, is a note; a spreading asked for and identified as 0 is a note, not silence."""
    agreeing = health.report(_run(tmp_path, capture=CaptureRecord(up_axis="+y", up_found="cameras", declared_fps=30.0)))
    assert agreeing["warnings"] == agreeing["notes"] == []
    report = health.report(_run(tmp_path, capture=CaptureRecord(up_axis="+z", up_found="cameras", declared_fps=25.0),
                                spreading=(True, 0.0)))
    (warning,) = report["warnings"]
    assert "play at 30 fps but the camera file says 25 fps" in warning
    notes = " | ".join(report["notes"])
    assert "up was read as +z from the cameras" in notes and "--world-up" in notes
    assert "spreading (entrainment) was asked for, but the video showed none" in notes
    assumed = health.report(_run(tmp_path, capture=CaptureRecord(up_axis="+y", up_found="default"), spreading=(True, 0.06)))
    assert any("agree on no up direction, so +y was assumed" in n for n in assumed["notes"])
    assert not any("spreading" in n for n in assumed["notes"])
    assert {c["name"]: c["level"] for c in assumed["checks"]}["spreading"] == "ok"
