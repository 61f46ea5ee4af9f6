"""The typed records a run's manifest holds beside its frames: how a reconstruction found its
background, capture, source and physics, and the settings of each kind of run (one model per
kind, `settings_model`). Pydantic models, torch-free, frozen, refusing fields they do not know."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict

from fluidcore.runs.layout import RunKind
from fluidcore.spec.controls import BallParams, WindParams
from fluidcore.spec.reconstruct import ReconstructConfig, VisualSettings
from fluidcore.spec.scene import SourcePlace, UpAxis, UpFound
from fluidcore.spec.source_hint import SourceHint

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
    diffusivity: float | None = None  # the carrier's turbulent diffusivity of the smoke (world units^2 / s); None: the paper model
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
