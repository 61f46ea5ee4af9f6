"""Physics identified per scene from the observed input view (issue 12), not taken from a dataset.

The dataset presets (`fluidcore.physics.PRESETS`) hold constants tuned on one capture: their
buoyancy, in particular, sets how fast a plume rises, and a plume from another source, in
other units or another gas rises at its own rate. Here the buoyancy (an acceleration along up,
world units / s^2), the source's radius and height and the age of the plume at the first frame
are chosen so that the simulated plume, rendered into the input camera, covers
what the video shows frame after frame:

    observed    the smoke mask of every observed frame (|frame - background| above the noise),
                pooled onto cells about one kernel radius wide;
    simulated   the physics of this scene (box, source, kernel radius, rest density of the prior
                preset) run from an empty box; each step's particles projected into the same
                camera mark their cells;
    misfit      mean over the frames of 1 - IoU(simulated cells, observed cells), plus the mean
                distance between the simulated and observed tops of the plume (the rise, which
                the IoU of a thin column barely sees) as a fraction of the image, averaged over
                ROLLOUT_SEEDS seedings of the source and minimised also over the plume's age
                (how many steps the source had been emitting when frame 0 was taken), which one
                rollout per seeding answers for every age.

Rendering by cell occupancy instead of splatting Gaussians keeps a candidate at one simulation
per seeding (a second or two) and compares what the image fit cannot change later: where smoke
is. The parameters are continuous, each within wide physical bounds (`search_space`: the
buoyancy from 0.05x to 20x drag x the video's rise speed, the source's radius half to twice the image estimate of
`fluidcore.reconstruct.source_estimate.estimate_source` and its height a radius and a half below
to two above it, the plume's spreading rate `fluidcore.physics.entrainment` where asked), and one
Nelder-Mead search over the whole observed window (MAX_SECONDS) minimises the misfit within
MAX_EVALUATIONS rollouts. The seedings are the same for every candidate, so the misfit is a
deterministic function of the parameters. A source the user gave stays as given (`SourceKept`).

The search replaced a coarse-to-fine grid (five buoyancies, three radii, two heights, two
refinements) whose buoyancy sat on its floor (0.5 x drag x rise speed) and whose radius sat on
its lowest factor (0.8) on every dev scene and ScalarFlow: the grid's ends, not the video,
chose them. Scanned without the floor, the misfit's minimum over the buoyancy lies inside the
new bounds on D and ScalarFlow (docs/bench_generalise.md, "Continuous identification").

The drag is the prior's: silhouettes fix the plume's terminal speed buoyancy / drag, not how it
splits. Searched too (a tenth to ten times the prior's), on the synthetic plume of the tests it
came out 1.42x the truth and the buoyancy 1.56x, their ratio within 10% of the truth's.

The inflow speed is the terminal speed of the identified buoyancy (`identify` says why
it is not searched on its own). The candidates' rollouts seed what their inlet carries at that
speed at rest density (n0 pi r^2 v dt, n0 = 8 rho0 / h^3); the reconstruction seeds the smoke
volume the video shows leaving the inlet, at the observed rise speed where that is faster
(`fluidcore.reconstruct.scene_physics.inflow_rate_speed` says why the two differ). Both are
capped by the quality's particle budget. The rest density stays the prior's (a silhouette says
nothing of it); the record says so. Smoke that rises in the video never gets zero buoyancy: the
buoyancy's lower bound (`buoyancy_floor`) is positive whenever the video's smoke climbs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
import torch
from scipy import ndimage, optimize

from fluidcore.cameras import Camera
from fluidcore.errors import InputError
from fluidcore.jobs import StepProgress
from fluidcore.physics import Box, PBFConfig, Source
from fluidcore.physics.build import build_simulator
from fluidcore.physics.carrier import eddy_diffusivity, eddy_viscosity
from fluidcore.runs import IdentificationPrior, IdentifiedRecord
from fluidcore.spec.physics import Vec3
from fluidcore.spec.scene import Air, Scene, SourcePlace
from fluidcore.spec.simulation import PHYSICS_MODES, MotionModel
from fluidcore.spec.solids import SolidBall
from fluidcore.spec.source_hint import SourceKept

# Windows in seconds, counted in frames at the clip's rate (`PBFConfig.frames_in`); measured at 30 fps.
MAX_AGE_SECONDS = 1.5  # how long the source may have been emitting before the first observed frame
# Observed frames the misfit is measured over (the first ones): the whole window of a clip up to
# 4 s. Over the first 45 only, ScalarFlow's misfit told buoyancy 0.5x from 0.7x drag x rise speed
# by 0.011-0.014 (seeds 0-2), less than one seeding differs from another (0.03); over its 90
# frames by 0.04-0.06 (docs/bench_generalise.md, "Identification from the whole window";
# i22_ident_misfit_scans.json). The source is judged over the same window: over 90 frames F's
# silhouettes preferred its image radius to 0.8x of it, where the first 45 alone preferred 0.8x.
MAX_SECONDS = 4.0
# Candidates rolled out per identification (ROLLOUT_SEEDS times each), per motion model: the carrier
# searches five parameters where the paper model searches three (four with its spreading).
MAX_EVALUATIONS = {"paper": 40, "carrier": 60}
OCCUPIED = 0.3  # fraction of a cell's pixels that must be smoke for the cell to count as smoke
FOOTPRINT = 1  # cells (about a kernel radius each) around a particle that its smoke covers
# Seedings of the source each candidate's misfit is averaged over, per motion model (see _Search.misfit).
# The carrier's markers only mark the air, which smooths their seeding out: the identified candidate's
# misfit over five seedings had a standard deviation of 0.002 on D and 0.005 on F (seed 0, preview),
# where the paper model's one seeding spreads 0.005-0.016; one rollout each keeps its five-parameter
# search within the time of the paper model's three-parameter one.
ROLLOUT_SEEDS = {"paper": 3, "carrier": 1}
# The bounds of the search (`search_space`), each relative to what the video or the prior says.
BUOYANCY_RANGE = (0.05, 20.0)  # x drag x the observed rise speed (x the prior's buoyancy where the smoke does not climb)
START_BUOYANCY = 0.5  # x drag x rise speed: where the search starts (the old grid's choice on every dev scene)
RADIUS_RANGE = (0.5, 2.0)  # x the image estimate's radius
HEIGHT_RANGE = (-1.5, 2.0)  # the centre's height along up from the estimate's, in the estimate's radii
SPREADING_RANGE = (0.0, 0.2)  # the spreading rate db/dz (0: the paper's column; MTT's 6/5 alpha_e for alpha_e up to 0.16)
FIRST_STEP = 0.1  # the initial simplex's step along each parameter, as a fraction of its (log) range
# The carrier's search (`search_space`): its buoyancy (x rise^2 / source radius), inflow speed (x the
# observed rise speed) and the smoke's turbulent diffusivity (x rise x source radius; 0: markers carried
# by the resolved air alone), bounds and starts. Silhouettes tell the inflow's momentum from the
# buoyancy poorly: searched over 0.1-3x the rise, the inflow went to half of it on D and F (seed 0,
# 0.12 and 0.13 m/s against the truths' 0.28 and 0.22) and F's velocity error at frame 45 to 0.64;
# held within 0.7-1.5x the rise (a forced plume's inlet blows at about the speed its smoke is seen
# rising) it came out at 1.12x and 1.04x (0.26 m/s both) and F's error at 0.57
# (docs/bench_generalise.md, "The buoyant-air carrier").
CARRIER_RANGES = {"buoyancy": (0.02, 20.0), "inflow_speed": (0.7, 1.5), "diffusivity": (0.0, 0.5)}
CARRIER_START = {"buoyancy": 0.4, "inflow_speed": 1.0, "diffusivity": 0.05}


# What of a given source (`fluidcore.spec.source_hint.SourceKept`) the record's `held_from_prior` names.
KEPT_SOURCE: dict[str, tuple[str, ...]] = {"nothing": (), "center": ("source center",), "place": ("source center", "source radius")}


class IdentificationError(InputError):
    """The observed frames cannot identify the physics (e.g. no smoke at all)."""


@dataclass(frozen=True)
class Observation:
    """The input view's smoke, pooled onto cells: what a candidate's rollout must cover."""

    camera: Camera  # at the masks' resolution
    cells: np.ndarray  # (T, gh, gw) bool
    cell: int  # pixels per cell side
    height: np.ndarray  # (gh, gw) each cell's height along the image's up direction, in pixels

    @classmethod
    def from_masks(cls, camera: Camera, masks: np.ndarray, cell: int, center: np.ndarray, up: np.ndarray) -> Observation:
        """Pool (T, H, W) bool masks into cells of `cell` x `cell` pixels; heights are measured
        along the direction in which `up` points in the image at `center`."""
        from fluidcore.reconstruct.rays import image_up

        t, h, w = masks.shape
        gh, gw = h // cell, w // cell
        if gh < 2 or gw < 2:
            raise IdentificationError(f"masks of {w}x{h} px are too small for cells of {cell} px")
        pooled = masks[:, : gh * cell, : gw * cell].reshape(t, gh, cell, gw, cell).mean(axis=(2, 4))
        up2d = image_up(camera, center, up)
        rows, cols = np.mgrid[0:gh, 0:gw]
        height = ((cols + 0.5) * up2d[0] + (rows + 0.5) * up2d[1]) * cell
        return cls(camera, pooled > OCCUPIED, cell, height - height.min())

    def project(self, points: np.ndarray) -> np.ndarray:
        """(gh, gw) bool: the cells the points fall in, grown by a particle's footprint."""
        out = np.zeros(self.cells.shape[1:], dtype=bool)
        if len(points) == 0:
            return out
        uv, depth = self.camera.project_numpy(points)
        col, row = (uv[:, 0] // self.cell).astype(np.int64), (uv[:, 1] // self.cell).astype(np.int64)
        ok = (depth > 0) & (col >= 0) & (row >= 0) & (col < out.shape[1]) & (row < out.shape[0])
        out[row[ok], col[ok]] = True
        return ndimage.binary_dilation(out, iterations=FOOTPRINT)

    def tops(self, cells: np.ndarray) -> np.ndarray:
        """(T,) height of the highest smoke cell of each frame (pixels; 0 for an empty frame)."""
        return np.where(cells.any(axis=(1, 2)), np.where(cells, self.height, 0.0).max(axis=(1, 2)), 0.0)


def buoyancy_floor(rise_speed: float, drag: float) -> float:
    """The least buoyancy a plume rising at `rise_speed` may be given (0 when it does not rise):
    the lower bound of the search (`search_space`).

    Sparse smoke tends to the terminal speed buoyancy / drag; smoke seen rising at speed u
    therefore needs a buoyancy near drag x u, and never zero. The bound sits far below that
    (BUOYANCY_RANGE), so the video, not the bound, decides.
    """
    if not math.isfinite(rise_speed) or rise_speed <= 0.0:
        return 0.0
    return BUOYANCY_RANGE[0] * max(drag, 1e-3) * rise_speed


def rise_speed(observation: Observation, center: np.ndarray, fps: float) -> float:
    """Speed (world units / s) at which the top of the observed smoke climbs, measured at the
    source's depth by a line fitted over the frames; 0 when it climbs less than a cell over
    them. Frames whose top
    is at the image's upper edge are left out (the plume has left the view there)."""
    camera = observation.camera
    depth = float(camera.world_to_camera[2, :3] @ center + camera.world_to_camera[2, 3])
    tops = observation.tops(observation.cells)
    seen = observation.cells.any(axis=(1, 2)) & (tops < observation.height.max() - observation.cell)
    frames = np.flatnonzero(seen)
    if len(frames) < 3:
        return 0.0
    slope = float(np.polyfit(frames, tops[frames], 1)[0])  # px per frame
    if slope * (frames[-1] - frames[0]) < observation.cell:  # less than one cell over the window: no climb
        return 0.0
    return slope * depth / camera.fx * fps


def inlet_rate(radius: float, speed: float, config: PBFConfig, budget: int) -> int:
    """Particles per step the inlet carries at rest density (`PBFConfig.inlet_capacity`), at
    least 1 and at most `budget` (the quality's resolution)."""
    return int(min(max(round(config.inlet_capacity(radius, speed)), 1), budget))


class Candidate(NamedTuple):
    """One point of the search, in the scene's units."""

    buoyancy: float  # world units / s^2 along up
    source_radius: float  # world units
    source_height: float  # the source centre's height along up, world units
    entrainment: float  # the spreading rate db/dz
    inflow_speed: float = 0.0  # world units / s along up: the carrier's, searched (the paper model's follows from the buoyancy)
    diffusivity: float = 0.0  # world units^2 / s: the carrier's turbulent diffusivity of the smoke, searched


@dataclass(frozen=True)
class Parameter:
    """A searched parameter: its bounds (those of `Candidate`'s field of the same name) and where
    the search starts. Positive scales are searched in log space, so a factor of two is the same
    step anywhere in the range."""

    name: str
    lo: float
    hi: float
    start: float
    log: bool

    def unit(self, value: float) -> float:
        """`value` mapped to [0, 1] over the bounds."""
        if self.log:
            return math.log(value / self.lo) / math.log(self.hi / self.lo)
        return (value - self.lo) / (self.hi - self.lo)

    def value(self, unit: float) -> float:
        """The inverse of `unit`, clipped to the bounds."""
        unit = min(max(float(unit), 0.0), 1.0)
        if self.log:
            return self.lo * (self.hi / self.lo) ** unit
        return self.lo + unit * (self.hi - self.lo)


@dataclass(frozen=True)
class ScenePrior:
    """A scene before its physics is chosen: box, up and air as the reconstruction sets them, the
    physics mode (`PHYSICS_MODES`) and its prior preset's physics in this scene's units, and
    where the source was estimated to be (`place`); what the source seeds, and how fast, is what
    the physics decides. `seed` seeds the source's particles. `solids`: the static balls the user
    placed, in every candidate's rollouts as in the reconstruction."""

    box: Box
    up: Vec3  # unit length
    air: Air
    mode: str
    physics: PBFConfig
    place: SourcePlace
    seed: int
    motion: MotionModel = "paper"
    solids: tuple[SolidBall, ...] = ()

    @property
    def preset(self) -> str:
        return PHYSICS_MODES[self.mode]

    @property
    def up_vector(self) -> np.ndarray:
        """(3,) `up` as a float64 array of unit length (normalised again against a caller's rounding)."""
        return np.asarray(self.up, dtype=np.float64) / np.linalg.norm(self.up)

    def scene(self, physics: PBFConfig, place: SourcePlace, rate: int, velocity: np.ndarray,
              diffusivity: float | None = None) -> Scene:
        """This scene under `physics`, its source at `place` seeding `rate` particles per step at
        `velocity`; the carrier's air gets the eddy viscosity of that inflow
        (`fluidcore.physics.carrier.eddy_viscosity`) and the smoke's turbulent `diffusivity`
        (identified; without one, the prior's `eddy_diffusivity` of that viscosity)."""
        source = Source(place.center, place.radius, rate, tuple(float(c) for c in velocity), self.seed)
        air = self.air
        if self.motion == "carrier":
            viscosity = eddy_viscosity(float(np.linalg.norm(velocity)), place.radius)
            air = replace(air, viscosity=viscosity,
                          diffusivity=eddy_diffusivity(viscosity) if diffusivity is None else diffusivity)
        return Scene(self.box.lo, self.box.hi, self.up, physics, source, air, self.motion, self.solids)


def search_space(prior: ScenePrior, rise: float, keep: SourceKept, spreading: bool) -> tuple[list[Parameter], Candidate]:
    """The parameters the identification varies, with their bounds (see the module docstring),
    and the candidate that holds the rest: what of the source the user gave (`keep`), the
    spreading rate unless `spreading`. `rise`: the observed smoke's rise speed (`rise_speed`).

    The paper model's buoyancy is scaled by drag x rise (its sparse smoke's terminal speed is
    buoyancy / drag). The carrier's buoyancy acts on air at the inlet's concentration, and a
    plume of radius r driven by it rises at about sqrt(b r): its scale is rise^2 / r, and its
    inflow speed is searched too, scaled by the rise (CARRIER_RANGES)."""
    config, place = prior.physics, prior.place
    up = prior.up_vector
    height = float(np.dot(place.center, up))
    if prior.motion == "carrier":
        speed = rise if rise > 0.0 else max(config.terminal_speed, 1e-6)
        scale = speed * speed / place.radius
        mixing = speed * place.radius  # the plume's own scale of a diffusivity, world units^2 / s
        held = Candidate(CARRIER_START["buoyancy"] * scale, place.radius, height, 0.0, CARRIER_START["inflow_speed"] * speed,
                         CARRIER_START["diffusivity"] * mixing)
        space = [Parameter("buoyancy", CARRIER_RANGES["buoyancy"][0] * scale, CARRIER_RANGES["buoyancy"][1] * scale,
                           held.buoyancy, True),
                 Parameter("inflow_speed", CARRIER_RANGES["inflow_speed"][0] * speed, CARRIER_RANGES["inflow_speed"][1] * speed,
                           held.inflow_speed, True),
                 Parameter("diffusivity", CARRIER_RANGES["diffusivity"][0] * mixing, CARRIER_RANGES["diffusivity"][1] * mixing,
                           held.diffusivity, False)]
    else:
        drag = max(config.drag, 1e-3)
        scale = drag * rise if rise > 0.0 else max(float(np.dot(config.body_acceleration, up)), 1e-6)
        start = START_BUOYANCY * scale if rise > 0.0 else scale
        held = Candidate(start, place.radius, height, 0.0)
        space = [Parameter("buoyancy", BUOYANCY_RANGE[0] * scale, BUOYANCY_RANGE[1] * scale, start, True)]
    if keep in ("nothing", "center"):
        space.append(Parameter("source_radius", RADIUS_RANGE[0] * place.radius, RADIUS_RANGE[1] * place.radius, place.radius, True))
    if keep == "nothing":
        space.append(Parameter("source_height", height + HEIGHT_RANGE[0] * place.radius, height + HEIGHT_RANGE[1] * place.radius,
                               height, False))
    if spreading:
        space.append(Parameter("entrainment", *SPREADING_RANGE, SPREADING_RANGE[0], False))
    return space, held


class _Search:
    """Rollouts of candidates (cached per candidate) scored against the observed frames (cached
    per candidate). Each rollout simulates the prior's scene (its air included) under the
    candidate's physics."""

    def __init__(self, observation: Observation, prior: ScenePrior, budget: int, device: torch.device | str,
                 on_evaluation: StepProgress | None = None) -> None:
        self.observation, self.prior, self.budget, self.device = observation, prior, budget, device
        self.on_evaluation = on_evaluation  # told (candidates rolled out, evaluations) after each
        self.evaluations = MAX_EVALUATIONS[prior.motion]  # the most candidates the search rolls out
        self.up = prior.up_vector
        self.frames = min(len(observation.cells), prior.physics.frames_in(MAX_SECONDS))
        self.max_age = prior.physics.frames_in(MAX_AGE_SECONDS)
        self.scores: dict[Candidate, tuple[float, int]] = {}

    def misfit(self, candidate: Candidate) -> tuple[float, int]:
        """(least misfit over the plume ages, that age) of one candidate over the observed frames
        (up to MAX_SECONDS). The misfit of each age is averaged over ROLLOUT_SEEDS seedings of the
        source: one seeding's misfit has a spread of 0.005-0.016 over seeds (six seedings of three
        source sizes on D and F), more than the 0.004 by which ScalarFlow's seed 0 once preferred
        buoyancy 0.27 to 0.19 (docs/bench_generalise.md, "Identification from the whole window")."""
        key = _key(candidate)
        if key not in self.scores:
            scene = self.scene(key)
            rollouts = [self._simulate(replace(scene, source=replace(scene.source, seed=scene.source.seed + k)))
                        for k in range(ROLLOUT_SEEDS[self.prior.motion])]
            scores = np.mean([self._age_scores(simulated) for simulated in rollouts], axis=0)
            age = int(np.argmin(scores))
            self.scores[key] = (float(scores[age]), age)
            if self.on_evaluation is not None:
                self.on_evaluation(min(len(self.scores), self.evaluations), self.evaluations)
        return self.scores[key]

    def tried(self) -> dict[str, tuple[float, float]]:
        """The least and greatest value of each `Candidate` field the rolled-out candidates tried,
        for the fields that varied, and the plume's age in frames."""
        ranges = {name: (min(values), max(values)) for name, values in zip(Candidate._fields, zip(*self.scores, strict=True))
                  if max(values) > min(values)}
        return {**ranges, "age": (0.0, float(self.max_age))}

    def scene(self, candidate: Candidate) -> Scene:
        """The scene a candidate simulates: the carrier's inflow at the candidate's speed, the
        paper model's at its terminal speed (`identify` says why it is not searched there)."""
        config = replace(with_buoyancy(self.prior.physics, candidate.buoyancy, self.up), entrainment=candidate.entrainment)
        speed = candidate.inflow_speed if self.prior.motion == "carrier" else config.terminal_speed
        place = self.prior.place
        lift = candidate.source_height - float(np.dot(place.center, self.up))
        center = place.center if abs(lift) < 1e-9 else tuple(float(c) for c in np.asarray(place.center) + lift * self.up)
        rate = inlet_rate(candidate.source_radius, speed, config, self.budget)
        return self.prior.scene(config, SourcePlace(center, candidate.source_radius), rate, speed * self.up,
                                candidate.diffusivity)

    def _simulate(self, scene: Scene) -> np.ndarray:
        """(max_age + frames, gh, gw) bool: the cells a rollout of `scene` from an empty box covers
        after each step (index k = after k + 1 steps)."""
        simulator = build_simulator(scene, device=self.device)
        state = simulator.new_state()
        projected = []
        for _ in range(self.max_age + self.frames):
            state, _ = simulator.step(state)
            projected.append(self.observation.project(state.positions[state.alive].cpu().numpy().astype(np.float64)))
        return np.stack(projected)

    def _age_scores(self, simulated: np.ndarray) -> np.ndarray:
        """(max_age + 1,) misfit of one rollout over the observed frames, per plume age."""
        frames = self.frames
        observed = self.observation.cells[:frames]
        simulated_tops, observed_tops = self.observation.tops(simulated), self.observation.tops(observed)
        extent = max(float(self.observation.height.max()), 1.0)
        scores = np.empty(self.max_age + 1)
        for age in range(self.max_age + 1):
            window = simulated[age : age + frames]
            union = (window | observed).sum(axis=(1, 2))
            inter = (window & observed).sum(axis=(1, 2))
            scores[age] = float(np.mean(1.0 - np.where(union > 0, inter / np.maximum(union, 1), 1.0)))
            scores[age] += float(np.mean(np.abs(simulated_tops[age : age + frames] - observed_tops))) / extent
        return scores


def _key(candidate: Candidate) -> Candidate:
    return Candidate(*(round(float(x), 9) for x in candidate))


def with_buoyancy(config: PBFConfig, buoyancy: float, up: np.ndarray) -> PBFConfig:
    """`config` whose body acceleration is `buoyancy` along `up` (alpha in the config's units)."""
    gravity_along_up = -float(np.dot(config.gravity, up))  # 9.8 when gravity points down
    return replace(config, alpha=-buoyancy * config.length_scale / gravity_along_up)


def identify(
    observation: Observation,
    prior: ScenePrior,
    budget: int,
    device: torch.device | str = "cpu",
    spreading: bool = False,
    keep: SourceKept = "nothing",
    on_evaluation: StepProgress | None = None,
) -> IdentifiedRecord:
    """Buoyancy, inflow speed and rate, source and plume age for this scene (see the module
    docstring).

    The inflow speed is the terminal speed buoyancy / drag rather than a search dimension of its
    own: on a synthetic plume, halving it changed the silhouette misfit by 0.002 where halving
    the buoyancy changed it by 0.04 (its momentum is gone within a few 1/drag), so the images do
    not pin it down. `prior` is the scene to start from (the preset in this scene's units, the
    estimated source's place); `budget` caps the particles seeded per step; `spreading`: whether
    the plume's spreading rate is searched too (else the paper's column). `keep`: what of the
    prior's source the user gave and the search leaves as it is (`SourceKept`). `on_evaluation`
    hears of each candidate rolled out (done, the most it rolls out): the slow part of a reconstruction's
    prepare stage, which a job reports as its progress.
    """
    if not observation.cells.any():
        raise IdentificationError("no smoke in the observed frames to identify the physics from")
    config, place = prior.physics, prior.place
    up_v = prior.up_vector
    speed_obs = rise_speed(observation, np.asarray(place.center), 1.0 / config.dt)
    space, held = search_space(prior, speed_obs, keep, spreading)
    search = _Search(observation, prior, budget, device, on_evaluation)
    best = _minimise(search, space, held)
    misfit, age = search.misfit(best)
    fitted = search.scene(best).source
    held = ("eddy viscosity",) if prior.motion == "carrier" else ("drag", "rho0")
    record = IdentificationPrior(preset=prior.preset, buoyancy=float(np.dot(config.body_acceleration, up_v)), drag=config.drag,
                                 rho0=config.rho0, held_from_prior=(*held, *KEPT_SOURCE[keep]),
                                 inflow_speed="searched" if prior.motion == "carrier" else "buoyancy / drag",
                                 budget=budget, source=place)
    return IdentifiedRecord(buoyancy=best.buoyancy, inflow_speed=float(np.dot(fitted.velocity, up_v)),
                            rate=fitted.rate, age=age, misfit=misfit, rise_speed=speed_obs,
                            floor=buoyancy_floor(speed_obs, config.drag), evaluations=len(search.scores),
                            source_center=fitted.center, source_radius=fitted.radius, entrainment=best.entrainment,
                            diffusivity=best.diffusivity if prior.motion == "carrier" else None,
                            prior=record, tried=search.tried(),
                            bounds={**{p.name: (p.lo, p.hi) for p in space}, "age": (0.0, float(search.max_age))})


def _minimise(search: _Search, space: list[Parameter], held: Candidate) -> Candidate:
    """The candidate of least misfit found by a bounded Nelder-Mead search over `space` (each
    parameter mapped to [0, 1], log scales in log), from the parameters' starts, within
    MAX_EVALUATIONS rollouts; the fields not in `space` keep `held`'s values."""

    def candidate(unit: np.ndarray) -> Candidate:
        return held._replace(**{p.name: p.value(u) for p, u in zip(space, unit, strict=True)})

    start = np.array([p.unit(p.start) for p in space])
    simplex = [start] + [start + np.where(np.arange(len(space)) == k, FIRST_STEP if start[k] + FIRST_STEP <= 1.0 else -FIRST_STEP, 0.0)
                         for k in range(len(space))]
    result = optimize.minimize(lambda unit: search.misfit(candidate(unit))[0], start, method="Nelder-Mead",
                               bounds=[(0.0, 1.0)] * len(space),
                               options={"initial_simplex": np.array(simplex), "maxfev": search.evaluations, "xatol": 0.01, "fatol": 1e-3})
    return _key(candidate(result.x))
