"""The upload form's field-of-view mode (web/js/upload.js) in headless Chromium, the in-process API
behind it: the scene box the server would make from the typed field of view is drawn on the
video's first frame and follows the value (issue 48: a guessed field of view could not be checked
against the footage). Judged from the first frame's pixels."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from tests.support.api import Service
from tests.support.browser import in_process

pytestmark = pytest.mark.browser
sync_api = pytest.importorskip("playwright.sync_api")

W, H = 240, 320
# Columns where the first frame's pixels are the box's yellow (#ffd23f), on the rows of its middle
# third (where the far face's vertical edges run and no other edge does).
YELLOW_COLUMNS = """() => { const c = document.querySelector('#video-list canvas'); const x = c.getContext('2d');
    const d = x.getImageData(0, 0, c.width, c.height).data; const found = new Set();
    for (let row = Math.floor(c.height / 3); row < Math.floor(2 * c.height / 3); row++)
        for (let col = 0; col < c.width; col++) { const i = 4 * (row * c.width + col);
            if (d[i] > 200 && d[i + 1] > 170 && d[i + 2] < 120) found.add(col); }
    return [...found].sort((a, b) => a - b); }"""


def far_face_left(fov: float) -> float:
    """The column of the box's far face's left edge: the box's middle section fills the frame 1 unit
    away and it is as deep as wide, so its far face lies 1 + tan(fov / 2) away (fluidcore.cameras.single)."""
    return W / 2 - (W / 2) / (1 + math.tan(math.radians(fov / 2)))


def test_the_field_of_views_box_is_drawn_on_the_first_frame_and_follows_the_value(  # type: ignore[no-untyped-def]
    static_web: str, browser, sqlite_service: Service, tmp_path: Path, screens: Path,
) -> None:
    from tests.support.service import write_video

    api = sqlite_service
    auth = api.key("alice")
    clip = write_video(tmp_path / "clip.mp4", width=W, height=H, n_frames=3)
    page = browser.new_page(viewport={"width": 1280, "height": 900})
    errors: list[str] = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    page.route("**/v1/**", in_process(api))
    page.goto(static_web)
    page.get_by_label("API key").fill(auth["Authorization"].removeprefix("Bearer "))
    page.keyboard.press("Enter")
    sync_api.expect(page.locator("#jobs-title")).to_be_visible()
    page.get_by_role("button", name="Upload", exact=True).click()
    page.locator("#upload-files").set_input_files([clip])
    sync_api.expect(page.locator("#video-list canvas")).to_have_count(1)
    assert page.evaluate(YELLOW_COLUMNS) == []  # no field of view yet: the frame as decoded

    fov = page.get_by_label("Horizontal field of view")
    seen = {}
    for degrees in (40, 70):
        fov.fill(str(degrees))
        expected = far_face_left(degrees)  # 32.0 at 40 degrees, 49.4 at 70
        page.wait_for_function(f"() => ({YELLOW_COLUMNS})().some(col => Math.abs(col + 0.5 - {expected}) < 1.5)")
        columns = np.array(page.evaluate(YELLOW_COLUMNS))
        left = columns[columns < W / 2]
        assert np.abs(left + 0.5 - expected).max() < 2.5, (degrees, left)  # the far face's edge, and nothing else there
        right = columns[columns >= W / 2]
        assert np.abs(right + 0.5 - (W - expected)).max() < 2.5, (degrees, right)  # and its mirror
        seen[degrees] = expected
    sync_api.expect(page.locator("#camera-summary")).to_contain_text("Yellow on the first frame: that box")
    page.screenshot(path=screens / "upload-fov-box.png", full_page=True)
    fov.fill("")
    page.wait_for_function(f"() => ({YELLOW_COLUMNS})().length === 0")  # the frame as decoded again
    assert seen[70] - seen[40] > 10
    assert not errors, errors
    page.close()
