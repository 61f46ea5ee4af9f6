"""Prediction (the paper's Algorithm S2), re-simulation and counterfactuals: a run continued by physics.

    run_predict     from the last frame of a run, simulate N more frames (the source keeps seeding)
    run_interact    the same under a wind and/or with a ball in the way (fluidcore.interaction)
    run_resimulate  from the FIRST frame of a run, simulate its whole window again (the paper's
                    re-simulation task: how much of the reconstruction the physics alone explains)

Every new frame costs one simulator step, with the parent's scene and physics except that the
source seeds no faster than its inlet carries particles away at rest density (`inlet_source`)
and, when the parent is a reconstruction, the buoyancy is scaled to the one under which physics
best replays the reconstruction's last frames (`calibrate_buoyancy`, a one-off cost of a few
dozen steps); the run's manifest records both. The visual Gaussians ride on the physical velocity
field exactly as during reconstruction (`fluidcore.reconstruct.physical.visual_means`:
kernel-interpolated displacement, forward Euler), so a prediction continues the reconstruction
without a visual jump; Gaussians are born with every new physical particle and take the
fitted appearance of the reconstruction's Gaussians nearest the source, because newborn smoke
should look like the smoke the video showed coming out of it. A ball pushes the visual
Gaussians out of itself as it does the physical particles.

Each writes an ordinary run folder (fluidcore.runs) with the parent recorded, so rendering is
`fluidcore.pipeline.render_artifacts` (one render per camera per frame) and a stopped job
resumes from its last written frame with identical results: all randomness is a function of
(seed, frame).

Refinement. Algorithm S2 then renders these rough frames, refines them with a video diffusion
model and reconstructs on the refined frames (Algorithm S1). That model belongs to
`fluidcore.generative`, a later stage; `refinement_status` is the one place it plugs in.
Until it exists the simulated result stands and the manifest says why (`refinement`).
"""

from __future__ import annotations

import importlib.util
import math
import os
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from fluidcore.interaction import BallParams, InteractionError, InteractionParams, WindParams, parse_interaction
from fluidcore.physics import ForceField, ParticleState, PBFConfig, Simulator, Source, Sphere, wind_force
from fluidcore.physics.coupling import push_out
from fluidcore.pipeline import Cancelled, Progress, ShouldCancel
from fluidcore.reconstruct.physical import PositionProblem, visual_means
from fluidcore.reconstruct.saved import load_frame_state, to_frame_state
from fluidcore.reconstruct.visual import Appearance
from fluidcore.runs import FrameState, Run, RunError, Scene

TEMPLATE_SIZE = 64  # fitted Gaussians nearest the source whose appearance newborn Gaussians copy
BIRTH_SPREAD = 0.25  # jitter of a newborn Gaussian around its physical particle, in kernel radii (as in S1)
DEFAULT_VISUAL = {"velocity_radius": 2.0, "per_physical": 2, "seed": 0}  # for parents that record none
NO_REFINER = "skipped: no video model weights"
PROFILE_BANDS = 12  # height bands of the appearance profile newborn and rising smoke is held to
HOLD_RATE = 0.25  # fraction of a band's departure from the profile undone per frame
# Held attributes are shifted in the space they are drawn in and kept valid there: a mean of
# opacity logits is dominated by the few (nearly) opaque Gaussians of a band.
HELD_RANGE = {"colors": (0.0, 1.0), "opacities": (1e-4, 1.0 - 1e-4)}
CALIBRATION_FRAMES = 10  # last reconstructed frames the buoyancy is identified on
BUOYANCY_SCALES = (0.0, 0.25, 0.5, 0.75, 1.0, 1.5, 2.0)  # candidate multiples of the preset buoyancy


class PredictError(ValueError):
    """A run that cannot be continued, or a bad horizon; the message names the field."""


# -- one frame -----------------------------------------------------------------------------------
@dataclass
class Visual:
    """The visual layer carried from frame to frame: Gaussian centres and their appearance."""

    means: torch.Tensor  # (G, 3) world units
    appearance: Appearance


@dataclass(frozen=True)
class Ball:
    """A ball in simulator terms: the sphere, and the first new frame it is in the scene."""

    sphere: Sphere
    first_frame: int


@dataclass(frozen=True)
class HeightProfile:
    """The mean appearance of the smoke by height in the last reconstructed frame.

    Smoke thins as it rises, and the reconstruction's image fit keeps each height looking the way
    the video does: Gaussians born dark and large at the source were lightened and shrunk by the
    fit as they climbed. A simulation alone carries them up unchanged, so the plume darkens and
    widens above the source frame after frame. `hold`, once per frame, undoes HOLD_RATE of each
    band's departure from the profile's mean colour and opacity (a stationarity prior over the
    short horizons a prediction covers, relaxed so the handover is gradual), keeping each
    Gaussian's difference from its band's mean. Scales are left to the Gaussians: holding them
    too made the ScalarFlow prediction worse (docs/bench_predict.md).
    """

    edges: tuple[float, ...]  # band boundaries along `up`; heights outside go to the end bands
    up: tuple[float, float, float]
    means: dict[str, tuple[tuple[float, ...], ...]]  # attribute -> per band, per channel
    counts: tuple[int, ...]  # Gaussians per band; an empty band holds nothing

    @classmethod
    def observe(cls, visual: Visual, up: Sequence[float], bands: int = PROFILE_BANDS) -> HeightProfile:
        if len(visual.means) == 0:
            raise PredictError("state: the frame to continue has no visual Gaussians to take the look of the smoke from")
        height = visual.means @ visual.means.new_tensor(up)
        edges = torch.linspace(float(height.min()), float(height.max()), bands + 1, dtype=torch.float64)
        band = _band(height, edges)
        means = {name: _band_means(value, band, bands).tolist() for name, value in _profiled(visual.appearance).items()}
        if any(not math.isfinite(x) for rows in means.values() for row in rows for x in row):
            raise FloatingPointError("appearance profile: a band mean is NaN or Inf")
        counts = tuple(torch.bincount(band, minlength=bands).tolist())
        rows = {name: tuple(tuple(row) for row in value) for name, value in means.items()}
        return cls(tuple(edges.tolist()), (float(up[0]), float(up[1]), float(up[2])), rows, counts)

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> HeightProfile:
        means = {k: tuple(map(tuple, v)) for k, v in data["means"].items()}
        return cls(tuple(data["edges"]), tuple(data["up"]), means, tuple(data["counts"]))

    def to_json(self) -> dict[str, Any]:
        means = {k: [list(row) for row in v] for k, v in self.means.items()}
        return {"edges": list(self.edges), "up": list(self.up), "means": means, "counts": list(self.counts)}

    def hold(self, visual: Visual) -> Visual:
        """`visual` with each band's mean appearance moved HOLD_RATE of the way to the profile's."""
        if len(visual.means) == 0:
            return visual
        bands = len(self.edges) - 1
        band = _band(visual.means @ visual.means.new_tensor(self.up), torch.tensor(self.edges, dtype=torch.float64))
        present = visual.means.new_tensor(self.counts)[band] > 0
        held = {}
        for name, value in _profiled(visual.appearance).items():
            target = value.new_tensor(self.means[name])
            shift = HOLD_RATE * (target - _band_means(value, band, bands))[band]
            held[name] = (value + torch.where(present[:, None], shift, torch.zeros_like(shift))).clamp(*HELD_RANGE[name])
        a = visual.appearance
        return Visual(visual.means, Appearance(a.log_scales, a.quats, torch.logit(held["opacities"][:, 0]), held["colors"]))


def _profiled(appearance: Appearance) -> dict[str, torch.Tensor]:
    """The attributes a height profile holds, each as (G, channels)."""
    return {"colors": appearance.colors, "opacities": torch.sigmoid(appearance.opacity_logits)[:, None]}


def _band(height: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    inner = edges[1:-1].to(height)
    return torch.bucketize(height, inner)


def _band_means(value: torch.Tensor, band: torch.Tensor, bands: int) -> torch.Tensor:
    """Mean of `value` (G, C) per band; an empty band's mean is 0 (callers never use it)."""
    sums = value.new_zeros(bands, value.shape[1]).index_add_(0, band, value)
    counts = torch.bincount(band, minlength=bands).clamp(min=1).to(value)
    return sums / counts[:, None]


class Rollout:
    """Steps a physical state and its visual Gaussians forward together, one frame per call.

    `template` is the appearance newborn Gaussians copy (one row picked at random per birth);
    `velocity_radius` (world units) is the kernel radius of the velocity interpolation that
    carries the Gaussians, `per_physical` how many are born per new physical particle.
    """

    def __init__(
        self,
        simulator: Simulator,
        template: Appearance,
        *,
        velocity_radius: float,
        per_physical: int,
        seed: int,
        ball: Ball | None = None,
        profile: HeightProfile | None = None,
    ) -> None:
        if len(template) == 0 and per_physical > 0:
            raise PredictError("template: no Gaussians to copy the appearance of newborn smoke from")
        self.simulator = simulator
        self.template = template
        self.velocity_radius = velocity_radius
        self.per_physical = per_physical
        self.seed = seed
        self.ball = ball
        self.profile = profile
        self._static_spheres = tuple(simulator.spheres)

    def advance(self, state: ParticleState, visual: Visual, index: int, t: int) -> Visual:
        """New frame `index` (0 = the first new one; video frame `t`): step `state` in place and
        return the visual layer moved along with it."""
        sim, dt = self.simulator, self.simulator.config.dt
        sim.spheres = self._spheres(index)
        alive_before, positions_before = state.alive.clone(), state.positions.clone()
        sim.step(state)
        slots = torch.nonzero(state.alive).flatten()
        p, v = state.positions[slots], state.velocities[slots]
        was_alive = _grown(alive_before, state.capacity)[slots]
        p_prev = torch.where(was_alive[:, None], _grown(positions_before, state.capacity)[slots], p - dt * v)
        owner, offsets, born = self._births(torch.nonzero(~was_alive).flatten(), t)
        problem = PositionProblem(p_prev, p, v, visual.means, owner, offsets, self.velocity_radius)
        means = visual_means(p, problem, dt)
        if sim.spheres:
            means, _ = push_out(means, sim.spheres, state.time)
        appearance = visual.appearance.cat(born)
        keep = _inside(means, sim.box.lo, sim.box.hi)
        if not bool(torch.isfinite(means).all()):
            raise FloatingPointError(f"visual Gaussians became NaN or Inf at frame {t}")
        moved = Visual(means[keep], _select(appearance, keep))
        return moved if self.profile is None else self.profile.hold(moved)

    def _spheres(self, index: int) -> tuple[Sphere, ...]:
        if self.ball is None or index < self.ball.first_frame:
            return self._static_spheres
        return (*self._static_spheres, self.ball.sphere)

    def _births(self, rows: torch.Tensor, t: int) -> tuple[torch.Tensor, torch.Tensor, Appearance]:
        """Gaussians for the physical particles born this frame (`rows` of the live particles):
        owner row, offset from it, and an appearance copied from the template."""
        generator = torch.Generator().manual_seed(self.seed * 1_000_003 + t)
        owner = rows.repeat_interleave(self.per_physical)
        spread = BIRTH_SPREAD * self.simulator.config.h
        offsets = (torch.randn(len(owner), 3, generator=generator) * spread).to(rows.device)
        pick = torch.randint(max(len(self.template), 1), (len(owner),), generator=generator).to(rows.device)
        return owner, offsets, _select(self.template, pick)


def _grown(tensor: torch.Tensor, capacity: int) -> torch.Tensor:
    """A per-slot tensor padded (zeros / False) to the capacity a step may have grown to."""
    extra = capacity - tensor.shape[0]
    return tensor if extra <= 0 else torch.cat([tensor, tensor.new_zeros((extra, *tensor.shape[1:]))])


def _inside(points: torch.Tensor, lo: Sequence[float], hi: Sequence[float]) -> torch.Tensor:
    return ((points >= points.new_tensor(lo)) & (points <= points.new_tensor(hi))).all(dim=1)


def _select(appearance: Appearance, index: torch.Tensor) -> Appearance:
    return Appearance(
        appearance.log_scales[index], appearance.quats[index], appearance.opacity_logits[index], appearance.colors[index]
    )


def inlet_source(source: Source, config: PBFConfig) -> Source:
    """The source, seeding no faster than its inlet carries particles away at rest density.

    A source ball of radius r whose particles leave at speed v stays at rest density when it
    seeds n0 pi r^2 v dt particles per step, n0 = 8 rho0 / h^3 being the number density at rest
    (fluidcore.physics: density 1 = 8 particles per h^3). Seeding faster piles particles up at
    the inlet: during reconstruction the image fit absorbs the excess, but a free simulation
    pushes it sideways and the plume's base widens and darkens frame after frame. The inlet
    speed is the source's velocity, or the buoyancy-drag terminal speed when that is larger.
    """
    speed = math.hypot(*source.velocity)
    if config.drag > 0:
        speed = max(speed, math.hypot(*config.body_acceleration) / config.drag)
    capacity = 8.0 * config.rho0 / config.h**3 * math.pi * source.radius**2 * speed * config.dt
    if speed == 0.0 or source.rate <= capacity:
        return source
    return replace(source, rate=max(1, round(capacity)))


def calibrate_buoyancy(
    parent: Run, scene: Scene, start_frame: int, device: str, scales: Sequence[float] = BUOYANCY_SCALES
) -> tuple[float, dict[str, float]]:
    """The multiple of the scene's buoyancy under which physics best replays the reconstruction's
    last `CALIBRATION_FRAMES` frames (system identification on the observed window only).

    The preset alpha is a property of a dataset, not of this plume: a reconstruction whose column
    is denser than rest density feels no drag inside it (drag scales with 1 - rho/rho0), so with
    the preset buoyancy a free simulation accelerates the column well beyond the speed the video
    showed. Each candidate re-simulates the window from the reconstructed state at its start and
    is scored by the mean squared distance, over every frame of the window, between simulated and
    reconstructed positions of the particles alive in both. Returns (scale, error per scale).
    """
    frames = [t for t in parent.frames() if start_frame - CALIBRATION_FRAMES <= t <= start_frame]
    if len(frames) < 2 or frames != list(range(frames[0], start_frame + 1)):
        return 1.0, {}
    targets = [parent.read_frame(t) for t in frames[1:]]
    begin, _ = _load_state(parent.read_frame(frames[0]), device)
    config, box, source = scene.simulator_parts()
    errors: dict[str, float] = {}
    for scale in scales:
        simulator = Simulator(replace(config, alpha=config.alpha * scale), box, source, device=device)
        state, total = begin.clone(), 0.0
        for target in targets:
            simulator.step(state)
            total += _tracking_error(state, begin.alive, target)
        errors[f"{scale:g}"] = total / len(targets)
    best = min(scales, key=lambda scale: errors[f"{scale:g}"])
    return float(best), errors


def _tracking_error(state: ParticleState, tracked: torch.Tensor, target: FrameState) -> float:
    """Mean squared distance between simulated and reconstructed positions of the particles that
    were alive at the window's start and still are in both."""
    n = min(len(tracked), len(target.alive), state.capacity)
    alive = torch.from_numpy(np.ascontiguousarray(target.alive[:n])).to(tracked.device)
    both = tracked[:n] & state.alive[:n] & alive
    if not bool(both.any()):
        return 0.0
    reference = torch.from_numpy(np.ascontiguousarray(target.positions[:n])).to(state.positions)
    return float(((state.positions[:n][both] - reference[both]).mean(dim=0) ** 2).sum())


def source_template(visual: Visual, center: Sequence[float], size: int = TEMPLATE_SIZE) -> Appearance:
    """The appearance of the `size` Gaussians nearest the source centre: what newborn smoke looks like."""
    distance = torch.linalg.vector_norm(visual.means - visual.means.new_tensor(center), dim=1)
    nearest = torch.argsort(distance)[:size]
    return _select(visual.appearance, nearest)


# -- interventions -------------------------------------------------------------------------------
def wind_field(wind: WindParams, start_time: float, dt: float, base_height: float, up: Sequence[float]) -> ForceField:
    """The physics force field of a wind whose frame 0 is the step starting at `start_time`.

    Frame windows become time windows half a step early, so the step that produces new frame
    f (starting at start_time + f dt) is inside [start_frame, end_frame) without relying on
    exact float equality of accumulated times.
    """
    end = None if wind.end_frame is None else start_time + (wind.end_frame - 0.5) * dt
    return wind_force(
        wind.direction,
        wind.strength,
        wind.growth,
        base_height=base_height,
        start_time=start_time + (wind.start_frame - 0.5) * dt,
        end_time=end,
        up=tuple(up),
    )


def ball_sphere(ball: BallParams, start_time: float, dt: float) -> Ball:
    """The sphere of a ball that is at `ball.center` at the end of new frame `ball.start_frame`
    (the step starting at start_time + start_frame dt) and moves at `ball.velocity` after."""
    arrival = start_time + (ball.start_frame + 1) * dt
    center = tuple(c - u * arrival for c, u in zip(ball.center, ball.velocity))
    return Ball(Sphere(center=center, radius=ball.radius, velocity=ball.velocity), ball.start_frame)


# -- run folders ---------------------------------------------------------------------------------
def run_predict(
    parent_run: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    *,
    frames: int,
    device: str = "cpu",
    progress: Progress | None = None,
    should_cancel: ShouldCancel | None = None,
) -> Path:
    """Simulate `frames` frames after the parent's last frame (no interventions)."""
    return _continue(parent_run, out_dir, "predict", frames, InteractionParams(), device, progress, should_cancel)


def run_interact(
    parent_run: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    *,
    frames: int,
    wind: WindParams | Mapping[str, Any] | None = None,
    ball: BallParams | Mapping[str, Any] | None = None,
    device: str = "cpu",
    progress: Progress | None = None,
    should_cancel: ShouldCancel | None = None,
) -> Path:
    """Like `run_predict`, under a wind and/or with a ball (frames counted from the first new one)."""
    params = parse_interaction(_as_mapping(wind), _as_mapping(ball))
    if params.wind is None and params.ball is None:
        raise InteractionError("interact needs a wind, a ball or both (predict asks for neither)")
    return _continue(parent_run, out_dir, "interact", frames, params, device, progress, should_cancel)


def run_resimulate(
    parent_run: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    *,
    device: str = "cpu",
    progress: Progress | None = None,
    should_cancel: ShouldCancel | None = None,
) -> Path:
    """Simulate the parent's window again from its first frame: frame 0 is the reconstructed
    initial state itself, every later frame is physics only."""
    parent = _open_parent(parent_run)
    first, stop = parent.frames()[0], parent.frames()[-1] + 1
    return _write(parent, out_dir, "resimulate", first, (first, stop), InteractionParams(), device, progress, should_cancel)


def _continue(
    parent_run: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    kind: str,
    frames: int,
    params: InteractionParams,
    device: str,
    progress: Progress | None,
    should_cancel: ShouldCancel | None,
) -> Path:
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
        raise PredictError(f"frames must be a whole number >= 1, got {frames!r}")
    parent = _open_parent(parent_run)
    last = parent.frames()[-1]
    return _write(parent, out_dir, kind, last, (last + 1, last + 1 + frames), params, device, progress, should_cancel)


def _open_parent(path: str | os.PathLike[str]) -> Run:
    parent = Run.open(path)
    if not parent.frames():
        raise PredictError(f"run: {path} has no finished frame to start from")
    return parent


def _write(
    parent: Run,
    out_dir: str | os.PathLike[str],
    kind: str,
    start_frame: int,
    frame_range: tuple[int, int],
    params: InteractionParams,
    device: str,
    progress: Progress | None,
    should_cancel: ShouldCancel | None,
) -> Path:
    """Write the frames of `frame_range` into a new (or resumed) run continuing `parent` from
    its frame `start_frame` (written unchanged first when it lies inside the range)."""
    scene = _continued_scene(parent.scene)
    start = _load_state(parent.read_frame(start_frame), device)
    buoyancy_scale, calibration, profile = 1.0, {}, None
    if kind != "resimulate" and parent.kind == "reconstruct":
        buoyancy_scale, calibration = calibrate_buoyancy(parent, scene, start_frame, device)
        scene = replace(scene, physics={**scene.physics, "alpha": scene.physics["alpha"] * buoyancy_scale})
        profile = HeightProfile.observe(start[1], scene.up)
    elif kind != "resimulate" and parent.manifest["settings"].get("appearance_profile"):
        profile = HeightProfile.from_json(parent.manifest["settings"]["appearance_profile"])  # a chained prediction
    n_frames = frame_range[1] - frame_range[0]
    params.check_run_scene(scene.to_json(), n_frames)  # before anything is written
    visual_settings = _visual_settings(parent)
    run = Run.create(
        out_dir,
        kind=kind,
        cameras=parent.cameras(),
        input_views=parent.manifest["input_views"],
        frame_range=frame_range,
        fps=parent.fps,
        channels=parent.channels,
        background_color=parent.background_color,
        scene=scene,
        settings={
            "start_frame": start_frame,
            "visual": visual_settings,
            "parent_source_rate": parent.scene.source["rate"],
            "buoyancy_scale": buoyancy_scale,
            "buoyancy_calibration_error": calibration,
            "appearance_profile": None if profile is None else profile.to_json(),
            "wind": None if params.wind is None else params.wind.model_dump(),
            "ball": None if params.ball is None else params.ball.model_dump(),
        },
        parent=Path(parent.path).resolve(),
    )
    run.update(refinement=refinement_status())
    rollout = _rollout(scene, start, params, visual_settings, device, profile)
    state, visual = start if run.next_frame() == frame_range[0] else _load_state(run.read_frame(run.frames()[-1]), device)
    report = progress or (lambda fraction, stage: None)
    for t in range(run.next_frame(), frame_range[1]):
        if should_cancel is not None and should_cancel():
            raise Cancelled(f"{kind} cancelled; {out_dir} resumes from frame {t}")
        began = time.perf_counter()
        stats: dict[str, float] = {}
        if t > start_frame:
            visual = rollout.advance(state, visual, t - start_frame - 1, t)
            stats = {"particles": float(state.n_alive), "gaussians": float(len(visual.means))}
        run.write_frame(t, _frame_state(state, visual), stats, time.perf_counter() - began)
        report((t + 1 - frame_range[0]) / n_frames, kind)
    return Path(out_dir)


def _continued_scene(scene: Scene) -> Scene:
    """The parent's scene, its source seeding at most what the inlet carries at rest density."""
    config, _, source = scene.simulator_parts()
    return replace(scene, source={**scene.source, "rate": inlet_source(source, config).rate})


def _rollout(
    scene: Scene,
    start: tuple[ParticleState, Visual],
    params: InteractionParams,
    visual: Mapping[str, Any],
    device: str,
    profile: HeightProfile | None,
) -> Rollout:
    """The simulator of the parent's scene with the interventions, ready to continue `start`.

    New frame 0 is the step that begins at the start state's time; the interventions' frame
    numbers are counted from there.
    """
    config, box, source = scene.simulator_parts()
    time0 = start[0].time
    base_height = float(np.dot(source.center, scene.up))
    force = None if params.wind is None else wind_field(params.wind, time0, config.dt, base_height, scene.up)
    ball = None if params.ball is None else ball_sphere(params.ball, time0, config.dt)
    return Rollout(
        Simulator(config, box, source, force=force, device=device),
        source_template(start[1], source.center),
        velocity_radius=visual["velocity_radius"] * config.h,
        per_physical=visual["per_physical"],
        seed=visual["seed"],
        ball=ball,
        profile=profile,
    )


def refinement_status() -> str:
    """What became of Algorithm S2's refinement step for a run written now.

    The seam for `fluidcore.generative`: once that stage provides a video model with weights,
    this is where the rough renders of the new frames are refined and reconstructed again.
    """
    if importlib.util.find_spec("fluidcore.generative") is None:
        return NO_REFINER
    return "skipped: fluidcore.generative has no video refinement step yet"


def _visual_settings(parent: Run) -> dict[str, Any]:
    """How visual Gaussians move and are born in the parent: a prediction must continue alike."""
    settings = parent.manifest.get("settings", {})
    if "visual" in settings:
        return dict(settings["visual"])
    quality = settings.get("quality", {})
    return {
        "velocity_radius": float(quality.get("velocity_radius", DEFAULT_VISUAL["velocity_radius"])),
        "per_physical": int(quality.get("visual_per_physical", DEFAULT_VISUAL["per_physical"])),
        "seed": int(quality.get("seed", DEFAULT_VISUAL["seed"])),
    }


def _as_mapping(value: WindParams | BallParams | Mapping[str, Any] | None) -> Mapping[str, Any] | None:
    return value.model_dump() if isinstance(value, (WindParams, BallParams)) else value


def _load_state(saved: FrameState, device: str) -> tuple[ParticleState, Visual]:
    if "step" not in saved.extra:
        raise RunError("state: no extra_step (the simulator step count) to continue from")
    state, means, appearance = load_frame_state(saved, device)
    return state, Visual(means, appearance)


def _frame_state(state: ParticleState, visual: Visual) -> FrameState:
    return to_frame_state(state, visual.means, visual.appearance)
