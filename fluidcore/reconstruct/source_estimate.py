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
    rests on the floor. For one input view `depth_range` says how far along its ray the centre
    could be, whatever cue chose the depth. A known `center` (the user's) is kept, and only the
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
    depth_range = None if real >= 2 else ray_in_box(origins[0], directions[0], lo, hi)
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
    center = np.clip(center, lo, hi)
    radii = [r * float(camera.world_to_camera[2, :3] @ center + camera.world_to_camera[2, 3]) / camera.fx for camera, (_, _, r), _, _ in views]
    return SourceEstimate(center=center, radius=weighted_median(radii, weights), pixels=pixels, depth_cue=cue,
                          depth_range=depth_range, generated=used if cue != "given" else {})


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
