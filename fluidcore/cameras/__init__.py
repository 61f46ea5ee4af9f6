"""Cameras: one pinhole Camera type (OpenCV axes, continuous pixels), the readers for the camera
files users bring, and scene boxes.

`load(path)` recognises the format from the content, never from the file name, because uploads
arrive under arbitrary names:
  - a file starting with the zip signature, or a folder holding cameras/images .bin/.txt: a COLMAP
    sparse model (fluidcore.cameras.colmap); any other folder: its transforms.json or info.json;
  - a JSON object with `frames` or PINF's `train_videos`: nerfstudio transforms.json or PINF/HyFluid
    info.json (fluidcore.cameras.json_formats).

No torch at import time: the API validates uploaded camera files with this package.
"""

from __future__ import annotations

from pathlib import Path

from fluidcore.cameras.boxes import Box, box_center, box_edges, capture_box, check_box_visible, frusta_box, scene_box
from fluidcore.cameras.camera import Camera, CameraError, check_ranges, check_rigid, look_at, orbit, render_size, rotate_about_axis
from fluidcore.cameras.colmap import find_model_dir, load_colmap_dir, load_colmap_zip
from fluidcore.cameras.json_formats import declared_fps, is_camera_json, load_json_cameras, read_json, to_transforms, write_transforms
from fluidcore.cameras.undistort import undistort_frames

ZIP_MAGIC = b"PK\x03\x04"
JSON_START = (b"{", b"\xef\xbb\xbf{")  # optionally after a UTF-8 byte-order mark
DATASET_FILES = ("transforms.json", "info.json")


def load(path: str | Path) -> dict[str, Camera]:
    """Cameras by name from a nerfstudio transforms.json, a PINF info.json, or a COLMAP model
    (folder or .zip). Raises CameraError naming the file and field on any invalid input."""
    path = Path(path)
    if path.is_dir():
        return _load_folder(path)
    if not path.is_file():
        raise CameraError(f"{path}: no such file or folder")
    with path.open("rb") as handle:
        head = handle.read(64)
    if head.startswith(ZIP_MAGIC):
        return load_colmap_zip(path)
    if head.lstrip().startswith(JSON_START):
        data = read_json(path)
        if not is_camera_json(data):
            raise CameraError(f"{path.name}: JSON without camera entries (missing field frames)")
        return load_json_cameras(path, data)
    raise CameraError(
        f"{path.name}: unrecognised camera file; expected transforms.json / info.json (JSON), "
        "a COLMAP sparse model folder, or a .zip of one"
    )


def _load_folder(folder: Path) -> dict[str, Camera]:
    """A COLMAP model in the folder, else the folder's transforms.json or info.json (a dataset
    folder as nerfstudio and PINF lay them out)."""
    if find_model_dir(folder) is not None:
        return load_colmap_dir(folder)
    for name in DATASET_FILES:
        if (folder / name).is_file():
            return load(folder / name)
    raise CameraError(
        f"{folder.name}: no COLMAP model (cameras/images .bin or .txt) and no {' or '.join(DATASET_FILES)} in the folder"
    )


def check_video_size(camera: Camera, video: str, width: int, height: int) -> None:
    """Raise CameraError unless the frames of `video` (a file name, for the message) are exactly
    the camera's size. The one rule for "this video fits this camera", applied by the API to
    uploads and by the reconstruction job to the CLI's videos, with the same message.

    The intrinsics are in pixels of one particular frame size; a video at another size would
    put every projected point in the wrong place, and a resized copy of the right aspect ratio
    cannot be told from a different camera. A caller that knows the video is a resized copy
    can deliberately use `camera.scaled(width, height)` instead.
    """
    if (width, height) != (camera.width, camera.height):
        raise CameraError(
            f"video: {video} is {width}x{height} but camera {camera.name!r} is {camera.width}x{camera.height} "
            "(its intrinsics are in pixels of that size); calibrate at the video's size or resize the video"
        )


__all__ = [
    "Box",
    "Camera",
    "CameraError",
    "box_center",
    "box_edges",
    "capture_box",
    "check_box_visible",
    "check_ranges",
    "declared_fps",
    "check_rigid",
    "check_video_size",
    "frusta_box",
    "load",
    "look_at",
    "orbit",
    "render_size",
    "rotate_about_axis",
    "scene_box",
    "to_transforms",
    "undistort_frames",
    "write_transforms",
]
