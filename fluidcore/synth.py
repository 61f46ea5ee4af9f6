"""A synthetic smoke scene with known ground truth, so anyone can try the whole pipeline.

A small plume is simulated with `fluidcore.physics` (a source at the bottom of a box, the
ScalarFlow constants) and rendered with `fluidcore.render` from cameras spread around it,
dark smoke on a white background like the ScalarFlow benchmark. The folder it writes is an
ordinary input scene plus the truth:

    DIR/transforms.json         nerfstudio cameras (file_path = videos/NAME.mp4) and PINF voxel box
    DIR/videos/NAME.mp4         one H.264 video per camera
    DIR/truth/frame_000000.npz  positions, velocities (world units) of the live particles per frame
    DIR/synth.json              the spec (SynthSpec) and the source, for reference

Rendering and reconstruction share one renderer, so the scene tests the optimisation and the
physics prior, not robustness to a different image formation model.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch

from fluidcore.cameras import Camera, look_at, write_transforms
from fluidcore.errors import InputError
from fluidcore.physics import PRESETS, Box, PBFConfig, Source
from fluidcore.physics.build import build_simulator
from fluidcore.render import Gaussians, render
from fluidcore.spec.scene import Scene

SIM_BOX_HEIGHT = 75.0  # the box's height in the preset's units (2 per kernel radius: the rule of fluidcore.reconstruct.scene_physics)


class SynthError(InputError):
    """An invalid synthetic-scene spec; the message names the field."""


@dataclass(frozen=True)
class SynthSpec:
    """What to generate. Lengths in world units; the box is centred on the y (up) axis."""

    frames: int = 8
    width: int = 48
    height: int = 64
    views: int = 5
    box_size: tuple[float, float, float] = (0.5, 0.8, 0.5)
    source_radius: float = 0.05
    particles_per_step: int = 12
    camera_distance: float = 1.6
    camera_height: float = 0.3  # above the box's mid-height, looking at it from slightly above
    smoke_color: float = 0.25
    smoke_opacity: float = 0.2
    fps: float = 30.0
    seed: int = 0
    buoyancy_scale: float = 1.0  # multiple of the ScalarFlow preset's buoyancy (scenes with other physics)

    def __post_init__(self) -> None:
        for name in ("frames", "width", "height", "views", "particles_per_step"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise SynthError(f"{name} must be a positive integer, got {value!r}")
        for name in ("source_radius", "camera_distance", "fps", "buoyancy_scale"):
            if not getattr(self, name) > 0:
                raise SynthError(f"{name} must be positive, got {getattr(self, name)}")
        for name in ("width", "height"):  # H.264 yuv420p pads an odd side, and the video would not fit its camera
            if getattr(self, name) % 2:
                raise SynthError(f"{name} must be even (the videos are H.264 yuv420p), got {getattr(self, name)}")
        if min(self.box_size) <= 0:
            raise SynthError(f"box_size must be positive, got {self.box_size}")
        if not (0 <= self.smoke_color <= 1 and 0 < self.smoke_opacity < 1):
            raise SynthError("smoke_color must be in [0, 1] and smoke_opacity in (0, 1)")

    def box(self) -> Box:
        sx, sy, sz = self.box_size
        return Box((-sx / 2, 0.0, -sz / 2), (sx / 2, sy, sz / 2))

    def config(self) -> PBFConfig:
        scale = SIM_BOX_HEIGHT / self.box_size[1]
        base = PRESETS["scalarflow"]
        return replace(base, alpha=base.alpha * self.buoyancy_scale, length_scale=scale, h=2.0 / scale, dt=1.0 / self.fps)

    def source(self) -> Source:
        config = self.config()
        velocity = (0.0, config.terminal_speed, 0.0)
        return Source((0.0, 1.5 * self.source_radius, 0.0), self.source_radius, self.particles_per_step, velocity, self.seed)

    def scene(self) -> Scene:
        """The plume's scene: y up, still air."""
        box = self.box()
        return Scene(box.lo, box.hi, (0.0, 1.0, 0.0), self.config(), self.source())

    def cameras(self) -> dict[str, Camera]:
        """`views` cameras on a half circle (-90..+90 degrees) around the plume, view_00..."""
        mid = np.array([0.0, 0.45 * self.box_size[1], 0.0])
        f = 1.2 * self.height * self.camera_distance / self.box_size[1]  # the box's height fills ~80% of the frame
        like = Camera("like", f, f, self.width / 2, self.height / 2, self.width, self.height, np.eye(4))
        cameras = {}
        for k in range(self.views):
            angle = math.pi * (k / (self.views - 1) - 0.5) if self.views > 1 else 0.0
            eye = mid + np.array([self.camera_distance * math.sin(angle), self.camera_height, self.camera_distance * math.cos(angle)])
            name = f"view_{k:02d}"
            cameras[name] = replace(look_at(eye, mid, (0.0, 1.0, 0.0), like, name), file_path=f"videos/{name}.mp4")
        return cameras


@dataclass
class SynthScene:
    spec: SynthSpec
    cameras: dict[str, Camera]
    videos: dict[str, np.ndarray]  # uint8 (T, H, W, 3) per camera, before encoding
    positions: list[np.ndarray]  # per frame, live particles (N_t, 3)
    velocities: list[np.ndarray]


def particle_gaussians(positions: torch.Tensor, spec: SynthSpec) -> Gaussians:
    """How the ground truth looks: one round grey Gaussian per physical particle."""
    n = len(positions)
    h = spec.config().h
    return Gaussians(
        positions,
        torch.full((n, 3), math.log(0.6 * h)),
        torch.tensor([1.0, 0.0, 0.0, 0.0]).repeat(n, 1),
        torch.full((n,), math.log(spec.smoke_opacity / (1 - spec.smoke_opacity))),
        torch.full((n, 1), spec.smoke_color),
    )


def generate(spec: SynthSpec) -> SynthScene:
    """Simulate and render the scene in memory (the 20 stabilisation steps come first)."""
    simulator = build_simulator(spec.scene())
    state = simulator.stabilize(simulator.new_state(), 20)
    cameras = spec.cameras()
    frames: dict[str, list[np.ndarray]] = {name: [] for name in cameras}
    positions, velocities = [], []
    for t in range(spec.frames):
        if t > 0:
            state, _ = simulator.step(state)
        alive = state.alive
        positions.append(state.positions[alive].numpy().copy())
        velocities.append(state.velocities[alive].numpy().copy())
        gaussians = particle_gaussians(state.positions[alive], spec)
        with torch.no_grad():
            for name, camera in cameras.items():
                image = render(gaussians, camera, 1.0, depth=False).image
                frames[name].append((image.clamp(0, 1).expand(-1, -1, 3).numpy() * 255 + 0.5).astype(np.uint8))
    videos = {name: np.stack(f) for name, f in frames.items()}
    return SynthScene(spec, cameras, videos, positions, velocities)


def write(scene: SynthScene, out_dir: str | Path) -> Path:
    """Write the scene folder (see the module docstring); returns the transforms.json path."""
    from fluidcore.video import write_mp4

    out = Path(out_dir)
    spec = scene.spec
    (out / "videos").mkdir(parents=True, exist_ok=True)
    (out / "truth").mkdir(exist_ok=True)
    for name, video in scene.videos.items():
        write_mp4(out / "videos" / f"{name}.mp4", video, fps=spec.fps)
    for t, (p, v) in enumerate(zip(scene.positions, scene.velocities, strict=True)):
        np.savez(out / "truth" / f"frame_{t:06d}.npz", positions=p, velocities=v)
    box = spec.box()
    path = write_transforms(
        out / "transforms.json",
        scene.cameras,
        fps=spec.fps,
        # PINF voxel box: world = V' @ (voxel_scale * s) + t, V' = voxel_matrix rotation with columns 0 and 2 swapped
        voxel_scale=list(spec.box_size),
        voxel_matrix=[[0, 0, 1, box.lo[0]], [0, 1, 0, box.lo[1]], [1, 0, 0, box.lo[2]], [0, 0, 0, 1]],
    )
    (out / "synth.json").write_text(json.dumps({"spec": asdict(spec), "source": asdict(spec.source())}, indent=1))
    return path
