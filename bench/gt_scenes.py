"""Ground truth of a benchmark scene, one small reader per folder layout (bench/generalise.py).

Every reader answers the same questions, so the protocol never asks which layout it runs on:

    cameras, input path      the cameras file and the ONE video the reconstruction may see
    truth(view, frames)      uint8 (T, H, W, 3) ground-truth frames of a camera (absolute frame numbers)
    velocity(t)              (points (N, 3), velocities (N, 3)) in world units where the smoke is, or None
    top_height(t)            the plume's top along up (world units), or None
    variants()               the counterfactual variants beside the scene (wind / ball with their truth)
    late_start(variant)      first frame of the variant's "late" window

Layouts:

    PhiFlowScene     ../shared/devdata (transforms.json, videos/view_KK.mp4, gt/meta.json, gt/density_ and
                     velocity_XXXX.npz at the saved frames; variants are sibling folders whose meta.json names
                     this scene in `counterfactual_of`, described by the parent folder's protocol.json where
                     there is one (input view, windows, what-ifs), else by each variant's meta.json)
    SynthScene       `fluidnexus synth` (transforms.json, videos/, truth/frame_XXXXXX.npz particles)
    ScalarFlowScene  ../shared/realdata/scalarflow (videos/input_view_02.mp4, gt/nvs_view_0K.mp4 for
                     t < 120, gt/future_view_0K.mp4 frame i = t 60 + i, windows.json)

`open_scene` picks the reader from the files a folder holds.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fluidcore.spec.scene import SourcePlace
from fluidnexus.reporting import UserError

DENSITY_THRESHOLD = 0.05  # GT density above which a voxel counts as smoke (the dev protocol)
TOP_QUANTILE = 0.98  # a plume's top: this quantile of the smoke's height (robust to a stray wisp)


@dataclass(frozen=True)
class Variant:
    """A counterfactual twin of the scene: the same plume under a wind or around a ball."""

    name: str
    scene: GroundTruth
    branch_frame: int  # the factual reconstruction is continued from this frame
    first_frame: int  # the first frame the intervention acts on (scoring starts here)
    wind: dict[str, Any] | None = None  # WindParams fields relative to the first new frame, with a world base_height
    ball: dict[str, Any] | None = None  # BallParams fields relative to the first new frame
    late_start: int = 0


@dataclass
class GroundTruth:
    """A scene folder with ground-truth videos; subclasses say where each file lives."""

    root: Path
    cameras_path: Path
    cameras: dict[str, Any] = field(repr=False)
    n_frames: int
    fps: float

    kind = "scene"

    def input_path(self, view: str) -> Path:
        camera = self.cameras.get(view)
        if camera is None:
            raise UserError(f"--input-view: no camera {view!r} in {self.cameras_path} (have {', '.join(self.cameras)})")
        if not camera.file_path:
            raise UserError(f"--input-view {view}: {self.cameras_path.name} names no video for it")
        return self.root / camera.file_path

    def views(self) -> list[str]:
        """Cameras with ground-truth video."""
        return [name for name, camera in self.cameras.items() if camera.file_path]

    def truth(self, view: str, frames: list[int], size: tuple[int, int] | None = None) -> np.ndarray:
        return read_frames_at(self.root / self.cameras[view].file_path, frames, size)

    def velocity(self, t: int) -> tuple[np.ndarray, np.ndarray] | None:
        return None

    def velocity_frames(self) -> list[int]:
        return []

    def top_height(self, t: int) -> float | None:
        return None

    def source_truth(self) -> SourcePlace | None:
        """The true source's place (world units), where the layout records it."""
        return None

    def source_height(self) -> float | None:
        truth = self.source_truth()
        return None if truth is None else truth.center[1]

    def variants(self) -> list[Variant]:
        return []

    @property
    def protocol(self) -> dict[str, Any] | None:
        """The scene's machine-readable protocol (input view, windows, what-ifs): the parent
        folder's protocol.json when it names this folder as its factual scene."""
        path = self.root.parent / "protocol.json"
        if not path.is_file():
            return None
        protocol = json.loads(path.read_text())
        return protocol if protocol.get("scenes", {}).get("factual") == self.root.name else None


class PhiFlowScene(GroundTruth):
    """The independent-solver layout (../shared/devdata/README.md)."""

    kind = "phiflow"

    @property
    def meta(self) -> dict[str, Any]:
        return json.loads((self.root / "gt" / "meta.json").read_text())

    def velocity_frames(self) -> list[int]:
        return [t for t in self.meta["saved_frames"] if (self.root / "gt" / f"velocity_{t:04d}.npz").is_file()]

    def _grid(self, t: int) -> tuple[np.ndarray, np.ndarray]:
        """(centres (X, Y, Z, 3) world, density (X, Y, Z)) at saved frame t."""
        meta = self.meta
        density = np.load(self.root / "gt" / f"density_{t:04d}.npz")["density"].astype(np.float32)
        axes = [
            meta["domain_world_min"][k] + (np.arange(density.shape[k]) + 0.5) * meta["voxel_size"][k] for k in range(3)
        ]
        centres = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
        return centres, density

    def velocity(self, t: int) -> tuple[np.ndarray, np.ndarray] | None:
        if t not in self.velocity_frames():
            return None
        centres, density = self._grid(t)
        velocity = np.load(self.root / "gt" / f"velocity_{t:04d}.npz")["velocity"].astype(np.float32)
        smoke = density > DENSITY_THRESHOLD
        return centres[smoke].astype(np.float32), velocity[smoke]

    def top_height(self, t: int) -> float | None:
        if t not in self.meta["saved_frames"]:
            return None
        centres, density = self._grid(t)
        smoke = density > DENSITY_THRESHOLD
        return float(np.quantile(centres[smoke][:, 1], TOP_QUANTILE)) if smoke.any() else None

    def source_truth(self) -> SourcePlace | None:
        source = self.meta["source"]
        return SourcePlace(source["center_world"], source["radius"])

    def variants(self) -> list[Variant]:
        protocol = self.protocol
        if protocol is not None:
            return _protocol_variants(protocol, self)
        out = []
        for folder in sorted(p for p in self.root.parent.iterdir() if p.is_dir() and p != self.root):
            meta_path = folder / "gt" / "meta.json"
            if not meta_path.is_file():
                continue
            meta = json.loads(meta_path.read_text())
            if meta.get("counterfactual_of") != self.root.name:
                continue
            variant = _phiflow_variant(folder, meta, self)
            if variant is not None:
                out.append(variant)
        return out


def _phiflow_variant(folder: Path, meta: dict[str, Any], factual: PhiFlowScene) -> Variant | None:
    """A sibling folder's wind or obstacle, in the terms of `fluidcore.spec.controls` (frames counted
    from the first new frame after the branch)."""
    scene = open_scene(folder)
    late = _anchor_late_starts(folder.parent / "anchors.json").get(folder.name)
    wind, obstacle = meta["forces"].get("wind"), meta.get("obstacle")
    if wind is not None:  # an exponential wind whose strength is given at the true source's height
        branch = int(wind["start_frame"]) - 1
        params = {"direction": tuple(wind["direction_world"]), "strength": float(wind["strength"]),
                  "growth": float(wind.get("growth", 0.0)), "base_height": float(wind.get("source_height_world", 0.0)),
                  "start_frame": 0}
        return Variant(folder.name, scene, branch, branch + 1, wind=params,
                       late_start=late if late is not None else branch + 1 + (factual.n_frames - branch - 1) // 3)
    if obstacle is not None and obstacle.get("shape") == "sphere":
        first = int(obstacle.get("present_from_frame", 0))
        branch = max(first - 1, 0)
        params = {"center": tuple(obstacle["center_world"]), "radius": float(obstacle["radius"]),
                  "velocity": tuple(obstacle.get("velocity_world", (0.0, 0.0, 0.0))), "start_frame": max(first - branch - 1, 0)}
        return Variant(folder.name, scene, branch, first, ball=params,
                       late_start=late if late is not None else branch + (factual.n_frames - branch) // 3)
    return None


def _protocol_variants(protocol: dict[str, Any], factual: GroundTruth) -> list[Variant]:
    """The what-ifs of a protocol.json: a wind ramping linearly from zero at world height y0 to
    `acc_top` at y_top (WindParams profile linear, based at y_top, growth 1 / (y_top - y0)) and
    a ball; each branched the frame before it starts, scored late on the protocol's window."""
    out = []
    scenes, wind, ball = protocol["scenes"], protocol.get("wind"), protocol.get("ball")
    if wind is not None and "wind" in scenes:
        start, y0, y_top = int(wind["start_frame"]), float(wind["y0_world"]), float(wind["y_top_world"])
        params = {"direction": tuple(wind["direction"]), "strength": float(wind["acc_top"]), "profile": "linear",
                  "growth": 1.0 / (y_top - y0), "base_height": y_top, "start_frame": 0}
        scene = open_scene(factual.root.parent / scenes["wind"])
        out.append(Variant(scene.root.name, scene, start - 1, start, wind=params, late_start=int(wind["late"][0])))
    if ball is not None and "ball" in scenes:
        first = int(ball.get("start_frame", 0))
        branch = max(first - 1, 0)
        params = {"center": tuple(ball["center"]), "radius": float(ball["radius"]),
                  "velocity": tuple(ball.get("velocity", (0.0, 0.0, 0.0))), "start_frame": max(first - branch - 1, 0)}
        scene = open_scene(factual.root.parent / scenes["ball"])
        out.append(Variant(scene.root.name, scene, branch, first, ball=params, late_start=int(ball["late"][0])))
    return out


def _anchor_late_starts(path: Path) -> dict[str, int]:
    """`{variant: first late frame}` from an anchors.json task line like 'D_wind: frames 45..149, late 75..149'."""
    if not path.is_file():
        return {}
    text = json.loads(path.read_text()).get("tasks", {}).get("counterfactual", "")
    return {name: int(start) for name, start in re.findall(r"(\w+): frames \d+\.\.\d+, late (\d+)\.\.\d+", text)}


class SynthScene(GroundTruth):
    """`fluidnexus synth`: the velocity truth is the simulated particles themselves."""

    kind = "synth"

    def velocity_frames(self) -> list[int]:
        return [int(p.stem.split("_")[1]) for p in sorted((self.root / "truth").glob("frame_*.npz"))]

    def velocity(self, t: int) -> tuple[np.ndarray, np.ndarray] | None:
        path = self.root / "truth" / f"frame_{t:06d}.npz"
        if not path.is_file():
            return None
        data = np.load(path)
        return data["positions"].astype(np.float32), data["velocities"].astype(np.float32)

    def top_height(self, t: int) -> float | None:
        truth = self.velocity(t)
        return None if truth is None or len(truth[0]) == 0 else float(np.quantile(truth[0][:, 1], TOP_QUANTILE))

    def source_truth(self) -> SourcePlace | None:
        source = json.loads((self.root / "synth.json").read_text())["source"]
        return SourcePlace(source["center"], source["radius"])


class ScalarFlowScene(GroundTruth):
    """The real-footage layout (../shared/realdata/README.md section 4): held-out views exist only as
    gt/ clips; frames from the future clip's prediction window are read from it (as the anchors do)."""

    kind = "scalarflow"

    @property
    def windows(self) -> dict[str, Any]:
        return json.loads((self.root / "windows.json").read_text())

    def views(self) -> list[str]:
        return [name for name in self.cameras if (self.root / "gt" / f"nvs_{name}.mp4").is_file()]

    def truth_path(self, view: str) -> Path:
        """The held-out view's clip of the observed window (its frame t = scene frame t)."""
        return self.root / "gt" / f"nvs_{view}.mp4"

    def truth(self, view: str, frames: list[int], size: tuple[int, int] | None = None) -> np.ndarray:
        future = self.windows["future"]
        first_predicted = future["prediction_t"][0]
        offset = first_predicted - future["prediction_clip_frames"][0]  # clip frame i = t - offset
        early = [t for t in frames if t < first_predicted]
        late = [t - offset for t in frames if t >= first_predicted]
        parts = []
        if early:
            parts.append(read_frames_at(self.truth_path(view), early, size))
        if late:
            parts.append(read_frames_at(self.root / "gt" / f"future_{view}.mp4", late, size))
        return np.concatenate(parts)


def read_frames_at(path: Path, frames: list[int], size: tuple[int, int] | None) -> np.ndarray:
    """The listed frames of a video (decoded once over their span)."""
    from fluidcore import video

    if not frames:
        raise UserError(f"{path}: no frames asked")
    clip = video.read_frames(path, min(frames), max(frames) + 1, size=size)
    if len(clip) < max(frames) + 1 - min(frames):
        raise UserError(f"{path}: holds fewer frames than {max(frames) + 1}")
    return clip[[t - min(frames) for t in frames]]


def open_scene(root: Path) -> GroundTruth:
    """The reader for the layout `root` holds (windows.json: ScalarFlow; gt/meta.json: PhiFlow;
    synth.json: synth; otherwise plain camera videos)."""
    from fluidcore import cameras as camera_io
    from fluidcore import video

    root = Path(root)
    cameras_path = root / "transforms.json"
    if not cameras_path.is_file():
        raise UserError(f"SCENE_DIR: {root} holds no transforms.json")
    cameras = camera_io.load(cameras_path)
    if (root / "windows.json").is_file():
        cls: type[GroundTruth] = ScalarFlowScene
    elif (root / "gt" / "meta.json").is_file():
        cls = PhiFlowScene
    elif (root / "synth.json").is_file():
        cls = SynthScene
    else:
        cls = GroundTruth
    info = None
    for camera in cameras.values():
        if camera.file_path and (root / camera.file_path).is_file():
            info = video.probe(root / camera.file_path)
            break
    if info is None:
        raise UserError(f"SCENE_DIR: no camera of {cameras_path} names a video that exists")
    n_frames = info.n_frames
    if cls is ScalarFlowScene:
        n_frames = json.loads((root / "windows.json").read_text())["nvs"]["n_frames"]
    return cls(root, cameras_path, cameras, n_frames, info.fps)
