"""The scene spec: what a simulator is built from (`fluidcore.physics.build.build_simulator`).

A scene is the box the particles live in, the up axis, the physics constants (`PBFConfig`, in
this scene's units), the source that seeds the smoke, the air around it and the motion model
that moves the smoke (`MOTION_MODELS`). Reconstruction, identification, calibration and every
continuation build their simulator from one of these, so they all simulate the same physics
(the air included when it is on).

In a run's manifest the "scene" record holds box, up, physics, source, air, motion and solids
(`to_json`): it is the one record of the physics the run simulates, which a continuation reads
back as it is (`fluidcore.runs.RunRecord.scene`). A record without the air is still air; one
without the motion model is the paper's (every run written before the carrier existed); one
without solids has none (every run written before them, issue 48).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, replace
from typing import Any, Literal

from fluidcore.errors import InputError
from fluidcore.spec.physics import Box, PBFConfig, PhysicsInputError, Source, Vec3, vec3
from fluidcore.spec.simulation import AIR_CELLS, MOTION_MODELS, MotionModel
from fluidcore.spec.solids import SolidBall, SolidError, check_solids


# The scene box is axis-aligned, so up is one of its six axis directions (fluidcore.cameras.world_up
# finds which; a run records how: `UpFound`).
UP_AXES: dict[str, Vec3] = {
    "+x": (1.0, 0.0, 0.0), "-x": (-1.0, 0.0, 0.0),
    "+y": (0.0, 1.0, 0.0), "-y": (0.0, -1.0, 0.0),
    "+z": (0.0, 0.0, 1.0), "-z": (0.0, 0.0, -1.0),
}
UpAxis = Literal["+x", "-x", "+y", "-y", "+z", "-z"]
UpFound = Literal["given", "camera file", "cameras", "default"]


class SceneError(InputError):
    """A scene that cannot be simulated (or a malformed scene record); the message names the field."""


@dataclass(frozen=True)
class Air:
    """The air a scene simulates around its smoke: an incompressible grid with `cells` cells on
    the box's long side (0: still air, the default), vorticity confinement `vorticity`
    (`fluidcore.physics.air.AirGrid`'s epsilon; 0 = off), and for the carrier
    (`fluidcore.physics.carrier`) its eddy viscosity `viscosity` and the smoke's turbulent
    `diffusivity` (world units^2 / s)."""

    cells: int = 0
    vorticity: float = 0.0
    viscosity: float = 0.0
    diffusivity: float = 0.0

    def __post_init__(self) -> None:
        if isinstance(self.cells, bool) or not isinstance(self.cells, int) or not (
                self.cells == 0 or AIR_CELLS[0] <= self.cells <= AIR_CELLS[1]):
            raise SceneError(f"air.cells must be 0 (still air) or an integer in {AIR_CELLS[0]}..{AIR_CELLS[1]}, got {self.cells!r}")
        for name in ("vorticity", "viscosity", "diffusivity"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 <= value < float("inf"):
                raise SceneError(f"air.{name} must be a finite number >= 0, got {value!r}")
            object.__setattr__(self, name, float(value))

    @property
    def simulated(self) -> bool:
        """Whether the air is a grid the simulator steps (else it is still)."""
        return self.cells > 0


@dataclass(frozen=True)
class SourcePlace:
    """Where a source is, before the physics says what it seeds and how fast: its centre (world)
    and radius (world units). What the source estimate finds, what a whole source hint gives, and
    what a refinement takes from the run it refines (`Source.place`)."""

    center: Vec3
    radius: float

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "center", vec3(self.center, "source.center"))
        except PhysicsInputError as exc:
            raise SceneError(str(exc)) from None
        if isinstance(self.radius, bool) or not isinstance(self.radius, (int, float)) or not 0.0 < self.radius < float("inf"):
            raise SceneError(f"source.radius must be a finite number > 0, got {self.radius!r}")
        object.__setattr__(self, "radius", float(self.radius))

    @classmethod
    def of(cls, source: Source) -> SourcePlace:
        """Where `source` is."""
        return cls(source.center, source.radius)

    def to_json(self) -> dict[str, Any]:
        return {"center": list(self.center), "radius": self.radius}


@dataclass(frozen=True)
class Scene:
    """Where the particles live and under which physics: everything a simulator is built from.

    `physics` is the scene's `PBFConfig` (world units, with the `length_scale` and kernel radius
    `h` chosen for this scene), `source` its `Source`, (`box_lo`, `box_hi`) the simulation box,
    `up` the scene's up axis, `air` the air around the smoke, `motion` the model that moves
    it (`MOTION_MODELS`; the carrier is its air, so it needs `air.simulated`) and `solids` the
    static balls in the box the smoke flows around (`fluidcore.spec.solids`; the simulator built
    from the scene steps with them, `fluidcore.physics.build.build_simulator`).
    """

    box_lo: Vec3
    box_hi: Vec3
    up: Vec3
    physics: PBFConfig
    source: Source
    air: Air = field(default_factory=Air)
    motion: MotionModel = "paper"
    solids: tuple[SolidBall, ...] = ()

    def __post_init__(self) -> None:
        try:
            for name in ("box_lo", "box_hi", "up"):
                object.__setattr__(self, name, vec3(getattr(self, name), f"scene.{name}"))
        except PhysicsInputError as exc:
            raise SceneError(str(exc)) from None
        if not all(lo < hi for lo, hi in zip(self.box_lo, self.box_hi)):
            raise SceneError("scene.box_lo must be below scene.box_hi on every axis")
        if not any(self.up):
            raise SceneError("scene.up must not be 0")
        for value, kind, name in ((self.physics, PBFConfig, "physics"), (self.source, Source, "source"), (self.air, Air, "air")):
            if not isinstance(value, kind):
                raise SceneError(f"scene.{name} must be a {kind.__name__}, got {type(value).__name__}")
        if self.motion not in MOTION_MODELS:
            raise SceneError(f"scene.motion must be one of {', '.join(MOTION_MODELS)}, got {self.motion!r}")
        if self.motion == "carrier" and not self.air.simulated:
            raise SceneError("scene.air.cells must be > 0 for the carrier: its air is the motion")
        object.__setattr__(self, "solids", tuple(self.solids))
        if not all(isinstance(solid, SolidBall) for solid in self.solids):
            raise SceneError("scene.solids must be SolidBall instances")
        try:
            check_solids(self.solids, self.box_lo, self.box_hi, "scene.solids")
        except SolidError as exc:
            raise SceneError(str(exc)) from None

    @property
    def box(self) -> Box:
        """The simulation box as the simulator takes it."""
        return Box(self.box_lo, self.box_hi)

    def to_json(self) -> dict[str, Any]:
        """The manifest's "scene" record (module docstring)."""
        return json.loads(json.dumps({
            "box": {"lo": list(self.box_lo), "hi": list(self.box_hi)},
            "up": list(self.up),
            "physics": asdict(self.physics),
            "source": asdict(self.source),
            "air": asdict(self.air),
            "motion": self.motion,
            "solids": [solid.model_dump(mode="json") for solid in self.solids],
        }))

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> Scene:
        """The scene of a manifest's "scene" record; a record without "air" is still air, one
        without "motion" the paper's, one without "solids" has none."""
        def tuples(d: Mapping[str, Any]) -> dict[str, Any]:
            return {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}

        try:
            return cls(
                box_lo=tuple(map(float, data["box"]["lo"])),
                box_hi=tuple(map(float, data["box"]["hi"])),
                up=tuple(map(float, data["up"])),
                physics=PBFConfig(**tuples(data["physics"])),
                source=Source(**tuples(data["source"])),
                air=Air(**data.get("air", {})),
                motion=data.get("motion", "paper"),
                solids=tuple(SolidBall(**solid) for solid in data.get("solids", [])),
            )
        except (KeyError, TypeError, ValueError, InputError) as exc:
            raise SceneError(f"scene: malformed ({exc})") from None

    def with_buoyancy_scaled(self, factor: float) -> Scene:
        """This scene with its buoyancy (`PBFConfig.alpha`) times `factor`."""
        return replace(self, physics=replace(self.physics, alpha=self.physics.alpha * factor))
