"""Physics identified per scene from the observed input view (issue 12), not taken from a dataset.

The dataset presets (`fluidcore.physics.PRESETS`) hold constants tuned on one capture: their
buoyancy, in particular, sets how fast a plume rises, and a plume from another source, in
other units or another gas rises at its own rate. Here the buoyancy (an acceleration along
up, world units / s^2) and the age of the plume at the first frame are chosen so that the simulated plume, rendered into the input camera, covers
what the video shows frame after frame:

    observed    the smoke mask of every observed frame (|frame - background| above the noise),
                pooled onto cells about one kernel radius wide;
    simulated   the physics of this scene (box, source, kernel radius, drag and rest density of
                the prior preset) run from an empty box; each step's particles projected into
                the same camera mark their cells;
    misfit      mean over the frames of 1 - IoU(simulated cells, observed cells), plus the mean
                distance between the simulated and observed tops of the plume (the rise, which
                the IoU of a thin column barely sees) as a fraction of the image, averaged over
                ROLLOUT_SEEDS seedings of the source and minimised also over the plume's age
                (how many steps the source had been emitting when frame 0 was taken), which one
                rollout per seeding answers for every age.

Rendering by cell occupancy instead of splatting Gaussians keeps a candidate at one simulation
per seeding (a second or two) and compares what the image fit cannot change later: where smoke
is. The search is coarse to fine (five buoyancies in log steps around one read off the video's
rise speed; then the plume's spreading rate, `SPREADING_RATES`: how fast the air it entrains
widens it, `fluidcore.physics.entrainment`; then the source's radius within 0.8-1.25x of the
image estimate of `fluidcore.reconstruct.source_estimate.estimate_source`, resting on the same bottom
edge, and its height half a radius either way, since a smoke edge biases both (a source the user
gave stays as given: `SourceKept`); then two finer buoyancy steps), bounded by MAX_EVALUATIONS candidates. Each stage keeps the previous stages'
choice unless one of its own candidates beats it. The rise is scored over the whole observed
window (MAX_SECONDS), the source over its first SOURCE_SECONDS, before the plume's head
spreads. The radius range stays narrow: given half to twice, the silhouette misfit chose 0.57x
the true radius on dev scene D and 0.69x the rig's on ScalarFlow, and with the spreading rate
searched too still 0.62x on D and 0.49x on ScalarFlow (0.86x on F), where the image estimate is
within 24% on both dev scenes.

The inflow speed is the terminal speed of the identified buoyancy (`identify` says why it is
not searched on its own). The candidates' rollouts seed what their inlet carries at that speed at
rest density (n0 pi r^2 v dt, n0 = 8 rho0 / h^3); the reconstruction seeds the smoke volume the
video shows leaving the inlet, at the observed rise speed where that is faster
(`fluidcore.reconstruct.scene_physics.inflow_rate_speed` says why the two differ). Both are capped by the quality's particle budget. Drag and
rest density stay the prior's (a silhouette says little about them); they are recorded as
such. Smoke that rises in the video never gets zero buoyancy: candidates are positive by
construction and `buoyancy_floor` bounds them below by the acceleration needed to hold the
observed rise speed against drag.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
import torch
from scipy import ndimage

from fluidcore.cameras import Camera
from fluidcore.errors import InputError
from fluidcore.physics import Box, PBFConfig, Source
from fluidcore.physics.build import build_simulator
from fluidcore.runs import IdentificationPrior, IdentifiedRecord
from fluidcore.spec.physics import Vec3
from fluidcore.spec.scene import Air, Scene, SourcePlace
from fluidcore.spec.simulation import PHYSICS_MODES
from fluidcore.spec.source_hint import SourceKept

# Windows in seconds, counted in frames at the clip's rate (`PBFConfig.frames_in`); measured at 30 fps.
MAX_AGE_SECONDS = 1.5  # how long the source may have been emitting before the first observed frame
# Observed frames the misfit is measured over (the first ones): the whole window of a clip up to
# 4 s. Over the first 45 only, ScalarFlow's misfit told buoyancy 0.5x from 0.7x drag x rise speed
# by 0.011-0.014 (seeds 0-2), less than one seeding differs from another (0.03); over its 90
# frames by 0.04-0.06, and 0.5x wins on D and F too (docs/bench_generalise.md, "Identification
# from the whole window"; i22_ident_misfit_scans.json).
MAX_SECONDS = 4.0
# ... but the source's size and height are judged on the first 45 (1.5 s at 30 fps): later frames
# show the truth's head spreading, which a column can only match with a wider inlet. Over 90
# frames the silhouettes of F preferred its image radius to 0.8x of it (0.364 against 0.371,
# mean of 6 seedings), over the first 45 0.8x by 0.289 against 0.336 (D: 0.343 against 0.357).
SOURCE_SECONDS = 1.5
MAX_EVALUATIONS = 20  # candidates rolled out per identification (ROLLOUT_SEEDS times each), all stages together
OCCUPIED = 0.3  # fraction of a cell's pixels that must be smoke for the cell to count as smoke
FOOTPRINT = 1  # cells (about a kernel radius each) around a particle that its smoke covers
FLOOR_FRACTION = 0.5  # buoyancy floor: this fraction of drag x observed rise speed
BUOYANCY_FACTORS = (0.25, 0.5, 1.0, 2.0, 4.0)  # stage-1 grid around the video's estimate
SOURCE_SIZES = (0.8, 1.0, 1.25)  # source radius factors (stage 2a); why not wider: docs/bench_generalise.md, "Where the source is, measured"
SOURCE_LIFTS = (-0.5, 0.5)  # then the centre moves along up from there, in radii of the estimate (stage 2b)
# Spreading rates db/dz tried (stage 1b, fluidcore.physics.entrainment): MTT's 6/5 alpha_e for an
# entrainment coefficient alpha_e of 0 (the paper's column), 0.05 and 0.1 (laboratory plumes).
SPREADING_RATES = (0.0, 0.06, 0.12)
ROLLOUT_SEEDS = 3  # seedings of the source each candidate's misfit is averaged over (see _Search.misfit)
REFINE = (2.0**0.5, 2.0**0.25)  # step of each refinement stage (factor per grid step)


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
    """The least buoyancy a plume rising at `rise_speed` may be given (0 when it does not rise).

    Sparse smoke tends to the terminal speed buoyancy / drag, and an inflow's momentum is
    gone after a few 1/drag; smoke seen rising at speed u therefore needs a buoyancy near
    drag x u, and never zero. FLOOR_FRACTION leaves room for the inflow's share.
    """
    if not math.isfinite(rise_speed) or rise_speed <= 0.0:
        return 0.0
    return FLOOR_FRACTION * max(drag, 1e-3) * rise_speed


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


# (buoyancy, source lift along up in radii, source radius factor, spreading rate db/dz)
Candidate = tuple[float, float, float, float]


@dataclass(frozen=True)
class ScenePrior:
    """A scene before its physics is chosen: box, up and air as the reconstruction sets them, the
    physics mode (`PHYSICS_MODES`) and its prior preset's physics in this scene's units, and
    where the source was estimated to be (`place`); what the source seeds, and how fast, is what
    the physics decides. `seed` seeds the source's particles."""

    box: Box
    up: Vec3  # unit length
    air: Air
    mode: str
    physics: PBFConfig
    place: SourcePlace
    seed: int

    @property
    def preset(self) -> str:
        return PHYSICS_MODES[self.mode]

    def scene(self, physics: PBFConfig, place: SourcePlace, rate: int, velocity: np.ndarray) -> Scene:
        """This scene under `physics`, its source at `place` seeding `rate` particles per step at `velocity`."""
        source = Source(place.center, place.radius, rate, tuple(float(c) for c in velocity), self.seed)
        return Scene(self.box.lo, self.box.hi, self.up, physics, source, self.air)


class _Search:
    """Rollouts of candidates (cached per candidate) scored against the observation's first
    frames (cached per candidate and window). Each rollout simulates the prior's scene (its air
    included) under the candidate's physics."""

    def __init__(self, observation: Observation, prior: ScenePrior, up: np.ndarray, budget: int,
                 device: torch.device | str) -> None:
        self.observation, self.prior = observation, prior
        self.up, self.budget, self.device = up, budget, device
        self.frames = min(len(observation.cells), prior.physics.frames_in(MAX_SECONDS))
        self.source_frames = prior.physics.frames_in(SOURCE_SECONDS)
        self.max_age = prior.physics.frames_in(MAX_AGE_SECONDS)
        self.rollouts: dict[Candidate, list[np.ndarray]] = {}  # per seeding: (max_age + frames, gh, gw) bool
        self.scores: dict[tuple[Candidate, int], tuple[float, int]] = {}

    def has_room(self, candidate: Candidate) -> bool:
        """Whether `candidate` can be scored: rolled out already, or fewer than MAX_EVALUATIONS were."""
        return _key(candidate) in self.rollouts or len(self.rollouts) < MAX_EVALUATIONS

    def misfit(self, candidate: Candidate, frames: int | None = None) -> tuple[float, int]:
        """(least misfit over the plume ages, that age) of one candidate over the first `frames`
        observed frames (default: all of them, up to MAX_SECONDS). The misfit of each age is
        averaged over ROLLOUT_SEEDS seedings of the source: one seeding's misfit has a spread of
        0.005-0.016 over seeds (six seedings of three source sizes on D and F), more than the 0.004
        by which ScalarFlow's seed 0 once preferred buoyancy 0.27 to 0.19 (docs/bench_generalise.md,
        "Identification from the whole window")."""
        key, frames = _key(candidate), self.frames if frames is None else min(frames, self.frames)
        if (key, frames) not in self.scores:
            if key not in self.rollouts:
                scene = self.scene(key)
                self.rollouts[key] = [self._simulate(replace(scene, source=replace(scene.source, seed=scene.source.seed + k)))
                                      for k in range(ROLLOUT_SEEDS)]
            scores = np.mean([self._age_scores(simulated, frames) for simulated in self.rollouts[key]], axis=0)
            age = int(np.argmin(scores))
            self.scores[(key, frames)] = (float(scores[age]), age)
        return self.scores[(key, frames)]

    def tried(self) -> dict[str, tuple[float, float]]:
        """The least and greatest value of each parameter the rolled-out candidates tried, for the
        parameters the search varied: whether the choice sits on an end of what was searched
        (fluidcore.health). Buoyancy in world units / s^2, the source's radius and its centre's
        height along up in world units, the spreading rate db/dz, the plume's age in frames."""
        place, up = self.prior.place, self.up
        values = {
            "buoyancy": [c[0] for c in self.rollouts],
            "source_radius": [place.radius * c[2] for c in self.rollouts],
            "source_height": [float(np.dot(place.center, up)) + c[1] * place.radius for c in self.rollouts],
            "entrainment": [c[3] for c in self.rollouts],
        }
        ranges = {name: (min(v), max(v)) for name, v in values.items() if v and max(v) > min(v)}
        return {**ranges, "age": (0.0, float(self.max_age))}

    def scene(self, candidate: Candidate) -> Scene:
        """The scene a candidate simulates (inflow at its terminal speed)."""
        buoyancy, lift, radius_factor, spreading = candidate
        config = replace(with_buoyancy(self.prior.physics, buoyancy, self.up), entrainment=spreading)
        speed = config.terminal_speed  # the inflow is not searched on its own: see `identify`
        place = self.prior.place
        radius = place.radius * radius_factor
        center = np.asarray(place.center) + lift * place.radius * self.up
        rate = inlet_rate(radius, speed, config, self.budget)
        return self.prior.scene(config, SourcePlace(tuple(float(c) for c in center), radius), rate, speed * self.up)

    def _simulate(self, scene: Scene) -> np.ndarray:
        """(max_age + frames, gh, gw) bool: the cells a rollout of `scene` from an empty box covers
        after each step (index k = after k + 1 steps)."""
        simulator = build_simulator(scene, device=self.device)
        state = simulator.new_state()
        projected = []
        for _ in range(self.max_age + self.frames):
            simulator.step(state)
            projected.append(self.observation.project(state.positions[state.alive].cpu().numpy().astype(np.float64)))
        return np.stack(projected)

    def _age_scores(self, simulated: np.ndarray, frames: int) -> np.ndarray:
        """(max_age + 1,) misfit of one rollout over the first `frames` observed frames, per plume age."""
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
    return tuple(round(float(x), 9) for x in candidate)  # type: ignore[return-value]


def with_buoyancy(config: PBFConfig, buoyancy: float, up: np.ndarray) -> PBFConfig:
    """`config` whose body acceleration is `buoyancy` along `up` (alpha in the config's units)."""
    gravity_along_up = -float(np.dot(config.gravity, up))  # 9.8 when gravity points down
    return replace(config, alpha=-buoyancy * config.length_scale / gravity_along_up)


def identify(
    observation: Observation,
    prior: ScenePrior,
    budget: int,
    device: torch.device | str = "cpu",
    spreading_rates: Sequence[float] = SPREADING_RATES,
    keep: SourceKept = "nothing",
) -> IdentifiedRecord:
    """Buoyancy, inflow speed and rate, and plume age for this scene (see the module docstring).

    The inflow speed is the buoyancy's terminal speed rather than a search dimension of its own:
    on a synthetic plume, halving it changed the silhouette misfit by 0.002 where halving the
    buoyancy changed it by 0.04 (its momentum is gone within a few 1/drag), so the images do
    not pin it down. `prior` is the scene to start from (the preset in this scene's units, the estimated
    source's place); `budget` caps the particles seeded per step; `spreading_rates` are the plume's
    spreading rates tried, the first one before the others (`(0.0,)`: no entrainment). `keep`:
    what of the prior's source the user gave and the search leaves as it is (`SourceKept`).
    """
    if not observation.cells.any():
        raise IdentificationError("no smoke in the observed frames to identify the physics from")
    config, place = prior.physics, prior.place
    up_v = np.asarray(prior.up, dtype=np.float64) / np.linalg.norm(prior.up)
    speed_obs = rise_speed(observation, np.asarray(place.center), 1.0 / config.dt)
    prior_buoyancy = float(np.dot(config.body_acceleration, up_v))
    floor = buoyancy_floor(speed_obs, config.drag)
    base = max(prior_buoyancy, config.drag * speed_obs, floor, 1e-6)
    search = _Search(observation, prior, up_v, budget, device)
    best = _best(search, None, [(base * f, 0.0, 1.0, spreading_rates[0]) for f in BUOYANCY_FACTORS], floor)
    a = best[0]
    best = _best(search, best, [(a, 0.0, 1.0, rate) for rate in spreading_rates], floor)
    spreading = best[3]
    # A resized source keeps resting on the smoke's bottom edge (source_estimate.source_in_view): its centre
    # moves up by (size - 1) radii; only then is the height searched on its own. Both over the
    # first SOURCE_SECONDS only (see there).
    if keep == "nothing":
        best = _best(search, best, [(a, size - 1.0, size, spreading) for size in SOURCE_SIZES], floor, search.source_frames)
        a, lift, size, _ = best
        best = _best(search, best, [(a, lift + step, size, spreading) for step in SOURCE_LIFTS], floor, search.source_frames)
    elif keep == "center":  # a radius measured around the given centre, which stays
        best = _best(search, best, [(a, 0.0, size, spreading) for size in SOURCE_SIZES], floor, search.source_frames)
    for step in REFINE:
        a, lift, size, spreading = best
        best = _best(search, best, [(a / step, lift, size, spreading), (a * step, lift, size, spreading)], floor)
    misfit, age = search.misfit(best)
    fitted = search.scene(best).source
    held = ("drag", "rho0", *KEPT_SOURCE[keep])
    record = IdentificationPrior(preset=prior.preset, buoyancy=prior_buoyancy, drag=config.drag, rho0=config.rho0,
                                 held_from_prior=held, inflow_speed="buoyancy / drag", budget=budget, source=place)
    return IdentifiedRecord(buoyancy=max(best[0], floor), inflow_speed=float(np.dot(fitted.velocity, up_v)), rate=fitted.rate,
                            age=age, misfit=misfit, rise_speed=speed_obs, floor=floor, evaluations=len(search.rollouts),
                            source_center=fitted.center, source_radius=fitted.radius, entrainment=best[3], prior=record,
                            tried=search.tried())


def _best(search: _Search, incumbent: Candidate | None, grid: list[Candidate], floor: float,
          frames: int | None = None) -> Candidate:
    """One stage of the coordinate search: of `incumbent` (the previous stages' choice) and the
    grid (buoyancies clamped to the floor; points past MAX_EVALUATIONS rollouts left out), the
    candidate with the least misfit over the first `frames` observed frames (default all).
    Stages compare their own candidates only, since they may score different windows."""
    candidates = [] if incumbent is None else [incumbent]
    candidates += [c for c in ((max(b, floor, 1e-6), lift, size, rate) for b, lift, size, rate in grid) if search.has_room(c)]
    return min(candidates, key=lambda c: search.misfit(c, frames)[0])
