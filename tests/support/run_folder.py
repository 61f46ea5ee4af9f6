"""A small run folder for the tests of the run format and of what reads it: one camera, a scene,
a run created with overridable fields, and a random frame state."""

from __future__ import annotations

import numpy as np

from fluidcore.cameras import Camera
from fluidcore.physics import PBFConfig, Source
from fluidcore.runs import FrameState, ReconstructSettings, Run
from fluidcore.spec.reconstruct import get
from fluidcore.spec.scene import Scene


def _camera(name: str = "cam") -> Camera:
    pose = np.eye(4)
    pose[2, 3] = 2.0
    return Camera(name, 50.0, 50.0, 16.0, 12.0, 32, 24, pose)


def _scene() -> Scene:
    return Scene(
        box_lo=(-1.0, 0.0, -1.0),
        box_hi=(1.0, 2.0, 1.0),
        up=(0.0, 1.0, 0.0),
        physics=PBFConfig(rho0=2.0, alpha=-3.0, h=0.1, length_scale=37.5),
        source=Source(center=(0.0, 0.1, 0.0), radius=0.1, rate=3, velocity=(0.0, 0.1, 0.0), seed=1),
    )


def _create(path, **changes):
    args = dict(
        kind="reconstruct",
        cameras={"cam": _camera()},
        input_views=["cam"],
        frame_range=(0, 3),
        fps=30.0,
        channels=1,
        background_color=[1.0],
        scene=_scene(),
        settings=ReconstructSettings(quality=get("preview").with_overrides(position_iterations=5)),
    )
    args.update(changes)
    return Run.create(path, **args)


def _state(seed: int, n: int = 6, g: int = 4) -> FrameState:
    rng = np.random.default_rng(seed)
    return FrameState(
        positions=rng.normal(size=(n, 3)).astype(np.float32),
        velocities=rng.normal(size=(n, 3)).astype(np.float32),
        alive=rng.random(n) > 0.3,
        time=0.1 * seed,
        gaussians={
            "means": rng.normal(size=(g, 3)),
            "log_scales": rng.normal(size=(g, 3)),
            "quats": rng.normal(size=(g, 4)),
            "opacity_logits": rng.normal(size=g),
            "colors": rng.random((g, 1)),
        },
        extra={"rng": np.arange(5, dtype=np.uint8)},
    )
