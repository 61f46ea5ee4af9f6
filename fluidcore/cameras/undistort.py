"""Lens undistortion with OpenCV: frames seen through a distorting lens, remapped to the pinhole
camera with the same intrinsics (`Camera.pinhole()`), which is what the renderer models.

Keeping fx, fy, cx, cy unchanged (rather than OpenCV's "optimal" new matrix) means the
undistorted frame has the camera's own size and principal point, so every other part of the
pipeline (frame sizes, boxes, sources in pixels) needs no change. Pixels whose source falls
outside the distorted frame are filled from the nearest edge pixel (a barrel lens leaves such
gaps at the corners).

Pixel conventions: ours are continuous (pixel centre at i + 0.5, as COLMAP and nerfstudio),
OpenCV's have centres at integers, so the principal point moves by half a pixel on the way in.
The coefficients are scale-free (normalised image coordinates), so frames decoded at a smaller
size undistort with the camera scaled to that size.
"""

from __future__ import annotations

import numpy as np

from fluidcore.cameras.camera import Camera, CameraError


def opencv_matrix(camera: Camera) -> np.ndarray:
    """(3, 3) intrinsics in OpenCV's pixel convention (centres at integer coordinates)."""
    return np.array([[camera.fx, 0.0, camera.cx - 0.5], [0.0, camera.fy, camera.cy - 0.5], [0.0, 0.0, 1.0]])


def undistort_maps(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(map_x, map_y) float32 (H, W): for each pinhole pixel, where it lies in the distorted frame."""
    import cv2

    k = opencv_matrix(camera)
    return cv2.initUndistortRectifyMap(
        k, np.asarray(camera.distortion, dtype=np.float64), None, k, (camera.width, camera.height), cv2.CV_32FC1
    )


def undistort_frames(camera: Camera, frames: np.ndarray) -> np.ndarray:
    """Frames (T, H, W, C) or (H, W, C) seen by `camera` (with its lens), as its pinhole would see them.

    `frames` may be at any size with the camera's aspect ratio (the camera is scaled to it).
    A camera without distortion returns the frames unchanged.
    """
    if not camera.distortion:
        return frames
    import cv2

    frames = np.asarray(frames)
    single = frames.ndim == 3
    batch = frames[None] if single else frames
    if batch.ndim != 4:
        raise CameraError(f"frames must be (T, H, W, C) or (H, W, C), got shape {frames.shape}")
    height, width = batch.shape[1:3]
    map_x, map_y = undistort_maps(camera.scaled(width, height))
    out = np.stack(
        [cv2.remap(frame, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(frame.shape)
         for frame in batch]
    )
    return out[0] if single else out
