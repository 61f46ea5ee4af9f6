"""fluidcore.overlay: the ball and the wind arrow drawn where and when the physics has them."""

from __future__ import annotations

import numpy as np
import pytest

from fluidcore.cameras import Camera, look_at
from fluidcore.spec.controls import parse_interaction
from fluidcore.overlay import BALL_COLOR, WIND_LABEL_SHARE, draw_interventions, side_by_side, wind_label
from fluidcore.spec.solids import SolidBall

CAMERA = look_at([0, 0.5, 2], [0, 0.5, 0], [0, 1, 0], Camera("c", 200, 200, 80, 60, 160, 120, np.eye(4)), "c")
DT = 1 / 30


def _draw(params, frames=(10, 11, 12, 13)):  # noqa: ANN001, ANN202
    blank = np.full((len(frames), 120, 160, 3), 20, np.uint8)
    return draw_interventions(blank, CAMERA, list(frames), params, first_new_frame=11, dt=DT, anchor=[0, 0.8, 0], arrow_length=0.3)


def test_ball_is_drawn_where_it_projects_from_its_start_frame_on() -> None:
    ball = {"center": [0.2, 0.5, 0.0], "radius": 0.1, "start_frame": 1}
    out = _draw(parse_interaction(None, ball))
    changed = np.any(out != 20, axis=-1)
    assert not changed[0].any() and not changed[1].any()  # before the run's new frames, and new frame 0
    (u, v), = CAMERA.project_numpy(np.array([0.2, 0.5, 0.0]))[0]
    radius_px = 200 * 0.1 / np.sqrt(4 - 0.01)
    assert changed[2, int(v), int(u)] and changed[3, int(v), int(u)]
    assert out[2, int(v), int(u)].argmax() == int(np.argmax(BALL_COLOR))  # orange, not smoke grey
    ys, xs = np.mgrid[0:120, 0:160]
    distance = np.hypot(xs + 0.5 - u, ys + 0.5 - v)
    assert changed[2][distance < radius_px - 1].all()  # the whole disc
    assert not changed[2][distance > radius_px + 2.5].any()  # and nothing beyond its anti-aliased rim


def test_the_smoke_under_the_ball_stays_visible() -> None:
    """Issue 48: the ball was drawn nearly opaque (0.6) over the smoke it deflects. Inside its rim
    the smoke's texture keeps most of its contrast, and the disc is still tinted orange."""
    rng = np.random.default_rng(0)
    smoke = np.repeat(rng.integers(60, 200, (1, 120, 160, 1), dtype=np.uint8), 3, axis=-1)  # grey speckle
    ball = {"center": [0.0, 0.5, 0.0], "radius": 0.15}
    out = draw_interventions(smoke, CAMERA, [11], parse_interaction(None, ball), first_new_frame=11, dt=DT,
                             anchor=[0, 0.8, 0], arrow_length=0.3)[0].astype(float)
    (u, v), = CAMERA.project_numpy(np.array([0.0, 0.5, 0.0]))[0]
    ys, xs = np.mgrid[0:120, 0:160]
    inside = np.hypot(xs + 0.5 - u, ys + 0.5 - v) < 200 * 0.15 / 2 - 3  # within the rim
    before = smoke[0].astype(float)[inside][:, 1]
    after = out[inside][:, 1]
    assert np.corrcoef(before, after)[0, 1] > 0.99  # the same speckle, not a flat disc
    assert np.std(after) > 0.7 * np.std(before)  # at least 70% of its contrast (0.4 at the old opacity)
    assert (out[inside][:, 0] - out[inside][:, 2]).mean() > 20  # still tinted orange


def test_a_moving_ball_moves_in_the_picture() -> None:
    ball = {"center": [-0.2, 0.5, 0.0], "radius": 0.05, "velocity": [3.0, 0.0, 0.0]}  # 0.1 units per frame
    out = _draw(parse_interaction(None, ball))
    columns = [np.nonzero(np.any(out[i] != 20, axis=-1))[1].mean() for i in (1, 2, 3)]
    step = 200 * 0.1 / 2  # pixels per frame at depth 2
    np.testing.assert_allclose(np.diff(columns), step, atol=1.0)


def test_wind_arrow_only_while_the_wind_blows() -> None:
    wind = {"direction": [1, 0, 0], "strength": 1.0, "start_frame": 1, "end_frame": 2, "profile": "uniform"}
    out = _draw(parse_interaction(wind, None))
    drawn = [bool(np.any(out[i] != 20)) for i in range(4)]
    assert drawn == [False, False, True, False]
    ys, xs = np.nonzero(np.any(out[2] != 20, axis=-1))
    (u0, _), (u1, _) = CAMERA.project_numpy(np.array([[0, 0.8, 0], [0.3, 0.8, 0]]))[0]
    assert xs.max() >= u1 - 3 and xs.min() <= u0 + 3  # the arrow spans the projected wind vector


def test_side_by_side_keeps_both_videos() -> None:
    left, right = np.zeros((2, 40, 60, 3), np.uint8), np.full((2, 40, 60, 3), 200, np.uint8)
    both = side_by_side(left, right)
    assert both.shape[:2] == (2, 40) and both.shape[2] > 120
    assert np.all(both[:, 30:, :50] == 0) and np.all(both[:, 30:, -50:] == 200)
    with pytest.raises(ValueError, match="differ in shape"):
        side_by_side(left, right[:, :20])


def _dark_box(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns of the label's black box (the frames here are grey, the arrow blue)."""
    return np.nonzero(np.all(image == 0, axis=-1))


@pytest.mark.parametrize("size", [(96, 96), (1160, 648), (480, 270)])
def test_wind_label_stays_inside_the_frame_and_grows_with_it(size: tuple[int, int]) -> None:
    height, width = size
    camera = look_at([0, 0.5, 2], [0, 0.5, 0], [0, 1, 0], Camera("c", 1.2 * width, 1.2 * width, width / 2, height / 2, width, height, np.eye(4)), "c")
    wind = parse_interaction({"direction": [1, 0, 0], "strength": 1.0, "growth": 1.0}, None)  # the longest label: "wind (exponential)"
    frame = np.full((1, height, width, 3), 128, np.uint8)
    out = draw_interventions(frame, camera, [1], wind, first_new_frame=1, dt=DT, anchor=[0.1, 0.8, 0], arrow_length=0.3)[0]
    rows, cols = _dark_box(out)
    assert rows.size, "no label drawn"
    assert rows.min() > 0 and cols.min() > 0 and rows.max() < height - 1 and cols.max() < width - 1
    white = np.all(out > 200, axis=-1)  # the text (anti-aliased); the grey frame is 128, the arrow blue
    text_rows = np.nonzero(white.any(axis=1))[0]
    assert text_rows.size and (text_rows.max() - text_rows.min()) >= 0.015 * max(size)  # readable in a player


@pytest.mark.parametrize("size", [(32, 48), (1160, 648)])
def test_side_by_side_titles_are_whole_and_scale_with_the_frames(size: tuple[int, int]) -> None:
    height, width = size
    grey = np.full((1, height, width, 3), 128, np.uint8)
    both = side_by_side(grey, grey)[0]
    half = both.shape[1] // 2
    for part in (both[:, :half], both[:, half:]):
        rows, cols = _dark_box(part)
        assert rows.size and rows.min() > 0  # the box (and so the title in it) is not cut at the top
        assert np.all(part > 200, axis=-1).any()  # some text is drawn in it
    rows, _ = _dark_box(both)
    assert rows.max() - rows.min() >= 0.025 * max(size) or max(size) < 100  # a title a viewer can read at that size


@pytest.mark.parametrize("size", [(96, 96), (480, 268), (1160, 648)])  # 480 x 268: ScalarFlow's input view at preview quality
def test_the_wind_label_tags_the_arrow_without_covering_the_smoke(size: tuple[int, int]) -> None:
    """Issue 35: a large "wind (exponential)" covered the video when growth was 0 (the same push
    at every height, whatever the profile). Now it reads "wind" there, and any wind label takes at
    most WIND_LABEL_SHARE of the frame's width (a longer one too, where that leaves it readable)."""
    height, width = size
    camera = look_at([0, 0.5, 2], [0, 0.5, 0], [0, 1, 0], Camera("c", 1.2 * width, 1.2 * width, width / 2, height / 2, width, height, np.eye(4)), "c")
    widths = {}
    for growth in (0.0, 1.0):
        wind = parse_interaction({"direction": [1, 0, 0], "strength": 1.0, "growth": growth}, None)
        frame = np.full((1, height, width, 3), 128, np.uint8)
        out = draw_interventions(frame, camera, [1], wind, first_new_frame=1, dt=DT, anchor=[0.1, 0.8, 0], arrow_length=0.3)[0]
        _, cols = _dark_box(out)
        widths[growth] = cols.max() - cols.min() + 1
    assert widths[0.0] <= WIND_LABEL_SHARE * width + 1, (widths, width)
    assert widths[0.0] < widths[1.0]  # "wind" against "wind (exponential)"
    assert [wind_label(parse_interaction({"direction": [1, 0, 0], "strength": 1.0, "growth": g, "profile": p}, None).wind)
            for g, p in ((0.0, "exponential"), (0.0, "linear"), (0.0, "uniform"), (0.5, "linear"))] == ["wind"] * 3 + ["wind (linear)"]


def test_the_scenes_solids_are_drawn_on_every_frame_as_the_what_ifs_ball_is() -> None:
    solid = SolidBall(center=(0.2, 0.5, 0.0), radius=0.1)
    blank = np.full((4, 120, 160, 3), 20, np.uint8)
    out = draw_interventions(blank, CAMERA, [10, 11, 12, 13], parse_interaction(None, None), first_new_frame=11, dt=DT,
                             anchor=[0, 0.8, 0], arrow_length=0.3, solids=(solid,))
    as_ball = _draw(parse_interaction(None, {"center": list(solid.center), "radius": solid.radius}))
    for frame in range(4):  # before the new frames too: a solid is there from the first step
        np.testing.assert_array_equal(out[frame], as_ball[1])
