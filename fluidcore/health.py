"""How far to trust a reconstruction: checks read off its run record, each with what to do (issue 34).

Derived from the manifest on every read (`report`), never stored apart from it, so a run written
before a check existed gets it too, and the CLI (`reconstruct`, `scene info`), the API
(`GET /v1/scenes/{id}` geometry) and the browser say the same thing. Torch-free.

A *warning* says the result is likely poor and what to give next; a *note* says what one view or
the identification could not tell, which the user may want to pin. Each threshold below gives
the values the dev scenes (D, F, H: independent-solver plumes) and ScalarFlow (real) showed at
preview quality, seed 0, none of which may warn, and the FluidNexus-Smoke clip's (a steady stem
before a textured cloth, `cameras single --fov 40`; docs/background_results.json), which should.

What to do is worded for where the report is read (issue 48): each check names its remedies
(`Remedy`), and `report(run, audience=...)` words them as the CLI's flags or the REST API's
parameters; the browser words the same remedies as its form's fields (web/js/results.js), from
each check's `finding` and `advice`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

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
# The input view's mean fit over what the background alone scores on the same frames (the
# yardstick, `fluidcore.reconstruct.yardstick`), in dB: D 35.3 over 22.7, F 38.0 over 23.6, H 40.7
# over 28.3, ScalarFlow 35.4 over 20.7 (frames 0-89, 0-119); FluidNexus-Smoke frames 0-29 29.7
# over 25.6 (issue 48). Below this margin the fit is little better than an empty scene.
MIN_MARGIN_DB = 3.0
# How far the observed smoke's centre must move over the clip, in image long sides, before its
# motion tells which way is up (`_rise`): along up D 0.48, F 0.35, H 0.43, ScalarFlow 0.33,
# FluidNexus-Smoke frames 0-29 0.095, FluidNexus-Ball frames 0-29 0.057; across up 0.03 at most
# on all of them but FluidNexus-Smoke over frames 0-119 (0.087, its plume leans).
MIN_RISE = 0.02
MIN_RISE_FRAMES = 3  # frames with smoke the motion is fitted over

Level = Literal["ok", "note", "warning"]
Remedy = Literal["source", "background_plate", "another_view", "world_up", "solids"]
Audience = Literal["cli", "api"]
# What to give next, in the words of where the report is read: the command line's flags, the REST
# API's fields. The browser words the same remedies as its form's fields (web/js/results.js).
REMEDIES: dict[Audience, dict[Remedy, str]] = {
    "cli": {
        "source": "give the source (--source X,Y,Z[,R])",
        "background_plate": "give a background plate (--background-frames START:END, frames without smoke)",
        "another_view": "add a view (another camera's VIEW=path.mp4)",
        "world_up": "give the right up (--world-up AXIS; a camera file made by `cameras single`: its --up, where world "
                    "up points in the image)",
        "solids": "place the ball where the smoke passes (--ball '{\"center\": [X, Y, Z], \"radius\": R}', world units; "
                  "`fluidnexus scene info RUN` shows the box and the source)",
    },
    "api": {
        "source": "give the source (params.source of a reconstruct job)",
        "background_plate": "give a background plate (params.background_frames of a reconstruct job, frames without smoke)",
        "another_view": "add a view (upload a camera file and another camera's video)",
        "world_up": "give the right up (params.world_up of a reconstruct job; a scene uploaded with fov: its up, where "
                    "world up points in the image)",
        "solids": "place the ball where the smoke passes (params.solids of a reconstruct job, world units; GET "
                  "/v1/scenes/{id} shows the box and the source)",
    },
}


@dataclass(frozen=True)
class Check:
    """One check of a run: what was found (in no reader's words) and the remedies to say with it."""

    name: str
    level: Level
    finding: str
    value: float | None = None
    advice: tuple[Remedy, ...] = ()

    def message(self, audience: Audience) -> str:
        """The finding and its remedies in `audience`'s words."""
        if not self.advice:
            return self.finding
        *others, last = [REMEDIES[audience][remedy] for remedy in self.advice]
        return f"{self.finding}: {'; '.join(others)}; or {last}" if others else f"{self.finding}: {last}"


def report(run: RunRecord, *, audience: Audience) -> dict[str, Any] | None:
    """{"warnings": [...], "notes": [...], "checks": [...]} of a reconstruction's run record, its
    remedies worded for `audience`; None for a run of another kind (a continuation inherits its
    reconstruction's). Each check also carries its `finding` and `advice` (the remedies' names),
    for a reader that words them itself."""
    from fluidcore.runs import RunKind

    if run.kind is not RunKind.RECONSTRUCT:
        return None
    checks = [check for check in (_fit(run), _explained(run), _source_size(run), _identification(run), _on_bounds(run),
                                  *_backgrounds(run), _depth(run), _frame_rate(run), _up(run), _spreading(run), _solids(run))
              if check is not None]
    return {
        "warnings": [c.message(audience) for c in checks if c.level == "warning"],
        "notes": [c.message(audience) for c in checks if c.level == "note"],
        "checks": [{**asdict(c), "advice": list(c.advice), "message": c.message(audience)} for c in checks],
    }


def _recorded(run: RunRecord, key: str) -> list[tuple[int, float]]:
    """(frame, value) of a per-frame record (the frame's losses) on the frames that hold it."""
    found = [(entry.get("t"), entry.get("losses", {}).get(key)) for entry in run.manifest.get("frames", [])]
    return [(int(t), float(v)) for t, v in found if t is not None and v is not None and math.isfinite(v)]


def _fit(run: RunRecord) -> Check | None:
    values = [v for _, v in _recorded(run, "input_psnr")]
    if not values:
        return None
    mean = sum(values) / len(values)
    if mean >= MIN_INPUT_FIT_DB:
        return Check("input fit", "ok", f"the input view is fitted at {mean:.1f} dB", mean)
    return Check("input fit", "warning",
                 f"the reconstruction fits its own input view at only {mean:.1f} dB (healthy runs: {MIN_INPUT_FIT_DB:g}+)", mean,
                 ("source", "background_plate", "another_view"))


def _explained(run: RunRecord) -> Check | None:
    """The fit against its yardstick, on the frames that recorded both (a run written before
    issue 48 has none): the mean PSNR of the background alone, and the share of the smoke's
    image energy the reconstruction explains, pooled over the frames (1 - sum of the render's
    squared error / sum of the background's; each frame's PSNR gives its mean squared error, and
    every frame has the same pixels). A frame's own share is not averaged: one with little smoke
    divides by almost nothing."""
    background = dict(_recorded(run, "background_psnr"))
    pairs = [(fit, background[t]) for t, fit in _recorded(run, "input_psnr") if t in background]
    if not pairs:
        return None
    fit = sum(f for f, _ in pairs) / len(pairs)
    empty = sum(b for _, b in pairs) / len(pairs)
    share = 1.0 - sum(10.0 ** (-f / 10.0) for f, _ in pairs) / sum(10.0 ** (-b / 10.0) for _, b in pairs)
    found = (f"the background alone scores {empty:.1f} dB on the same frames (an empty reconstruction), the fit "
             f"{fit:.1f} dB: it explains {100 * share:.0f}% of the smoke's image energy")
    if fit - empty >= MIN_MARGIN_DB:
        return Check("smoke explained", "ok", found, share)
    return Check("smoke explained", "warning",
                 f"{found}, within {MIN_MARGIN_DB:g} dB of the background: little of the smoke is reconstructed", share,
                 ("source", "background_plate", "another_view"))


def _source_size(run: RunRecord) -> Check:
    scene = run.scene
    lo, hi, up = scene.box_lo, scene.box_hi, scene.up
    widths = [h - l for h, l, u in zip(hi, lo, up, strict=True) if abs(u) < 0.5]  # the sides across up
    share = 2.0 * scene.source.radius / min(widths or [max(h - l for h, l in zip(hi, lo, strict=True))])
    if share <= MAX_SOURCE_SHARE:
        return Check("source size", "ok", f"the source is {share:.2f} of the box's width", share)
    return Check("source size", "warning",
                 f"the smoke source is {share:.2f} of the box's width across: smoke that never leaves the view (a steady "
                 "stem) or specks of background read as smoke widen it", share, ("source", "background_plate"))


def _identification(run: RunRecord) -> Check | None:
    identified = run.settings.physics.identified
    if identified is None:
        return None
    if identified.misfit <= MAX_MISFIT:
        return Check("identification", "ok", f"the identified plume matches the video's silhouettes (misfit {identified.misfit:.2f})"
                     f"{_searched(run)}", identified.misfit)
    return Check("identification", "warning",
                 f"the identified physics matches the video's smoke poorly (misfit {identified.misfit:.2f}, healthy runs "
                 f"below {MAX_MISFIT:g}): predictions and what-ifs inherit it", identified.misfit, ("source", "background_plate"))


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
                 f"identified on an end of the range searched: {'; '.join(ends)}{why}. A source you know is kept as given",
                 float(len(ends)), ("source",))


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
              "around it; if the smoke there is steady", record.covered, ("background_plate",))
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
                 "stretch of its ray; to pin it", stretch, ("source", "another_view"))


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
    """Whether the smoke rises along the run's up (`_rise`): a warning when it moves down or
    across it, whoever said which way up is (a camera file's `up` or the user's may be wrong too);
    without a measured rise (a run written before it, smoke that hardly moves), a note when up is
    a guess: the cameras agreed on no axis, or on one other than the +y most files use (a +z-up
    Blender world reads right from its cameras; a note says so)."""
    capture = run.settings.capture
    if capture is None:
        return None
    axis, found = capture.up_axis, capture.up_found
    source = "as given" if found == "given" else f"from the {found}"
    rise = _rise(run)
    if rise is not None and math.hypot(*rise) >= MIN_RISE:
        along, across = rise
        moved = (f"over the clip the smoke's centre moves {100 * along:+.0f}% of the input view along up ({axis}, {source}) "
                 f"and {100 * abs(across):.0f}% across it")
        if along >= abs(across):
            return Check("world up", "ok", f"the smoke rises along up: {moved}", along)
        way = "down, against up" if along <= -abs(across) else "across up rather than along it"
        return Check("world up", "warning", f"the smoke moves {way}: {moved}; the reconstruction simulates it rising along "
                     "up, so up is likely wrong (or a wind carries the smoke)", along, ("world_up",))
    if found in ("given", "camera file") or (found == "cameras" and axis == "+y"):
        return Check("world up", "ok", f"up is {axis} ({source}){_unchecked(rise)}")
    why = ("the cameras agree on no up direction, so +y was assumed" if found == "default"
           else f"up was read as {axis} from the cameras' mean image up")
    return Check("world up", "note", f"{why}{_unchecked(rise)}: the smoke rises along it and the floor faces it; if that "
                 "is wrong", advice=("world_up",))


def _rise(run: RunRecord) -> tuple[float, float] | None:
    """How far the observed smoke's centre moves over the run's frames along the image's up (the
    scene's up where the input view sees the source) and across it, in image long sides: lines
    fitted to the frames' records ("smoke_up", "smoke_across", `fluidcore.reconstruct.yardstick`)
    over the frames with smoke, times their span; None for fewer than MIN_RISE_FRAMES of them."""
    along, across = dict(_recorded(run, "smoke_up")), dict(_recorded(run, "smoke_across"))
    frames = sorted(set(along) & set(across))
    if len(frames) < MIN_RISE_FRAMES:
        return None
    span = frames[-1] - frames[0] + 1
    up, side = (float(np.polyfit(frames, [values[t] for t in frames], 1)[0]) * span for values in (along, across))
    return up, side


def _unchecked(rise: tuple[float, float] | None) -> str:
    """What the smoke's motion could not say about up, for a finding that rests on where up came from."""
    if rise is None:
        return ""
    return f"; the smoke's centre moves only {100 * math.hypot(*rise):.0f}% of the input view over the clip, too little to check it"


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


def _solids(run: RunRecord) -> Check | None:
    """A note naming each of the scene's solids no particle came within a kernel radius of on any
    frame: such a ball changes nothing the run simulates, and was likely placed off the smoke's path
    (a wrong depth, another unit). Read off the frames' records of the smoke's gap to each ball
    (`fluidcore.spec.solids.gap_record`), so it costs a pass over the manifest; a ball without any
    record (no frame had smoke) counts as untouched."""
    from fluidcore.spec.solids import gap_record

    scene = run.scene
    if not scene.solids:
        return None
    h = scene.physics.h
    untouched = []
    for index, solid in enumerate(scene.solids):
        gaps = [gap for _, gap in _recorded(run, gap_record(index))]
        if not gaps or min(gaps) >= h:
            nearest = f"the smoke's nearest {min(gaps):.3g} units from its surface" if gaps else "no smoke recorded"
            untouched.append(f"solids[{index}] (centre {[round(c, 4) for c in solid.center]}, radius {solid.radius:g}; "
                             f"{nearest})")
    if not untouched:
        count = len(scene.solids)
        which = "the scene's solid ball" if count == 1 else f"each of the scene's {count} solid balls"
        return Check("solids", "ok", f"the smoke touches {which}", float(count))
    return Check("solids", "note",
                 f"the smoke never comes within a kernel radius ({h:.3g} units) of {'; '.join(untouched)}: such a ball changes "
                 "nothing the run simulates; if it should be in the smoke's way", float(len(untouched)), ("solids",))
