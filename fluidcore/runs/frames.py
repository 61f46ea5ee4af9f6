"""What a run records of one frame: the state file's arrays (the particles, the visual
Gaussians and, where the run simulates it, the air), read and written torch-free, so the API and
the exporter read a frame without the simulator. The arrays are listed in `fluidcore.runs`."""

from __future__ import annotations

import io
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fluidcore.files import atomic_output
from fluidcore.runs.layout import RunError

GAUSSIAN_FIELDS = ("means", "log_scales", "quats", "opacity_logits", "colors")
AIR_FIELDS = ("air_x", "air_y", "air_z")
AIR_VERSION = 1  # the layout of the air arrays in a state file (fluidcore.runs); a reader refuses a later one


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
