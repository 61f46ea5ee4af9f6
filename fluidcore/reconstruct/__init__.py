"""Reconstruction (the paper's Algorithm S1): physical particles and visual Gaussians per frame
from one video or a few calibrated ones.

    init      background, smoke masks, source and length scale estimated from the input videos
    views     fitting targets: input views and pseudo-views (plume symmetry; generated views later)
    physical  the position fit of one frame (L_sim + L_incomp + image loss through advection)
    visual    visual Gaussians: birth, advection, appearance fit with temporal regularisation
    loop      `prepare` and `Reconstructor`: the per-frame driver with checkpoint / resume
    presets   quality presets (preview, standard, paper)

`fluidcore.pipeline.run_reconstruct` wraps this for the CLI and the worker.
"""

from fluidcore.reconstruct.loop import Reconstruction, ReconstructionError, Reconstructor, prepare
from fluidcore.reconstruct.presets import PRESETS, Quality, get

__all__ = ["PRESETS", "Quality", "Reconstruction", "ReconstructionError", "Reconstructor", "get", "prepare"]
