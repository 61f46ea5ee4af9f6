"""Where the smoke comes from, estimated from the input videos alone: the source, the smoke that
stays put at the bottom of the first second (along the scene's up axis), as a 3D centre and
radius, triangulated from two or more views (or from one view and its generated views), else
one view's guess.

Only the videos handed in are used (never a held-out view), and nothing here is tuned to a
particular clip: thresholds are in units of the scene box or of the image.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from fluidcore.reconstruct.images import EstimationError
from fluidcore.reconstruct.rays import (closest_point_to_rays, image_up, pixel_ray, ray_in_box, ray_point_nearest_axis,
                                        ray_point_on_floor)
from fluidcore.spec.scene import SourcePlace

if TYPE_CHECKING:
    from fluidcore.cameras import Camera

SOURCE_SECONDS = 1.0  # the first second of video says where smoke enters
SOURCE_PERSISTENCE = 0.8  # smoke in this fraction of those frames stays put: the inlet, not the rising puff
# across the generated ray becomes dx / tan(angle) along the input ray, 5.7 dx at 10 degrees (the
# floor cue's bound, for the same reason); a view nearly opposite or behind the input camera is left out.
GENERATED_MIN_ANGLE = math.sin(math.radians(10.0))
# Pixels of the first second's smoke the depth range is bounded by (`plume_depth_range`): every one
# that was smoke in this fraction of those frames, at most PLUME_PIXELS of them (evenly strided).
PLUME_SEEN = 0.05
PLUME_PIXELS = 4000



@dataclass(frozen=True)
class SourceEstimate:
    center: np.ndarray  # (3,) world
    radius: float  # world units
    pixels: dict[str, tuple[float, float, float]]  # per view: (u, v, radius in px) at full resolution
    depth_cue: str  # how the centre's depth was found: "given", "triangulated", "generated views", "floor" or "box axis"
    depth_range: tuple[np.ndarray, np.ndarray] | None  # one view: the nearest and farthest centres (3,) in the box on its ray
    generated: dict[str, float] = field(default_factory=dict)  # generated view -> its ray's weight in the triangulation

    @property
    def place(self) -> SourcePlace:
        return SourcePlace(tuple(self.center), self.radius)


@dataclass(frozen=True)
class GeneratedView:
    """A view the novel-view model drew (`fluidcore.reconstruct.pipeline.novel_views`), as the source
    estimate reads it: its camera, the smoke masks (T, H, W) of its first frames, and how far its
    ray is trusted next to an input view's 1 (the fit's loss weight of the view, `ViewTarget.weight`)."""

    camera: Camera
    masks: np.ndarray
    weight: float


def source_frames(fps: float, available: int) -> int:
    """How many of the first frames `source_in_view` reads: SOURCE_SECONDS of video, at least one."""
    return max(1, min(available, round(SOURCE_SECONDS * fps)))


def source_in_view(masks: np.ndarray, up2d: np.ndarray) -> tuple[float, float, float]:
    """(u, v, radius_px) of the source in one view from smoke masks (T, H, W) of the first frames.

    The inlet is the smoke that stays put: pixels that are smoke in SOURCE_PERSISTENCE of the
    frames (all smoke pixels when fewer persist, e.g. in a single frame), their largest connected
    region (`largest_region`). Its size is the widest
    row near the base, "near" meaning no higher above the bottom edge than the row is wide: a
    round source's widest row is its diameter (the lowest band of pixels, the previous
    estimate, saw only its bottom cap: 12.2 px on dev scene D's input view where the true
    source projects to 19.1 px), a flat inlet's is its width, and a plume that spreads above its
    source (half-width r + s z) adds at most s / (1/2 - s) radii. The source is the ball of
    that radius resting on the bottom edge, centred across on the widest row.
    """
    persistent = masks.mean(axis=0) >= SOURCE_PERSISTENCE
    if persistent.sum() < 4:
        persistent = masks.any(axis=0)
    rows, cols = np.nonzero(largest_region(persistent))
    if len(rows) < 4:
        raise EstimationError("source: no smoke visible in the first frames; give the source explicitly")
    uv = np.stack([cols + 0.5, rows + 0.5], axis=-1).astype(np.float64)
    side = np.array([-up2d[1], up2d[0]])
    height, across = uv @ up2d, uv @ side
    band = np.floor(height - height.min()).astype(np.int64)  # one-pixel bands along up, bottom first
    counts = np.bincount(band)
    first = int(np.argmax(counts >= 2))  # the bottom edge: the lowest band of two pixels or more
    bottom = height.min() + first - 0.5  # its pixels' lower edge
    lo = np.full(len(counts), np.inf)
    hi = np.full(len(counts), -np.inf)
    np.minimum.at(lo, band, across)
    np.maximum.at(hi, band, across)
    width = np.where(counts > 0, hi - lo + 1.0, 0.0)  # pixel centres: a row of n pixels is n wide
    above = np.arange(len(counts)) - first + 1.0  # each band's top above the bottom edge
    near = (above <= width) & (above > 0)
    widest = int(np.argmax(np.where(near, width, -1.0)))
    radius = max(0.5 * float(width[widest]), 1.0)
    center = (bottom + radius) * up2d + 0.5 * float(lo[widest] + hi[widest]) * side  # the ball resting on the edge
    return float(center[0]), float(center[1]), radius


def largest_region(mask: np.ndarray) -> np.ndarray:
    """(H, W) bool: the largest 8-connected region of `mask`. What a background estimate gets
    wrong stays put too (an edge of a textured background that the codec moves by a few codes):
    on the FluidNexus-Smoke clip such specks left and right of the stem made its bottom rows
    0.8 of the box wide; the inlet and the smoke it feeds are one region."""
    from scipy import ndimage

    labels, count = ndimage.label(mask, structure=np.ones((3, 3), dtype=bool))
    if count <= 1:
        return mask
    return labels == 1 + int(np.argmax(ndimage.sum_labels(mask, labels, index=np.arange(1, count + 1))))


def estimate_source(
    cameras: Mapping[str, object],
    masks: Mapping[str, np.ndarray],
    box: tuple[np.ndarray, np.ndarray],
    up: Sequence[float] = (0.0, 1.0, 0.0),
    center: Sequence[float] | None = None,
    generated: Sequence[GeneratedView] = (),
) -> SourceEstimate:
    """Source centre and radius from the smoke masks of the first frames of each input view.

    Two or more views triangulate the centre. One view leaves depth open. Views a novel-view
    model drew from it (`generated`) close it: their rays join the input ray's in a weighted
    least-squares triangulation ("generated views"), each counted with its own `weight` against
    the input view's 1. The input ray's distance does not change along that ray, so the depth
    comes from the generated views alone, while across it the input view outweighs them by the
    ratio of the weights; a generated view that shows no smoke, or whose ray runs within
    GENERATED_MIN_ANGLE of the input ray, is left out (and all are with two or more input views,
    which triangulate on their own). Without them, the
    centre is put on the input ray where it passes closest to the box's vertical axis (the box
    is where the smoke is), unless the source would then sink below the box's floor, which a
    camera looking down onto the floor steeply enough can tell (`ray_point_on_floor`): then it
    rests on the floor; else it stays where the box and the first second's smoke allow
    (`plume_depth_range`). For one input view `depth_range` says how far along its ray the centre
    could be (`plume_depth_range`), whatever cue chose the depth. A known `center` (the user's) is kept, and only the
    radius is measured, at its depth. The radius is the weighted median of every view's (one
    input view outweighs generated views whose weights sum below 1). Masks may be at any
    resolution; cameras are scaled to match them.
    """
    up_v = np.asarray(up, dtype=np.float64)
    up_v = up_v / np.linalg.norm(up_v)
    lo, hi = (np.asarray(x, dtype=np.float64) for x in box)
    box_center = 0.5 * (lo + hi)
    views, pixels = [], {}  # views: (camera at the mask's size, (u, v, r) there, image up, weight)
    for name, mask in masks.items():
        camera = cameras[name].scaled(mask.shape[2], mask.shape[1])
        up2d = image_up(camera, box_center, up_v)
        found = source_in_view(mask, up2d)
        views.append((camera, found, up2d, 1.0))
        sx, sy = cameras[name].width / mask.shape[2], cameras[name].height / mask.shape[1]
        pixels[name] = (found[0] * sx, found[1] * sy, found[2] * sx)
    real = len(views)
    crossing = [] if real != 1 else crossing_views(generated, pixel_ray(views[0][0], *views[0][1][:2])[1], box_center, up_v)
    views += [(camera, found, None, float(view.weight)) for view, camera, found in crossing]
    used = {view.camera.name: float(view.weight) for view, _, _ in crossing}
    rays = [pixel_ray(camera, found[0], found[1]) for camera, found, _, _ in views]
    origins, directions = np.array([o for o, _ in rays]), np.array([d for _, d in rays])
    weights = np.array([w for *_, w in views])
    depth_range = None
    if real == 1:
        camera, found, up2d, _ = views[0]
        depth_range = plume_depth_range(camera, next(iter(masks.values())), up2d, origins[0], directions[0], lo, hi)
    if center is not None:
        center, cue = np.asarray(center, dtype=np.float64), "given"
    elif len(rays) >= 2:
        center, cue = closest_point_to_rays(origins, directions, weights), "triangulated" if real >= 2 else "generated views"
    else:
        camera, found, up2d, _ = views[0]
        center, cue = ray_point_nearest_axis(origins[0], directions[0], box_center, up_v), "box axis"
        on_floor = ray_point_on_floor(camera, found, up2d, up_v, float(lo @ up_v))
        if on_floor is not None and (center - on_floor) @ directions[0] > 0.0:  # the guess would sink below the floor
            center, cue = on_floor, "floor"
        elif depth_range is not None:  # the box axis guess, kept where the plume can be
            center = _clamp_along(center, *depth_range)
    center = np.clip(center, lo, hi)
    radii = [r * float(camera.world_to_camera[2, :3] @ center + camera.world_to_camera[2, 3]) / camera.fx for camera, (_, _, r), _, _ in views]
    return SourceEstimate(center=center, radius=weighted_median(radii, weights), pixels=pixels, depth_cue=cue,
                          depth_range=depth_range, generated=used if cue != "given" else {})


def plume_depth_range(camera: Camera, masks: np.ndarray, up2d: np.ndarray, origin: np.ndarray, direction: np.ndarray,
                      lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The nearest and farthest points of the source's ray (`origin`, `direction`) where the
    source can be for one view: inside the box, and where the first second's smoke (`masks`
    (T, H, W), their largest region) fits in the box too.

    Each smoke pixel's ray runs through the box between two depths (along the camera's axis);
    the plume, at about the source's depth, lies within all of them, give or take its own
    half-width at that pixel's height (a plume is as deep as it is wide). On dev scenes D, F and
    H this keeps the true source inside and shortens the box's stretch of the ray from 0.49 to
    0.46, 0.32 to 0.23 and 0.46 to 0.37 (world units, camera depth). The whole window says more
    but is wrong: smoke that leaves through the box's open top is no longer inside it (F's
    range then missed the truth by 6 cm). None when the ray misses the box."""
    box_range = ray_in_box(origin, direction, lo, hi)
    if box_range is None:
        return None
    seen = largest_region(masks.mean(axis=0) >= PLUME_SEEN)
    rows, cols = np.nonzero(seen)
    if len(rows) == 0:
        return box_range
    axis, offset = camera.world_to_camera[2, :3], float(camera.world_to_camera[2, 3])
    depth_of = lambda point: float(axis @ point + offset)  # noqa: E731 - one expression, used twice
    near_z, far_z = depth_of(box_range[0]), depth_of(box_range[1])
    uv = np.stack([cols + 0.5, rows + 0.5], axis=-1).astype(np.float64)
    half_width = 0.5 * _band_widths(uv, up2d) * 0.5 * (near_z + far_z) / camera.fx  # world units, at mid-depth
    keep = slice(None, None, max(1, len(uv) // PLUME_PIXELS))
    z_near, z_far = _depths_in_box(camera, uv[keep], lo, hi)
    near_z = max(near_z, float(np.max(z_near - half_width[keep])))
    far_z = min(far_z, float(np.min(z_far + half_width[keep])))
    if not far_z > near_z:  # the smoke does not fit the box at one depth: say only what the box says
        return box_range
    along = float(axis @ direction)
    return origin + (near_z - depth_of(origin)) / along * direction, origin + (far_z - depth_of(origin)) / along * direction


def _band_widths(uv: np.ndarray, up2d: np.ndarray) -> np.ndarray:
    """(N,) the width across `up2d` of the one-pixel band along it that each pixel of `uv` (N, 2) lies in."""
    side = np.array([-up2d[1], up2d[0]])
    height, across = uv @ up2d, uv @ side
    band = np.floor(height - height.min()).astype(np.int64)
    lo, hi = np.full(band.max() + 1, np.inf), np.full(band.max() + 1, -np.inf)
    np.minimum.at(lo, band, across)
    np.maximum.at(hi, band, across)
    return (hi - lo + 1.0)[band]


def _depths_in_box(camera: Camera, uv: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,), (N,): the camera depths between which each pixel's ray (`uv` (N, 2)) runs inside the
    box (near > far where it misses it: such a pixel bounds nothing and is left out)."""
    rays = np.stack([(uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy, np.ones(len(uv))], axis=-1)
    c2w = camera.camera_to_world()
    directions, origin = rays @ c2w[:3, :3].T, c2w[:3, 3]  # depth 1 along the camera's axis at parameter 1
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - origin) / directions, (hi - origin) / directions
    flat = np.abs(directions) < 1e-12
    inside = (origin >= lo) & (origin <= hi)
    t1 = np.where(flat, np.where(inside, -np.inf, np.inf), t1)
    t2 = np.where(flat, np.where(inside, np.inf, -np.inf), t2)
    near, far = np.maximum(np.minimum(t1, t2).max(axis=1), 0.0), np.maximum(t1, t2).min(axis=1)
    hit = far > near
    return np.where(hit, near, -np.inf), np.where(hit, far, np.inf)


def _clamp_along(center: np.ndarray, near: np.ndarray, far: np.ndarray) -> np.ndarray:
    """`center`, a point of the segment's line, moved onto the segment [near, far] if off it."""
    span = far - near
    s = float(np.clip((center - near) @ span / max(float(span @ span), 1e-18), 0.0, 1.0))
    return near + s * span


def crossing_views(
    generated: Sequence[GeneratedView], input_direction: np.ndarray, box_center: np.ndarray, up: np.ndarray
) -> list[tuple[GeneratedView, Camera, tuple[float, float, float]]]:
    """The generated views that can tell the depth along the one input ray (direction
    `input_direction`): each with its camera at its masks' size and its source (u, v, r) there.
    A view that shows no smoke says nothing of the source; one whose ray runs within
    GENERATED_MIN_ANGLE of the input ray barely crosses it."""
    crossing = []
    for view in generated:
        camera = view.camera.scaled(view.masks.shape[2], view.masks.shape[1])
        try:
            found = source_in_view(view.masks, image_up(camera, box_center, up))
        except EstimationError:  # no smoke (or a view along the up axis)
            continue
        if np.linalg.norm(np.cross(pixel_ray(camera, found[0], found[1])[1], input_direction)) >= GENERATED_MIN_ANGLE:
            crossing.append((view, camera, found))
    return crossing


def weighted_median(values: Sequence[float], weights: Sequence[float]) -> float:
    """The value with half the total weight on either side; where the halves meet between two
    values, their mean (equal weights: `np.median`)."""
    order = np.argsort(values)
    v, w = np.asarray(values, dtype=np.float64)[order], np.asarray(weights, dtype=np.float64)[order]
    cumulative = np.cumsum(w)
    half = 0.5 * cumulative[-1]
    k = int(np.searchsorted(cumulative, half))
    if np.isclose(cumulative[k], half) and k + 1 < len(v):
        return float(0.5 * (v[k] + v[k + 1]))
    return float(v[k])
