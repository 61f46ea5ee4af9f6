"""The what-if page's 3D view (web/js/whatif.js) in headless Chromium, its /v1 answers faked: the
view looks across the plume whichever axis is up (a +z-up scene was seen from above, down the
plume), and the ball leaves the smoke inside and behind it visible (it was drawn nearly opaque).
Judged from the canvas's pixels, as a user sees them."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.support.browser import canvas_pixels

pytestmark = pytest.mark.browser
sync_api = pytest.importorskip("playwright.sync_api")

JOB = {"id": "job-view", "type": "predict", "state": "succeeded", "scene_id": None, "parent_job_id": "job-rec", "params": {}}


def smoke(page) -> np.ndarray:  # type: ignore[no-untyped-def]
    """(H, W) bool: the view's smoke, the particles' near-white (0xe8edf3) over the dark background:
    each channel bright and none much redder than the others (the ball is red, the wind blue)."""
    rgb = canvas_pixels(page, "#scene3d").astype(int)
    return (rgb > 150).all(axis=-1) & (rgb[..., 0] - rgb[..., 2] < 40)


def open_view(browser, static_web: str, positions: np.ndarray, up: tuple[float, float, float]):  # type: ignore[no-untyped-def]
    """The what-if page of a run whose last frame holds `positions`, in a box of side 1 about the origin."""
    from api.routers.limits import limits
    from service.settings import Settings

    particles = {
        "job_id": JOB["id"], "frame": 1, "frames": [0, 1], "total": len(positions), "positions": positions.ravel().tolist(),
        "scene": {"box_lo": [-0.5, -0.5, -0.5], "box_hi": [0.5, 0.5, 0.5], "up": list(up),
                  "source": {"center": [0.0, 0.0, 0.0], "radius": 0.05}, "dt": 1 / 30},
        "air": None,
    }
    page = browser.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    page.route("**/v1/jobs?limit=100", lambda route: route.fulfill(json={"items": [JOB]}))
    page.route(f"**/v1/jobs/{JOB['id']}/particles*", lambda route: route.fulfill(json=particles))
    page.route("**/v1/limits", lambda route: route.fulfill(body=json.dumps(limits(Settings())), content_type="application/json"))
    page.route("**/v1/wind/accelerations", lambda route: route.fulfill(json={"accelerations": [1.0] * 5}))
    page.goto(static_web)
    page.evaluate("""async () => { document.getElementById('view-whatif').hidden = false;
                                   await (await import('/js/whatif.js')).showWhatif('job-view'); }""")
    sync_api.expect(page.locator("#whatif-summary")).to_contain_text(f"Showing {len(positions)} of {len(positions)} particles")
    page.get_by_label("Wind", exact=True).uncheck()  # only the smoke and, later, the ball in view
    return page, errors


@pytest.mark.parametrize("up", [(0.0, 1.0, 0.0), (0.0, 0.0, 1.0)])
def test_the_view_looks_across_the_plume_whichever_axis_is_up(static_web: str, browser, up: tuple) -> None:  # type: ignore[no-untyped-def]
    """A column of smoke along up, 0.8 of the box's side: seen from the side it stands upright and
    spans a good part of the view's height; seen down its length (the +z-up bug) it shrank to a
    short stub."""
    column = np.outer(np.linspace(-0.4, 0.4, 400), up)
    page, errors = open_view(browser, static_web, column, up)
    seen = smoke(page)
    rows, cols = np.nonzero(seen)
    assert len(rows) > 100, "the column is not drawn"
    tall, wide = np.ptp(rows) + 1, np.ptp(cols) + 1
    assert tall > 0.25 * seen.shape[0], (tall, seen.shape)  # looked down its length, the column is a stub
    assert tall > 3 * wide, (tall, wide)  # upright on the screen
    assert not errors, errors
    page.close()


def test_the_ball_leaves_the_smoke_it_is_in_visible(static_web: str, browser) -> None:  # type: ignore[no-untyped-def]
    """A blob of smoke with a ball around it: nearly all of its pixels still read as smoke once the
    ball is on (a ball drawn opaque, or blended strongly over it, turned them red)."""
    rng = np.random.default_rng(0)
    blob = rng.uniform(-0.12, 0.12, (600, 3))
    page, errors = open_view(browser, static_web, blob, (0.0, 1.0, 0.0))
    alone = int(smoke(page).sum())
    assert alone > 200, "the blob is not drawn"
    page.get_by_label("Ball", exact=True).check()
    for field, value in (("ball centre x", "0"), ("ball centre y", "0"), ("ball centre z", "0")):
        page.get_by_label(field).fill(value)
    page.locator("#ball-radius").fill("0.2")
    sync_api.expect(page.locator("#whatif-problems")).to_be_empty()
    rgb = canvas_pixels(page, "#scene3d").astype(int)
    red = (rgb[..., 0] > 120) & (rgb[..., 1] < 90) & (rgb[..., 2] < 90)
    assert red.sum() > 100, "the ball is not drawn"  # its wireframe and shell show where it is
    with_ball = int(smoke(page).sum())
    assert with_ball > 0.9 * alone, (with_ball, alone)
    assert not errors, errors
    page.close()
