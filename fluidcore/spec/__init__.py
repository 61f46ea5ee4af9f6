"""The spec layer: every type a user supplies or a run records, torch-free and validated where it
is made, at the bottom of fluidcore (it imports nothing of fluidcore but `errors` and `names`).

The CLI, the API, the worker and the benchmarks build these objects at their edge and pass them
down as they are; the run record stores them as they are. Modules: `reconstruct` (what a
reconstruction spends and fits: `ReconstructConfig`, the quality presets), `simulation` (what the
simulator adds beyond the fit: the air, the plume's spreading), `scene` (what a simulator is built
from), `physics` (the physics constants and scene primitives a scene holds), `source_hint` (where
the user knows the source to be), `controls` (the interventions of a what-if), `jobs` (the
parameters of each job type, composed from the others) and `limits` (their bounds, as the browser
reads them at GET /v1/limits). Model (`scene`), state (`fluidcore.physics.ParticleState`) and
controls (`controls`) stay apart: `fluidcore.physics.build.build_simulator` joins them.
"""
