"""The pinhole Camera every part of FluidNexus shares, and helpers that place new ones.

Conventions (docs/architecture.md): OpenCV camera axes (x right, y down, z forward),
`world_to_camera` is a rigid 4x4 matrix, and pixel coordinates are continuous: pixel (i, j)
covers [i, i+1) x [j, j+1), so its centre is at (i + 0.5, j + 0.5) and the principal point is
given in the same coordinates (as nerfstudio and COLMAP do). With that convention resizing a
camera is an exact scale of fx, cx (and fy, cy), with no half-pixel fix-ups.

torch is imported inside the methods that return tensors only: the API validates uploaded
camera files with this module and must not pay for importing torch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Sequence

import numpy as np

from fluidcore.errors import InputError

if TYPE_CHECKING:  # pragma: no cover - typing only
    import torch

ORTHONORMAL_TOLERANCE = 1e-4  # max |R R^T - I|; poses stored as float32 are ~1e-7 off
_NEAR_DEPTH = 1e-9  # |z| below this is clamped in project() so uv stays finite


class CameraError(InputError):
    """A camera (or a camera file) is invalid; the message names the offending field."""


def check_rigid(matrix: np.ndarray, field_name: str) -> np.ndarray:
    """Return `matrix` (4x4, or 3x4 without the last row) as a float64 (4, 4) rigid transform,
    or raise naming `field_name`.

    A rigid transform has a finite orthonormal rotation with determinant +1 (a reflection
    would silently mirror the scene) and a last row of (0, 0, 0, 1).
    """
    try:
        m = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        raise CameraError(f"{field_name} must be a 4x4 matrix of numbers") from None
    if m.shape == (3, 4):  # some writers leave out the constant last row
        m = np.vstack((m, (0.0, 0.0, 0.0, 1.0)))
    if m.shape != (4, 4):
        raise CameraError(f"{field_name} must be a 4x4 matrix, got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise CameraError(f"{field_name} contains non-finite numbers")
    if not np.allclose(m[3], (0.0, 0.0, 0.0, 1.0), atol=1e-6):
        raise CameraError(f"{field_name} last row must be (0, 0, 0, 1), got {m[3].tolist()}")
    rotation = m[:3, :3]
    error = float(np.abs(rotation @ rotation.T - np.eye(3)).max())
    if error > ORTHONORMAL_TOLERANCE:
        raise CameraError(f"{field_name} rotation is not orthonormal (max |R R^T - I| = {error:.2e})")
    if np.linalg.det(rotation) < 0:
        raise CameraError(f"{field_name} rotation has determinant -1 (a reflection, not a rotation)")
    return m


def check_camera_name(name: object, field_name: str) -> str:
    """`name` if it follows the naming rule (fluidcore.names), else CameraError naming the field.
    Every camera reader applies it: a camera's name becomes a file name and a storage key."""
    from fluidcore.names import UnsafeName, check_name

    try:
        return check_name(name, field_name)
    except UnsafeName as error:
        raise CameraError(str(error)) from None


def check_new_camera(taken: Sequence[str] | dict[str, object], name: str, context: str) -> None:
    """CameraError unless `name` differs from every camera name in `taken`, in more than case: each
    becomes a file, and case-insensitive file systems store `Cam0.mp4` and `cam0.mp4` as one."""
    from fluidcore.names import case_twin

    if name in taken:
        raise CameraError(f"{context}: duplicated camera name {name!r}")
    twin = case_twin(taken, name)
    if twin is not None:
        raise CameraError(f"{context}: camera names {twin!r} and {name!r} differ only in case "
                          "(one file on case-insensitive file systems); rename one")


def _as_float(value: object, field_name: str) -> float:
    if isinstance(value, bool):
        raise CameraError(f"{field_name} must be a number, got {value!r}")
    try:
        return float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise CameraError(f"{field_name} must be a number, got {value!r}") from None


def _check_positive(value: object, field_name: str) -> float:
    number = _as_float(value, field_name)
    if not math.isfinite(number) or number <= 0:
        raise CameraError(f"{field_name} must be a positive finite number, got {value}")
    return number


def _check_size(value: object, field_name: str) -> int:
    number = _as_float(value, field_name)
    if not math.isfinite(number) or number != int(number) or number <= 0:
        raise CameraError(f"{field_name} must be a positive integer, got {value}")
    return int(number)


MIN_FIELD_OF_VIEW_DEG = 0.5  # a 4000 mm lens on a full-frame sensor; nothing narrower films smoke
MAX_FIELD_OF_VIEW_DEG = 170.0  # past a fisheye, which a pinhole model cannot describe anyway
MAX_PRINCIPAL_OFFSET = 1.0  # principal point at most one image size outside the frame
MAX_CAMERA_DISTANCE = 1.0e6  # world units from the origin


def check_ranges(camera: Camera) -> None:
    """Raise CameraError for values a Camera accepts but no real capture has: a field of view
    outside [MIN, MAX]_FIELD_OF_VIEW_DEG on either axis, a principal point more than
    MAX_PRINCIPAL_OFFSET image sizes outside the frame, a centre farther than MAX_CAMERA_DISTANCE.

    Construction only needs values to be finite; these bounds keep a typo (fl_x 1e-300, cx 1e300)
    from reaching the worker, where it overflows pixel grids instead of failing with a message.
    """
    for axis, focal, size in (("x", camera.fx, camera.width), ("y", camera.fy, camera.height)):
        fov = math.degrees(2.0 * math.atan(0.5 * size / focal))
        if not MIN_FIELD_OF_VIEW_DEG <= fov <= MAX_FIELD_OF_VIEW_DEG:
            raise CameraError(
                f"camera {camera.name!r}: fl_{axis} = {focal:g} gives a {fov:.3g} degree field of view over "
                f"{size} pixels; expected {MIN_FIELD_OF_VIEW_DEG:g} to {MAX_FIELD_OF_VIEW_DEG:g} degrees"
            )
    for key, value, size in (("cx", camera.cx, camera.width), ("cy", camera.cy, camera.height)):
        if not -MAX_PRINCIPAL_OFFSET * size <= value <= (1.0 + MAX_PRINCIPAL_OFFSET) * size:
            raise CameraError(f"camera {camera.name!r}: {key} = {value:g} is far outside the {size}-pixel frame")
    distance = math.hypot(*camera.center())  # no overflow warning for an absurd translation
    if distance > MAX_CAMERA_DISTANCE:
        raise CameraError(
            f"camera {camera.name!r}: centre is {distance:.3g} units from the origin (at most {MAX_CAMERA_DISTANCE:g})"
        )


@dataclass(frozen=True, eq=False)
class Camera:
    """A calibrated pinhole camera: intrinsics in pixels and a world-to-camera pose (OpenCV axes).

    Construction validates everything (positive focal lengths and sizes, finite principal
    point, rigid pose), so a Camera that exists is usable. The pose is stored as a read-only
    float64 copy.
    """

    name: str
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    world_to_camera: np.ndarray = field(repr=False)
    file_path: str | None = None
    distortion: tuple[float, ...] = ()  # OpenCV order (k1, k2, p1, p2[, k3[, k4, k5, k6]]); () = pinhole

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise CameraError(f"camera name must be a non-empty string, got {self.name!r}")
        values: dict[str, object] = {name: _check_positive(getattr(self, name), name) for name in ("fx", "fy")}
        for name in ("cx", "cy"):
            values[name] = _as_float(getattr(self, name), name)
            if not math.isfinite(values[name]):
                raise CameraError(f"{name} must be finite, got {getattr(self, name)}")
        for name in ("width", "height"):
            values[name] = _check_size(getattr(self, name), name)
        values["distortion"] = _check_distortion(self.distortion)
        pose = check_rigid(self.world_to_camera, "world_to_camera").copy()
        pose.setflags(write=False)
        values["world_to_camera"] = pose
        for name, value in values.items():  # normalised types: plain floats and ints
            object.__setattr__(self, name, value)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Camera):
            return NotImplemented
        return (
            (self.name, self.fx, self.fy, self.cx, self.cy, self.width, self.height, self.file_path, self.distortion)
            == (other.name, other.fx, other.fy, other.cx, other.cy, other.width, other.height, other.file_path,
                other.distortion)
            and np.array_equal(self.world_to_camera, other.world_to_camera)
        )

    __hash__ = None  # type: ignore[assignment]  # holds an array; equal cameras need not hash alike

    # --- geometry (numpy) -------------------------------------------------------------------
    def camera_to_world(self) -> np.ndarray:
        """(4, 4) float64 inverse of the pose, computed exactly for a rigid transform."""
        rotation = self.world_to_camera[:3, :3]
        inverse = np.eye(4)
        inverse[:3, :3] = rotation.T
        inverse[:3, 3] = -rotation.T @ self.world_to_camera[:3, 3]
        return inverse

    def center(self) -> np.ndarray:
        """(3,) camera centre in world coordinates."""
        return self.camera_to_world()[:3, 3]

    def forward(self) -> np.ndarray:
        """(3,) unit viewing direction (camera +z) in world coordinates."""
        return self.world_to_camera[2, :3].copy()

    def pinhole(self) -> Camera:
        """The same camera without lens distortion: what frames undistorted with
        `fluidcore.cameras.undistort_frames` are seen through (same intrinsics)."""
        return replace(self, distortion=())

    def scaled(self, width: int, height: int) -> Camera:
        """The same camera for frames resized to width x height (exact in continuous pixels)."""
        width, height = _check_size(width, "width"), _check_size(height, "height")
        sx, sy = width / self.width, height / self.height
        return replace(
            self, fx=self.fx * sx, fy=self.fy * sy, cx=self.cx * sx, cy=self.cy * sy, width=width, height=height
        )

    # --- tensors (torch imported lazily) -----------------------------------------------------
    def intrinsics(self, device: torch.device | str | None = None) -> torch.Tensor:
        """(3, 3) float32 K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]."""
        import torch

        return torch.tensor(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=torch.float32, device=device
        )

    def viewmat(self, device: torch.device | str | None = None) -> torch.Tensor:
        """(4, 4) float32 world-to-camera matrix (what gsplat calls `viewmats`)."""
        import torch

        return torch.tensor(self.world_to_camera, dtype=torch.float32, device=device)

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Project world points (N, 3) to continuous pixel coordinates uv (N, 2) and depth z (N,).

        Differentiable; runs on the points' device in their dtype. Points with depth <= 0 are
        behind the camera: their uv is finite but meaningless, so mask them with `depth > 0`.
        """
        import torch

        if points.ndim != 2 or points.shape[-1] != 3:
            raise CameraError(f"points must have shape (N, 3), got {tuple(points.shape)}")
        pose = torch.tensor(self.world_to_camera, dtype=points.dtype, device=points.device)
        camera_points = points @ pose[:3, :3].T + pose[:3, 3]
        depth = camera_points[:, 2]
        safe = torch.where(depth.abs() < _NEAR_DEPTH, torch.full_like(depth, _NEAR_DEPTH), depth)
        u = self.fx * camera_points[:, 0] / safe + self.cx
        v = self.fy * camera_points[:, 1] / safe + self.cy
        return torch.stack((u, v), dim=-1), depth

    def project_numpy(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """numpy twin of `project` (no torch) for validation code in the API process."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        camera_points = points @ self.world_to_camera[:3, :3].T + self.world_to_camera[:3, 3]
        depth = camera_points[:, 2]
        safe = np.where(np.abs(depth) < _NEAR_DEPTH, _NEAR_DEPTH, depth)
        uv = np.stack((self.fx * camera_points[:, 0] / safe + self.cx, self.fy * camera_points[:, 1] / safe + self.cy), -1)
        return uv, depth

    def in_frame(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: in front of the camera and inside [0, width) x [0, height)."""
        uv, depth = self.project_numpy(points)
        return (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < self.width) & (uv[:, 1] >= 0) & (uv[:, 1] < self.height)


OPENCV_DISTORTION_LENGTHS = (4, 5, 8)  # k1 k2 p1 p2 | + k3 | + k4 k5 k6


def _check_distortion(value: object) -> tuple[float, ...]:
    """Coefficients in OpenCV's order, all zero collapsing to () (a pinhole), so equal lenses compare equal."""
    try:
        coefficients = tuple(_as_float(v, "distortion") for v in value)  # type: ignore[union-attr]
    except TypeError:
        raise CameraError(f"distortion must be a list of numbers, got {value!r}") from None
    if not coefficients or not any(coefficients):
        return ()
    if len(coefficients) not in OPENCV_DISTORTION_LENGTHS or not all(map(math.isfinite, coefficients)):
        raise CameraError(
            f"distortion must be 4, 5 or 8 finite numbers (OpenCV's k1 k2 p1 p2 [k3 [k4 k5 k6]]), got {list(coefficients)}"
        )
    return coefficients


# --- placing new cameras ----------------------------------------------------------------------
def _unit(vector: np.ndarray, field_name: str) -> np.ndarray:
    norm = float(np.linalg.norm(vector))
    if not math.isfinite(norm) or norm < 1e-12:
        raise CameraError(f"{field_name} must be a finite non-zero vector, got {np.asarray(vector).tolist()}")
    return vector / norm


def look_at(
    eye: Sequence[float], target: Sequence[float], up: Sequence[float], like: Camera, name: str
) -> Camera:
    """A camera at `eye` looking at `target` with world `up` pointing up in the image.

    Intrinsics, size and file_path=None come from `like`. Raises CameraError when eye == target
    or when `up` is parallel to the viewing direction (the roll would be undefined).
    """
    eye_v = np.asarray(eye, dtype=np.float64)
    forward = _unit(np.asarray(target, dtype=np.float64) - eye_v, "target - eye")
    down = -_unit(np.asarray(up, dtype=np.float64), "up")
    right = np.cross(down, forward)
    if np.linalg.norm(right) < 1e-9:
        raise CameraError("up is parallel to the viewing direction; choose another up vector")
    right = right / np.linalg.norm(right)
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, :3] = np.stack((right, down, forward))
    pose[:3, 3] = -pose[:3, :3] @ eye_v
    return replace(like, name=name, world_to_camera=pose, file_path=None)


def orbit(
    center: Sequence[float],
    radius: float,
    height: float,
    n: int,
    like: Camera,
    *,
    up: Sequence[float] = (0.0, 1.0, 0.0),
    start_angle: float | None = None,
) -> list[Camera]:
    """`n` cameras evenly spaced on a circle of `radius` around the `up` axis through `center`,
    raised by `height` along `up`, all looking at `center` (a turntable video).

    `start_angle` (radians) defaults to the azimuth of `like`'s centre, so the orbit starts at
    the view the user knows (the input view) instead of an arbitrary one. Names are orbit_000...
    """
    radius, n = _check_positive(radius, "radius"), _check_size(n, "n")
    c = np.asarray(center, dtype=np.float64)
    up_v = _unit(np.asarray(up, dtype=np.float64), "up")
    # An orthonormal basis (a, b) of the plane perpendicular to up.
    helper = np.array([1.0, 0.0, 0.0]) if abs(up_v[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    a = _unit(helper - up_v * (helper @ up_v), "orbit basis")
    b = np.cross(up_v, a)
    if start_angle is None:
        offset = like.center() - c
        start_angle = math.atan2(float(offset @ b), float(offset @ a)) if np.linalg.norm(offset) > 0 else 0.0
    cameras = []
    for i in range(n):
        angle = start_angle + 2.0 * math.pi * i / n
        eye = c + radius * (math.cos(angle) * a + math.sin(angle) * b) + height * up_v
        cameras.append(look_at(eye, c, up_v, like, f"orbit_{i:03d}"))
    return cameras


def rotate_about_axis(camera: Camera, center: np.ndarray, up: np.ndarray, angle: float, name: str) -> Camera:
    """The camera carried around the axis through `center` along `up` by `angle` radians."""
    axis = up / np.linalg.norm(up)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rotation = np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)
    inverse = np.eye(4)  # world -> world map x -> R^T (x - c) + c, i.e. the inverse motion
    inverse[:3, :3] = rotation.T
    inverse[:3, 3] = center - rotation.T @ center
    return replace(camera, name=name, world_to_camera=camera.world_to_camera @ inverse, file_path=None)


def render_size(width: int, height: int, long_side: int, fraction: float = 1.0) -> tuple[int, int]:
    """(W, H) for rendering an input of width x height at `long_side * fraction`, never upscaled,
    aspect kept, at least 8 px per side."""
    target = min(max(width, height), long_side) * fraction
    factor = target / max(width, height)
    return max(8, round(width * factor)), max(8, round(height * factor))
