"""Calibrate a rig of fixed cameras from their own videos with COLMAP (pycolmap), when the rig
sees a static textured background.

Each video gives one image: the per-pixel median of frames spread over the clip, which keeps
the static background and drops the moving smoke (smoke at one pixel for less than half the
sampled frames vanishes). COLMAP then extracts SIFT features, matches every pair, and maps
incrementally; of the models it returns, the one with the most registered images is kept,
and every view must be in it.

COLMAP's world has an arbitrary origin, orientation and scale, so it is normalised to ours
(docs/cameras.md): the origin is the point the optical axes pass closest to (what the rig looks
at), +y is the cameras' mean image up, the cameras' mean viewing direction is -z, and the scale
puts the cameras `distance` world units from the origin on average. The scene box written with
the cameras is the region all views see (`frusta_box`).
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path

import numpy as np

from fluidcore.cameras.boxes import frusta_box
from fluidcore.cameras.camera import Camera, CameraError, check_camera_name
from fluidcore.cameras.colmap import cameras_from_reconstruction
from fluidcore.cameras.json_formats import write_transforms
from fluidcore.cameras.single import box_json
from fluidcore.cameras.world_up import DEFAULT_UP
from fluidcore.names import safe_join

BACKGROUND_FRAMES = 15  # frames per video in the median
MAX_VIDEOS = 64  # exhaustive matching is quadratic in the number of views


def background_image(video: str | os.PathLike[str], frames: int = BACKGROUND_FRAMES) -> np.ndarray:
    """uint8 (H, W, 3) per-pixel median of `frames` frames spread evenly over the video."""
    from fluidcore.video import probe, read_frames

    n = probe(video).n_frames
    step = max(1, n // frames)
    return np.median(read_frames(video, 0, n, step)[:frames], axis=0).astype(np.uint8)


def calibrate_rig(
    videos: Mapping[str, str | os.PathLike[str]], *, distance: float = 1.0, camera_model: str = "SIMPLE_RADIAL",
    work_dir: str | os.PathLike[str] | None = None,
) -> dict[str, Camera]:
    """Cameras by name (the keys of `videos`) in our world convention (see the module docstring).

    Lens distortion found by COLMAP stays on the cameras (the reconstruction undistorts the
    frames). Raises CameraError when COLMAP cannot register every view.
    """
    if not 2 <= len(videos) <= MAX_VIDEOS:
        raise CameraError(f"videos: calibrating a rig needs 2 to {MAX_VIDEOS} videos, got {len(videos)}")
    if not (np.isfinite(distance) and distance > 0):
        raise CameraError(f"distance must be a positive number of world units, got {distance}")
    for name in videos:
        check_camera_name(name, "videos: view name")
    with tempfile.TemporaryDirectory(prefix="fluidnexus-colmap-", dir=work_dir) as tmp:
        images = Path(tmp) / "images"
        images.mkdir()
        for name, video in videos.items():
            _write_png(safe_join(images, f"{name}.png"), background_image(video))
        model = _largest_model(Path(tmp), images, camera_model)
        cameras = cameras_from_reconstruction(model, "colmap")
    missing = sorted(set(videos) - set(cameras))
    if missing:
        raise CameraError(
            f"COLMAP registered {len(cameras)} of {len(videos)} views; not {', '.join(missing)} "
            "(too little static texture seen by several cameras, or too little overlap)"
        )
    return normalise_world({name: cameras[name] for name in videos}, distance)


def _write_png(path: Path, image: np.ndarray) -> None:
    import cv2

    if not cv2.imwrite(str(path), image[..., ::-1]):  # OpenCV writes BGR
        raise CameraError(f"cannot write {path}")


def _largest_model(folder: Path, images: Path, camera_model: str):  # noqa: ANN202 - pycolmap.Reconstruction
    import pycolmap

    database = folder / "database.db"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    pycolmap.extract_features(database, images, camera_mode=pycolmap.CameraMode.PER_IMAGE, reader_options=reader,
                              device=pycolmap.Device.cpu)
    pycolmap.match_exhaustive(database, device=pycolmap.Device.cpu)
    models = pycolmap.incremental_mapping(database, images, folder / "sparse")
    if not models:
        raise CameraError("COLMAP found no model: too few features matched between the views")
    return max(models.values(), key=lambda model: model.num_reg_images())


def normalise_world(cameras: Mapping[str, Camera], distance: float) -> dict[str, Camera]:
    """The same rig in our world frame: origin where the optical axes meet, +y the mean image
    up, mean viewing direction -z, cameras `distance` from the origin on average."""
    centers = np.array([c.center() for c in cameras.values()])
    forwards = np.array([c.forward() for c in cameras.values()])
    projectors = np.eye(3)[None] - forwards[:, :, None] * forwards[:, None, :]
    origin = np.linalg.solve(projectors.sum(axis=0), np.einsum("nij,nj->i", projectors, centers))
    up = -np.mean([c.world_to_camera[1, :3] for c in cameras.values()], axis=0)  # camera y points down
    up /= np.linalg.norm(up)
    back = -forwards.mean(axis=0)
    back -= (back @ up) * up  # what becomes +z: away from the scene, towards the cameras
    if np.linalg.norm(back) < 1e-6:
        raise CameraError("the cameras look along their own up direction; cannot orient the world")
    back /= np.linalg.norm(back)
    rotation = np.stack([np.cross(up, back), up, back])  # rows: new x, y, z in COLMAP's world
    scale = distance / float(np.mean(np.linalg.norm(centers - origin, axis=1)))
    out = {}
    for name, camera in cameras.items():
        pose = np.eye(4)
        pose[:3, :3] = camera.world_to_camera[:3, :3] @ rotation.T
        pose[:3, 3] = scale * (camera.world_to_camera[:3, :3] @ origin + camera.world_to_camera[:3, 3])
        out[name] = replace(camera, world_to_camera=pose)
    return out


def write_rig(
    out: str | os.PathLike[str], videos: Mapping[str, str | os.PathLike[str]], *, distance: float = 1.0,
    camera_model: str = "SIMPLE_RADIAL",
) -> Path:
    """`calibrate_rig` written as a transforms.json (file paths relative to it) with its scene box."""
    out = Path(out)
    cameras = calibrate_rig(videos, distance=distance, camera_model=camera_model)
    cameras = {
        name: replace(camera, file_path=os.path.relpath(Path(videos[name]).resolve(), out.resolve().parent))
        for name, camera in cameras.items()
    }
    return write_transforms(out, cameras, scene_box=box_json(frusta_box(cameras)), up=DEFAULT_UP)  # normalised +y up

