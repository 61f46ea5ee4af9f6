"""Reconstruction (the paper's Algorithm S1): physical particles and visual Gaussians per frame
from one video or a few calibrated ones.

    job       `run_reconstruct`: the job the CLI, the worker and the benchmark run
    pipeline  one reconstruction from decoded footage: read_inputs, novel views, prepare, fit
    images    the input videos as images: resizing, background and noise, the one smoke mask
    rays      the input cameras' ray geometry
    source_estimate  the source's place estimated from the input videos
    identify  the search for the scene's physics in the input view
    scene_physics  what a reconstruction simulates with, by physics mode
    views     fitting targets: input views, pseudo-views (plume symmetry) and generated views
    physical  the position fit of one frame (L_sim + L_incomp + image loss through advection)
    visual    visual Gaussians: birth, advection, appearance fit with temporal regularisation
    loop      `read_inputs`, `prepare` and `Reconstructor`: the per-frame driver with checkpoint / resume

The quality presets and the config a reconstruction runs with are the spec layer's
(fluidcore.spec.reconstruct). Everything here (torch) loads on first use (`fluidcore.lazy`).
"""

from fluidcore.lazy import lazy_exports

__getattr__ = lazy_exports(
    __name__,
    {
        "Reconstruction": "loop",
        "ReconstructionError": "loop",
        "Reconstructor": "loop",
        "prepare": "loop",
        "read_inputs": "loop",
        "run_reconstruct": "job",
    },
)

__all__ = [
    "Reconstruction", "ReconstructionError", "Reconstructor", "prepare", "read_inputs", "run_reconstruct",
]
