"""The run folder: what a reconstruction (or a prediction built on one) leaves on disk.

A run is generic on purpose: cameras, a frame range, one particle state per frame and an
optional parent run. Reconstruction, prediction, interaction and re-simulation all write the
same format, so one renderer and one exporter serve them all.

Layout (format version 3)::

    RUN/
      manifest.json            everything but the arrays (see below); rewritten atomically
      background.npz           optional: one static background image per camera, key = camera name,
                               float32 (H, W, C) in [0, 1] at that camera's full resolution
      states/frame_000123.npz  the state after frame 123 (frame numbers are video frame indices)

`manifest.json` keys:

    format, format_version   "fluidnexus-run", 3 (1 and 2 are still read: `_migrate` brings them up to date on read)
    kind                     a `RunKind`: "reconstruct" | "predict" | "interact" | "resimulate"
    parent                   the run this one continues, as a path relative to this run folder (so a
                             chain of runs moves as one: another work dir, another worker), or null;
                             an absolute path (written before this rule) is still read
    created, versions        UTC ISO time; {"fluidnexus", "torch", "numpy", "python"}
    cameras                  {name: {fx, fy, cx, cy, width, height, world_to_camera (4x4), file_path}}
    input_views              camera names whose video was fed in
    fps, frame_range         frames per second; [start, stop) requested
    channels                 1 (grey smoke) or 3
    background_color         list of C floats: what empty space looks like from any camera
    scene                    {"box": {"lo", "hi"}, "up", "physics": PBFConfig fields, "source": Source fields,
                             "air": {"cells", "vorticity", "viscosity", "diffusivity"}, "motion"}
                             (`fluidcore.spec.scene.Scene`, read back typed by `RunRecord.scene`): the
                             one record of the physics the run simulates, its motion model and air
                             included (versions 1 and 2 kept the air in the settings: a reconstruction's
                             quality `air_cells`, `air_vorticity`, a continuation's settings alike;
                             "motion" and the air's "viscosity" and "diffusivity" came within version 3,
                             read as the paper model and 0 where absent)
    settings                 the settings that produced the run, one model per kind:
                             `ReconstructSettings` or `ContinuationSettings` (every field written;
                             version 1 left out what a feature added later, read as its default;
                             versions 1 and 2 kept a reconstruction's quality flat, and its
                             visual settings apart from it)
    frames                   [{"t", "file", "losses": {...}, "seconds"}] in order of completion
    complete                 true once every frame of frame_range is written

A state file (`numpy.savez`, uncompressed, float32 unless noted) holds:

    positions (P, 3), velocities (P, 3)    physical particles, WORLD units and units/s; P = capacity
    alive (P,) bool                        which slots hold a particle
    time () float64                        simulator time in seconds
    gauss_means (G, 3), gauss_log_scales (G, 3), gauss_quats (G, 4) (w, x, y, z),
    gauss_opacity_logits (G,), gauss_colors (G, C)      the visual Gaussians, world units
    extra_NAME                             anything else a writer needs to resume exactly
                                           (e.g. a random generator's state)
    air_version () int, air_origin (3,) float64, air_spacing () float64,
    air_x (nx+1, ny, nz), air_y (nx, ny+1, nz), air_z (nx, ny, nz+1)
                                           only in runs that simulate the air (scene air `cells`
                                           > 0): the air's face velocities on its MAC grid (units/s),
                                           the grid's lowest corner and cell size (`SavedAir`,
                                           air_version 1); a file without them holds still air

Every reader goes through `RunRecord` (a run folder: `Run`, a subclass; a manifest fetched from
storage: `RunRecord.from_bytes`), and the file names above are spelled only in `layout`
(`MANIFEST`, `state_file`), so the API reads a run in storage the way a job reads it on disk.

The package, bottom up: `layout` (the files' names, the format, `RunKind`, `RunError`), `frames`
(a state file: `FrameState`, `SavedAir`), `records` (the manifest's typed records and settings),
`migrate` (older versions brought up to date on read), `folder` (`RunRecord`, `Run`). This face
exports what callers use.

Resuming: a writer opens an existing folder with `Run.create(...)`; if the folder holds a run
with the same kind, cameras and settings, the completed frames are kept and `next_frame()` says
where to go on. A folder holding a different run is refused rather than overwritten.
"""

from fluidcore.runs.folder import Run, RunRecord, camera_from_json, camera_to_json, versions
from fluidcore.runs.frames import AIR_FIELDS, AIR_VERSION, GAUSSIAN_FIELDS, FrameState, SavedAir
from fluidcore.runs.layout import (BACKGROUND, FORMAT, FORMAT_VERSION, MANIFEST, READABLE_VERSIONS, REFINED_RUN,
                                   STATES_DIR, RunError, RunKind, state_file)
from fluidcore.runs.records import (AppearanceProfile, BackgroundRecord, CaptureRecord, ContinuationSettings,
                                    IdentificationPrior, IdentifiedRecord, PhysicsRecord, ReconstructSettings,
                                    Settings, SourceEstimateRecord, SymmetryRecord, ViewRecord, settings_model)

__all__ = [
    "AIR_FIELDS", "AIR_VERSION", "BACKGROUND", "FORMAT", "FORMAT_VERSION", "GAUSSIAN_FIELDS", "MANIFEST",
    "READABLE_VERSIONS", "REFINED_RUN", "STATES_DIR", "AppearanceProfile", "BackgroundRecord", "CaptureRecord",
    "ContinuationSettings", "FrameState", "IdentificationPrior", "IdentifiedRecord", "PhysicsRecord",
    "ReconstructSettings", "Run", "RunError", "RunKind", "RunRecord", "SavedAir", "Settings", "SourceEstimateRecord",
    "SymmetryRecord", "ViewRecord", "camera_from_json", "camera_to_json", "settings_model", "state_file", "versions",
]
