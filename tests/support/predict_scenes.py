"""A small rising plume written as a run folder, for the prediction and interaction tests.

The plume is simulated with the same physics the predictions use (the synthetic scene's box,
source and ScalarFlow constants) and stored the way a reconstruction stores its frames: one
visual Gaussian per physical particle. A run that is pure physics has a known re-simulation
(itself), and being small it steps in milliseconds.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import torch

from fluidcore.physics import ParticleState, Simulator
from fluidcore.physics.build import build_simulator
from fluidcore.runs import FrameState, PhysicsRecord, ReconstructSettings, Run, RunKind
from fluidcore.smoke import Appearance, SmokeState
from fluidcore.spec.reconstruct import get
from fluidcore.spec.scene import Air, Scene
from fluidcore.spec.solids import SolidBall
from fluidcore.synth import SynthSpec, particle_gaussians

SPEC = SynthSpec(width=24, height=32, views=2, particles_per_step=16)


def scene_of(spec: SynthSpec = SPEC, air: Air = Air(), motion: str = "paper") -> Scene:
    """The plume's scene; with simulated `air` it simulates the air, as a reconstruction does,
    and with the carrier that air carries the smoke."""
    return replace(spec.scene(), air=air, motion=motion)


def simulator_of(spec: SynthSpec = SPEC, air: Air = Air(), motion: str = "paper") -> Simulator:
    return build_simulator(scene_of(spec, air, motion))


def frame_state(state: ParticleState, spec: SynthSpec = SPEC) -> FrameState:
    """The state as a reconstruction would store it: one visual Gaussian per live particle."""
    g = particle_gaussians(state.positions[state.alive], spec)
    appearance = Appearance(g.log_scales, g.quats, g.opacity_logits, g.colors)
    return SmokeState(state.clone(), g.means.clone(), appearance).to_frame()


def plume_run(path: Path, frames: int = 4, warmup: int = 30, spec: SynthSpec = SPEC,
              quality: dict | None = None, physics: str = "scalarflow", solids: tuple[SolidBall, ...] = ()) -> Path:
    """A 'reconstruct' run of `frames` frames of a plume that has risen for `warmup` steps
    (`quality`: overrides of the preview quality its settings record, whose Gaussians are one per
    particle with fixed opacity unless they say otherwise; its motion the paper model's unless they
    say "motion": "carrier"; with `air_cells` there the plume is simulated with the air, and every
    frame saves it; `physics`: the physics mode it records, a preset's unless "auto"; `solids`: the
    static balls in its scene, in the plume's way from its first step)."""
    config = get("preview").with_overrides(**{"per_physical": 1, "opacity_concentration": False, "motion": "paper",
                                              **(quality or {})})
    simulation = config.simulation
    scene = replace(scene_of(spec, Air(simulation.cells, simulation.air_vorticity), simulation.motion),  # the air its quality asks for
                    solids=solids)
    simulator = build_simulator(scene)
    state = simulator.stabilize(simulator.new_state(), 20)
    for _ in range(warmup):
        state, _ = simulator.step(state)
    run = Run.create(
        path,
        kind=RunKind.RECONSTRUCT,
        cameras=spec.cameras(),
        input_views=["view_00"],
        frame_range=(0, frames),
        fps=spec.fps,
        channels=1,
        background_color=[1.0],
        scene=scene,
        settings=ReconstructSettings(quality=config, physics=PhysicsRecord(mode=physics)),
    )
    for t in range(frames):
        if t > 0:
            state, _ = simulator.step(state)
        run.write_frame(t, frame_state(state, spec), {}, 0.0)
    return path


def live(saved: FrameState) -> torch.Tensor:
    """Positions of the live physical particles of a stored frame."""
    return torch.from_numpy(saved.positions[saved.alive])


def horizontal_distance(points: torch.Tensor, axis_point: tuple[float, float, float]) -> torch.Tensor:
    """Distance of each point from the vertical line through `axis_point`."""
    offset = points - points.new_tensor(axis_point)
    return torch.sqrt(offset[:, 0] ** 2 + offset[:, 2] ** 2)

