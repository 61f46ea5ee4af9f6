"""The upload form's field-of-view mode (web/js/upload.js) in headless Chromium, the in-process API
behind it: the scene box the server would make from the typed field of view is drawn on the
video's first frame and follows the value (issue 48: a guessed field of view could not be checked
against the footage). Judged from the first frame's pixels."""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import pytest

from tests.support.api import Service
from tests.support.browser import canvas_pixels, signed_in

pytestmark = pytest.mark.browser
sync_api = pytest.importorskip("playwright.sync_api")

W, H = 240, 320
FRAME = "#video-list canvas"


def yellow_columns(page) -> np.ndarray:  # type: ignore[no-untyped-def]
    """Columns where the first frame shows the box's yellow (#ffd23f), on the rows of its middle
    third (where the far face's vertical edges run and no other edge does)."""
    rgb = canvas_pixels(page, FRAME)[H // 3 : 2 * H // 3].astype(int)
    yellow = (rgb[..., 0] > 200) & (rgb[..., 1] > 170) & (rgb[..., 2] < 120)
    return np.flatnonzero(yellow.any(axis=0))


def far_face_left(fov: float) -> float:
    """The column of the box's far face's left edge: the box's middle section fills the frame 1 unit
    away and it is as deep as wide, so its far face lies 1 + tan(fov / 2) away (fluidcore.cameras.single)."""
    return W / 2 - (W / 2) / (1 + math.tan(math.radians(fov / 2)))


def drawn(page, check, seconds: float = 20.0) -> np.ndarray:  # type: ignore[no-untyped-def]
    """The yellow columns once `check(columns)` holds (the box is drawn when the server answers)."""
    end = time.monotonic() + seconds
    while not check(columns := yellow_columns(page)) and time.monotonic() < end:
        page.wait_for_timeout(100)
    assert check(columns), columns
    return columns


def test_the_field_of_views_box_is_drawn_on_the_first_frame_and_follows_the_value(  # type: ignore[no-untyped-def]
    static_web: str, browser, sqlite_service: Service, tmp_path: Path, screens: Path,
) -> None:
    from tests.support.service import write_video

    clip = write_video(tmp_path / "clip.mp4", width=W, height=H, n_frames=3)
    page, errors = signed_in(browser, static_web, sqlite_service, sqlite_service.key("alice"))
    page.get_by_role("button", name="Upload", exact=True).click()
    page.locator("#upload-files").set_input_files([clip])
    sync_api.expect(page.locator(FRAME)).to_have_count(1)
    assert len(yellow_columns(page)) == 0  # no field of view yet: the frame as decoded

    fov = page.get_by_label("Horizontal field of view")
    for degrees in (40, 70):
        fov.fill(str(degrees))
        expected = far_face_left(degrees)  # 32.0 at 40 degrees, 49.4 at 70
        columns = drawn(page, lambda columns: bool(len(columns)) and np.abs(columns + 0.5 - expected).min() < 1.5)
        left, right = columns[columns < W / 2], columns[columns >= W / 2]
        assert np.abs(left + 0.5 - expected).max() < 2.5, (degrees, left)  # the far face's edge, and nothing else there
        assert np.abs(right + 0.5 - (W - expected)).max() < 2.5, (degrees, right)  # and its mirror
    sync_api.expect(page.locator("#camera-summary")).to_contain_text("Yellow on the first frame: that box")
    page.screenshot(path=screens / "upload-fov-box.png", full_page=True)
    fov.fill("")
    drawn(page, lambda columns: len(columns) == 0)  # the frame as decoded again
    assert not errors, errors
    page.close()
