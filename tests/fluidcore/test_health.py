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
         spreading: tuple[bool, float] = (False, 0.0), tried: dict | None = None, bounds: dict | None = None,
         records: list[dict] | None = None) -> RunRecord:
    """A reconstruction's record; `records`: each frame's losses (default: two frames fitted at `psnr`)."""
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
    records = records or [{"input_psnr": psnr}] * 2
    frames = [{"t": t, "losses": losses} for t, losses in enumerate(records)]
    return RunRecord({**run.manifest, "frame_range": [0, len(frames)], "frames": frames})


def cli_report(run: RunRecord) -> dict:
    """The report as the command line prints it."""
    report = health.report(run, audience="cli")
    assert report is not None
    return report


def test_a_healthy_run_warns_of_nothing(tmp_path: Path) -> None:
    report = cli_report(_run(tmp_path))
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
    report = cli_report(_run(tmp_path, **fields))
    (warning,) = report["warnings"]
    assert words in warning and ("--source" in warning or "--background-frames" in warning)
    assert [c["name"] for c in report["checks"] if c["level"] == "warning"] == [check]


def test_notes_say_what_was_not_fitted(tmp_path: Path) -> None:
    report = cli_report(_run(tmp_path, buoyancy=0.5, floor=0.5, covered=0.05,
                                depth_range=((0.0, 0.05, 0.25), (0.0, 0.05, -0.25))))
    assert report["warnings"] == []
    notes = " | ".join(report["notes"])
    assert "sits on its floor" in notes and "never left 5.0% of view view_02" in notes and "0.5-unit stretch" in notes


def test_parameters_on_an_end_of_the_searched_range_are_named(tmp_path: Path) -> None:
    """Each identified value at an end of what the search tried is named with that range; values
    inside their ranges are not. A run that searched nothing at its ends has no such note."""
    tried = {"buoyancy": (0.5, 4.0), "source_radius": (0.03, 0.05), "source_height": (0.04, 0.06), "age": (0.0, 45.0)}
    (note,) = cli_report(_run(tmp_path, buoyancy=0.5, floor=0.5, tried=tried))["notes"]
    assert "buoyancy 0.5 (the lowest searched of 0.5-4)" in note and "sits on its floor" in note
    assert "source radius 0.03 (the lowest searched of 0.03-0.05)" in note
    assert "source height" not in note and "plume age" not in note  # a plume that starts in frame 0 is an answer
    inside = {"buoyancy": (0.5, 4.0), "source_radius": (0.02, 0.05), "age": (-1.0, 45.0)}
    assert cli_report(_run(tmp_path, buoyancy=1.0, floor=0.5, tried=inside))["notes"] == []


def test_the_search_bounds_are_shown_and_a_value_on_one_named(tmp_path: Path) -> None:
    """A run that recorded its search's bounds shows each identified value with them in the
    identification's check, and names one that sits on a bound; the bounds, not the range tried,
    decide (the tried range's ends are inside them)."""
    bounds = {"buoyancy": (0.05, 20.0), "source_radius": (0.015, 0.06), "source_height": (0.0, 0.1), "age": (0.0, 45.0)}
    tried = {"buoyancy": (1.0, 4.0), "source_radius": (0.03, 0.05)}
    report = cli_report(_run(tmp_path, buoyancy=1.0, floor=0.05, tried=tried, bounds=bounds))
    assert report["notes"] == []
    (check,) = [c for c in report["checks"] if c["name"] == "identification"]
    assert "buoyancy 1 (searched 0.05-20)" in check["message"] and "source radius 0.03 (searched 0.015-0.06)" in check["message"]
    (note,) = cli_report(_run(tmp_path, buoyancy=20.0, floor=0.05, bounds=bounds))["notes"]
    assert "buoyancy 20 (the highest searched of 0.05-20)" in note and "source radius" not in note


def test_scene_info_carries_the_same_report(tmp_path: Path) -> None:
    run = _run(tmp_path, psnr=20.0)
    assert scene_info.from_run(run, "api")["health"] == health.report(run, audience="api")


def test_what_the_capture_and_the_simulation_left_unsaid_is_reported(tmp_path: Path) -> None:
    """A camera file's fps the videos do not play at warns; an up read off the cameras other than
    +y, or assumed, is a note; a spreading asked for and identified as 0 is a note, not silence."""
    agreeing = cli_report(_run(tmp_path, capture=CaptureRecord(up_axis="+y", up_found="cameras", declared_fps=30.0)))
    assert agreeing["warnings"] == agreeing["notes"] == []
    report = cli_report(_run(tmp_path, capture=CaptureRecord(up_axis="+z", up_found="cameras", declared_fps=25.0),
                                spreading=(True, 0.0)))
    (warning,) = report["warnings"]
    assert "play at 30 fps but the camera file says 25 fps" in warning
    notes = " | ".join(report["notes"])
    assert "up was read as +z from the cameras" in notes and "--world-up" in notes
    assert "spreading (entrainment) was asked for, but the video showed none" in notes
    assumed = cli_report(_run(tmp_path, capture=CaptureRecord(up_axis="+y", up_found="default"), spreading=(True, 0.06)))
    assert any("agree on no up direction, so +y was assumed" in n for n in assumed["notes"])
    assert not any("spreading" in n for n in assumed["notes"])
    assert {c["name"]: c["level"] for c in assumed["checks"]}["spreading"] == "ok"


def _mse(psnr: float) -> float:
    return 10.0 ** (-psnr / 10.0)


def test_the_fit_is_measured_against_the_background_alone(tmp_path: Path) -> None:
    """Issue 48: beside the fit, what the background alone scores on the same frames and the share
    of the smoke's image energy explained, pooled over the frames (not the mean of each frame's
    share, which a frame with little smoke would swamp); a warning within 3 dB of the background."""
    poor = [{"input_psnr": 30.0, "background_psnr": 28.0}, {"input_psnr": 31.0, "background_psnr": 28.5}]
    report = cli_report(_run(tmp_path, records=poor))
    (check,) = [c for c in report["checks"] if c["name"] == "smoke explained"]
    share = 1 - (_mse(30.0) + _mse(31.0)) / (_mse(28.0) + _mse(28.5))
    assert check["level"] == "warning" and check["value"] == pytest.approx(share)
    (warning,) = report["warnings"]  # 30.5 dB passes the absolute bar: only the yardstick warns
    assert f"the background alone scores 28.2 dB on the same frames (an empty reconstruction), the fit 30.5 dB: it explains {100 * share:.0f}%" in warning
    assert "within 3 dB of the background" in warning and "--background-frames" in warning

    uneven = [{"input_psnr": 30.0, "background_psnr": 20.0}, {"input_psnr": 20.0, "background_psnr": 19.0}]
    (check,) = [c for c in cli_report(_run(tmp_path, records=uneven))["checks"] if c["name"] == "smoke explained"]
    pooled = 1 - (_mse(30.0) + _mse(20.0)) / (_mse(20.0) + _mse(19.0))
    per_frame = 0.5 * ((1 - _mse(30.0) / _mse(20.0)) + (1 - _mse(20.0) / _mse(19.0)))
    assert check["value"] == pytest.approx(pooled) and abs(pooled - per_frame) > 0.03
    assert check["level"] == "ok"  # 25 dB over 19.5: more than 3 dB above the background

    healthy = [{"input_psnr": 35.0, "background_psnr": 22.0}] * 3
    report = cli_report(_run(tmp_path, records=healthy))
    assert report["warnings"] == [] and {c["name"]: c["level"] for c in report["checks"]}["smoke explained"] == "ok"


def _rising(along: float, across: float, frames: int = 10) -> list[dict]:
    """Frames whose smoke centre moves `along` up and `across` it over the clip, in image long sides."""
    return [{"input_psnr": 35.0, "smoke_up": -0.3 + along * k / frames, "smoke_across": 0.05 + across * k / frames}
            for k in range(frames)]


@pytest.mark.parametrize("found", ["given", "camera file", "cameras"])
def test_world_up_is_checked_against_the_smokes_rise(tmp_path: Path, found: str) -> None:
    """Issue 48: an up the user, the camera file or the cameras got wrong said "world up: ok".
    Now smoke that rises along up is ok, smoke that moves down or across it warns, whoever said
    which way up is; smoke too still to tell leaves the old verdict, and says so."""
    capture = CaptureRecord(up_axis="+y", up_found=found)

    def up_check(records: list[dict]) -> dict:
        return next(c for c in cli_report(_run(tmp_path, capture=capture, records=records))["checks"] if c["name"] == "world up")

    rising = up_check(_rising(0.3, 0.02))
    assert rising["level"] == "ok" and "the smoke rises along up" in rising["message"] and "+30% of the input view along up" in rising["message"]
    for records, words in ((_rising(-0.3, 0.02), "down, against up"), (_rising(0.05, -0.2), "across up rather than along it")):
        check = up_check(records)
        assert check["level"] == "warning" and words in check["message"] and "--world-up" in check["message"], check
    still = up_check(_rising(0.005, 0.0))
    assert still["level"] == "ok" and "too little to check it" in still["message"]
    few = up_check(_rising(-0.3, 0.0, frames=2))  # two frames: no line to fit, the old verdict
    assert few["level"] == "ok" and "too little" not in few["message"]


def test_the_advice_is_worded_for_where_it_is_read(tmp_path: Path) -> None:
    """The same findings: flags for the command line, the job's fields for the REST API, and the
    remedies by name (`advice`) for the browser, which words them as its form's fields."""
    run = _run(tmp_path, psnr=26.0, radius=0.1, capture=CaptureRecord(up_axis="+y", up_found="given"),
               records=[{**r, "input_psnr": 26.0, "background_psnr": 25.0} for r in _rising(-0.3, 0.0)])
    cli, rest = health.report(run, audience="cli"), health.report(run, audience="api")
    assert cli is not None and rest is not None and len(cli["warnings"]) == len(rest["warnings"]) == 4
    for text in cli["warnings"]:
        assert "--" in text and "params." not in text, text
    for text in rest["warnings"]:
        assert "params." in text and "--" not in text, text
    checks = {c["name"]: c for c in rest["checks"]}
    assert checks["input fit"]["advice"] == ["source", "background_plate", "another_view"]
    assert checks["world up"]["advice"] == ["world_up"] and "params.world_up" in checks["world up"]["message"]
    assert rest["warnings"][0].startswith(checks["input fit"]["finding"] + ": give the source (params.source")
    assert all(c["finding"] == c["message"] for c in rest["checks"] if not c["advice"])
