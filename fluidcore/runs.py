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
                             "air": {"cells", "vorticity"}} (`fluidcore.spec.scene.Scene`, read back
                             typed by `RunRecord.scene`): the one record of the air the run simulates
                             (versions 1 and 2 kept it in the settings: a reconstruction's quality
                             `air_cells`, `air_vorticity`, a continuation's settings alike)
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
storage: `RunRecord.from_bytes`), and the file names above are named only here (`MANIFEST`,
`state_file`), so the API reads a run in storage the way a job reads it on disk.

Resuming: a writer opens an existing folder with `Run.create(...)`; if the folder holds a run
with the same kind, cameras and settings, the completed frames are kept and `next_frame()` says
where to go on. A folder holding a different run is refused rather than overwritten.
"""

from __future__ import annotations

import enum
import io
import json
import os
import platform
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, ValidationError

from fluidcore.errors import InputError
from fluidcore.files import atomic_output
from fluidcore.spec.controls import BallParams, WindParams
from fluidcore.spec.reconstruct import ReconstructConfig, VisualSettings, quality_fields
from fluidcore.spec.scene import Scene, SceneError, SourcePlace, UpAxis, UpFound
from fluidcore.spec.source_hint import SourceHint

FORMAT = "fluidnexus-run"
FORMAT_VERSION = 3
READABLE_VERSIONS = (1, 2, 3)
MANIFEST = "manifest.json"
BACKGROUND = "background.npz"
STATES_DIR = "states"
REFINED_RUN = "refined"  # sub-run of a prediction: the reconstruction on its video-model-refined frames
GAUSSIAN_FIELDS = ("means", "log_scales", "quats", "opacity_logits", "colors")
AIR_FIELDS = ("air_x", "air_y", "air_z")
AIR_VERSION = 1  # the layout of the air arrays in a state file (module docstring); a reader refuses a later one


class RunError(InputError):
    """A run folder that is missing, damaged, or holds a different run than expected."""


class RunKind(enum.StrEnum):
    """What wrote a run. The service's job types (`service.job_types.JobType`) are these kinds:
    each job writes the run of its own kind."""

    RECONSTRUCT = "reconstruct"
    PREDICT = "predict"
    INTERACT = "interact"
    RESIMULATE = "resimulate"


_RECORD = ConfigDict(extra="forbid", frozen=True)


class ViewRecord(BaseModel):
    """One view a reconstruction fitted: its camera, kind (input, symmetry, generated) and weight."""

    model_config = _RECORD
    camera: str
    kind: str
    weight: float


class SourceEstimateRecord(BaseModel):
    """How the source's place was found from the input videos (`fluidcore.reconstruct.source_estimate.
    estimate_source`): the depth cue, and for one view the stretch of its ray inside the box
    where the centre could lie as well (world units), which the source hint can then pin."""

    model_config = _RECORD
    depth_cue: str  # "triangulated", "generated views", "floor", "box axis" or "given"
    depth_range: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None  # nearest, farthest
    pixels: dict[str, tuple[float, float, float]] = {}  # input camera -> (u, v, radius) in pixels
    generated: dict[str, float] = {}  # generated view -> its ray's weight in the triangulation (the input view's is 1)


class BackgroundRecord(BaseModel):
    """How one input view's background was found (`fluidcore.reconstruct.images`): from a plate
    (frames of the clip without smoke) or from the smoke's frames themselves, and then how much
    of the view the smoke covered in every frame, filled from its surroundings."""

    model_config = _RECORD
    plate_frames: tuple[int, int] | None = None  # [start, end) of the plate; None: estimated from the clip
    textured: bool  # an image was kept (False: one colour everywhere)
    covered: float = 0.0  # fraction of the view's pixels the smoke never left (filled from around them)


class CaptureRecord(BaseModel):
    """What a reconstruction read off the capture beyond its frames: which way the world's up
    points and how that was found (`fluidcore.cameras.world_up`), and the frame rate the camera
    file states, if any, beside the videos' own (the manifest's `fps`, which the run uses)."""

    model_config = _RECORD
    up_axis: UpAxis  # the scene's `up` as an axis name
    up_found: UpFound
    declared_fps: float | None = None  # the camera file's `fps`; None: it states none


class IdentificationPrior(BaseModel):
    """What the identification started from (the physics preset in the scene's units) and what
    it kept of it."""

    model_config = _RECORD
    preset: str
    buoyancy: float
    drag: float
    rho0: float
    held_from_prior: tuple[str, ...]
    inflow_speed: str  # how the inflow's speed follows from the rest ("buoyancy / drag")
    budget: int  # the particles per step the inlet may seed at most
    source: SourcePlace  # where the identification started the source from (world units)


class IdentifiedRecord(BaseModel):
    """The physics identified from the input view and how it was found
    (`fluidcore.reconstruct.identify.identify`)."""

    model_config = _RECORD
    buoyancy: float  # world units / s^2 along up
    inflow_speed: float  # world units / s along up
    rate: int  # particles per step
    age: int  # steps the source had emitted before frame 0
    misfit: float  # mean 1 - IoU over the frames, at the optimum
    rise_speed: float  # observed speed of the plume's top (world units / s), what the floor uses
    floor: float  # the buoyancy floor
    evaluations: int
    source_center: tuple[float, float, float]  # world
    source_radius: float
    prior: IdentificationPrior
    entrainment: float = 0.0  # the plume's spreading rate db/dz (fluidcore.physics.entrainment); before it: none
    # Per parameter the search varied, the least and greatest value its candidates tried (`_Search.tried`:
    # buoyancy, source_radius, source_height along up, entrainment, age in frames); None before it
    tried: dict[str, tuple[float, float]] | None = None
    # Per parameter searched, the bounds of the search (`identify.search_space`, and the plume's age in frames); None before them
    bounds: dict[str, tuple[float, float]] | None = None


class PhysicsRecord(BaseModel):
    """How a reconstruction's physics was chosen (`fluidcore.reconstruct.scene_physics.scene_physics`):
    the mode, the prior preset and, for "auto", what was identified; then what the scene simulates
    with. Only the mode is known of a run written before --physics (it ran the preset); a field a
    later version added is None in a run written before it."""

    model_config = _RECORD
    mode: str  # "auto" (identified from the video) or the preset's name (fluidcore.spec.simulation.PHYSICS_MODES)
    prior_preset: str | None = None
    kernel_radius: float | None = None
    identified: IdentifiedRecord | None = None  # None: a preset's physics
    buoyancy: float | None = None
    inflow_speed: float | None = None
    inflow_rate: int | None = None
    inflow_rate_speed: float | None = None
    drag: float | None = None
    rho0: float | None = None
    entrainment: float | None = None
    stabilization_steps: int | None = None


class SymmetryRecord(BaseModel):
    """How much the symmetry prior was trusted (fluidcore.reconstruct.views.symmetry_support)."""

    model_config = _RECORD
    mirror_agreement: float  # of the input view's smoke with its mirror image about the source's axis
    weight: float  # the pseudo-views' total loss weight


class ReconstructSettings(BaseModel):
    """The settings of a reconstruction (kind "reconstruct"). What a continuation needs of its
    visual layer is the quality's (`ReconstructConfig.visual_settings`)."""

    model_config = _RECORD
    quality: ReconstructConfig
    physics: PhysicsRecord = PhysicsRecord(mode="scalarflow")  # before --physics: the preset
    symmetry: SymmetryRecord | None = None  # None: no symmetry prior (several input views, or none asked for)
    source_hint: SourceHint | None = None  # the source the reconstruction was given, as given
    source_estimate: SourceEstimateRecord | None = None  # None: the user gave the whole source, or an older run
    views: tuple[ViewRecord, ...] = ()
    backgrounds: dict[str, BackgroundRecord] = {}  # input camera -> how its background was found; {}: an older run
    capture: CaptureRecord | None = None  # None: an older run, or a refinement (its parent's scene)


class AppearanceProfile(BaseModel):
    """The mean appearance of the smoke by height that a prediction holds its smoke to
    (`fluidcore.predict.priors.HeightProfile` adds how it is observed and held), recorded so that
    a chained prediction holds it alike."""

    model_config = _RECORD
    edges: tuple[float, ...]  # band boundaries along `up`; heights outside go to the end bands
    up: tuple[float, float, float]
    means: dict[str, tuple[tuple[float, ...], ...]]  # attribute -> per band, per channel
    counts: tuple[int, ...]  # Gaussians per band; an empty band holds nothing


class ContinuationSettings(BaseModel):
    """The settings of a run continuing its parent by physics (predict, interact, resimulate)."""

    model_config = _RECORD
    branch_frame: int  # the parent frame this run continues from
    visual: VisualSettings
    parent_source_rate: int
    identified_on_frame: int | None = None
    buoyancy_scale: float = 1.0
    buoyancy_calibration_error: dict[str, float] = {}  # tracking error per buoyancy scale tried (predict.identification)
    appearance_profile: AppearanceProfile | None = None
    priors: tuple[str, ...] = ()
    wind: WindParams | None = None
    ball: BallParams | None = None


Settings = ReconstructSettings | ContinuationSettings


def settings_model(kind: RunKind) -> type[Settings]:
    return ReconstructSettings if kind is RunKind.RECONSTRUCT else ContinuationSettings


@dataclass(frozen=True)
class SavedAir:
    """The air of a saved frame, torch-free: face velocities (world units/s) on a MAC grid with
    lowest corner `origin` and cubic cells of `spacing` (`fluidcore.physics.AirState` as numpy).
    The exporter and the API read it without the simulator, hence a numpy sampler here next to
    the torch one in fluidcore.physics.air."""

    faces: tuple[np.ndarray, np.ndarray, np.ndarray]
    origin: np.ndarray
    spacing: float

    def __post_init__(self) -> None:
        if len(self.faces) != 3 or any(f.ndim != 3 for f in self.faces):
            raise RunError("state: air needs three 3-D face arrays (air_x, air_y, air_z)")
        cells = np.asarray(self.cells)
        for axis, face in enumerate(self.faces):
            if face.shape != tuple(cells + np.eye(3, dtype=int)[axis]):
                raise RunError(f"state: {AIR_FIELDS[axis]} has shape {face.shape}, not the faces of a {tuple(cells)} grid")
        if np.shape(self.origin) != (3,) or not np.all(np.isfinite(self.origin)) or not 0 < self.spacing < np.inf:
            raise RunError("state: air_origin must be 3 finite numbers and air_spacing a number > 0")

    @property
    def cells(self) -> tuple[int, int, int]:
        """(nx, ny, nz): the grid's cells, read off the faces that are not along each axis."""
        return self.faces[1].shape[0], self.faces[0].shape[1], self.faces[0].shape[2]

    def arrays(self) -> dict[str, np.ndarray]:
        """The state file's air arrays (module docstring)."""
        return {
            "air_version": np.asarray(AIR_VERSION, dtype=np.int64),
            "air_origin": np.asarray(self.origin, dtype=np.float64),
            "air_spacing": np.asarray(self.spacing, dtype=np.float64),
            **{name: face.astype(np.float32, copy=False) for name, face in zip(AIR_FIELDS, self.faces)},
        }

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, np.ndarray], where: str) -> SavedAir | None:
        """The air in a state file's arrays; None (still air) in a file written without it."""
        if "air_version" not in arrays:
            return None
        if int(arrays["air_version"]) != AIR_VERSION:
            raise RunError(f"state file {where}: air_version {int(arrays['air_version'])} is not supported "
                           f"(this version reads {AIR_VERSION}); written by a newer FluidNexus?")
        faces = tuple(arrays[name] for name in AIR_FIELDS)
        return cls(faces, np.asarray(arrays["air_origin"], dtype=np.float64), float(arrays["air_spacing"]))  # type: ignore[arg-type]

    def velocity_at(self, points: np.ndarray) -> np.ndarray:
        """The air's velocity (N, 3) at world `points` (N, 3): each component trilinear on its own
        faces; points beyond the grid take the value at its border (as AirGrid.velocity_at)."""
        s = (np.asarray(points, dtype=np.float64).reshape(-1, 3) - self.origin) / self.spacing  # grid units
        out = np.empty((len(s), 3), dtype=np.float32)
        for axis, face in enumerate(self.faces):
            index = s - np.where(np.arange(3) == axis, 0.0, 0.5)  # faces along `axis` sit half a cell off the others
            index = np.clip(index, 0.0, np.asarray(face.shape) - 1.0)
            base = np.minimum(np.floor(index).astype(np.int64), np.maximum(np.asarray(face.shape) - 2, 0))
            frac = index - base
            value = np.zeros(len(s))
            for corner in range(8):
                bits = [(corner >> a) & 1 for a in range(3)]
                weight = np.prod([frac[:, a] if bit else 1.0 - frac[:, a] for a, bit in enumerate(bits)], axis=0)
                at = tuple(np.minimum(base[:, a] + bit, face.shape[a] - 1) for a, bit in enumerate(bits))
                value += weight * face[at]
            out[:, axis] = value
        return out


@dataclass
class FrameState:
    """One frame's particles, as numpy arrays in world units (see the module docstring), and the
    air around them when the run simulates it (None: still air)."""

    positions: np.ndarray
    velocities: np.ndarray
    alive: np.ndarray
    time: float
    gaussians: dict[str, np.ndarray]
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    air: SavedAir | None = None

    def __post_init__(self) -> None:
        n = len(self.positions)
        if self.positions.shape != (n, 3) or self.velocities.shape != (n, 3) or self.alive.shape != (n,):
            raise RunError(
                f"state: positions {self.positions.shape}, velocities {self.velocities.shape} and "
                f"alive {self.alive.shape} must be (P, 3), (P, 3), (P,)"
            )
        missing = [k for k in GAUSSIAN_FIELDS if k not in self.gaussians]
        if missing:
            raise RunError(f"state: gaussians lack {missing}")
        g = len(self.gaussians["means"])
        if any(len(self.gaussians[k]) != g for k in GAUSSIAN_FIELDS):
            raise RunError("state: gaussian arrays differ in length")
        for name, array in self._arrays().items():
            if array.dtype.kind == "f" and not np.all(np.isfinite(array)):
                raise RunError(f"state: {name} holds NaN or infinite values")

    def _arrays(self) -> dict[str, np.ndarray]:
        arrays = {
            "positions": self.positions.astype(np.float32, copy=False),
            "velocities": self.velocities.astype(np.float32, copy=False),
            "alive": self.alive.astype(bool, copy=False),
            "time": np.asarray(self.time, dtype=np.float64),
        }
        arrays.update({f"gauss_{k}": self.gaussians[k].astype(np.float32, copy=False) for k in GAUSSIAN_FIELDS})
        arrays.update({f"extra_{k}": v for k, v in self.extra.items()})
        if self.air is not None:
            arrays.update(self.air.arrays())
        return arrays

    def save(self, path: Path) -> None:
        """Write atomically: a reader never sees half a file, a crash leaves the old one."""
        with atomic_output(path) as temporary, temporary.open("wb") as file:
            np.savez(file, **self._arrays())

    @classmethod
    def load(cls, path: Path) -> FrameState:
        try:
            data = Path(path).read_bytes()
        except OSError as exc:
            raise RunError(f"state file {path}: unreadable ({exc})") from None
        return cls.from_bytes(data, str(path))

    @classmethod
    def from_bytes(cls, data: bytes, where: str) -> FrameState:
        """A state file's content (read from disk, or fetched from storage by the API); `where`
        names it in errors."""
        try:
            with np.load(io.BytesIO(data)) as loaded:
                arrays = {k: loaded[k] for k in loaded.files}
        except (OSError, ValueError) as exc:
            raise RunError(f"state file {where}: unreadable ({exc})") from None
        try:
            return cls(
                positions=arrays["positions"],
                velocities=arrays["velocities"],
                alive=arrays["alive"],
                time=float(arrays["time"]),
                gaussians={k: arrays[f"gauss_{k}"] for k in GAUSSIAN_FIELDS},
                extra={k[6:]: v for k, v in arrays.items() if k.startswith("extra_")},
                air=SavedAir.from_arrays(arrays, where),
            )
        except KeyError as exc:
            raise RunError(f"state file {where}: missing array {exc}") from None

    def export(self) -> dict[str, np.ndarray]:
        """The user-facing arrays: live particles only (`fluidnexus export`)."""
        alive = self.alive.astype(bool)
        out = {
            "positions": self.positions[alive].astype(np.float32),
            "velocities": self.velocities[alive].astype(np.float32),
            "time": np.asarray(self.time),
        }
        out.update({f"gaussian_{k}": v.astype(np.float32) for k, v in self.gaussians.items()})
        return out


def _relative(target: str | os.PathLike[str], start: Path) -> str:
    """`target` as a POSIX path relative to the folder `start` (both resolved first)."""
    return Path(os.path.relpath(Path(target).resolve(), Path(start).resolve())).as_posix()


def camera_to_json(camera: Any) -> dict[str, Any]:
    return {
        "fx": float(camera.fx),
        "fy": float(camera.fy),
        "cx": float(camera.cx),
        "cy": float(camera.cy),
        "width": int(camera.width),
        "height": int(camera.height),
        "world_to_camera": np.asarray(camera.world_to_camera, dtype=np.float64).tolist(),
        "file_path": camera.file_path,
    }


def camera_from_json(name: str, data: Mapping[str, Any]) -> Any:
    from fluidcore.cameras import Camera

    try:
        return Camera(
            name=name,
            fx=float(data["fx"]),
            fy=float(data["fy"]),
            cx=float(data["cx"]),
            cy=float(data["cy"]),
            width=int(data["width"]),
            height=int(data["height"]),
            world_to_camera=np.asarray(data["world_to_camera"], dtype=np.float64),
            file_path=data.get("file_path"),
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise RunError(f"cameras.{name}: malformed ({exc})") from None


def versions() -> dict[str, str]:
    import fluidcore

    found = {"fluidnexus": fluidcore.__version__, "numpy": np.__version__, "python": platform.python_version()}
    try:
        import torch

        found["torch"] = torch.__version__
    except ImportError:
        pass
    return found


def state_file(t: int) -> str:
    """Where frame t's state lies in a run folder (relative, POSIX): the one place that knows."""
    return f"{STATES_DIR}/frame_{t:06d}.npz"


def _nested_settings(settings: dict[str, Any]) -> dict[str, Any]:
    """A reconstruction's settings of format 1 or 2 as format 3 has them: the flat quality nested
    (`fluidcore.spec.reconstruct.quality_fields`), and the visual settings, which version 3 reads
    off the quality, folded into it (version 1 did not record the concentration rule in the
    quality: its visual settings say whether the run followed it)."""
    visual = settings.pop("visual", None) or {}
    quality = settings.get("quality")
    if isinstance(quality, Mapping):
        settings["quality"] = quality_fields(
            {"opacity_concentration": visual.get("opacity_concentration", False), **quality})
    return settings


def _scene_with_air(scene: Any, settings: dict[str, Any], kind: RunKind) -> Any:
    """A scene record of format 1 or 2 with the air its run simulated, which those versions kept
    in the settings: a reconstruction in its flat quality (kept there too: the quality still asks
    for the air), a continuation in its own fields (taken out: they are the scene's now). A record
    that is not a mapping is left for `RunRecord.scene` to refuse."""
    if kind is RunKind.RECONSTRUCT:
        quality = settings.get("quality")
        held = quality if isinstance(quality, Mapping) else {}
        air = {"cells": held.get("air_cells", 0), "vorticity": held.get("air_vorticity", 0.0)}
    else:
        air = {"cells": settings.pop("air_cells", 0), "vorticity": settings.pop("air_vorticity", 0.0)}
    return {**scene, "air": air} if isinstance(scene, Mapping) else scene


def _migrate(manifest: dict[str, Any], where: str) -> dict[str, Any]:
    """A manifest of any readable version as the current version: checked, settings completed
    with the defaults of their kind's model (version 1 left out what a feature added later), the
    air of versions 1 and 2 moved from the settings into the scene record."""
    if manifest.get("format") != FORMAT:
        raise RunError(f"run: {where} is not a {FORMAT} manifest")
    if manifest.get("format_version") not in READABLE_VERSIONS:
        raise RunError(f"run: format_version {manifest.get('format_version')} is not supported")
    try:
        kind = RunKind(manifest.get("kind"))
    except ValueError:
        raise RunError(f"run: {where} has kind {manifest.get('kind')!r}, not one of {[k.value for k in RunKind]}") from None
    model = settings_model(kind)
    settings = dict(manifest.get("settings") or {})
    migrated: dict[str, Any] = {}
    if manifest["format_version"] < 3:
        migrated["scene"] = _scene_with_air(manifest.get("scene"), settings, kind)
        if kind is RunKind.RECONSTRUCT:
            settings = _nested_settings(settings)
    if manifest["format_version"] == 1:  # free-form then: what no model field names is dropped
        settings = {k: v for k, v in settings.items() if k in model.model_fields}
    if kind is not RunKind.RECONSTRUCT and "branch_frame" not in settings and manifest.get("frames"):
        settings["branch_frame"] = int(manifest["frames"][0]["t"]) - 1  # version 1 before --from-frame
    try:
        typed = model.model_validate(settings)
    except ValidationError as exc:
        raise RunError(f"run: {where}: settings do not fit a {kind} run ({exc.errors()[0]['loc']}: {exc.errors()[0]['msg']})") from None
    return {**manifest, "format_version": FORMAT_VERSION, "kind": kind.value, **migrated, "settings": typed.model_dump(mode="json")}


class RunRecord:
    """A run's manifest, read and migrated (`_migrate`), with typed accessors: what every reader
    of a run sees, whether it holds the folder (`Run`) or only the manifest's bytes (the API,
    from storage: `from_bytes`)."""

    def __init__(self, manifest: dict[str, Any]) -> None:
        self.manifest = manifest

    @classmethod
    def from_bytes(cls, data: bytes, where: str) -> RunRecord:
        """The manifest in `data` (`where` names it in errors)."""
        return cls(_parse_manifest(data, where))

    @property
    def kind(self) -> RunKind:
        return RunKind(self.manifest["kind"])

    @property
    def settings(self) -> Settings:
        """`ReconstructSettings` for a reconstruction, else `ContinuationSettings`."""
        return settings_model(self.kind).model_validate(self.manifest["settings"])

    def visual_settings(self) -> VisualSettings:
        """How this run moves and bears visual Gaussians, which a continuation of it keeps: a
        reconstruction's quality says it, a continuation records what it kept."""
        settings = self.settings
        return settings.quality.visual_settings() if isinstance(settings, ReconstructSettings) else settings.visual

    @property
    def channels(self) -> int:
        return int(self.manifest["channels"])

    @property
    def fps(self) -> float:
        return float(self.manifest["fps"])

    @property
    def scene(self) -> Scene:
        """The scene the run simulates, its air included, as recorded; a malformed record is this
        run's error."""
        try:
            return Scene.from_json(self.manifest["scene"])
        except SceneError as exc:
            raise RunError(str(exc)) from None

    @property
    def input_views(self) -> list[str]:
        return list(self.manifest["input_views"])

    @property
    def frame_range(self) -> tuple[int, int]:
        start, stop = self.manifest["frame_range"]
        return int(start), int(stop)

    @property
    def background_color(self) -> list[float]:
        return list(self.manifest["background_color"])

    def cameras(self) -> dict[str, Any]:
        return {name: camera_from_json(name, data) for name, data in self.manifest["cameras"].items()}

    def frames(self) -> list[int]:
        """Completed frames, in order."""
        return [int(entry["t"]) for entry in self.manifest["frames"]]

    def next_frame(self) -> int:
        """Where a writer goes on: the first frame of the range not yet written."""
        done = self.frames()
        return done[-1] + 1 if done else self.frame_range[0]

    def frame_log(self, t: int) -> dict[str, Any]:
        for entry in self.manifest["frames"]:
            if entry["t"] == t:
                return dict(entry)
        raise RunError(f"frame: {t} is not in this run (frames {self._frames_text()})")

    def _frames_text(self) -> str:
        done = self.frames()
        return f"{done[0]}..{done[-1]}" if done else "none"


def _parse_manifest(data: bytes, where: str) -> dict[str, Any]:
    try:
        manifest = json.loads(data)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise RunError(f"run: {where} is not valid JSON ({exc})") from None
    if not isinstance(manifest, dict):
        raise RunError(f"run: {where} is not a {FORMAT} manifest")
    return _migrate(manifest, where)


class Run(RunRecord):
    """A run folder opened for reading, or for writing frame after frame."""

    def __init__(self, path: Path, manifest: dict[str, Any]) -> None:
        super().__init__(manifest)
        self.path = path

    # -- opening -------------------------------------------------------------------------
    @classmethod
    def open(cls, path: str | os.PathLike[str]) -> Run:
        path = Path(path)
        manifest_path = path / MANIFEST
        if not manifest_path.is_file():
            raise RunError(f"run: {path} is not a run folder (no {MANIFEST})")
        return cls(path, _parse_manifest(manifest_path.read_bytes(), str(manifest_path)))

    @classmethod
    def create(
        cls,
        path: str | os.PathLike[str],
        *,
        kind: RunKind,
        cameras: Mapping[str, Any],
        input_views: Sequence[str],
        frame_range: tuple[int, int],
        fps: float,
        channels: int,
        background_color: Sequence[float],
        scene: Scene,
        settings: Settings,
        parent: str | os.PathLike[str] | None = None,
    ) -> Run:
        """Start a run in `path`, or reopen the same run there to resume it."""
        path = Path(path)
        if channels not in (1, 3) or len(background_color) != channels:
            raise RunError(f"channels must be 1 or 3 with as many background values, got {channels}")
        if frame_range[1] <= frame_range[0]:
            raise RunError(f"frame_range: {frame_range} is empty")
        if not isinstance(settings, settings_model(RunKind(kind))):
            raise RunError(f"settings: a {kind} run records {settings_model(RunKind(kind)).__name__}")
        identity = {
            "kind": RunKind(kind).value,
            "parent": None if parent is None else _relative(parent, path),
            "cameras": {name: camera_to_json(cam) for name, cam in cameras.items()},
            "input_views": list(input_views),
            "frame_range": [int(frame_range[0]), int(frame_range[1])],
            "fps": float(fps),
            "channels": int(channels),
            "scene": scene.to_json(),
            "settings": settings.model_dump(mode="json"),
        }
        if (path / MANIFEST).exists():
            run = cls.open(path)
            differs = [k for k, v in identity.items() if run.manifest.get(k) != v]
            if differs:
                raise RunError(
                    f"out: {path} already holds a different run ({', '.join(differs)} differ); "
                    "choose another folder or delete it"
                )
            return run
        if path.exists() and any(path.iterdir()):
            raise RunError(f"out: {path} exists and is not a run folder; refusing to write into it")
        manifest = {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            **identity,
            "background_color": [float(c) for c in background_color],
            "created": datetime.now(UTC).isoformat(timespec="seconds"),
            "versions": versions(),
            "frames": [],
            "complete": False,
        }
        run = cls(path, manifest)
        run._save_manifest()
        return run

    # -- reading ------------------------------------------------------------------------
    @property
    def parent(self) -> Run | None:
        parent = self.manifest.get("parent")
        return None if parent is None else Run.open(self.path / parent)  # an absolute path stays itself

    def reconstruction(self) -> Run | None:
        """The reconstruction this run is or descends from (its nearest reconstruct ancestor),
        whose quality, physics and views every continuation of it keeps; None for a run with no
        reconstruction behind it (one made by hand or by a test)."""
        run: Run | None = self
        while run is not None and run.kind is not RunKind.RECONSTRUCT:
            run = run.parent
        return run

    def state_path(self, t: int) -> Path:
        return self.path / state_file(t)

    def read_frame(self, t: int) -> FrameState:
        if t not in self.frames():
            raise RunError(f"frame: {t} is not in this run (frames {self._frames_text()})")
        return FrameState.load(self.state_path(t))

    def background_images(self) -> dict[str, np.ndarray]:
        path = self.path / BACKGROUND
        if not path.is_file():
            return {}
        with np.load(path) as data:
            return {k: data[k] for k in data.files}

    def refined(self) -> Run | None:
        """The sub-run of a prediction reconstructed on its video-model-refined frames, if any."""
        return Run.open(self.path / REFINED_RUN) if (self.path / REFINED_RUN / MANIFEST).is_file() else None

    # -- writing ------------------------------------------------------------------------
    def write_background(self, images: Mapping[str, np.ndarray]) -> None:
        with atomic_output(self.path / BACKGROUND) as temporary, temporary.open("wb") as file:
            np.savez(file, **{k: np.asarray(v, np.float32) for k, v in images.items()})

    def write_frame(self, t: int, state: FrameState, losses: Mapping[str, float], seconds: float) -> None:
        """Append frame t: the state file first, then the manifest, so a crash in between
        leaves a manifest that does not list the frame (it is recomputed on resume)."""
        if t != self.next_frame():
            raise RunError(f"frame: writing {t} but the run expects {self.next_frame()} next")
        bad = {k: v for k, v in losses.items() if not np.isfinite(v)}
        if bad:
            raise RunError(f"losses of frame {t} are not finite: {bad}")
        state.save(self.state_path(t))
        entry = {
            "t": int(t),
            "file": state_file(t),
            "losses": {k: float(v) for k, v in losses.items()},
            "seconds": float(seconds),
        }
        self.manifest["frames"].append(entry)
        self.manifest["complete"] = self.next_frame() >= self.frame_range[1]
        self._save_manifest()

    def update(self, **fields: Any) -> None:
        """Record extra top-level manifest fields (e.g. a summary); identity fields are refused."""
        frozen = {"format", "format_version", "kind", "cameras", "frames", "settings", "scene", "frame_range"}
        if frozen & fields.keys():
            raise RunError(f"update: {sorted(frozen & fields.keys())} cannot be changed")
        self.manifest.update(json.loads(json.dumps(fields)))
        self._save_manifest()

    def _save_manifest(self) -> None:
        text = json.dumps(self.manifest, indent=1)
        with atomic_output(self.path / MANIFEST) as temporary:
            temporary.write_bytes(text.encode())
