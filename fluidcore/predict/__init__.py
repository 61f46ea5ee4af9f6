"""Prediction (the paper's Algorithm S2), re-simulation and counterfactuals: a run continued by
physics. Parallel to `fluidcore.reconstruct` (Algorithm S1).

    job             `run_predict`, `run_interact`, `run_resimulate`: the jobs the CLI, the worker
                    and the benchmark run; each writes a run folder continuing its parent
    rollout         `Rollout`: one simulator step per new frame, visual Gaussians carried along;
                    the source's inlet rate and the newborn smoke's look
    identification  `calibrate_buoyancy`: the buoyancy fitted to the reconstruction's last frames
    interventions   wind and ball parameters turned into a force field and a sphere (the one place)
    priors          the appearance height profile, and the seam for generative refinement

Torch loads on first use of a name (`fluidcore.lazy`).
"""

from fluidcore.lazy import lazy_exports

__getattr__ = lazy_exports(
    __name__,
    {
        "run_predict": "job",
        "run_interact": "job",
        "run_resimulate": "job",
        "Rollout": "rollout",
        "calibrate_buoyancy": "identification",
        "HeightProfile": "priors",
    },
)

__all__ = ["HeightProfile", "Rollout", "calibrate_buoyancy", "run_interact", "run_predict", "run_resimulate"]
