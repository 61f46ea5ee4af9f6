"""The per-frame driver of Algorithm S1, with a checkpoint after every frame.

`read_inputs` turns decoded input videos into `InputViews` (targets at the working resolution,
and their backgrounds); views made from them before any fit (the generative novel views,
fluidcore.reconstruct.job) join them, and `prepare` turns all of it into a frozen
`Reconstruction` (every view it fits, the source estimated from the first second's smoke,
physics in this scene's units);
`run` then goes frame by frame:

    frame 0: the source seeds particles for 20 stabilisation steps; positions are fitted
             (with `first_frame_factor` times more iterations), the visual Gaussians are born
             on them and their appearance is fitted;
    frame t: p_sim = Sim(p_{t-1}, u_{t-1}) (which also seeds new particles and, with
             `simulation.air_cells`, steps the air from p_{t-1}: the air is saved with the frame),
             positions fitted
             (fluidcore.reconstruct.physical; with the input view's optical flow between
             frames t-1 and t, fluidcore.reconstruct.flow, when its weight is not 0),
             u_t = (p_t - p_{t-1}) / dt, visual Gaussians
             advected and their appearance fitted (fluidcore.reconstruct.visual).

Before a frame's fit, the carried state advected by the simulator is rendered in the input view
and scored against the frame it has not yet seen ("forecast_psnr" in the frame's losses, next
to the fitted "input_psnr"): a held-out-frame check that needs no other camera. An appearance
that paints the input view over a wrong 3D state fits well and forecasts badly.

Each frame's state is written to the run folder before the next begins. Randomness (view
choice, spawn jitter, source seeding) is a function of (seed, frame) only, and every frame
starts from the saved float32 state, so a resumed run computes exactly what an uninterrupted
one does.
"""

from __future__ import annotations

import random
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
import torch

from fluidcore.cameras import Camera, render_size
from fluidcore.errors import InputError
from fluidcore.jobs import StepProgress
from fluidcore.physics import Box, ParticleState, interpolate_velocity, step_record
from fluidcore.physics.build import build_simulator
from fluidcore.physics.coupling import push_out, surface_gaps
from fluidcore.reconstruct.flow import FlowField, FlowObservation, input_flow
from fluidcore.reconstruct.images import Background, estimate_background, plate_background, resize_image, smoke_mask, to_float
from fluidcore.carry import PositionProblem, carry, visual_means
from fluidcore.reconstruct.physical import fit_positions
from fluidcore.reconstruct.scene_physics import scene_physics, scene_prior
from fluidcore.reconstruct.source_estimate import GeneratedView, estimate_source, source_frames
from fluidcore.spec.source_hint import SourceHint
from fluidcore.reconstruct.views import ViewTarget, image_loss, mirror_agreement, symmetry_support, symmetry_views
from fluidcore.reconstruct.visual import OpacityTie, ScaleBounds, fit_appearance, spawn
from fluidcore.reconstruct.yardstick import input_fit, psnr_db
from fluidcore.render import Gaussians, render
from fluidcore.runs import BackgroundRecord, CaptureRecord, PhysicsRecord, ReconstructSettings, Run, RunKind, SourceEstimateRecord, SymmetryRecord
from fluidcore.smoke import Appearance, SmokeState
from fluidcore.spec.reconstruct import MIN_FIT_SIDE, ReconstructConfig
from fluidcore.spec.scene import Air, Scene, SourcePlace
from fluidcore.spec.simulation import DEFAULT_PHYSICS
from fluidcore.spec.solids import SolidBall, check_solids, gap_record

FrameCallback = Callable[[int, dict[str, float]], None]


class ReconstructionError(InputError):
    """Inputs a reconstruction cannot start from; the message names the field."""


@dataclass(frozen=True)
class Plate:
    """A background plate: frames of the input videos that show no smoke."""

    frame_range: tuple[int, int]  # [start, end) in the videos
    videos: Mapping[str, np.ndarray]  # input camera -> uint8 (P, H, W, 3), any size with the camera's aspect


@dataclass(frozen=True)
class InputViews:
    """The input videos as fitting targets, and what is read off them before any fit."""

    targets: tuple[ViewTarget, ...]  # kind "input", at the working resolution, in the order of the videos
    frame_range: tuple[int, int]
    channels: int
    background_images: dict[str, np.ndarray]  # camera -> background image at the camera's full size (where not flat)
    backgrounds: dict[str, BackgroundRecord]  # camera -> how its background was found

    @property
    def names(self) -> list[str]:
        return [v.camera.name for v in self.targets]


@dataclass(frozen=True)
class Reconstruction:
    """Everything fixed before frame 0."""

    cameras: dict[str, Camera]
    views: tuple[ViewTarget, ...]  # the input views first, then pseudo- or generated views
    input_views: list[str]
    frame_range: tuple[int, int]
    fps: float
    channels: int
    background_color: np.ndarray
    background_images: dict[str, np.ndarray]
    backgrounds: dict[str, BackgroundRecord]
    smoke_color: np.ndarray
    scene: Scene  # what the reconstruction simulates, and every prediction from it
    quality: ReconstructConfig
    physics: PhysicsRecord  # how the physics was chosen (fluidcore.reconstruct.scene_physics)
    stabilization_steps: int
    symmetry: SymmetryRecord | None = None  # mirror agreement of the input smoke and the symmetry prior's weight
    source_hint: SourceHint | None = None  # the source `prepare` was given (by the user, or a refinement's parent), if any
    source_estimate: SourceEstimateRecord | None = None  # how the source was found from the videos, if it was
    flow: FlowField | None = None  # optical flow of the first input view (None when its loss weight is 0)
    capture: CaptureRecord | None = None  # how up was found and the camera file's fps (the job's `Footage`)

    @property
    def fit_scene(self) -> Scene:
        """The scene the fit steps: the scene without entrainment. The plume's spreading
        (`PBFConfig.entrainment`, identified from the input view) is for the free simulation
        that continues the fit; inside the fit it spread the particles along the input ray, which
        one view does not pin back (dev scene F, seed 0: novel views 32.20 -> 31.30 dB with it,
        docs/bench_generalise.md, "Entrainment")."""
        return replace(self.scene, physics=replace(self.scene.physics, entrainment=0.0))

    def settings(self) -> ReconstructSettings:
        return ReconstructSettings(
            quality=self.quality,
            physics=self.physics,
            symmetry=self.symmetry,
            source_hint=self.source_hint,
            source_estimate=self.source_estimate,
            backgrounds=self.backgrounds,
            capture=self.capture,
            views=tuple({"camera": v.camera.name, "kind": v.kind, "weight": v.weight} for v in self.views),
        )


def read_inputs(
    cameras: Mapping[str, Camera],
    videos: Mapping[str, np.ndarray],
    *,
    frame_range: tuple[int, int],
    quality: ReconstructConfig,
    plate: Plate | None = None,
    device: str | torch.device = "cpu",
) -> InputViews:
    """The input `videos` (uint8 (T, H, W, 3) per input camera, frames of `frame_range` only, at
    any size with the camera's aspect) as targets at the quality's working resolution, with their
    backgrounds: from the `plate` where one is given, else estimated from the frames."""
    if not videos:
        raise ReconstructionError("videos: at least one input view is needed")
    unknown = sorted(set(videos) - set(cameras))
    if unknown:
        raise ReconstructionError(f"videos: no camera named {unknown} in the cameras file (have {sorted(cameras)})")
    n_frames = frame_range[1] - frame_range[0]
    lengths = {name: len(v) for name, v in videos.items()}
    if any(n != n_frames for n in lengths.values()):
        raise ReconstructionError(f"videos: expected {n_frames} frames per view for {frame_range}, got {lengths}")
    from fluidcore.video import is_grayscale

    channels = 1 if all(is_grayscale(v) for v in videos.values()) else 3
    targets, images, records = [], {}, {}
    for name, frames in videos.items():
        camera = cameras[name]
        width, height = render_size(camera.width, camera.height, quality.fit.long_side)
        data = _working(frames, channels, width, height)
        if plate is None:
            background = estimate_background(data)
        else:
            background = plate_background(_working(plate.videos[name], channels, width, height), data)
        records[name] = _background_record(background, None if plate is None else plate.frame_range)
        if background.image is not None:
            images[name] = resize_image(background.image, camera.width, camera.height)
        bg = torch.from_numpy(background.as_image(height, width).copy()) if background.image is not None else torch.from_numpy(background.color)
        noise = torch.from_numpy(background.noise).to(device)
        targets.append(ViewTarget(camera.scaled(width, height), torch.from_numpy(data).to(device), bg.to(device), noise))
    return InputViews(tuple(targets), frame_range, channels, images, records)


def _working(frames: np.ndarray, channels: int, width: int, height: int) -> np.ndarray:
    """uint8 (T, H, W, 3) -> float (T, height, width, channels): the frames as the fit reads them."""
    data = to_float(frames, channels)
    return np.stack([resize_image(f, width, height) for f in data])


def _background_record(background: Background, plate_frames: tuple[int, int] | None) -> BackgroundRecord:
    covered = 0.0 if background.covered is None else float(background.covered.mean())
    return BackgroundRecord(plate_frames=plate_frames, textured=background.image is not None, covered=covered)


def prepare(
    cameras: Mapping[str, Camera],
    inputs: InputViews,
    *,
    fps: float,
    quality: ReconstructConfig,
    box: tuple[np.ndarray, np.ndarray],
    up: Sequence[float] = (0.0, 1.0, 0.0),
    source: SourceHint | SourcePlace | None = None,
    physics: str = DEFAULT_PHYSICS,
    solids: Sequence[SolidBall] = (),
    extra_views: Sequence[ViewTarget] = (),
    pseudo_views: bool = True,
    device: str | torch.device = "cpu",
    on_evaluation: StepProgress | None = None,
) -> Reconstruction:
    """Background, source and physics for reconstructing `inputs`, and every view it fits.

    `source` is where the user knows the source to be (its radius, if not given, is measured at
    that depth), or the place of the source of a run this one refines; otherwise it is estimated
    from the first frames. `physics` is "auto" (identified from the first input view,
    fluidcore.reconstruct.identify) or a preset name. `solids`: static balls in the scene (in the
    box), simulated from the identification's rollouts on. `extra_views` are views made before the fit
    (the generative novel views of a single input view): those of kind "generated" join the
    source estimate's triangulation at their loss weight (`estimate_source`), so the
    identification starts from their depth too, and they take the place of the symmetry
    pseudo-views, which a single view otherwise gets; `pseudo_views=False` fits `inputs` alone
    (a refinement fits its refined input views only). `on_evaluation`: the identification's progress.
    """
    targets, channels = list(inputs.targets), inputs.channels
    def first_second(view: ViewTarget) -> np.ndarray:  # the smoke the source estimate and the smoke colour read
        return smoke_mask(view.frames[: source_frames(fps, len(view.frames))], view.background, view.noise)

    masks = {v.camera.name: first_second(v) for v in targets}
    up_v = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    background_color = np.median([v.background.reshape(-1, channels).median(0).values.cpu().numpy() for v in targets], axis=0)
    smoke_color = _smoke_color(targets, masks, background_color)

    if isinstance(source, SourceHint):
        source.check_in_box(*box)
    check_solids(solids, *box)
    place = source.place if isinstance(source, SourceHint) else source
    estimate_record = None
    if place is None:
        generated = [  # the novel-view model's views close the depth one input view leaves open
            GeneratedView(v.camera, first_second(v), v.weight)
            for v in extra_views if v.kind == "generated"
        ]
        estimate = estimate_source(cameras, masks, box, up_v, None if source is None else source.center, generated)
        place = estimate.place
        estimate_record = SourceEstimateRecord(
            depth_cue=estimate.depth_cue,
            depth_range=None if estimate.depth_range is None else tuple(tuple(map(float, p)) for p in estimate.depth_range),
            pixels={name: tuple(map(float, px)) for name, px in estimate.pixels.items()},
            generated=estimate.generated,
        )
    sim_box = Box(tuple(map(float, box[0])), tuple(map(float, box[1])))
    first = targets[0]
    simulation = quality.simulation
    prior = scene_prior(physics, sim_box, up_v, fps, place, Air(simulation.cells, simulation.air_vorticity), quality.seed,
                        simulation.motion, tuple(solids))
    chosen = scene_physics(first, prior, budget=quality.fit.particles_per_frame, entrainment=quality.simulation.entrainment,
                           keep_source=source.kept if isinstance(source, SourceHint) else "nothing", device=device,
                           on_evaluation=on_evaluation)
    center = np.asarray(chosen.scene.source.center)
    pseudo, symmetry = [], None
    priors = quality.priors
    if priors.symmetry_views > 0 and len(targets) == 1:  # real views from other directions beat a symmetry guess
        agreement = mirror_agreement(targets[0], center, up_v)
        weight = priors.symmetry_weight * symmetry_support(agreement) / priors.symmetry_views
        symmetry = SymmetryRecord(mirror_agreement=agreement, weight=weight * priors.symmetry_views)
        if weight > 0 and pseudo_views and not extra_views:
            pseudo = symmetry_views(targets, center, up_v, priors.symmetry_views, weight)
    flow = input_flow(first.camera, first.frames, first.background, first.noise) if quality.weights.flow > 0 else None
    return Reconstruction(
        cameras=dict(cameras),
        views=(*targets, *pseudo, *extra_views),
        input_views=inputs.names,
        frame_range=inputs.frame_range,
        fps=fps,
        channels=channels,
        background_color=background_color.astype(np.float32),
        background_images=inputs.background_images,
        backgrounds=inputs.backgrounds,
        smoke_color=smoke_color,
        scene=chosen.scene,
        quality=quality,
        physics=chosen.record,
        stabilization_steps=chosen.stabilization_steps,
        symmetry=symmetry,
        flow=flow,
        source_hint=source if isinstance(source, SourceHint) or source is None else SourceHint(center=source.center, radius=source.radius),
        source_estimate=estimate_record,
    )


def _smoke_color(targets: Sequence[ViewTarget], masks: Mapping[str, np.ndarray], background: np.ndarray) -> np.ndarray:
    """Initial Gaussian colour: the background pushed twice as far as the average smoke pixel,
    so partly transparent Gaussians can reach the observed contrast."""
    values = []
    for view, mask in zip(targets, masks.values(), strict=True):
        frames = view.frames[: len(mask)].cpu().numpy()
        values.append(frames[mask])
    smoke = np.concatenate(values) if values else np.empty((0, len(background)))
    if len(smoke) == 0:
        return background.astype(np.float32)
    return np.clip(background + 2.0 * (smoke.mean(0) - background), 0.0, 1.0).astype(np.float32)


class Reconstructor:
    """Runs a prepared reconstruction into a run folder, one checkpointed frame at a time."""

    def __init__(self, rec: Reconstruction, device: str | torch.device = "cpu") -> None:
        self.rec = rec
        self.device = torch.device(device)
        # with the scene's air the air is part of the state: stepped from the fitted particles of
        # each frame, saved with it, and continued by every prediction and branch of the run
        self.simulator = build_simulator(rec.fit_scene, device=self.device)

    def open_run(self, out_dir) -> Run:
        rec = self.rec
        run = Run.create(
            out_dir,
            kind=RunKind.RECONSTRUCT,
            cameras=rec.cameras,
            input_views=rec.input_views,
            frame_range=rec.frame_range,
            fps=rec.fps,
            channels=rec.channels,
            background_color=rec.background_color.tolist(),
            scene=rec.scene,
            settings=rec.settings(),
        )
        if rec.background_images and not run.background_images():
            run.write_background(rec.background_images)
        return run

    def run(self, out_dir, on_frame: FrameCallback | None = None, should_stop: Callable[[], bool] | None = None) -> Run:
        """Fit every frame not yet in `out_dir`; `on_frame(t, losses)` after each checkpoint.
        `should_stop()` is asked between frames; when it says so the run stops (resumable)."""
        run = self.open_run(out_dir)
        smoke = self._resume(run)
        for t in range(run.next_frame(), self.rec.frame_range[1]):
            if should_stop is not None and should_stop():
                break
            start = time.perf_counter()
            smoke, losses = self.frame(t, smoke, first=t == self.rec.frame_range[0])
            run.write_frame(t, smoke.to_frame(), losses, time.perf_counter() - start)
            if on_frame is not None:
                on_frame(t, losses)
        return run

    # -- one frame ----------------------------------------------------------------------
    def frame(self, t: int, smoke: SmokeState, first: bool) -> tuple[SmokeState, dict[str, float]]:
        """Fit frame `t` from the state after frame t-1 (`first`: from the stabilised particles)."""
        rec, config = self.rec, self.simulator.config
        q, fit, visual, lr = rec.quality, rec.quality.fit, rec.quality.visual, rec.quality.optimiser
        index = t - rec.frame_range[0]
        seed = q.seed * 1_000_003 + t
        generator = torch.Generator().manual_seed(seed)
        chooser = random.Random(seed)
        color = smoke.appearance.colors.mean(0) if len(smoke.appearance) else torch.from_numpy(rec.smoke_color).to(self.device)

        def births(rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, Appearance]:
            return spawn(rows, visual.per_physical, spread=0.25 * config.h, scale=0.35 * config.h,
                         opacity=visual.initial_opacity, color=color, generator=generator)

        carried = carry(smoke, self.simulator, births, visual.velocity_radius * config.h, first=first)
        state, problem, appearance = carried.state, carried.problem, carried.appearance
        forecast = self._input_psnr(index, visual_means(problem.p_sim, problem, config.dt), appearance)
        iterations = fit.position_iterations * (fit.first_frame_factor if first else 1)
        loss_fn = self._image_loss(index, iterations, chooser)
        flow = None if first or rec.flow is None else FlowObservation(rec.flow, index - 1, problem.p_prev, config.h)
        p, terms = fit_positions(problem, appearance, loss_fn, self.simulator.integrator, q.weights, iterations,
                                 lr.lr_position, q.priors.next_step_incompressibility, flow)
        # the image fit may pull particles (and the Gaussians on them) into a solid: the scene keeps them out
        solids = self.simulator.solids
        p, _ = push_out(p, solids, state.time)
        means, _ = push_out(visual_means(p, problem, config.dt).detach(), solids, state.time)
        app_iterations = fit.appearance_iterations * (fit.first_frame_factor if first else 1)
        appearance, app_loss = fit_appearance(
            means,
            appearance,
            smoke.appearance,
            self._image_loss(index, app_iterations, chooser),
            app_iterations,
            {"color": lr.lr_color, "scale": lr.lr_scale, "opacity": lr.lr_opacity, "rotation": lr.lr_rotation},
            q.weights,
            ScaleBounds(visual.min_scale * config.h, visual.max_scale * config.h),
            OpacityTie(visual.opacity_spread),
        )
        state.positions[carried.slots] = p
        state.velocities[carried.slots] = self._velocities(state, p, problem, first)
        losses = {**terms, "appearance": app_loss, **self._input_fit(index, means, appearance), "forecast_psnr": forecast}
        fitted = SmokeState(state, means, appearance).cropped(rec.scene.box_lo, rec.scene.box_hi)
        losses.update({"particles": float(state.n_alive), "gaussians": float(len(fitted.means)), **step_record(carried.step),
                       **self._solid_gaps(fitted.particles)})
        return fitted, losses

    def _solid_gaps(self, state: ParticleState) -> dict[str, float]:
        """How far the frame's smoke kept from each of the scene's solids (`gap_record`), what the
        health report reads to tell a ball the smoke never touched; nothing without solids or smoke."""
        alive = state.positions[state.alive]
        if not self.simulator.solids or alive.shape[0] == 0:
            return {}
        return {gap_record(index): gap for index, gap in enumerate(surface_gaps(alive, self.simulator.solids, state.time))}

    def _velocities(self, state: ParticleState, p: torch.Tensor, problem: PositionProblem, first: bool) -> torch.Tensor:
        """The fitted particles' velocities u_t: the motion model's own where it has a velocity
        field of its own (the carrier's air, at the fitted positions), else the smoothed
        displacements of the fit (`smooth_velocities`; the simulator's on the first frame)."""
        if self.simulator.motion == "carrier":
            return self.simulator.velocity_at(state, p)
        if first:
            return problem.v_sim
        return smooth_velocities(p, (p - problem.p_prev) / self.simulator.config.dt, problem.velocity_radius)

    def _image_loss(self, index: int, iterations: int, chooser: random.Random) -> Callable[[Gaussians, int], torch.Tensor]:
        """One random view per iteration (probability ~ weight), coarse to fine over the iterations;
        symmetry pseudo-views at `priors.symmetry_long_side` when it is set and smaller."""
        views = self.rec.views
        weights = [v.weight for v in views]
        stages = self.rec.quality.fit.coarse_to_fine
        symmetry_side = self.rec.quality.priors.symmetry_long_side
        w = self.rec.quality.weights

        def loss(gaussians: Gaussians, k: int) -> torch.Tensor:
            view = chooser.choices(views, weights=weights)[0]
            fraction = stages[min(k * len(stages) // max(iterations, 1), len(stages) - 1)]
            long_side = max(view.camera.width, view.camera.height)
            if view.kind == "symmetry" and symmetry_side is not None and symmetry_side < long_side:
                fraction = symmetry_side / long_side
            size = (max(MIN_FIT_SIDE, round(view.camera.width * fraction)), max(MIN_FIT_SIDE, round(view.camera.height * fraction)))
            camera, target, background = view.at(index, size)
            image = render(gaussians, camera, background, depth=False).image
            return image_loss(image, target, background, w.l1, w.dssim)

        return loss

    def _input_psnr(self, index: int, means: torch.Tensor, appearance: Appearance) -> float:
        """PSNR of the fitted frame on the (first) input view at working resolution: a progress
        signal, not a score (scores come from views never fed in)."""
        image, target, _ = self._input_render(index, means, appearance)
        return psnr_db(image, target)

    def _input_fit(self, index: int, means: torch.Tensor, appearance: Appearance) -> dict[str, float]:
        """The frame's record of the input view: its PSNR and its yardstick (fluidcore.reconstruct.yardstick)."""
        image, target, background = self._input_render(index, means, appearance)
        view, scene = self.rec.views[0], self.rec.scene
        return input_fit(image, target, background, view.noise, view.camera, scene.source.center, scene.up)

    def _input_render(self, index: int, means: torch.Tensor, appearance: Appearance) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(render, footage, background) of frame `index` in the (first) input view at working resolution."""
        view = self.rec.views[0]
        camera, target, background = view.at(index, (view.camera.width, view.camera.height))
        with torch.no_grad():
            image = render(appearance.gaussians(means), camera, background, depth=False).image
        return image, target, background

    # -- checkpoints ---------------------------------------------------------------------
    def _resume(self, run: Run) -> SmokeState:
        """The state after the run's last written frame, or the stabilised source before frame 0."""
        done = run.frames()
        if done:
            return SmokeState.from_frame(run.read_frame(done[-1]), self.device)
        state = self.simulator.stabilize(self.simulator.new_state(), self.rec.stabilization_steps)
        return SmokeState.start(state, self.rec.channels)


def smooth_velocities(positions: torch.Tensor, raw: torch.Tensor, radius: float) -> torch.Tensor:
    """u_t as the kernel average of the finite differences (p_t - p_{t-1}) / dt around each particle.

    A finite difference divides the position fit's per-frame noise by dt, and that noise is
    fed back through Sim(p_t, u_t) into the next frame; averaging over the particles within
    `radius` (the radius the visual Gaussians are advected with) keeps the flow and drops
    particle-scale jitter no image resolves. (On the synthetic test scene the velocity error
    is the same with and without it: there the error comes from the density, not from jitter.)
    """
    return interpolate_velocity(positions, positions, raw, radius)

