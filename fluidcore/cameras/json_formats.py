"""Camera JSON files: nerfstudio `transforms.json` and PINF/HyFluid `info.json`.

Both store one camera-to-world `transform_matrix` per entry in OpenGL/Blender camera axes
(x right, y up, looking along -z); we flip y and z to OpenCV axes and invert.

Entries come from `frames` (nerfstudio, and FluidNexus's own transforms.json) or from PINF's
`train_videos` / `val_videos` / `test_videos` lists. Intrinsics are looked up per entry first,
then at the top level (nerfstudio allows both), in this order:
  1. `fl_x`, `fl_y` (fl_y defaults to fl_x), `cx`, `cy` (default w/2, h/2), `w`, `h`;
  2. `camera_angle_x` (horizontal field of view, radians) with the size from `camera_hw` = [H, W]
     or `w`/`h`, or, as PINF does, from the entry's video (`file_name`/`file_path`) when
     that file exists inside the camera file's folder; square pixels and a centred principal
     point.

Lens distortion: nerfstudio's OPENCV model (`k1`, `k2`, `k3`, `p1`, `p2`) becomes the camera's
`distortion` (OpenCV order k1 k2 p1 p2 k3); the reconstruction undistorts the frames with OpenCV
(fluidcore.cameras.undistort) and works with the pinhole camera. `k4` belongs to the fisheye
model, which is rejected. `camera_model` must be PINHOLE, OPENCV or absent.

A camera's name is the entry's `camera` field, else the stem of its `file_path` / `file_name`;
it must follow the naming rule of fluidcore.names (it becomes a file name and a storage key).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from fluidcore.cameras.camera import Camera, CameraError, check_camera_name, check_new_camera, check_rigid
from fluidcore.files import atomic_output

OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])  # flips camera y and z axes
OPENCV_FIELDS = ("k1", "k2", "p1", "p2", "k3")  # nerfstudio's names, in OpenCV's coefficient order
PINF_VIDEO_LISTS = ("train_videos", "val_videos", "test_videos")
SUPPORTED_MODELS = ("PINHOLE", "OPENCV")


def read_json(path: Path) -> dict[str, Any]:
    """Parse a camera JSON file; anything but a JSON object is a CameraError."""
    try:
        data = json.loads(path.read_text(encoding="utf-8-sig"))
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise CameraError(f"{path.name}: not valid JSON ({error})") from error
    except RecursionError:  # Python's parser recurses per nesting level; no camera file nests deeply
        raise CameraError(f"{path.name}: JSON nested too deeply") from None
    if not isinstance(data, dict):
        raise CameraError(f"{path.name}: top level must be a JSON object, got {type(data).__name__}")
    return data


def top_level_fields(path: Path) -> dict[str, Any] | None:
    """The top-level object of a camera JSON file (its box, up, fps, ...); None for a COLMAP model
    (a folder or a zip), which has no such fields."""
    if path.is_dir():
        return None
    with path.open("rb") as handle:
        if handle.read(4) == b"PK\x03\x04":
            return None
    return read_json(path)


def declared_fps(path: Path) -> float | None:
    """The frame rate a camera JSON file states (`fps`, as nerfstudio's and FluidNexus's files may);
    None when it states none. Only checked against the videos' own rate (`fluidcore.video.rate_mismatch`)."""
    fields = top_level_fields(path)
    value = None if fields is None else fields.get("fps")
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value > 0):
        raise CameraError(f"{path.name}: fps must be a positive number, got {value!r}")
    return float(value)


def is_camera_json(data: dict[str, Any]) -> bool:
    """True when the object has camera entries in either layout."""
    return isinstance(data.get("frames"), list) or any(isinstance(data.get(k), list) for k in PINF_VIDEO_LISTS)


def load_json_cameras(path: Path, data: dict[str, Any]) -> dict[str, Camera]:
    """Cameras by name from a parsed transforms.json / info.json (see the module docstring)."""
    entries = _entries(data)
    if not entries:
        raise CameraError(f"{path.name}: frames is empty (no cameras)")
    cameras: dict[str, Camera] = {}
    listed_in: dict[str, str] = {}  # camera name -> the list that first gave it
    for where, entry in entries:
        camera = _entry_camera(path, data, where, entry)
        in_list = where.split("[", 1)[0]
        # PINF lists the same video in train and test; within one list a repeat is a mistake (issue 49:
        # 5 cameras repeated to 65 entries were accepted as 5)
        if camera == cameras.get(camera.name) and listed_in[camera.name] != in_list:
            continue
        check_new_camera(cameras, camera.name, f"{path.name}: {where}")
        cameras[camera.name] = camera
        listed_in[camera.name] = in_list
    return cameras


def _entries(data: dict[str, Any]) -> list[tuple[str, dict[str, Any]]]:
    lists = ["frames"] if isinstance(data.get("frames"), list) else [k for k in PINF_VIDEO_LISTS if k in data]
    entries = []
    for key in lists:
        for i, entry in enumerate(data[key]):
            if not isinstance(entry, dict):
                raise CameraError(f"{key}[{i}] must be an object, got {type(entry).__name__}")
            entries.append((f"{key}[{i}]", entry))
    return entries


def _entry_camera(path: Path, data: dict[str, Any], where: str, entry: dict[str, Any]) -> Camera:
    video = entry.get("file_path", entry.get("file_name"))
    if video is not None and not isinstance(video, str):
        raise CameraError(f"{path.name}: {where}.file_path must be a string or null, got {video!r}")
    name = entry.get("camera", Path(video).stem if video else None)
    if name is None:
        raise CameraError(f"{path.name}: {where}: missing field camera (and no file_path to name it by)")
    if not isinstance(name, str) or not name:
        raise CameraError(f"{path.name}: {where}: camera must be a non-empty string, got {name!r}")
    check_camera_name(name, f"{path.name}: {where}.camera")
    context = f"{path.name}: {where} ({name})"
    try:
        fx, fy, cx, cy, width, height = _intrinsics(path, data, entry, video)
        distortion = _distortion(data, entry)
        camera_to_world = check_rigid(_field(entry, "transform_matrix"), "transform_matrix")
        world_to_camera = np.linalg.inv(camera_to_world @ OPENGL_TO_OPENCV)
        return Camera(name, fx, fy, cx, cy, width, height, world_to_camera, file_path=video, distortion=distortion)
    except CameraError as error:
        raise CameraError(f"{context}: {error}") from None


def _field(entry: dict[str, Any], key: str) -> Any:
    if key not in entry or entry[key] is None:
        raise CameraError(f"missing field {key}")
    return entry[key]


def _lookup(data: dict[str, Any], entry: dict[str, Any], key: str) -> Any:
    """Per-entry value first, then the shared top-level one (nerfstudio semantics)."""
    return entry[key] if entry.get(key) is not None else data.get(key)


def _number(value: Any, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise CameraError(f"{key} must be a number, got {value!r}")
    if not math.isfinite(value):
        raise CameraError(f"{key} must be finite, got {value}")
    return float(value)


def _size(value: Any, key: str) -> int:
    number = _number(value, key)
    if number != int(number) or number <= 0:
        raise CameraError(f"{key} must be a positive integer, got {value!r}")
    return int(number)


def _intrinsics(
    path: Path, data: dict[str, Any], entry: dict[str, Any], video: str | None
) -> tuple[float, float, float, float, int, int]:
    width, height = _image_size(path, data, entry, video)
    fl_x = _lookup(data, entry, "fl_x")
    if fl_x is not None:
        fx = _number(fl_x, "fl_x")
        fl_y = _lookup(data, entry, "fl_y")
        fy = fx if fl_y is None else _number(fl_y, "fl_y")
    else:
        angle = _lookup(data, entry, "camera_angle_x")
        if angle is None:
            raise CameraError("missing field fl_x (or camera_angle_x)")
        angle = _number(angle, "camera_angle_x")
        if not 0.0 < angle < math.pi:
            raise CameraError(f"camera_angle_x must be in (0, pi) radians, got {angle}")
        fx = fy = 0.5 * width / math.tan(0.5 * angle)
    for key, value in (("fl_x", fx), ("fl_y", fy)):
        if value <= 0:
            raise CameraError(f"{key} must be positive (focal length), got {value}")
    cx = _lookup(data, entry, "cx")
    cy = _lookup(data, entry, "cy")
    cx = 0.5 * width if cx is None else _number(cx, "cx")
    cy = 0.5 * height if cy is None else _number(cy, "cy")
    return fx, fy, cx, cy, width, height


def _image_size(path: Path, data: dict[str, Any], entry: dict[str, Any], video: str | None) -> tuple[int, int]:
    w, h = _lookup(data, entry, "w"), _lookup(data, entry, "h")
    if w is not None or h is not None:
        for key, value in (("w", w), ("h", h)):
            if value is None:
                raise CameraError(f"missing field {key}")
        return _size(w, "w"), _size(h, "h")
    hw = _lookup(data, entry, "camera_hw")
    if hw is not None:
        if not isinstance(hw, (list, tuple)) or len(hw) != 2:
            raise CameraError(f"camera_hw must be [height, width], got {hw!r}")
        return _size(hw[1], "camera_hw[1] (width)"), _size(hw[0], "camera_hw[0] (height)")
    video_file = _file_in_folder(path.parent, video) if video else None
    if video_file is not None:
        from fluidcore.video import VideoError, probe

        try:
            info = probe(video_file)
        except VideoError as error:
            raise CameraError(f"missing fields w/h, and the size cannot be read from {video}: {error}") from None
        return info.width, info.height
    raise CameraError(
        "missing fields w and h (or camera_hw, or a readable video in file_path inside the cameras file's folder)"
    )


def _file_in_folder(folder: Path, relative: str) -> Path | None:
    """The file `relative` names if it lies inside `folder` (an absolute path, `..` or a link
    leading out does not count), else None. A camera file is user input: on a server it must not
    make the reader open, or reveal the existence of, any file but the ones uploaded with it."""
    from fluidcore.names import UnsafePath, safe_join

    try:
        candidate = safe_join(folder, relative)
    except UnsafePath:
        return None
    return candidate if candidate.is_file() else None


def _distortion(data: dict[str, Any], entry: dict[str, Any]) -> tuple[float, ...]:
    model = _lookup(data, entry, "camera_model")
    if model is not None and model not in SUPPORTED_MODELS:
        raise CameraError(f"camera_model {model!r} is not supported; use one of {', '.join(SUPPORTED_MODELS)}")
    k4 = _lookup(data, entry, "k4")
    if k4 is not None and _number(k4, "k4") != 0.0:
        raise CameraError(f"k4 = {k4}: a fisheye coefficient; only the OPENCV (k1 k2 k3 p1 p2) lens model is supported")
    values = [_lookup(data, entry, key) for key in OPENCV_FIELDS]
    return tuple(0.0 if v is None else _number(v, key) for key, v in zip(OPENCV_FIELDS, values))


def to_transforms(cameras: Mapping[str, Camera], **top_level: Any) -> dict[str, Any]:
    """A nerfstudio transforms.json object for `cameras` (per-frame intrinsics; OPENCV when a
    camera has lens distortion, else PINHOLE), the exact inverse of the reader; `top_level` adds
    fields such as scene_box or voxel_scale/voxel_matrix."""
    frames = [
        {
            "camera": name,
            "file_path": camera.file_path,
            "fl_x": camera.fx,
            "fl_y": camera.fy,
            "cx": camera.cx,
            "cy": camera.cy,
            "w": camera.width,
            "h": camera.height,
            "transform_matrix": (camera.camera_to_world() @ OPENGL_TO_OPENCV).tolist(),
            **_distortion_fields(camera),
        }
        for name, camera in cameras.items()
    ]
    distorted = any(camera.distortion for camera in cameras.values())
    return {"camera_model": "OPENCV" if distorted else "PINHOLE", **top_level, "frames": frames}


def _distortion_fields(camera: Camera) -> dict[str, float]:
    if not camera.distortion:
        return {}
    if len(camera.distortion) > len(OPENCV_FIELDS) and any(camera.distortion[len(OPENCV_FIELDS):]):
        raise CameraError(f"camera {camera.name!r}: k4..k6 (rational lens model) have no transforms.json field")
    return dict(zip(OPENCV_FIELDS, camera.distortion))


def write_transforms(path: str | Path, cameras: Mapping[str, Camera], **top_level: Any) -> Path:
    """Write `to_transforms(...)` atomically (temporary file, then rename); returns the path."""
    path = Path(path)
    with atomic_output(path, suffix=".json") as temporary, temporary.open("w", encoding="utf-8") as file:
        json.dump(to_transforms(cameras, **top_level), file, indent=1)
    return path
