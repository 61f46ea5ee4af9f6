"""Drawing what a what-if changed onto rendered frames: the ball where it is, and an arrow for
the wind while it blows; the scene's own solid balls (`fluidcore.spec.solids`) on every frame,
drawn as the what-if's ball is; and the side-by-side factual | what-if picture.

The ball is one-way coupled and invisible to the smoke renderer, so without this a what-if
video shows the smoke swerving around nothing. Whether (and where) an intervention is drawn on
a frame comes from the same `WindParams.active` / `BallParams.active` / `center_at` that the
simulator's forces and spheres follow (fluidcore.spec.controls), so the picture never disagrees
with the physics. Frames are uint8 (T, H, W, 3) at the camera's size; torch-free.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from fluidcore.cameras import Camera
from fluidcore.spec.controls import InteractionParams, WindParams
from fluidcore.spec.solids import SolidBall
from fluidcore.runs import ContinuationSettings, RunRecord

BALL_COLOR = (235, 120, 30)  # RGB; an orange no smoke colour is close to
# The disc's tint over the frame: a light one, so the smoke in front of and behind the ball keeps its
# look (issue 48: at 0.6 the disc hid the smoke it deflects); its rim says where the ball is.
BALL_OPACITY = 0.2
WIND_COLOR = (40, 170, 255)
LABEL_COLOR = (255, 255, 255)


def draw_interventions(
    frames: np.ndarray, camera: Camera, frame_numbers: Sequence[int], params: InteractionParams, *,
    first_new_frame: int, dt: float, anchor: Sequence[float], arrow_length: float, solids: Sequence[SolidBall] = (),
) -> np.ndarray:
    """A copy of `frames` (video frames `frame_numbers`) with the scene's `solids` on every frame
    and the ball and the wind drawn where they are active. Intervention frame k is video frame
    first_new_frame + k; the wind arrow starts at world point `anchor` and is `arrow_length` world
    units long."""
    out = np.array(frames, copy=True)
    for image, t in zip(out, frame_numbers, strict=True):
        k = t - first_new_frame
        for solid in solids:
            _draw_ball(image, camera, solid.center, solid.radius)
        if params.ball is not None and k >= 0 and params.ball.active(k):
            _draw_ball(image, camera, params.ball.center_at(k, dt), params.ball.radius)
        if params.wind is not None and k >= 0 and params.wind.active(k):
            _draw_wind(image, camera, params.wind, anchor, arrow_length)
    return out


def _draw_ball(image: np.ndarray, camera: Camera, center: Sequence[float], ball_radius: float) -> None:
    """The sphere at `center` (world) of `ball_radius`: its outline (a disc of the projected
    radius) tinted lightly over the frame, with a solid rim."""
    import cv2

    uv, depth = camera.project_numpy(np.asarray(center, dtype=np.float64))
    if depth[0] <= ball_radius:  # behind or around the camera: nothing sensible to draw
        return
    radius = camera.fx * ball_radius / np.sqrt(depth[0] ** 2 - ball_radius**2)
    shift = 4  # cv2 draws with sub-pixel precision given as fixed point with this many bits
    pixel = tuple(int(round((c - 0.5) * (1 << shift))) for c in uv[0])  # continuous -> OpenCV pixel centres
    size = int(round(radius * (1 << shift)))
    disc = image.copy()
    cv2.circle(disc, pixel, size, BALL_COLOR, thickness=-1, lineType=cv2.LINE_AA, shift=shift)
    blended = cv2.addWeighted(disc, BALL_OPACITY, image, 1.0 - BALL_OPACITY, 0.0)
    cv2.circle(blended, pixel, size, BALL_COLOR, thickness=max(1, image.shape[1] // 200), lineType=cv2.LINE_AA, shift=shift)
    image[...] = blended


def _draw_wind(image: np.ndarray, camera: Camera, wind: WindParams, anchor: Sequence[float], length: float) -> None:
    import cv2

    start = np.asarray(anchor, dtype=np.float64)
    uv, depth = camera.project_numpy(np.stack([start, start + length * np.asarray(wind.direction)]))
    if np.any(depth <= 0):
        return
    a, b = (tuple(int(round(c - 0.5)) for c in p) for p in uv)
    if a == b:  # blowing straight at or away from the camera: a marker instead of an arrow
        cv2.circle(image, a, max(3, image.shape[1] // 60), WIND_COLOR, 2, cv2.LINE_AA)
    else:
        cv2.arrowedLine(image, a, b, WIND_COLOR, max(2, image.shape[1] // 120), cv2.LINE_AA, tipLength=0.25)
    _label(image, wind_label(wind), (a[0] + 4, a[1] + 4), share=WIND_LABEL_SHARE)


def wind_label(wind: WindParams) -> str:
    """The arrow's tag: its profile only where the push changes with height (with a growth of 0,
    "wind (exponential)" named a profile the picture does not show, in letters over the smoke)."""
    return "wind" if wind.same_at_every_height else f"wind ({wind.profile})"


LABEL_HEIGHT = 0.03  # text cap height as a fraction of the image's long side: 35 px on ScalarFlow's 1160 px views
LABEL_MIN_SCALE = 0.35  # OpenCV font scale below which its strokes merge (about 8 px letters)
LABEL_PAD = 2  # pixels of dark box around the text
WIND_LABEL_SHARE = 0.4  # of the frame's width, unless that is below readable: the wind's label tags the arrow, it does not cover the smoke
LABEL_FIT_TRIES = 4  # shrinks of a label measured wider than its room (OpenCV rounds glyphs to pixels: 0.35 gives 89 px where 1.0 gives 267)


def _label(image: np.ndarray, text: str, origin: tuple[int, int], width: int | None = None, share: float = 1.0) -> None:
    """White text on a dark box (readable on smoke and on background alike), sized with the image
    and kept inside it: its top-left corner goes at `origin` or as near as fits, and it is shrunk
    to fit `width` pixels (default: the image's width) so a small video shows it whole, and to
    `share` of that where it stays readable (LABEL_MIN_SCALE)."""
    import cv2

    height_px, width_px = image.shape[:2]
    width = width_px if width is None else width
    font = cv2.FONT_HERSHEY_SIMPLEX
    (unit_w, unit_h), _ = cv2.getTextSize(text, font, 1.0, 1)
    wanted = LABEL_HEIGHT * max(height_px, width_px) / unit_h
    room = min(width, width_px) - 3 * LABEL_PAD - 2  # text starts 2 pads in; its box ends a pad and a pixel short of the edge
    scale = min(max(LABEL_MIN_SCALE, min(wanted, share * room / unit_w)), room / unit_w)  # inside the image first, readable second
    for _ in range(LABEL_FIT_TRIES):  # glyph sizes are rounded to pixels, so width is not linear in scale
        thickness = max(1, round(scale))
        (text_w, text_h), baseline = cv2.getTextSize(text, font, scale, thickness)
        if text_w <= room:
            break
        scale *= room / (text_w + 1)
    x = min(max(origin[0], 2 * LABEL_PAD), max(2 * LABEL_PAD, width_px - text_w - 2 * LABEL_PAD))
    y = min(max(origin[1], 2 * LABEL_PAD) + text_h, height_px - baseline - 2 * LABEL_PAD)
    cv2.rectangle(image, (x - LABEL_PAD, y - text_h - LABEL_PAD), (x + text_w + LABEL_PAD, y + baseline), (0, 0, 0), thickness=-1)
    cv2.putText(image, text, (x, y), font, scale, LABEL_COLOR, thickness, cv2.LINE_AA)


def side_by_side(left: np.ndarray, right: np.ndarray, labels: tuple[str, str] = ("factual", "what-if")) -> np.ndarray:
    """(T, H, 2W + gap, 3): two videos of the same frames next to each other, each labelled."""
    if left.shape != right.shape:
        raise ValueError(f"side_by_side: videos differ in shape ({left.shape} vs {right.shape})")
    gap = np.full((*left.shape[:2], max(2, left.shape[2] // 100), 3), 255, np.uint8)
    both = np.concatenate([np.array(left, copy=True), gap, np.array(right, copy=True)], axis=2)
    offset = left.shape[2] + gap.shape[2]
    margin = max(LABEL_PAD, left.shape[2] // 100)
    for image in both:
        _label(image, labels[0], (margin, margin), width=left.shape[2])
        _label(image, labels[1], (offset + margin, margin), width=left.shape[2])
    return both


def run_interventions(run: RunRecord) -> tuple[InteractionParams, int]:
    """The interventions a run was simulated with (none for runs without) and the video frame
    number of its intervention frame 0 (the frame after the branch frame)."""
    settings = run.settings
    if not isinstance(settings, ContinuationSettings):  # a reconstruction: no interventions, from its start
        return InteractionParams(), run.frame_range[0]
    return InteractionParams(wind=settings.wind, ball=settings.ball), settings.branch_frame + 1


def draw_run_interventions(run: RunRecord, camera: Camera, frame_numbers: Sequence[int], frames: np.ndarray) -> np.ndarray:
    """`draw_interventions` with what the run recorded: its scene's solids, its wind and ball, its
    branch frame, its step length; the wind arrow starts above the box centre and is a quarter of
    the box long."""
    params, first_new = run_interventions(run)
    scene = run.scene
    if params.wind is None and params.ball is None and not scene.solids:
        return frames
    lo, hi = np.asarray(scene.box_lo), np.asarray(scene.box_hi)
    up = np.asarray(scene.up) / np.linalg.norm(scene.up)
    height = float(np.abs(hi - lo) @ np.abs(up))
    anchor = 0.5 * (lo + hi) + 0.3 * height * up
    return draw_interventions(
        frames, camera, frame_numbers, params, first_new_frame=first_new, dt=scene.physics.dt,
        anchor=anchor, arrow_length=0.25 * float(np.min(hi - lo)), solids=scene.solids,
    )
