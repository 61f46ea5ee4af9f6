"""The run folder: what a reconstruction (or a prediction built on one) leaves on disk.

A run is generic on purpose: cameras, a frame range, one particle state per frame and an
optional parent run. Reconstruction, prediction, interaction and re-simulation all write the
same format, so one renderer and one exporter serve them all.

Layout (format version 1)::

    RUN/
      manifest.json            everything but the arrays (see below); rewritten atomically
      background.npz           optional: one static background image per camera, key = camera name,
                               float32 (H, W, C) in [0, 1] at that camera's full resolution
      states/frame_000123.npz  the state after frame 123 (frame numbers are video frame indices)

`manifest.json` keys:

    format, format_version   "fluidnexus-run", 1
    kind                     "reconstruct" | "predict" | "interact" | "resimulate" | ...
    parent                   the run this one continues, as a path relative to this run folder (so a
                             chain of runs moves as one: another work dir, another worker), or null;
                             an absolute path (written before this rule) is still read
    created, versions        UTC ISO time; {"fluidnexus", "torch", "numpy", "python"}
    cameras                  {name: {fx, fy, cx, cy, width, height, world_to_camera (4x4), file_path}}
    input_views              camera names whose video was fed in
    fps, frame_range         frames per second; [start, stop) requested
    channels                 1 (grey smoke) or 3
    background_color         list of C floats: what empty space looks like from any camera
    scene                    {"box": {"lo", "hi"}, "up", "physics": PBFConfig fields, "source": Source fields}
    settings                 free-form dict of the settings that produced the run
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

Resuming: a writer opens an existing folder with `Run.create(...)`; if the folder holds a run
with the same kind, cameras and settings, the completed frames are kept and `next_frame()` says
where to go on. A folder holding a different run is refused rather than overwritten.
"""

from __future__ import annotations

import json
import os
import platform
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from fluidcore.errors import InputError
from fluidcore.files import atomic_output

FORMAT = "fluidnexus-run"
FORMAT_VERSION = 1
MANIFEST = "manifest.json"
BACKGROUND = "background.npz"
STATES_DIR = "states"
REFINED_RUN = "refined"  # sub-run of a prediction: the reconstruction on its video-model-refined frames
GAUSSIAN_FIELDS = ("means", "log_scales", "quats", "opacity_logits", "colors")


class RunError(InputError):
    """A run folder that is missing, damaged, or holds a different run than expected."""


@dataclass(frozen=True)
class Scene:
    """Where the particles live and under which physics: enough to rebuild the Simulator.

    `physics` holds the `fluidcore.physics.PBFConfig` fields (world units, with the
    `length_scale` and kernel radius `h` chosen for this scene), `source` the
    `fluidcore.physics.Source` fields, `box` the simulation box; `up` is the scene's up axis.
    """

    box_lo: tuple[float, float, float]
    box_hi: tuple[float, float, float]
    up: tuple[float, float, float]
    physics: dict[str, Any]
    source: dict[str, Any]

    def __post_init__(self) -> None:
        for name in ("box_lo", "box_hi", "up"):
            value = np.asarray(getattr(self, name), dtype=np.float64)
            if value.shape != (3,) or not np.all(np.isfinite(value)):
                raise RunError(f"scene.{name} must be 3 finite numbers, got {getattr(self, name)!r}")
        if not np.all(np.asarray(self.box_lo) < np.asarray(self.box_hi)):
            raise RunError("scene.box_lo must be below scene.box_hi on every axis")

    def to_json(self) -> dict[str, Any]:
        return json.loads(
            json.dumps(
                {
                    "box": {"lo": list(self.box_lo), "hi": list(self.box_hi)},
                    "up": list(self.up),
                    "physics": self.physics,
                    "source": self.source,
                }
            )
        )

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> Scene:
        try:
            return cls(
                box_lo=tuple(map(float, data["box"]["lo"])),
                box_hi=tuple(map(float, data["box"]["hi"])),
                up=tuple(map(float, data["up"])),
                physics=dict(data["physics"]),
                source=dict(data["source"]),
            )
        except (KeyError, TypeError) as exc:
            raise RunError(f"scene: malformed ({exc})") from None

    def simulator_parts(self) -> tuple[Any, Any, Any]:
        """(PBFConfig, Box, Source) as recorded: what a continuation passes to `Simulator`."""
        from fluidcore.physics import Box, PBFConfig, Source

        def tuples(d: dict[str, Any]) -> dict[str, Any]:
            return {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}

        return PBFConfig(**tuples(self.physics)), Box(self.box_lo, self.box_hi), Source(**tuples(self.source))


@dataclass
class FrameState:
    """One frame's particles, as numpy arrays in world units (see the module docstring)."""

    positions: np.ndarray
    velocities: np.ndarray
    alive: np.ndarray
    time: float
    gaussians: dict[str, np.ndarray]
    extra: dict[str, np.ndarray] = field(default_factory=dict)

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
        return arrays

    def save(self, path: Path) -> None:
        """Write atomically: a reader never sees half a file, a crash leaves the old one."""
        with atomic_output(path) as temporary, temporary.open("wb") as file:
            np.savez(file, **self._arrays())

    @classmethod
    def load(cls, path: Path) -> FrameState:
        try:
            with np.load(path) as data:
                arrays = {k: data[k] for k in data.files}
        except (OSError, ValueError) as exc:
            raise RunError(f"state file {path}: unreadable ({exc})") from None
        try:
            return cls(
                positions=arrays["positions"],
                velocities=arrays["velocities"],
                alive=arrays["alive"],
                time=float(arrays["time"]),
                gaussians={k: arrays[f"gauss_{k}"] for k in GAUSSIAN_FIELDS},
                extra={k[6:]: v for k, v in arrays.items() if k.startswith("extra_")},
            )
        except KeyError as exc:
            raise RunError(f"state file {path}: missing array {exc}") from None

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


class Run:
    """A run folder opened for reading, or for writing frame after frame."""

    def __init__(self, path: Path, manifest: dict[str, Any]) -> None:
        self.path = path
        self.manifest = manifest

    # -- opening -------------------------------------------------------------------------
    @classmethod
    def open(cls, path: str | os.PathLike[str]) -> Run:
        path = Path(path)
        manifest_path = path / MANIFEST
        if not manifest_path.is_file():
            raise RunError(f"run: {path} is not a run folder (no {MANIFEST})")
        try:
            manifest = json.loads(manifest_path.read_text())
        except json.JSONDecodeError as exc:
            raise RunError(f"run: {manifest_path} is not valid JSON ({exc})") from None
        if manifest.get("format") != FORMAT:
            raise RunError(f"run: {manifest_path} is not a {FORMAT} manifest")
        if manifest.get("format_version") != FORMAT_VERSION:
            raise RunError(f"run: format_version {manifest.get('format_version')} is not supported")
        return cls(path, manifest)

    @classmethod
    def create(
        cls,
        path: str | os.PathLike[str],
        *,
        kind: str,
        cameras: Mapping[str, Any],
        input_views: Sequence[str],
        frame_range: tuple[int, int],
        fps: float,
        channels: int,
        background_color: Sequence[float],
        scene: Scene,
        settings: Mapping[str, Any],
        parent: str | os.PathLike[str] | None = None,
    ) -> Run:
        """Start a run in `path`, or reopen the same run there to resume it."""
        path = Path(path)
        if channels not in (1, 3) or len(background_color) != channels:
            raise RunError(f"channels must be 1 or 3 with as many background values, got {channels}")
        if frame_range[1] <= frame_range[0]:
            raise RunError(f"frame_range: {frame_range} is empty")
        identity = {
            "kind": kind,
            "parent": None if parent is None else _relative(parent, path),
            "cameras": {name: camera_to_json(cam) for name, cam in cameras.items()},
            "input_views": list(input_views),
            "frame_range": [int(frame_range[0]), int(frame_range[1])],
            "fps": float(fps),
            "channels": int(channels),
            "scene": scene.to_json(),
            "settings": json.loads(json.dumps(dict(settings))),
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
    def kind(self) -> str:
        return str(self.manifest["kind"])

    @property
    def channels(self) -> int:
        return int(self.manifest["channels"])

    @property
    def fps(self) -> float:
        return float(self.manifest["fps"])

    @property
    def scene(self) -> Scene:
        return Scene.from_json(self.manifest["scene"])

    @property
    def parent(self) -> Run | None:
        parent = self.manifest.get("parent")
        return None if parent is None else Run.open(self.path / parent)  # an absolute path stays itself

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
        return done[-1] + 1 if done else int(self.manifest["frame_range"][0])

    def state_path(self, t: int) -> Path:
        return self.path / STATES_DIR / f"frame_{t:06d}.npz"

    def read_frame(self, t: int) -> FrameState:
        if t not in self.frames():
            raise RunError(f"frame: {t} is not in this run (frames {self._frames_text()})")
        return FrameState.load(self.state_path(t))

    def frame_log(self, t: int) -> dict[str, Any]:
        for entry in self.manifest["frames"]:
            if entry["t"] == t:
                return dict(entry)
        raise RunError(f"frame: {t} is not in this run (frames {self._frames_text()})")

    def background_images(self) -> dict[str, np.ndarray]:
        path = self.path / BACKGROUND
        if not path.is_file():
            return {}
        with np.load(path) as data:
            return {k: data[k] for k in data.files}

    def _frames_text(self) -> str:
        done = self.frames()
        return f"{done[0]}..{done[-1]}" if done else "none"

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
            "file": f"{STATES_DIR}/frame_{t:06d}.npz",
            "losses": {k: float(v) for k, v in losses.items()},
            "seconds": float(seconds),
        }
        self.manifest["frames"].append(entry)
        self.manifest["complete"] = self.next_frame() >= self.manifest["frame_range"][1]
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
