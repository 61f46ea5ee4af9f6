"""Ray geometry of the input cameras: the image's up direction, a pixel's ray, and where rays
meet each other, a line, the floor or the scene box (world units)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from fluidcore.reconstruct.images import EstimationError

# the floor misplaces the source by dz / tan(descent) in depth, 5.7 dz at 10 degrees.
FLOOR_MIN_DESCENT = math.sin(math.radians(10.0))
# A generated view's ray tells the depth along the input ray only when it crosses it: an error dx


def image_up(camera, point: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(2,) unit direction in the image in which the world's up axis points, at `point`."""
    scale = max(float(np.linalg.norm(camera.center() - point)), 1e-6) * 0.05
    uv, _ = camera.project_numpy(np.stack([point, point + scale * up]))
    direction = uv[1] - uv[0]
    norm = np.linalg.norm(direction)
    if norm < 1e-9:
        raise EstimationError(f"camera {camera.name} looks along the up axis; cannot tell where smoke rises")
    return direction / norm


def pixel_ray(camera, u: float, v: float) -> tuple[np.ndarray, np.ndarray]:
    """World origin and unit direction of the ray through continuous pixel (u, v)."""
    direction_cam = np.array([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, 1.0])
    c2w = camera.camera_to_world()
    direction = c2w[:3, :3] @ direction_cam
    return c2w[:3, 3].copy(), direction / np.linalg.norm(direction)


def closest_point_to_rays(origins: np.ndarray, directions: np.ndarray, weights: Sequence[float] | None = None) -> np.ndarray:
    """Least-squares point nearest to several rays (needs two non-parallel ones), each ray's
    squared distance counted `weights[i]` times (default: all alike)."""
    a = np.zeros((3, 3))
    b = np.zeros(3)
    for o, d, w in zip(origins, directions, np.ones(len(origins)) if weights is None else weights, strict=True):
        projector = w * (np.eye(3) - np.outer(d, d))
        a += projector
        b += projector @ o
    return np.linalg.solve(a, b)


def ray_point_nearest_axis(origin: np.ndarray, direction: np.ndarray, axis_point: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """The point of a ray closest to a line (the box's vertical axis): one view's depth guess."""
    w = origin - axis_point
    b = direction @ axis
    denom = 1.0 - b * b
    if denom < 1e-9:
        raise EstimationError("source: the input ray is parallel to the scene's up axis")
    s = (b * (axis @ w) - direction @ w) / denom
    return origin + max(s, 0.0) * direction


def ray_point_on_floor(
    camera, pixel: tuple[float, float, float], up2d: np.ndarray, up: np.ndarray, floor: float
) -> np.ndarray | None:
    """One view's depth from the floor: the source's bottom edge (the pixel `pixel` = (u, v, r)
    minus r along the image's up `up2d`) cast onto the plane up . x = `floor`; returns the point
    of the centre's ray at that depth, or None when the ray descends too shallowly to say
    (FLOOR_MIN_DESCENT) or meets the floor behind the camera."""
    u, v, r = pixel
    origin, direction = pixel_ray(camera, u - r * up2d[0], v - r * up2d[1])
    descent = -float(direction @ up)
    if descent < FLOOR_MIN_DESCENT:
        return None
    base = origin + (float(origin @ up) - floor) / descent * direction
    depth_axis = camera.world_to_camera[2, :3]
    origin, direction = pixel_ray(camera, u, v)
    along = float(depth_axis @ direction)
    if along <= 1e-9:
        return None
    return origin + float(depth_axis @ (base - origin)) / along * direction


def ray_in_box(origin: np.ndarray, direction: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The nearest and farthest points of a ray inside the box [lo, hi] (None when it misses)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - origin) / direction, (hi - origin) / direction
    t1 = np.where(np.abs(direction) < 1e-12, np.where((origin >= lo) & (origin <= hi), -np.inf, np.inf), t1)
    t2 = np.where(np.abs(direction) < 1e-12, np.where((origin >= lo) & (origin <= hi), np.inf, -np.inf), t2)
    near, far = max(float(np.minimum(t1, t2).max()), 0.0), float(np.maximum(t1, t2).min())
    if not far > near:
        return None
    return origin + near * direction, origin + far * direction
