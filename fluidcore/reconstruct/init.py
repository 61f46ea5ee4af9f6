"""What a reconstruction needs before its first frame, estimated from the input videos alone.

* the background: a colour for empty space (what every novel view shows where there is no
  smoke), only when a view's background is textured a static image for that view, and the
  video's own noise per channel;
* the smoke mask of a frame: where some channel differs from the background by more than
  SMOKE_SIGMAS of that channel's noise;
* the source: where smoke enters the scene (the smoke that stays put at the bottom of the
  first second, along the scene's up axis), as a 3D centre and radius.

Only the videos handed in are used (never a held-out view), and nothing here is tuned to a
particular clip: thresholds are in units of the image's own noise or of the scene box.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from fluidcore.errors import InputError
from fluidcore.spec.scene import SourcePlace

if TYPE_CHECKING:
    import torch

    from fluidcore.cameras import Camera


MAX_BACKGROUND_FRAMES = 40  # frames sampled for the per-pixel background statistic
TEXTURED_FRACTION = 0.2  # a background image is kept when this much of the view is not flat
# A pixel differs from the background (smoke, or a textured background) where some channel lies
# more than SMOKE_SIGMAS of that channel's noise away. Set from the noise statistics, not from a
# scene: Gaussian noise exceeds 5 sigma with probability 5.7e-7, so a preview frame (480 x 270
# pixels, 3 channels) shows 0.2 false smoke pixels on average.
SMOKE_SIGMAS = 5.0
# The least noise a video is taken to have, per channel: one 8-bit code value. An 8-bit video
# rounds every value to steps of 1/255 (and an mp4 codec moves values by about a step around
# anything that changes), so noise below a step is not taken at its word (the dev scenes and
# ScalarFlow have perfectly still backgrounds: 0 measured) and a difference of a step or two is
# no evidence of smoke.
NOISE_FLOOR = 1.0 / 255.0
SOURCE_SECONDS = 1.0  # the first second of video says where smoke enters
SOURCE_PERSISTENCE = 0.8  # smoke in this fraction of those frames stays put: the inlet, not the rising puff
# The floor cue needs a ray that descends steeply enough onto the floor: a base that sits dz above
# the floor misplaces the source by dz / tan(descent) in depth, 5.7 dz at 10 degrees.
FLOOR_MIN_DESCENT = math.sin(math.radians(10.0))
# A generated view's ray tells the depth along the input ray only when it crosses it: an error dx
# across the generated ray becomes dx / tan(angle) along the input ray, 5.7 dx at 10 degrees (the
# floor cue's bound, for the same reason); a view nearly opposite or behind the input camera is left out.
GENERATED_MIN_ANGLE = math.sin(math.radians(10.0))


class EstimationError(InputError):
    """The videos do not show what an estimate needs (e.g. no smoke in the first frames)."""


@dataclass(frozen=True)
class Background:
    """A view's background: a colour, plus a static image when the view's background is textured,
    and the video's noise: how far a pixel strays from it while nothing is there."""

    color: np.ndarray  # (C,) float32 in [0, 1]
    image: np.ndarray | None  # (H, W, C) float32, or None: the colour everywhere
    noise: np.ndarray  # (C,) float32: each channel's noise (standard deviation), at least NOISE_FLOOR

    def as_image(self, height: int, width: int) -> np.ndarray:
        """(H, W, C) float32 at the requested size (area-resampled from the stored image)."""
        if self.image is None:
            return np.broadcast_to(self.color, (height, width, len(self.color))).astype(np.float32)
        return resize_image(self.image, width, height)


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
    """A view the novel-view model drew (`fluidcore.reconstruct.job.novel_views`), as the source
    estimate reads it: its camera, the smoke masks (T, H, W) of its first frames, and how far its
    ray is trusted next to an input view's 1 (the fit's loss weight of the view, `ViewTarget.weight`)."""

    camera: Camera
    masks: np.ndarray
    weight: float


def to_float(frames: np.ndarray, channels: int) -> np.ndarray:
    """uint8 (T, H, W, 3) -> float32 (T, H, W, channels) in [0, 1] (grey = channel mean)."""
    data = frames.astype(np.float32) / 255.0
    return data.mean(axis=-1, keepdims=True) if channels == 1 else data


def resize_image(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """Area-style resize of an (H, W, C) float image (torch's antialiased bilinear)."""
    if image.shape[:2] == (height, width):
        return image.astype(np.float32)
    import torch
    import torch.nn.functional as F

    tensor = torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32)).permute(2, 0, 1)[None]
    out = F.interpolate(tensor, size=(height, width), mode="bilinear", antialias=True, align_corners=False)
    return out[0].permute(1, 2, 0).numpy()


def estimate_noise(frames: np.ndarray) -> np.ndarray:
    """(C,) float32: each channel's noise in `frames` (T, H, W, C), at least NOISE_FLOOR.

    Per pixel, the standard deviation over time; then the median over pixels, which are those
    the smoke never crosses as long as it crosses fewer than half of them (36% of dev scene D's
    input view over its 90 frames, 14% of ScalarFlow's): the temporal spread of the background,
    blind to a textured background's spatial pattern. Not the median absolute deviation, though
    it is robust within a pixel: on 8-bit values it moves in half steps (Gaussian noise of 2 codes
    reads 1.48, of 1 code 1.48 or 0), where the median of standard deviations reads 2.01 and 1.03.
    """
    spread = frames.std(axis=0)  # (H, W, C)
    sigma = np.median(spread.reshape(-1, spread.shape[-1]), axis=0)
    return np.maximum(sigma, NOISE_FLOOR).astype(np.float32)


def estimate_background(frames: np.ndarray) -> Background:
    """Background of one view from its frames (float (T, H, W, C) in [0, 1]).

    The colour is the median over the frame of the per-pixel temporal median: smoke covers
    well under half of a typical frame. The background is textured when that per-pixel median
    differs from the colour beyond the noise (as smoke would) on more than TEXTURED_FRACTION of
    the view; only then is an image returned, because a flat background is better described by
    its colour than by an image that still holds the smoke that never leaves (e.g. right above
    the source). The image is the per-pixel temporal median (smoke covers a pixel in fewer than
    half of the frames), and where smoke stays longer, the value over time closest to the colour
    ("the least smoky moment"), the true background wherever the smoke ever leaves; not that
    everywhere, since the noise pulls it towards the colour by two or three of its units.
    """
    import torch

    if frames.ndim != 4 or frames.shape[0] == 0:
        raise EstimationError(f"video: expected frames (T, H, W, C), got shape {frames.shape}")
    step = max(1, len(frames) // MAX_BACKGROUND_FRAMES)
    sample = frames[::step]
    noise = estimate_noise(sample)
    median = np.median(sample, axis=0)
    color = np.median(median.reshape(-1, median.shape[-1]), axis=0).astype(np.float32)
    least_smoky = np.take_along_axis(sample, np.abs(sample - color).mean(axis=-1).argmin(axis=0)[None, ..., None], axis=0)[0]
    median_t, noise_t = torch.from_numpy(median), torch.from_numpy(noise)
    if is_smoke(smoke_contrast(median_t, torch.from_numpy(color), noise_t)).mean() <= TEXTURED_FRACTION:
        return Background(color=color, image=None, noise=noise)
    smoky = is_smoke(smoke_contrast(median_t, torch.from_numpy(least_smoky), noise_t))[..., None]  # smoke there more often than not
    return Background(color=color, image=np.where(smoky, least_smoky, median).astype(np.float32), noise=noise)


def smoke_contrast(frames: torch.Tensor, background: torch.Tensor, noise: torch.Tensor) -> np.ndarray:
    """(..., H, W) float32: how far `frames` (..., H, W, C) lie from the `background` ((H, W, C)
    or (C,)) in units of the video's `noise` ((C,), `Background.noise`), in the channel where they
    lie farthest; the measure every smoke mask thresholds.

    The farthest channel, not the mean over channels: coloured smoke over a coloured background
    may change one channel only (the mean divides it by the channel count) or shift channels in
    opposite directions (a grey image does not change at all); nor the norm over channels, which
    counts a decoded video's noise, shared by its channels, sqrt(C) times over
    (tests/fluidcore/test_smoke_mask.py).
    """
    return ((frames - background).abs() / noise.to(frames)).amax(dim=-1).cpu().numpy()


def smoke_mask(frames: torch.Tensor, background: torch.Tensor, noise: torch.Tensor) -> np.ndarray:
    """(..., H, W) bool: where `frames` (..., H, W, C) differ visibly from the `background`
    ((H, W, C) or (C,)), beyond the video's `noise` ((C,)): the one smoke mask of the
    reconstruction (source estimate, physics identification, mirror agreement, optical flow
    confidence)."""
    return is_smoke(smoke_contrast(frames, background, noise))


def is_smoke(contrast: np.ndarray) -> np.ndarray:
    """Where a `smoke_contrast` is visible smoke (for a caller that needs the contrast too)."""
    return contrast > SMOKE_SIGMAS


def image_up(camera, point: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(2,) unit direction in the image in which the world's up axis points, at `point`."""
    scale = max(float(np.linalg.norm(camera.center() - point)), 1e-6) * 0.05
    uv, _ = camera.project_numpy(np.stack([point, point + scale * up]))
    direction = uv[1] - uv[0]
    norm = np.linalg.norm(direction)
    if norm < 1e-9:
        raise EstimationError(f"camera {camera.name} looks along the up axis; cannot tell where smoke rises")
    return direction / norm


def source_frames(fps: float, available: int) -> int:
    """How many of the first frames `source_in_view` reads: SOURCE_SECONDS of video, at least one."""
    return max(1, min(available, round(SOURCE_SECONDS * fps)))


def source_in_view(masks: np.ndarray, up2d: np.ndarray) -> tuple[float, float, float]:
    """(u, v, radius_px) of the source in one view from smoke masks (T, H, W) of the first frames.

    The inlet is the smoke that stays put: pixels that are smoke in SOURCE_PERSISTENCE of the
    frames (all smoke pixels when fewer persist, e.g. in a single frame). Its size is the widest
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
    rows, cols = np.nonzero(persistent)
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
