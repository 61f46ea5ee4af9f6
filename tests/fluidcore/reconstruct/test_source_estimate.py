"""The source's size and place in one view (fluidcore.reconstruct.source_estimate.source_in_view), on masks
drawn here with a known source: a round one under a rising puff, a flat inlet, a tilted camera."""

from __future__ import annotations

import numpy as np
import pytest

from fluidcore.reconstruct import images, source_estimate
from fluidcore.reconstruct.rays import ray_in_box

H, W = 200, 160
UP = np.array([0.0, -1.0])  # image rows grow downwards, so the world's up points to smaller v


def _disc(center: tuple[float, float], radius: float) -> np.ndarray:
    v, u = np.mgrid[0:H, 0:W] + 0.5
    return (u - center[0]) ** 2 + (v - center[1]) ** 2 <= radius**2


def _frames(source: np.ndarray, column_halfwidth: float, puff_radius: float, n: int = 30) -> np.ndarray:
    """`n` masks: the source always there, a stem above it growing with time, and a puff wider than
    the source that rises through the picture (smoke in few frames at any one place)."""
    v, u = np.mgrid[0:H, 0:W] + 0.5
    rows = np.nonzero(source.any(axis=1))[0]
    top, axis = rows.min(), float(np.nonzero(source.any(axis=0))[0].mean()) + 0.5
    masks = []
    for k in range(n):
        head = top - 4.0 * (k + 1)
        stem = (np.abs(u - axis) <= column_halfwidth) & (v <= top + 1) & (v >= head)
        puff = (u - axis) ** 2 + (v - head) ** 2 <= puff_radius**2
        masks.append(source | stem | puff)
    return np.stack(masks)


@pytest.mark.parametrize("radius", [6.0, 12.0, 20.0])
def test_a_round_source_under_a_wide_rising_puff_is_measured_at_its_widest_row(radius: float) -> None:
    """The lowest band of smoke sees only the disc's bottom cap; the widest row resting on the
    bottom edge is the disc's diameter, and the puff (1.6x wider) passes by too fast to count."""
    center = (80.0, 160.0)
    masks = _frames(_disc(center, radius), 0.5 * radius, 1.6 * radius)
    u, v, r = source_estimate.source_in_view(masks, UP)
    assert r == pytest.approx(radius, rel=0.1)
    assert abs(u - center[0]) <= 1.0 and abs(v - center[1]) <= 1.0


def test_a_flat_inlet_is_its_half_width_and_the_ball_rests_on_its_bottom() -> None:
    v, u = np.mgrid[0:H, 0:W] + 0.5
    inlet = (np.abs(u - 70.0) <= 10.0) & (v >= 170.0) & (v <= 176.0)  # 20 px wide, 6 px tall
    masks = _frames(inlet, 6.0, 18.0)
    u0, v0, r = source_estimate.source_in_view(masks, UP)
    assert r == pytest.approx(10.0, rel=0.15)
    assert abs(u0 - 70.0) <= 1.0
    assert v0 == pytest.approx(176.0 - r, abs=1.5)  # a ball of radius r resting on the inlet's bottom edge


def test_specks_that_stay_put_beside_the_source_do_not_widen_it() -> None:
    """What a background estimate gets wrong on a textured background stays put in every frame
    too: specks level with the source, left and right of it, are not the inlet (before, its
    bottom rows reached from one speck to the other)."""
    center, radius = (80.0, 160.0), 8.0
    masks = _frames(_disc(center, radius), 0.5 * radius, 1.6 * radius)
    masks[:, 162:166, 10:14] = True  # specks in every frame, far left and far right at the source's height
    masks[:, 158:161, 140:145] = True
    u, v, r = source_estimate.source_in_view(masks, UP)
    assert r == pytest.approx(radius, rel=0.1) and abs(u - center[0]) <= 1.0


def test_a_tilted_up_direction_measures_across_it() -> None:
    """A camera rolled by 30 degrees: the disc is measured along the image's up, not along rows."""
    angle = np.deg2rad(30.0)
    up = np.array([np.sin(angle), -np.cos(angle)])
    masks = np.stack([_disc((80.0, 120.0), 15.0)] * 10)
    u, v, r = source_estimate.source_in_view(masks, up)
    assert r == pytest.approx(15.0, rel=0.1)
    assert np.hypot(u - 80.0, v - 120.0) <= 1.5


def test_one_frame_of_smoke_is_enough_and_no_smoke_is_a_clear_error() -> None:
    u, v, r = source_estimate.source_in_view(_disc((50.0, 60.0), 8.0)[None], UP)
    assert r == pytest.approx(8.0, rel=0.15)
    with pytest.raises(images.EstimationError, match="give the source explicitly"):
        source_estimate.source_in_view(np.zeros((3, H, W), bool), UP)


def test_the_source_frames_are_one_second_of_video() -> None:
    assert source_estimate.source_frames(30.0, 90) == 30
    assert source_estimate.source_frames(30.0, 12) == 12
    assert source_estimate.source_frames(0.5, 90) == 1


def _camera(eye: tuple[float, float, float], target: tuple[float, float, float]):
    from fluidcore.cameras import Camera, look_at

    like = Camera("like", 300.0, 300.0, 160.0, 120.0, 320, 240, np.eye(4))
    return look_at(eye, target, (0.0, 1.0, 0.0), like, "cam")


def _sphere_points(camera, center: np.ndarray, radius: float) -> np.ndarray:
    """(H, W) how many of 200 000 points filling a ball land in each pixel: its silhouette, and
    the smoke's thickness along each ray (the chord, thin at the rim)."""
    rng = np.random.default_rng(0)
    points = rng.normal(size=(200_000, 3))
    points = center + radius * points / np.linalg.norm(points, axis=1, keepdims=True) * rng.random((200_000, 1)) ** (1 / 3)
    uv, _ = camera.project_numpy(points)
    counts = np.zeros((camera.height, camera.width))
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
    np.add.at(counts, (uv[inside, 1].astype(int), uv[inside, 0].astype(int)), 1.0)
    return counts


def _sphere_masks(camera, center: np.ndarray, radius: float, frames: int = 8) -> np.ndarray:
    """The silhouette of a ball, drawn by projecting points that fill it."""
    return np.stack([_sphere_points(camera, center, radius) > 0] * frames)


BOX = (np.array([-0.3, 0.0, -0.3]), np.array([0.3, 0.8, 0.3]))
SOURCE = np.array([0.08, 0.045, -0.06])  # resting 0.5 cm above the floor, 10 cm off the box's vertical axis
SOURCE_RADIUS = 0.04


def test_a_camera_looking_down_keeps_the_source_off_the_floor() -> None:
    """A source nearer the camera than the box's axis: the axis guess along the descending ray would
    sink below the floor, so the source rests on the floor instead. One farther away than the axis
    keeps the axis guess (the floor only bounds the depth)."""
    camera = _camera((0.0, 0.9, 1.4), (0.0, 0.1, 0.0))  # about 30 degrees down
    near = SOURCE * np.array([1.0, 1.0, -1.0])  # 6 cm in front of the axis
    estimate = source_estimate.estimate_source({"cam": camera}, {"cam": _sphere_masks(camera, near, SOURCE_RADIUS)}, BOX)
    assert estimate.depth_cue == "floor"
    assert np.linalg.norm(estimate.center - near) < 0.015
    assert estimate.radius == pytest.approx(SOURCE_RADIUS, rel=0.15)
    behind = source_estimate.estimate_source({"cam": camera}, {"cam": _sphere_masks(camera, SOURCE, SOURCE_RADIUS)}, BOX)
    assert behind.depth_cue == "box axis"


def test_a_level_camera_leaves_the_depth_to_a_range_that_holds_the_truth() -> None:
    camera = _camera((0.0, 0.05, 1.4), (0.0, 0.05, 0.0))
    estimate = source_estimate.estimate_source({"cam": camera}, {"cam": _sphere_masks(camera, SOURCE, SOURCE_RADIUS)}, BOX)
    assert estimate.depth_cue == "box axis"
    near, far = estimate.depth_range
    segment = far - near
    t = np.clip((SOURCE - near) @ segment / (segment @ segment), 0.0, 1.0)
    assert np.linalg.norm(near + t * segment - SOURCE) < 0.01  # the truth lies on the reported stretch of the ray
    assert np.all(near >= BOX[0] - 1e-9) and np.all(far <= BOX[1] + 1e-9)
    assert estimate.radius == pytest.approx(SOURCE_RADIUS * (1.4 - 0.0) / (1.4 + 0.06), rel=0.2)  # at the axis guess's depth


def test_a_raised_source_near_a_wall_gets_a_range_the_box_and_its_smoke_shorten() -> None:
    """A source on a stand (20 cm above the floor), 24 cm from the box's axis, 2 cm from a wall in x, with a
    column of smoke above it: the rays through the column leave the box through that wall, so the
    plume cannot lie as deep as the source's ray alone would allow. The reported range holds the
    truth and is shorter than the box's stretch of the ray; the centre lies in it."""
    camera = _camera((0.0, 0.3, 1.4), (0.0, 0.3, 0.0))  # level with the source
    source = np.array([0.24, 0.2, 0.05])
    column = [source + np.array([0.0, h, 0.0]) for h in np.linspace(0.0, 0.4, 9)]
    silhouette = np.any([_sphere_points(camera, c, SOURCE_RADIUS) > 0 for c in column], axis=0)
    masks = np.stack([silhouette] * 8)
    estimate = source_estimate.estimate_source({"cam": camera}, {"cam": masks}, BOX)
    assert estimate.depth_cue == "box axis"
    near, far = estimate.depth_range
    origin, direction = camera.center(), (source - camera.center()) / np.linalg.norm(source - camera.center())
    box_near, box_far = ray_in_box(origin, direction, *BOX)
    assert np.linalg.norm(far - near) < 0.8 * np.linalg.norm(box_far - box_near)
    segment = far - near
    t = (source - near) @ segment / (segment @ segment)
    assert 0.0 <= t <= 1.0 and np.linalg.norm(near + t * segment - source) < 0.01  # the truth lies in it
    s = (estimate.center - near) @ segment / (segment @ segment)
    assert -1e-9 <= s <= 1.0 + 1e-9


def test_two_views_triangulate_and_report_no_range() -> None:
    a, b = _camera((0.0, 0.05, 1.4), (0.0, 0.05, 0.0)), _camera((1.4, 0.05, 0.0), (0.0, 0.05, 0.0))
    masks = {"a": _sphere_masks(a, SOURCE, SOURCE_RADIUS), "b": _sphere_masks(b, SOURCE, SOURCE_RADIUS)}
    estimate = source_estimate.estimate_source({"a": a, "b": b}, masks, BOX)
    assert estimate.depth_cue == "triangulated" and estimate.depth_range is None
    assert np.linalg.norm(estimate.center - SOURCE) < 0.01


def test_dark_smoke_on_a_bright_background_gives_the_source_its_size() -> None:
    """The whole image path on a bright, noisy 8-bit video: a dense ball of smoke that darkens a
    white wall (by half where it is thickest, by a tenth at the rim), with 2 codes of noise; the
    background, its noise, the one smoke mask and the estimate find the ball's size and place."""
    import torch

    camera = _camera((0.0, 0.9, 1.4), (0.0, 0.1, 0.0))
    near = SOURCE * np.array([1.0, 1.0, -1.0])
    thickness = _sphere_points(camera, near, SOURCE_RADIUS)
    rng = np.random.default_rng(1)
    darkening = 0.5 * (1.0 - np.exp(-8.0 * thickness / thickness.max()))
    frames = np.stack([0.92 * (1.0 - darkening) + 2.0 / 255.0 * rng.normal(size=thickness.shape) for _ in range(8)])
    frames = np.round(np.clip(frames, 0.0, 1.0)[..., None].repeat(3, axis=-1) * 255.0).astype(np.float32) / 255.0
    background = images.estimate_background(frames)
    assert background.image is None and background.color == pytest.approx(np.full(3, 0.92), abs=1.5 / 255.0)
    masks = images.smoke_mask(torch.from_numpy(frames), torch.from_numpy(background.color), torch.from_numpy(background.noise))
    estimate = source_estimate.estimate_source({"cam": camera}, {"cam": masks}, BOX)
    assert estimate.radius == pytest.approx(SOURCE_RADIUS, rel=0.15)
    assert np.linalg.norm(estimate.center - near) < 0.015


def test_a_generated_view_gives_one_view_its_depth_at_its_weight() -> None:
    """One level input view (depth open) and a view drawn from the side: the generated ray fixes
    the depth ("generated views"), the range still reports what the input view alone allows,
    and a generated view that shows no smoke is left out (back to the box-axis guess)."""
    a, b = _camera((0.0, 0.05, 1.4), (0.0, 0.05, 0.0)), _camera((1.4, 0.05, 0.0), (0.0, 0.05, 0.0))
    real = {"a": _sphere_masks(a, SOURCE, SOURCE_RADIUS)}
    drawn = source_estimate.GeneratedView(b, _sphere_masks(b, SOURCE, SOURCE_RADIUS), 0.25)
    alone = source_estimate.estimate_source({"a": a}, real, BOX)
    assert alone.depth_cue == "box axis" and abs(alone.center[2] - SOURCE[2]) > 0.04  # the axis guess misses the depth
    estimate = source_estimate.estimate_source({"a": a}, real, BOX, generated=[drawn])
    assert estimate.depth_cue == "generated views" and estimate.generated == {"cam": 0.25}
    assert np.linalg.norm(estimate.center - SOURCE) < 0.01
    assert estimate.depth_range is not None and set(estimate.pixels) == {"a"}
    assert estimate.radius == pytest.approx(SOURCE_RADIUS, rel=0.15)
    empty = source_estimate.GeneratedView(b, np.zeros_like(drawn.masks), 0.25)
    assert source_estimate.estimate_source({"a": a}, real, BOX, generated=[empty]).depth_cue == "box axis"


def test_the_input_view_outweighs_a_generated_one_across_its_ray() -> None:
    """A generated view that misplaces the source sideways: the centre stays nearer the input
    ray the lighter the generated view is (the weight is what trusting it less means)."""
    a, b = _camera((0.0, 0.05, 1.4), (0.0, 0.05, 0.0)), _camera((1.4, 0.05, 0.0), (0.0, 0.05, 0.0))
    real = {"a": _sphere_masks(a, SOURCE, SOURCE_RADIUS)}
    wrong = _sphere_masks(b, SOURCE + np.array([0.0, 0.05, 0.0]), SOURCE_RADIUS)  # 5 cm high in the drawn view
    lifts = [source_estimate.estimate_source({"a": a}, real, BOX, generated=[source_estimate.GeneratedView(b, wrong, w)]).center[1] - SOURCE[1]
             for w in (1.0, 0.25)]
    assert 0.0 < lifts[1] < lifts[0] < 0.05


def test_the_weighted_median_is_the_median_for_equal_weights() -> None:
    for values in ([3.0], [1.0, 4.0], [5.0, 1.0, 2.0], [4.0, 1.0, 3.0, 2.0]):
        assert source_estimate.weighted_median(values, [1.0] * len(values)) == pytest.approx(float(np.median(values)))
    assert source_estimate.weighted_median([1.0, 2.0, 3.0], [0.25, 1.0, 0.25]) == 2.0
    assert source_estimate.weighted_median([1.0, 2.0, 3.0], [1.0, 0.25, 0.25]) == 1.0


def test_a_generated_view_along_the_input_ray_is_left_out() -> None:
    """A view drawn from behind the source, looking back along the input ray: its ray cannot say
    how far along the input ray the source is, so the one-view guess stands."""
    a, behind = _camera((0.0, 0.05, 1.4), (0.0, 0.05, 0.0)), _camera((0.0, 0.05, -1.4), (0.0, 0.05, 0.0))
    real = {"a": _sphere_masks(a, SOURCE, SOURCE_RADIUS)}
    drawn = source_estimate.GeneratedView(behind, _sphere_masks(behind, SOURCE, SOURCE_RADIUS), 0.25)
    estimate = source_estimate.estimate_source({"a": a}, real, BOX, generated=[drawn])
    assert estimate.depth_cue == "box axis" and estimate.generated == {}
