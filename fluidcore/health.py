"""How far to trust a reconstruction: checks read off its run record, each with what to do (issue 34).

Derived from the manifest on every read (`report`), never stored apart from it, so a run written
before a check existed gets it too, and the CLI (`reconstruct`, `scene info`), the API
(`GET /v1/scenes/{id}` geometry) and the browser say the same thing. Torch-free.

A *warning* says the result is likely poor and what to give next; a *note* says what one view or
the identification could not tell, which the user may want to pin. Each threshold below gives
the values the dev scenes (D, F, H: independent-solver plumes) and ScalarFlow (real) showed at
preview quality, seed 0, none of which may warn, and the FluidNexus-Smoke clip's (a steady stem
before a textured cloth, `cameras single --fov 40`; docs/background_results.json), which should.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any, Literal

if TYPE_CHECKING:
    from fluidcore.runs import RunRecord

# Mean input-view PSNR over the frames: D 35.3, F 38.0, H 40.7, ScalarFlow 35.4; FluidNexus-Smoke 26.5.
MIN_INPUT_FIT_DB = 30.0
# Source diameter over the box's narrower horizontal side: D 0.14, ScalarFlow 0.08;
# FluidNexus-Smoke 0.76 with the stem in its background.
MAX_SOURCE_SHARE = 0.3
# The identification's silhouette misfit (1 - IoU plus the rise error): D 0.37, ScalarFlow 0.32;
# FluidNexus-Smoke 0.69 to 0.78.
MAX_MISFIT = 0.5
# Fraction of an input view whose background was filled because the smoke never left it: 0 on the
# dev scenes and ScalarFlow (flat backgrounds); 4.8% on FluidNexus-Smoke.
COVERED_NOTE = 0.005

Level = Literal["ok", "note", "warning"]


@dataclass(frozen=True)
class Check:
    name: str
    level: Level
    message: str
    value: float | None = None


def report(run: RunRecord) -> dict[str, Any] | None:
    """{"warnings": [...], "notes": [...], "checks": [...]} of a reconstruction's run record; None
    for a run of another kind (a continuation inherits its reconstruction's)."""
    from fluidcore.runs import RunKind

    if run.kind is not RunKind.RECONSTRUCT:
        return None
    checks = [check for check in (_fit(run), _source_size(run), _identification(run), _on_bounds(run),
                                  *_backgrounds(run), _depth(run), _frame_rate(run), _up(run), _spreading(run))
              if check is not None]
    return {
        "warnings": [c.message for c in checks if c.level == "warning"],
        "notes": [c.message for c in checks if c.level == "note"],
        "checks": [asdict(c) for c in checks],
    }


def _fit(run: RunRecord) -> Check | None:
    values = [entry.get("losses", {}).get("input_psnr") for entry in run.manifest.get("frames", [])]
    values = [float(v) for v in values if v is not None and math.isfinite(v)]
    if not values:
        return None
    mean = sum(values) / len(values)
    if mean >= MIN_INPUT_FIT_DB:
        return Check("input fit", "ok", f"the input view is fitted at {mean:.1f} dB", mean)
    return Check("input fit", "warning",
                 f"the reconstruction fits its own input view at only {mean:.1f} dB (healthy runs: {MIN_INPUT_FIT_DB:g}+): "
                 "check the source (a hint: --source), the background (a plate: --background-frames), or add a view", mean)


def _source_size(run: RunRecord) -> Check:
    scene = run.scene
    lo, hi, up = scene.box_lo, scene.box_hi, scene.up
    widths = [h - l for h, l, u in zip(hi, lo, up, strict=True) if abs(u) < 0.5]  # the sides across up
    share = 2.0 * scene.source.radius / min(widths or [max(h - l for h, l in zip(hi, lo, strict=True))])
    if share <= MAX_SOURCE_SHARE:
        return Check("source size", "ok", f"the source is {share:.2f} of the box's width", share)
    return Check("source size", "warning",
                 f"the smoke source is {share:.2f} of the box's width across: smoke that never leaves the view (a steady "
                 "stem) or specks of background read as smoke widen it; give the source (--source X,Y,Z,R) or a "
                 "background plate (--background-frames)", share)


def _identification(run: RunRecord) -> Check | None:
    identified = run.settings.physics.identified
    if identified is None:
        return None
    if identified.misfit <= MAX_MISFIT:
        return Check("identification", "ok", f"the identified plume matches the video's silhouettes (misfit {identified.misfit:.2f})"
                     f"{_searched(run)}", identified.misfit)
    return Check("identification", "warning",
                 f"the identified physics matches the video's smoke poorly (misfit {identified.misfit:.2f}, healthy runs "
                 f"below {MAX_MISFIT:g}): predictions and what-ifs inherit it; give the source (--source X,Y,Z,R) or a "
                 "background plate (--background-frames)", identified.misfit)


# How each identified parameter reads in a note, and its value in a run record.
BOUND_NAMES = {"buoyancy": "buoyancy", "source_radius": "source radius", "source_height": "source height",
               "entrainment": "spreading rate", "age": "plume age (frames)"}
# Ends that are the physics' own, not the search's: a plume that starts in the first frame (age 0),
# one that does not spread (rate 0). A value there is an answer, not a limit of the search.
PHYSICAL_ENDS = {("age", "lowest"), ("entrainment", "lowest")}


def _on_bounds(run: RunRecord) -> Check | None:
    """The identified parameters that sit on an end of the range the identification searched
    (`IdentifiedRecord.bounds`; a run written before them: the range its grid tried,
    `IdentifiedRecord.tried`): there the search's limits, not the video, decided them. A run
    written before either gets the buoyancy floor's note alone."""
    identified = run.settings.physics.identified
    if identified is None:
        return None
    floor = math.isclose(identified.buoyancy, identified.floor, rel_tol=1e-6)
    limits = _limits(run)
    ends = [_end(name, value, limits[name]) for name, value in _identified_values(run).items() if name in limits]
    ends = [end for end in ends if end is not None]
    if floor and not limits:
        ends = [f"buoyancy {identified.buoyancy:.3g}"]
    if not ends:
        return None
    why = (f"; the buoyancy sits on its floor, set from the observed rise speed ({identified.rise_speed:.3g}/s) and the "
           "drag: the video's rise, not the fit, decided it" if floor else "")
    return Check("identification bounds", "note",
                 f"identified on an end of the range searched: {'; '.join(ends)}{why}. A source you know "
                 "(--source X,Y,Z,R) is kept as given", float(len(ends)))


def _limits(run: RunRecord) -> dict[str, tuple[float, float]]:
    """Per identified parameter, the range searched (see `_on_bounds`); empty for the oldest runs."""
    identified = run.settings.physics.identified
    assert identified is not None
    return identified.bounds or identified.tried or {}


def _searched(run: RunRecord) -> str:
    """": buoyancy 0.29 (searched 0.035-14), ..." for a run that recorded its search's bounds."""
    identified = run.settings.physics.identified
    assert identified is not None
    if identified.bounds is None:
        return ""
    values = _identified_values(run)
    return ": " + ", ".join(f"{BOUND_NAMES[name]} {values[name]:.3g} (searched {lo:.3g}-{hi:.3g})"
                            for name, (lo, hi) in identified.bounds.items() if name in values)


def _identified_values(run: RunRecord) -> dict[str, float]:
    identified = run.settings.physics.identified
    assert identified is not None
    up = run.scene.up
    return {"buoyancy": identified.buoyancy, "source_radius": identified.source_radius,
            "source_height": sum(c * u for c, u in zip(identified.source_center, up, strict=True)),
            "entrainment": identified.entrainment, "age": float(identified.age)}


def _end(name: str, value: float, tried: tuple[float, float]) -> str | None:
    """"NAME VALUE (the lowest searched of LO-HI)" when value is at an end of `tried` (the range searched), else None."""
    lo, hi = tried
    scale = max(abs(lo), abs(hi), 1e-12)
    for end, word in ((lo, "lowest"), (hi, "highest")):
        if (name, word) not in PHYSICAL_ENDS and math.isclose(value, end, rel_tol=1e-6, abs_tol=1e-9 * scale):
            return f"{BOUND_NAMES[name]} {value:.3g} (the {word} searched of {lo:.3g}-{hi:.3g})"
    return None


def _backgrounds(run: RunRecord) -> list[Check]:
    return [
        Check("background", "note",
              f"the smoke never left {100 * record.covered:.1f}% of view {view}: its background there was filled from "
              "around it; if the smoke there is steady, give a background plate (--background-frames)", record.covered)
        for view, record in run.settings.backgrounds.items() if record.covered > COVERED_NOTE
    ]


def _depth(run: RunRecord) -> Check | None:
    estimate = run.settings.source_estimate
    if estimate is None or estimate.depth_range is None:
        return None
    near, far = estimate.depth_range
    stretch = math.dist(near, far)
    return Check("depth", "note",
                 f"one view: the source's depth comes from the {estimate.depth_cue} cue, anywhere on a {stretch:.3g}-unit "
                 "stretch of its ray; pin it with --source or add a second view", stretch)


def _frame_rate(run: RunRecord) -> Check | None:
    from fluidcore.video import rate_mismatch

    capture = run.settings.capture
    if capture is None or capture.declared_fps is None:
        return None
    mismatch = rate_mismatch(run.fps, capture.declared_fps)
    if mismatch is None:
        return Check("frame rate", "ok", f"the videos play at {run.fps:g} fps, as the camera file says", run.fps)
    return Check("frame rate", "warning", mismatch, run.fps)


def _up(run: RunRecord) -> Check | None:
    """A note when up is a guess: the cameras agreed on no axis, or on one other than the +y most
    files use (a +z-up Blender world reads right from its cameras; a note says so)."""
    capture = run.settings.capture
    if capture is None:
        return None
    axis, found = capture.up_axis, capture.up_found
    if found in ("given", "camera file") or (found == "cameras" and axis == "+y"):
        return Check("world up", "ok", f"up is {axis} ({'as given' if found == 'given' else 'from the ' + found})")
    why = ("the cameras agree on no up direction, so +y was assumed" if found == "default"
           else f"up was read as {axis} from the cameras' mean image up")
    return Check("world up", "note", f"{why}: the smoke rises along it and the floor faces it; if that is wrong, give "
                 "--world-up (or world_up in the reconstruct job, or `up` in the camera file)")


def _spreading(run: RunRecord) -> Check | None:
    """A note when the plume's spreading was asked for and the video showed none: the run
    simulates none, which the user would otherwise take for spreading applied."""
    if not run.settings.quality.simulation.entrainment:
        return None
    rate = run.scene.physics.entrainment
    if rate > 0:
        return Check("spreading", "ok", f"the plume spreads by {rate:.2f} per unit risen, as the video showed", rate)
    return Check("spreading", "note", "spreading (entrainment) was asked for, but the video showed none: the identification "
                 "picked 0, so the predictions and what-ifs simulate none", 0.0)
