"""A run folder read and written: `RunRecord`, a manifest with typed accessors (what every reader
of a run sees, whether it holds the folder or only the manifest's bytes), and `Run`, the folder
itself, opened for reading or written frame after frame (resumable)."""

from __future__ import annotations

import json
import os
import platform
from collections.abc import Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from fluidcore.files import atomic_output
from fluidcore.runs.frames import FrameState
from fluidcore.runs.layout import BACKGROUND, FORMAT, FORMAT_VERSION, MANIFEST, REFINED_RUN, RunError, RunKind, state_file
from fluidcore.runs.migrate import parse_manifest
from fluidcore.runs.records import ReconstructSettings, Settings, settings_model
from fluidcore.spec.reconstruct import VisualSettings
from fluidcore.spec.scene import Scene, SceneError


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


class RunRecord:
    """A run's manifest, read and migrated (`fluidcore.runs.migrate`), with typed accessors: what every reader
    of a run sees, whether it holds the folder (`Run`) or only the manifest's bytes (the API,
    from storage: `from_bytes`)."""

    def __init__(self, manifest: dict[str, Any]) -> None:
        self.manifest = manifest

    @classmethod
    def from_bytes(cls, data: bytes, where: str) -> RunRecord:
        """The manifest in `data` (`where` names it in errors)."""
        return cls(parse_manifest(data, where))

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
        return cls(path, parse_manifest(manifest_path.read_bytes(), str(manifest_path)))

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
