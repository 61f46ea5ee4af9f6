"""Which way is up in a camera file's world: the axis buoyancy lifts the smoke along, the box's
floor faces, and the source's cues, the wind's heights and the plots measure heights on.

The scene box is axis-aligned, so up is one of the six axis directions. It is found, in order:

1. from the user (`--world-up`, the reconstruct job's `world_up`): they know their world;
2. from the camera file's top-level `up` (FluidNexus's own camera files write it; a Blender
   export, +z up, can say so in one line);
3. from the cameras: their mean image-up direction (each camera's -y axis in the world, as
   nerfstudio orients a capture), when it lies within `MAX_TILT_DEG` of an axis. A rig around
   the smoke averages its tilts away; one camera tilted down by less than that reads right too;
4. else +y, the convention of the dev scenes, ScalarFlow and PINF's files.

Exports, scene info and what-if parameters stay in the user's world: nothing is rotated, the
physics takes `up` as a parameter.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from fluidcore.cameras.camera import Camera, CameraError
from fluidcore.cameras.json_formats import top_level_fields
from fluidcore.spec.physics import Vec3
from fluidcore.spec.scene import UP_AXES, UpAxis, UpFound

DEFAULT_UP: UpAxis = "+y"
# The cameras' mean image up may be this far from an axis and still name it. A rig level with the
# smoke (D, F, H, ScalarFlow) is within 1 degree; a single camera looking down at the smoke by 30
# degrees or more is as close to a horizontal axis as to the vertical one, so it names none.
MAX_TILT_DEG = 30.0
# A declared `up` given as three numbers may be off an axis by rounding only.
MAX_DECLARED_TILT_DEG = 1.0
# The mean of the cameras' image ups must be at least this long: cameras rolled every which way
# (a turntable of phones) agree on no up.
MIN_AGREEMENT = 0.5

@dataclass(frozen=True)
class WorldUp:
    """The world's up axis and how it was found (recorded in the run, shown in scene info)."""

    axis: UpAxis
    found: UpFound

    @property
    def vector(self) -> Vec3:
        return UP_AXES[self.axis]


def parse_axis(value: Any, field_name: str) -> UpAxis:
    """The axis `value` names: "+z", "z", "-y", or three numbers along an axis. Anything else is
    a CameraError naming the field: the box is axis-aligned, so up must be one of its axes."""
    if isinstance(value, str):
        text = value.strip().lower()
        text = text if text[:1] in "+-" else "+" + text
        if text in UP_AXES:
            return text
        raise CameraError(f"{field_name}: {value[:40]!r} is not an axis; give one of {', '.join(UP_AXES)}")
    try:
        vector = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        vector = np.zeros(0)
    if vector.shape != (3,) or not np.all(np.isfinite(vector)) or not np.any(vector):
        raise CameraError(f"{field_name}: give an axis ({', '.join(UP_AXES)}) or three numbers along one, got {str(value)[:60]}")
    axis, tilt = nearest_axis(vector)
    if tilt > MAX_DECLARED_TILT_DEG:
        raise CameraError(f"{field_name}: {vector.tolist()} is {tilt:.1f} degrees off the nearest axis ({axis}); the scene "
                          "box is axis-aligned, so up must lie along one of its axes")
    return axis


def nearest_axis(vector: np.ndarray) -> tuple[UpAxis, float]:
    """The axis nearest the direction of `vector` (3,), non-zero, and the angle to it in degrees."""
    unit = vector / np.linalg.norm(vector)
    index = int(np.argmax(np.abs(unit)))
    axis = ("+" if unit[index] > 0 else "-") + "xyz"[index]
    return axis, math.degrees(math.acos(min(1.0, abs(float(unit[index])))))


def declared_up(path: str | Path) -> UpAxis | None:
    """The axis a camera JSON file's top-level `up` names; None when it has none (or is a COLMAP model)."""
    fields = top_level_fields(Path(path))
    if fields is None or fields.get("up") is None:
        return None
    return parse_axis(fields["up"], f"{Path(path).name}: up")


def cameras_up(cameras: Mapping[str, Camera] | Sequence[Camera]) -> UpAxis | None:
    """The axis the cameras' mean image up points along, or None when they agree on none (see
    MAX_TILT_DEG and MIN_AGREEMENT)."""
    found = list(cameras.values()) if isinstance(cameras, Mapping) else list(cameras)
    if not found:
        return None
    ups = np.stack([camera.camera_to_world()[:3, :3] @ np.array([0.0, -1.0, 0.0]) for camera in found])
    mean = ups.mean(axis=0)
    if np.linalg.norm(mean) < MIN_AGREEMENT:
        return None
    axis, tilt = nearest_axis(mean)
    return axis if tilt <= MAX_TILT_DEG else None


def world_up(path: str | Path, cameras: Mapping[str, Camera], given: str | None = None) -> WorldUp:
    """The up of the world of the camera file at `path` with its `cameras`, in the order of the
    module docstring; `given` is the user's axis (already parsed)."""
    if given is not None:
        return WorldUp(parse_axis(given, "world_up"), "given")
    declared = declared_up(path)
    if declared is not None:
        return WorldUp(declared, "camera file")
    inferred = cameras_up(cameras)
    if inferred is not None:
        return WorldUp(inferred, "cameras")
    return WorldUp(DEFAULT_UP, "default")
