"""The prediction jobs (Algorithm S2): a run continued by physics, written as a new run.

    run_predict     from the last frame of a run, simulate N more frames (the source keeps seeding)
    run_interact    the same under a wind and/or with a ball in the way (fluidcore.spec.controls)
    run_resimulate  from the FIRST frame of a run, simulate its whole window again (the paper's
                    re-simulation task: how much of the reconstruction the physics alone explains)

Each continues the parent's scene and physics, except that the source seeds no faster than its
inlet carries particles away at rest density (`rollout.inlet_source`) and, when the parent is a
reconstruction with preset physics, the buoyancy is scaled to the one under which physics best
replays the reconstruction's last frames (`identification.calibrate_buoyancy`) and the appearance
height profile of its last frame is held (`priors.HeightProfile`); physics identified from the
video (fluidcore.reconstruct.identify) is used as it is, without that prior. The manifest
records all three (settings `buoyancy_scale`, `appearance_profile`, `priors`).
Each writes an ordinary run folder (fluidcore.runs) with the parent recorded relative to it, so
rendering is `fluidcore.artifacts`, and a stopped job resumes from its last written frame with
identical results. Device, progress, cancellation (its `JobContext`) and input errors follow
`fluidcore.jobs`.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from fluidcore.spec.controls import InteractionParams, Intervention, branch_frame, parse_interaction
from fluidcore.jobs import Cancelled, JobContext, JobInputError
from fluidcore.physics import step_record
from fluidcore.physics.build import build_simulator
from fluidcore.predict.identification import calibrate_buoyancy
from fluidcore.predict.interventions import interventions
from fluidcore.predict.priors import HeightProfile, refine_future
from fluidcore.predict.rollout import Rollout, continued_scene, source_template
from fluidcore.runs import ContinuationSettings, ReconstructSettings, Run, RunKind
from fluidcore.smoke import SmokeState
from fluidcore.spec.reconstruct import VisualSettings
from fluidcore.spec.scene import Scene

if TYPE_CHECKING:
    from fluidcore.generative.stages import GenerativeSettings

NOT_REFINED = "skipped: only predictions are refined (Algorithm S2); what-if and re-simulation runs show the physics"


@dataclass(frozen=True)
class Continuation:
    """What a continuation asks for besides its frames: the kind of run it writes, the
    interventions it applies and, for a prediction, the generative settings of its refinement.
    How the kinds differ is answered here, once."""

    kind: RunKind  # PREDICT, INTERACT or RESIMULATE
    params: InteractionParams = field(default_factory=InteractionParams)
    generative: GenerativeSettings | None = None

    @property
    def keeps_priors(self) -> bool:
        """Whether the parent's calibration and look carry over: a re-simulation measures what
        the physics alone explains, so it takes neither."""
        return self.kind is not RunKind.RESIMULATE

    @property
    def refined(self) -> bool:
        """Only predictions are refined (Algorithm S2); what-ifs and re-simulations show the physics."""
        return self.kind is RunKind.PREDICT


def run_predict(
    parent_run: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    *,
    frames: int,
    from_frame: int | None = None,
    generative: GenerativeSettings | None = None,
    context: JobContext = JobContext(),
) -> Path:
    """Simulate `frames` frames after the parent's frame `from_frame` (default: its last), no
    interventions; then, when the video model's weights exist (`generative`, default:
    `fluidcore.weights.weights_dir()`), refine and reconstruct them (`priors.refine_future`,
    Algorithm S2)."""
    return _continue(parent_run, out_dir, Continuation(RunKind.PREDICT, generative=generative), frames, from_frame, context)


def run_interact(
    parent_run: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    params: InteractionParams,
    *,
    frames: int,
    from_frame: int | None = None,
    context: JobContext = JobContext(),
) -> Path:
    """Like `run_predict`, under a wind and/or with a ball (frames counted from the first new one).

    `params` (a wind, a ball or both) are the validated edge types; the run's scene checks them
    before anything is written (`InteractionParams.check_scene`).

    `from_frame` branches the what-if off any finished frame of the parent (default: its last):
    frame 0 re-simulates the whole clip with the intervention from the start, a mid-clip frame
    asks "what if the wind had started here".
    """
    params = parse_interaction(params.wind, params.ball, Intervention)  # the one rule: a wind, a ball or both
    return _continue(parent_run, out_dir, Continuation(RunKind.INTERACT, params), frames, from_frame, context)


def run_resimulate(
    parent_run: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    *,
    context: JobContext = JobContext(),
) -> Path:
    """Simulate the parent's window again from its first frame: frame 0 is the reconstructed
    initial state itself, every later frame is physics only."""
    parent = _open_parent(parent_run)
    first, stop = parent.frames()[0], parent.frames()[-1] + 1
    return _write(parent, out_dir, Continuation(RunKind.RESIMULATE), first, (first, stop), context)


def _continue(
    parent_run: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    request: Continuation,
    frames: int,
    from_frame: int | None,
    context: JobContext,
) -> Path:
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
        raise JobInputError(f"frames must be a whole number >= 1, got {frames!r}")
    parent = _open_parent(parent_run)
    branch = branch_frame(from_frame, parent.frames(), str(parent.path))
    return _write(parent, out_dir, request, branch, (branch + 1, branch + 1 + frames), context)


def _open_parent(path: str | os.PathLike[str]) -> Run:
    parent = Run.open(path)
    if not parent.frames():
        raise JobInputError(f"run: {path} has no finished frame to start from")
    return parent


def _write(
    parent: Run,
    out_dir: str | os.PathLike[str],
    request: Continuation,
    start_frame: int,
    frame_range: tuple[int, int],
    context: JobContext,
) -> Path:
    """Write the frames of `frame_range` into a new (or resumed) run continuing `parent` from
    its frame `start_frame` (written unchanged first when it lies inside the range); a
    prediction is then refined (Algorithm S2), other kinds are not."""
    scene = continued_scene(parent.scene)
    device, params = context.device, request.params
    start = SmokeState.from_frame(parent.read_frame(start_frame), device)
    buoyancy_scale, calibration, profile, observed = 1.0, {}, None, None
    parent_settings = parent.settings
    if request.keeps_priors and isinstance(parent_settings, ReconstructSettings):
        # Identified physics (fluidcore.reconstruct.identify) is used as it is, without the height-profile
        # prior: with it the future scored +0.33 dB on the dev scene but -0.17 dB on ScalarFlow
        # (docs/bench_generalise.md). Preset physics keeps the paper path: calibration and the prior,
        # both taken from the reconstruction's last frames even for a branch from an earlier one:
        # the whole window is observed footage, and at an early branch frame (frame 0 above all)
        # the plume has not risen yet to show its speed or its look higher up.
        if parent_settings.physics.mode != "auto":
            observed = parent.frames()[-1]
            buoyancy_scale, calibration = calibrate_buoyancy(parent, scene, observed, device)
            look = start if observed == start_frame else SmokeState.from_frame(parent.read_frame(observed), device)
            profile = HeightProfile.observe(look, scene.up)
        scene = scene.with_buoyancy_scaled(buoyancy_scale)
    elif request.keeps_priors and parent_settings.appearance_profile:
        profile = HeightProfile.of(parent_settings.appearance_profile)  # a chained prediction
    n_frames = frame_range[1] - frame_range[0]
    params.check_scene(scene, n_frames)  # before anything is written
    visual_settings = parent.visual_settings()
    run = Run.create(
        out_dir,
        kind=request.kind,
        cameras=parent.cameras(),
        input_views=parent.input_views,
        frame_range=frame_range,
        fps=parent.fps,
        channels=parent.channels,
        background_color=parent.background_color,
        scene=scene,
        settings=ContinuationSettings(
            branch_frame=start_frame,
            visual=visual_settings,
            parent_source_rate=parent.scene.source.rate,
            identified_on_frame=observed,
            buoyancy_scale=buoyancy_scale,
            buoyancy_calibration_error=calibration,
            appearance_profile=profile,
            priors=() if profile is None else ("appearance height profile (fluidcore.predict.priors.HeightProfile)",),
            wind=params.wind,
            ball=params.ball,
        ),
        parent=parent.path,
    )
    run.update(refinement="pending: runs after the last simulated frame" if request.refined else NOT_REFINED)
    rollout = _rollout(scene, start, params, visual_settings, device, profile)
    smoke = start if run.next_frame() == frame_range[0] else SmokeState.from_frame(run.read_frame(run.frames()[-1]), device)
    smoke = smoke.with_particles(rollout.simulator.adopt_air(smoke.particles))
    for t in range(run.next_frame(), frame_range[1]):
        if context.should_cancel():
            raise Cancelled(f"{request.kind} cancelled; {out_dir} resumes from frame {t}")
        began = time.perf_counter()
        stats: dict[str, float] = {}
        if t > start_frame:
            smoke, step = rollout.advance(smoke, t - start_frame - 1, t)
            stats = {"particles": float(smoke.particles.n_alive), "gaussians": float(len(smoke.means)), **step_record(step)}
        run.write_frame(t, smoke.to_frame(), stats, time.perf_counter() - began)
        context.progress((t + 1 - frame_range[0]) / n_frames, request.kind)
    if request.refined:
        run.update(refinement=refine_future(run, request.generative, context))
    return Path(out_dir)


def _rollout(
    scene: Scene,
    start: SmokeState,
    params: InteractionParams,
    visual: VisualSettings,
    device: str,
    profile: HeightProfile | None,
) -> Rollout:
    """The simulator of the parent's scene with the interventions, ready to continue `start`.

    New frame 0 is the step that begins at the start state's time; the interventions' frame
    numbers are counted from there and reach the simulator with each step (`Interventions.controls`).
    When the scene simulates the air, the wind pushes that air (instead of the wind's uniformly
    accelerated air); the rollout continues the air saved with `start` (`Simulator.adopt_air`:
    still air when the parent frame holds none, resampled onto this grid when the parent's lies
    on another).
    """
    applied = interventions(params, scene.physics, scene.source, scene.up, start.particles.time)
    return Rollout(
        build_simulator(scene, device=device),
        source_template(start, scene.source.center),
        velocity_radius=visual.velocity_radius * scene.physics.h,
        per_physical=visual.per_physical,
        seed=visual.seed,
        interventions=applied,
        profile=profile,
        opacity_concentration=visual.opacity_concentration,
    )
