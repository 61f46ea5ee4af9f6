"""Where the smoke is: a scene's bounding box from its camera file, or estimated from the cameras.

A camera JSON file declares the box in one of two ways (docs/cameras.md, "Scene box"):
`scene_box` = {"min": [x, y, z], "max": [x, y, z]}, the world-space bounds (FluidNexus's own
field, written by `fluidnexus cameras single|colmap`), or PINF's voxel box.

PINF's voxel box (also copied into FluidNexus transforms.json files): simulation coordinates
s in [0, 1]^3 map to world coordinates as

    world = V' @ (voxel_scale * s) + t,

where t is the translation of `voxel_matrix` and V' is its rotation with the first and third
columns swapped: PINF's loader swaps them ("swap_zx") before use, and its world-to-simulation
transform is the inverse of that swapped matrix divided by voxel_scale. The box is the image of
the unit cube; we return its axis-aligned bounds in world coordinates.

Scenes without a box get `frusta_box`: the bounds of the region every camera sees (the
intersection of the view frusta), which is where reconstruction can be constrained at all.
With a single camera that region is an unbounded cone: such scenes need a declared box.
"""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from fluidcore.cameras.camera import MAX_CAMERA_DISTANCE, Camera, CameraError
from fluidcore.cameras.json_formats import top_level_fields

Box = tuple[np.ndarray, np.ndarray]  # (lo (3,), hi (3,)) float64, world coordinates
# A box a reconstruction can simulate in (`check_box`): its corners as far out as a camera may be,
# its sides at least MIN_BOX_SIDE world units and MIN_SIDE_PER_REACH of its farthest corner's
# distance, so the single-precision particle positions resolve its kernel radius (the box's
# height / 37.5) to about a thousand steps. Past them a box of +-1e308 overflowed to infinite
# sides and one of 1e-300 underflowed to a zero kernel, each a failed job after a 201 (issue 49).
MAX_BOX_REACH = MAX_CAMERA_DISTANCE
MIN_BOX_SIDE = 1e-4
MIN_SIDE_PER_REACH = 1e-3


def scene_box(path: str | Path) -> Box | None:
    """The world-space box a camera JSON file declares (`scene_box`, or `voxel_scale` +
    `voxel_matrix`), or None when the file declares none (or is not JSON, e.g. a COLMAP model)."""
    path = Path(path)
    data = top_level_fields(path)
    if data is None:
        return None
    if data.get("scene_box") is not None:
        return bounds_box(data["scene_box"], f"{path.name}: scene_box")
    if data.get("voxel_matrix") is None and data.get("voxel_scale") is None:
        return None
    return voxel_box(data, path.name)


def capture_box(path: str | Path, cameras: Sequence[Camera] | dict[str, Camera]) -> Box:
    """The box a capture is reconstructed in: the one its camera file declares, else the
    cameras' shared view (`frusta_box`, which raises CameraError when they share none)."""
    box = scene_box(path)
    return box if box is not None else frusta_box(cameras)


def bounds_box(value: Any, source: str) -> Box:
    """A box from {"min": [x, y, z], "max": [x, y, z]}, checked by `check_box`."""
    try:
        lo, hi = (np.asarray(value[key], dtype=np.float64) for key in ("min", "max"))
    except (KeyError, TypeError, ValueError):
        raise CameraError(f"{source} must be {{\"min\": [x, y, z], \"max\": [x, y, z]}}, got {value!r}") from None
    if lo.shape != (3,) or hi.shape != (3,):
        raise CameraError(f"{source}: min and max must be 3 finite numbers each")
    return check_box((lo, hi), source)


def check_box(box: Box, source: str) -> Box:
    """`box` if a reconstruction can simulate in it: finite, min < max on every axis, within
    MAX_BOX_REACH of the origin, no side below MIN_BOX_SIDE or MIN_SIDE_PER_REACH of that reach;
    else a CameraError naming `source` (the field, or the option the box came from)."""
    lo, hi = box
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise CameraError(f"{source}: min and max must be 3 finite numbers each")
    if not np.all(lo < hi):
        raise CameraError(f"{source}: min {lo.tolist()} must be below max {hi.tolist()} on every axis")
    reach = float(max(np.abs(lo).max(), np.abs(hi).max()))
    if reach > MAX_BOX_REACH:
        raise CameraError(f"{source}: a corner is {reach:.3g} world units from the origin; at most {MAX_BOX_REACH:g}")
    side, least = float(np.min(hi - lo)), max(MIN_BOX_SIDE, MIN_SIDE_PER_REACH * reach)
    if side < least:
        raise CameraError(f"{source}: its smallest side is {side:.3g} world units; a box reaching {reach:.3g} from the "
                          f"origin needs sides of at least {least:.3g}")
    return lo, hi


def voxel_box(data: dict[str, Any], source: str) -> Box:
    """Axis-aligned world bounds of PINF's voxel box (see the module docstring)."""
    scale = _voxel_scale(data.get("voxel_scale"), source)
    try:
        matrix = np.asarray(data.get("voxel_matrix"), dtype=np.float64)
    except (TypeError, ValueError):
        raise CameraError(f"{source}: voxel_matrix must be a 4x4 matrix of numbers") from None
    if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
        raise CameraError(f"{source}: voxel_matrix must be a finite 4x4 matrix, got shape {matrix.shape}")
    rotation = matrix[:3, [2, 1, 0]]  # PINF's swap_zx
    if abs(np.linalg.det(rotation)) < 1e-9:
        raise CameraError(f"{source}: voxel_matrix is singular")
    corners = np.array(list(itertools.product((0.0, 1.0), repeat=3)))
    with np.errstate(over="ignore", invalid="ignore"):
        world = (corners * scale) @ rotation.T + matrix[:3, 3]
    return check_box((world.min(axis=0), world.max(axis=0)), f"{source}: voxel_scale and voxel_matrix")


def _voxel_scale(value: Any, source: str) -> np.ndarray:
    try:
        scale = np.broadcast_to(np.asarray(value, dtype=np.float64), (3,)).copy()
    except (TypeError, ValueError):
        raise CameraError(f"{source}: voxel_scale must be one or three positive numbers, got {value!r}") from None
    if not np.all(np.isfinite(scale)) or np.any(scale <= 0):
        raise CameraError(f"{source}: voxel_scale must be positive and finite, got {scale.tolist()}")
    return scale


def frusta_box(cameras: Sequence[Camera] | dict[str, Camera]) -> Box:
    """Axis-aligned bounds of the region inside every camera's view frustum.

    Each frustum is 5 half-spaces (the four image-edge planes through the centre, and "in front
    of the camera"); the bounds of their intersection are 6 small linear programs (min and max
    of x, y, z), which scale to hundreds of cameras. An unbounded overlap (one camera, or
    cameras looking the same way) and an empty one raise CameraError.
    """
    from scipy.optimize import linprog  # lazy: heavy import, needed only here

    cams = list(cameras.values()) if isinstance(cameras, dict) else list(cameras)
    if not cams:
        raise CameraError("frusta_box needs at least one camera")
    normals, offsets = zip(*(_frustum_planes(c) for c in cams))
    a, b = np.vstack(normals), np.concatenate(offsets)  # inside: a @ x >= b
    bounds = np.empty((2, 3))
    for axis, sign in itertools.product(range(3), (1.0, -1.0)):
        objective = np.zeros(3)
        objective[axis] = sign
        result = linprog(objective, A_ub=-a, b_ub=-b, bounds=[(None, None)] * 3, method="highs")
        if result.status == 2:
            raise CameraError("the cameras' view frusta do not overlap; no common region to reconstruct")
        if result.status == 3:
            raise CameraError(
                "the cameras' view frusta overlap in an unbounded region (a single camera, or cameras "
                "looking the same way); give the scene a box (voxel_scale/voxel_matrix)"
            )
        if result.status != 0:
            raise CameraError(f"could not bound the cameras' common view ({result.message})")
        bounds[0 if sign > 0 else 1, axis] = result.x[axis]
    return bounds[0], bounds[1]


def _frustum_planes(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(5, 3) inward normals n and (5,) offsets b such that inside means n @ x >= b."""
    # Camera-frame inward normals of the planes through the centre and the image edges.
    w, h = camera.width, camera.height
    local = np.array(
        [
            [camera.fx, 0.0, camera.cx],  # u >= 0  <=>  fx x + cx z >= 0
            [-camera.fx, 0.0, w - camera.cx],  # u <= width
            [0.0, camera.fy, camera.cy],  # v >= 0
            [0.0, -camera.fy, h - camera.cy],  # v <= height
            [0.0, 0.0, 1.0],  # in front
        ]
    )
    rotation = camera.world_to_camera[:3, :3]
    normals = local @ rotation  # n_world = R^T n_cam, as rows
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return normals, normals @ camera.center()


def box_center(box: Box) -> np.ndarray:
    """(3,) centre of a box."""
    return 0.5 * (box[0] + box[1])


# A box edge is cut where it comes this close to the camera's plane (times the box's diagonal):
# nearer, its pixels run off towards infinity.
NEAR_SHARE = 1e-3

Segment = tuple[tuple[float, float], tuple[float, float]]  # two continuous pixels (u, v)


def box_edges(camera: Camera, box: Box) -> list[Segment]:
    """The box's 12 edges as `camera` sees them: pixel segments, each cut to its part in front of
    the camera (an edge wholly behind it is left out). What the upload form draws on a video's
    first frame to check a guessed field of view against the footage."""
    lo, hi = np.asarray(box[0], dtype=np.float64), np.asarray(box[1], dtype=np.float64)
    corners = np.array([[(lo, hi)[bits >> axis & 1][axis] for axis in range(3)] for bits in range(8)])
    _, depth = camera.project_numpy(corners)
    near = NEAR_SHARE * float(np.linalg.norm(hi - lo))
    segments = []
    for a, b in ((a, a | 1 << axis) for a in range(8) for axis in range(3) if not a >> axis & 1):
        if max(depth[a], depth[b]) < near:
            continue
        ends = [corners[a], corners[b]]
        for k, (here, there) in enumerate(((a, b), (b, a))):
            if depth[here] < near:  # depth is affine along the edge: cut it at `near`
                ends[k] = corners[here] + (near - depth[here]) / (depth[there] - depth[here]) * (corners[there] - corners[here])
        uv, _ = camera.project_numpy(np.stack(ends))
        if np.isfinite(uv).all():  # a degenerate box (a distance of a few float steps) leaves nothing to draw
            segments.append(((float(uv[0, 0]), float(uv[0, 1])), (float(uv[1, 0]), float(uv[1, 1]))))
    return segments


def check_box_visible(cameras: Sequence[Camera] | dict[str, Camera], box: Box) -> None:
    """Raise CameraError naming every camera that does not see the box centre in its frame.

    Meant for uploads: a camera file in the wrong axis convention (OpenCV poses labelled as
    OpenGL, world-to-camera given as camera-to-world) loads without complaint but points every
    camera away from the scene; this catches it before hours of reconstruction."""
    centre = box_center(box)[None]
    cams = list(cameras.values()) if isinstance(cameras, dict) else list(cameras)
    blind = [c.name for c in cams if not c.in_frame(centre)[0]]
    if blind:
        raise CameraError(
            f"cameras {', '.join(blind)} do not see the scene box centre {np.round(centre[0], 4).tolist()}; "
            "check that transform_matrix is camera-to-world in OpenGL axes (x right, y up, looking along -z)"
        )
