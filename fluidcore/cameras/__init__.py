"""Cameras: one pinhole Camera type (OpenCV axes, continuous pixels) and helpers that place cameras.

No torch at import time: the API validates uploaded camera files with this package.
"""

from fluidcore.cameras.camera import Camera, CameraError, check_rigid, look_at, orbit

__all__ = ["Camera", "CameraError", "check_rigid", "look_at", "orbit"]
