"""One uncalibrated camera (a phone video, a clip without calibration): a pinhole from the field
of view, and a scene box where the smoke must be.

A single view cannot tell scale or depth, so both are declared, not measured: the camera sits
`distance` world units from the world origin, looking at it along -z, and the scene box is the
view's cross-section at the origin (as wide and as tall as the frame there), as deep as it is
wide. World up is +y (docs/architecture.md); `up` says which way world up points in the image
(a phone held sideways records "left" or "right"). The box format is documented in
docs/cameras.md ("Scene box").
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from fluidcore.cameras.boxes import Box, check_box
from fluidcore.cameras.camera import Camera, CameraError, check_camera_name
from fluidcore.cameras.json_formats import write_transforms
from fluidcore.cameras.world_up import DEFAULT_UP

# Image direction (du, dv) in which world up points, for each --up choice.
IMAGE_UP = {"up": (0.0, -1.0), "down": (0.0, 1.0), "left": (-1.0, 0.0), "right": (1.0, 0.0)}
MIN_FOV_DEG, MAX_FOV_DEG = 1.0, 170.0


def single_camera(
    name: str, width: int, height: int, fov_deg: float, distance: float = 1.0, up: str = "up",
    file_path: str | None = None,
) -> tuple[Camera, Box]:
    """The camera (horizontal field of view `fov_deg`, square pixels, centred principal point)
    and the scene box in world units (see the module docstring)."""
    if not MIN_FOV_DEG <= fov_deg <= MAX_FOV_DEG or not math.isfinite(fov_deg):
        raise CameraError(f"fov must be between {MIN_FOV_DEG:g} and {MAX_FOV_DEG:g} degrees, got {fov_deg}")
    if not (math.isfinite(distance) and distance > 0):
        raise CameraError(f"distance must be a positive number of world units, got {distance}")
    if up not in IMAGE_UP:
        raise CameraError(f"up must be one of {', '.join(IMAGE_UP)}, got {up!r}")
    check_camera_name(name, "camera name (the video's file stem)")
    focal = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    du, dv = IMAGE_UP[up]
    roll = math.atan2(du, -dv)  # rotation about the optical axis taking the image's up to (du, dv)
    c, s = math.cos(roll), math.sin(roll)
    upright = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # x right, y down, z forward
    pose = np.eye(4)
    pose[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ upright
    pose[:3, 3] = -pose[:3, :3] @ np.array([0.0, 0.0, distance])
    camera = Camera(name, focal, focal, width / 2, height / 2, width, height, pose, file_path=file_path)
    half_along_up = distance * (height if du == 0 else width) / (2 * focal)
    half_across = distance * (width if du == 0 else height) / (2 * focal)
    half = np.array([half_across, half_along_up, half_across])
    return camera, check_box((-half, half), f"distance {distance:g} (with fov {fov_deg:g}): its scene box")


def write_single_camera(
    out: str | os.PathLike[str], video: str | os.PathLike[str], fov_deg: float, distance: float = 1.0, up: str = "up",
    name: str | None = None, max_pixels: int | None = None,
) -> Path:
    """Write a transforms.json for one `video` (its size read from the file) with its scene box.

    The camera is named after the video's file stem (or `name`); `file_path` is the video's
    path relative to the JSON file, as nerfstudio stores it. `max_pixels` caps the frame the
    size is read from (default `fluidcore.video.MAX_PIXELS`; the API passes its own, lower cap).
    """
    from fluidcore.video import MAX_PIXELS, VideoError, probe, read_header

    out, video = Path(out), Path(video)
    cap = MAX_PIXELS if max_pixels is None else max_pixels
    header = read_header(video, cap)  # a frame over the cap is refused by its declared size, before any decoding
    try:
        info = probe(video, cap)
    except VideoError as error:
        if header.width * header.height:
            raise
        raise VideoError(f"{video.name}: its header gives no frame size, and its first frame does not decode within the "
                         f"limit of {cap} pixels ({error})") from None
    file_path = os.path.relpath(video.resolve(), out.resolve().parent)
    camera, box = single_camera(name or video.stem, info.width, info.height, fov_deg, distance, up, file_path)
    # up stated: a camera rolled sideways (`up` left or right) would otherwise read as another world up
    return write_transforms(out, {camera.name: camera}, scene_box=box_json(box), up=DEFAULT_UP, fps=info.fps)


def box_json(box: Box) -> dict[str, list[float]]:
    """The `scene_box` field of a transforms.json (docs/cameras.md)."""
    return {"min": [float(v) for v in box[0]], "max": [float(v) for v in box[1]]}
