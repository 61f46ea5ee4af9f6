"""Between a run's saved frame (fluidcore.runs.FrameState, numpy) and the live tensors that
reconstruction and prediction carry from frame to frame: both resume from and write the same
files, so one conversion keeps the two readers of a run folder in step."""

from __future__ import annotations

import numpy as np
import torch

from fluidcore.physics import ParticleState
from fluidcore.reconstruct.visual import Appearance
from fluidcore.runs import FrameState


def load_frame_state(saved: FrameState, device: str | torch.device) -> tuple[ParticleState, torch.Tensor, Appearance]:
    """The particle state, visual Gaussian centres and appearance of `saved`, on `device`.
    `saved.extra` must hold the simulator's `step` (callers check it when they can name the run)."""
    tensor = lambda a: torch.from_numpy(np.ascontiguousarray(a)).to(device)  # noqa: E731
    state = ParticleState(
        tensor(saved.positions), tensor(saved.velocities), tensor(saved.alive), saved.time, int(saved.extra["step"])
    )
    g = saved.gaussians
    appearance = Appearance(tensor(g["log_scales"]), tensor(g["quats"]), tensor(g["opacity_logits"]), tensor(g["colors"]))
    return state, tensor(g["means"]), appearance


def to_frame_state(state: ParticleState, means: torch.Tensor, appearance: Appearance) -> FrameState:
    """The numpy FrameState a run stores for one frame (the inverse of `load_frame_state`)."""
    numpy = lambda x: x.detach().cpu().numpy()  # noqa: E731
    return FrameState(
        positions=numpy(state.positions),
        velocities=numpy(state.velocities),
        alive=numpy(state.alive),
        time=state.time,
        gaussians={
            "means": numpy(means),
            "log_scales": numpy(appearance.log_scales),
            "quats": numpy(appearance.quats),
            "opacity_logits": numpy(appearance.opacity_logits),
            "colors": numpy(appearance.colors),
        },
        extra={"step": np.asarray(state.step, dtype=np.int64)},
    )
