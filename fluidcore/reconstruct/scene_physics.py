"""What a reconstruction simulates with: the scene's physics, chosen by the physics mode.

The kernel radius is a resolution choice in the scene's own units; "auto" identifies the
buoyancy, source and plume age from the input view (`fluidcore.reconstruct.identify`), a preset
name keeps that preset's buoyancy in this scene's units. Either way the source's inlet is filled
at rest density (`inflow_rate_speed` says at which speed). `scene_prior` is the one check of
the physics mode.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch

from fluidcore.errors import InputError
from fluidcore.jobs import StepProgress
from fluidcore.physics import PRESETS, Box
from fluidcore.reconstruct.identify import Observation, ScenePrior, identify, inlet_rate, with_buoyancy
from fluidcore.reconstruct.views import ViewTarget
from fluidcore.runs import PhysicsRecord
from fluidcore.spec.scene import Air, Scene, SourcePlace
from fluidcore.spec.solids import SolidBall
from fluidcore.spec.simulation import DEFAULT_MOTION, PHYSICS_MODES, MotionModel
from fluidcore.spec.source_hint import SourceKept

KERNEL_RADII_PER_BOX = 37.5  # resolution: the scene box's height spans this many kernel radii
KERNEL_RADIUS_SIM = 2.0  # h in the presets' simulation units (the release: 0.02 world = 2 units), so
# length_scale = 2 / h converts a preset's alpha; an identified buoyancy is in world units already
PRESET_STABILIZATION_SECONDS = 20 / 30  # the paper's N_stable of 20 steps at 30 fps, used when the physics is not identified
# The quality's particle budget (`FitConfig.particles_per_frame`) is per frame of a 30 fps clip: the
# inflow's cap is that many particles per 1/30 s at any frame rate, so a 25 or 60 fps clip of the
# same smoke seeds the same particles per second (and the fit the same particles per second of video).
BUDGET_FPS = 30.0


def inflow_rate_speed(terminal_speed: float, rise_speed: float) -> float:
    """The speed at which the reconstruction's inlet is filled (`inlet_rate`): the observed smoke's
    rise speed where it is faster than the inflow's terminal speed, so the source seeds the smoke
    volume the video shows leaving it (its area times that speed) although the identified
    buoyancy sits on its floor, half the drag times that speed.

    Measured (docs/bench_generalise.md, "The inflow rate at the observed rise speed"): ScalarFlow's
    inlet went from 6 to 12 particles a step and its novel views and future gained on the
    mean of seeds 0-2; D and F were at the preview's budget at the terminal speed already and
    did not change. The identification's rollouts keep the terminal speed's rate: with the
    doubled rate there too, ScalarFlow's plume age fell from 12 to 4 steps and both seeds tried
    lost their gain (the misfit reads where smoke is, which more particles reach sooner, not
    how much of it there is).
    """
    if not math.isfinite(rise_speed):
        return terminal_speed
    return max(terminal_speed, rise_speed)


def frame_budget(particles_per_frame: int, fps: float) -> int:
    """The inflow's cap per frame of a clip at `fps`: the quality's budget per 1/BUDGET_FPS s."""
    return max(1, round(particles_per_frame * BUDGET_FPS / fps))


class PhysicsChoiceError(InputError):
    """An unknown --physics mode; the message names the choices."""


@dataclass(frozen=True)
class ScenePhysics:
    """The physics a reconstruction (and every prediction from it) simulates with."""

    scene: Scene
    stabilization_steps: int  # steps the source emits before frame 0
    record: PhysicsRecord  # for the manifest: mode, prior preset, identified values


def check_mode(mode: str) -> str:
    if mode not in PHYSICS_MODES:
        raise PhysicsChoiceError(f"physics must be one of {', '.join(PHYSICS_MODES)}, got {mode!r}")
    return mode


def scene_prior(mode: str, box: Box, up: np.ndarray, fps: float, place: SourcePlace, air: Air, seed: int,
                motion: MotionModel = DEFAULT_MOTION, solids: tuple[SolidBall, ...] = ()) -> ScenePrior:
    """The scene of a reconstruction before its physics is chosen: the prior preset of the
    physics `mode` in this scene's units, the source at its estimated `place` (at least half a
    kernel radius wide), moved by the `motion` model in `air` around the static `solids`.

    The kernel radius is a resolution choice in the scene's own units (its box's height over
    KERNEL_RADII_PER_BOX), and the preset's buoyancy is converted with it (`KERNEL_RADIUS_SIM`).
    """
    preset = PHYSICS_MODES[check_mode(mode)]
    h = float(np.abs(np.subtract(box.hi, box.lo)) @ np.abs(up)) / KERNEL_RADII_PER_BOX
    gravity = tuple(float(c) for c in -9.8 * up)
    physics = replace(PRESETS[preset], length_scale=KERNEL_RADIUS_SIM / h, h=h, gravity=gravity, dt=1.0 / fps)
    return ScenePrior(box, tuple(float(c) for c in up), air, mode, physics,
                      SourcePlace(place.center, max(place.radius, 0.5 * h)), seed, motion, solids)


def scene_physics(
    view: ViewTarget,
    prior: ScenePrior,
    *,
    budget: int,
    entrainment: bool,
    keep_source: SourceKept = "nothing",
    device: torch.device | str = "cpu",
    on_evaluation: StepProgress | None = None,
) -> ScenePhysics:
    """Physics for a scene seen in the input `view` (its camera, working-resolution frames,
    background and noise), starting from `prior` (`scene_prior`).

    The buoyancy, source and plume age come from `identify` when the prior's mode is "auto", in world
    units, so no length scale of another dataset enters them; a preset name keeps that preset's
    buoyancy (the paper's setting for its datasets). `entrainment`: whether the
    identification also searches the plume's spreading rate (`identify.SPREADING_RANGE`) or keeps the paper's
    column. `keep_source`: what of the prior's source the user gave and the identification keeps;
    `on_evaluation`: `identify`'s progress.
    The inflow leaves at the buoyancy's terminal speed; the source seeds what its inlet
    carries at rest density (`inlet_rate`, capped by `budget` per 1/30 s: `frame_budget`) at the faster of that speed and
    the rise speed of the observed smoke (`inflow_rate_speed`).
    """
    from fluidcore.reconstruct.images import smoke_mask

    up, h, place = np.asarray(prior.up), prior.physics.h, prior.place
    budget = frame_budget(budget, 1.0 / prior.physics.dt)
    found = None
    observed_rise = 0.0  # a preset's inlet is filled at its own terminal speed
    if prior.mode == "auto":
        camera = view.camera
        center = np.asarray(place.center)
        masks = smoke_mask(view.frames, view.background, view.noise)
        depth = float(camera.world_to_camera[2, :3] @ center + camera.world_to_camera[2, 3])
        cell = max(1, round(camera.fx * h / max(depth, 1e-9)))
        observation = Observation.from_masks(camera, masks, cell, center, up)
        found = identify(observation, prior, budget, device, entrainment, keep_source, on_evaluation)
        config = replace(with_buoyancy(prior.physics, found.buoyancy, up), entrainment=found.entrainment)
        place = SourcePlace(tuple(found.source_center), found.source_radius)
        steps = found.age + 1  # identified frame t = after age + t + 1 steps
        observed_rise = found.rise_speed
    else:
        config, steps = prior.physics, prior.physics.frames_in(PRESET_STABILIZATION_SECONDS)
    buoyancy = float(np.dot(config.body_acceleration, up))
    # the carrier's inflow speed is identified with the rest; the paper model's is its terminal speed
    speed = found.inflow_speed if found is not None and prior.motion == "carrier" else config.terminal_speed
    carried = inflow_rate_speed(speed, observed_rise)
    scene = prior.scene(config, place, inlet_rate(place.radius, carried, config, budget), speed * up,
                        None if found is None else found.diffusivity)
    record = PhysicsRecord(mode=prior.mode, prior_preset=prior.preset, kernel_radius=h, identified=found, buoyancy=buoyancy,
                           inflow_speed=speed, inflow_rate=scene.source.rate, inflow_rate_speed=carried, drag=config.drag,
                           rho0=config.rho0, entrainment=config.entrainment, stabilization_steps=steps)
    return ScenePhysics(scene, steps, record)
