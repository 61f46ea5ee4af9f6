"""The page's layout in a narrow (700 px) and a wide (1280 px) window, in headless Chromium with
the in-process API behind it (tests.support.browser): what issue 35 found on a fresh clone.

- the jobs table wraps between words, never inside one ("succeed/ed"), and stays in the window;
- the upload form's source field shows its example placeholder whole;
- a scene box edge just below 0 prints as 0, not "-0.00";
- the what-if view's source hint says nothing is wrong before it is touched;
- after a what-if branched inside the run the notice does not claim a factual prediction was
  queued (none is: its side-by-side shows the run itself), and after one from the run's end it
  names the one that was.

(The wind label drawn into what-if videos is fluidcore's: tests/fluidcore/test_overlay.py.)
Screenshots: docs/screens/layout-*-WIDTH.png with FLUIDNEXUS_SCREENSHOTS=1."""

from __future__ import annotations

import json
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest

from tests.support.api import Service, reconstruct, upload
from tests.support.browser import signed_in

pytestmark = pytest.mark.browser
sync_api = pytest.importorskip("playwright.sync_api")

# Each whole word of the table's cells that the browser laid out over more than one line, a
# percentage ("42 %") counted as one word (an error's ids and paths may break anywhere: they are
# one long word).
SPLIT_WORDS = """() => { const split = [];
  for (const cell of document.querySelectorAll('#jobs-table tbody td')) {
    const walker = document.createTreeWalker(cell, NodeFilter.SHOW_TEXT);
    for (let node; (node = walker.nextNode());) {
      if (node.parentElement.closest('.job-error')) continue;
      const whole = node.parentElement.closest('.job-percent');
      for (const m of whole ? [Object.assign([node.data], { index: 0 })] : node.data.matchAll(/\\S+/g)) {
        const range = document.createRange();
        range.setStart(node, m.index);
        range.setEnd(node, m.index + m[0].length);
        const lines = new Set([...range.getClientRects()].filter((r) => r.width > 0).map((r) => Math.round(r.top)));
        if (lines.size > 1) split.push(m[0]);
      }
    }
  }
  return split; }"""
PLACEHOLDER_FITS = """() => { const input = document.getElementById('source'), style = getComputedStyle(input);
  const context = document.createElement('canvas').getContext('2d');
  context.font = style.font;
  const room = input.clientWidth - parseFloat(style.paddingLeft) - parseFloat(style.paddingRight);
  return [context.measureText(input.placeholder).width, room]; }"""


def transforms_below_zero(folder: Path) -> Path:
    """A transforms.json whose voxel box ends at z = -0.001 (ScalarFlow's ends a hair below 0)."""
    from tests.support.service import camera_entry

    frames = [camera_entry(f"cam{i}", 32, 24, x) for i, x in enumerate((-1.0, 1.0))]
    box = {"voxel_scale": [0.5, 0.8, 0.4], "voxel_matrix": [[1, 0, 0, -0.2], [0, 1, 0, 0.0], [0, 0, 1, -0.501], [0, 0, 0, 1]]}
    path = folder / "transforms.json"
    path.write_text(json.dumps({"frames": frames, **box}))
    return path


def jobs_of_every_kind(api: Service, scene_dir: dict[str, Path]) -> tuple[dict[str, str], str]:
    """alice's succeeded one-view reconstruction whose source depth was a guess (its run stored),
    a prediction running on it and a failed one with a long error."""
    from fluidcore.runs import SourceEstimateRecord
    from service.models import JobState
    from tests.support.service import store_run

    auth = api.key("alice")
    scene_id = upload(api, auth, scene_dir).json()["id"]
    job_id = reconstruct(api, auth, scene_id, quality="preview").json()["id"]
    estimate = SourceEstimateRecord(depth_cue="box axis", depth_range=((0.0, 0.1, 0.5), (0.0, 0.1, -0.5)), pixels={"cam0": (16.0, 20.0, 2.0)})
    store_run(api.storage, job_id, {t: np.array([[0.0, 0.2, 0.0], [0.1, 0.3, 0.0]]) for t in (0, 1)}, source_estimate=estimate)
    api.set_job(job_id, state=JobState.SUCCEEDED, progress=1.0, stage="done", finished_at=datetime.now(UTC))
    for state, fields in ((JobState.RUNNING, {"progress": 0.42, "stage": "simulating frame 3 of 8"}),
                          (JobState.FAILED, {"error": "internal error (id 5f0c2a9e8b7d4c61a3e2f1d0c9b8a7f6): see the worker log"})):
        child = api.client.post("/v1/jobs", json={"type": "predict", "parent_job_id": job_id, "params": {"frames": 8}}, headers=auth)
        api.set_job(child.json()["id"], state=state, **fields)
    return auth, job_id


def check_jobs_table(page, width: int) -> None:  # type: ignore[no-untyped-def]
    page.get_by_role("button", name="Jobs").click()
    sync_api.expect(page.locator("#jobs-table .job-state", has_text="succeeded").first).to_be_visible()
    assert page.evaluate(SPLIT_WORDS) == []
    assert page.evaluate("() => document.documentElement.scrollWidth") <= width  # nothing sticks out of the window
    for button in page.locator("#jobs-table .job-actions button").all():
        box = button.bounding_box()
        assert box is not None and box["x"] + box["width"] <= width, box


@pytest.mark.parametrize("width", [700, 1280])
def test_the_pages_read_whole_at_700_and_1280_px(  # type: ignore[no-untyped-def]
    static_web: str, browser, sqlite_service: Service, scene_dir: dict, tmp_path: Path, screens: Path, width: int,
) -> None:
    api = sqlite_service
    auth, job_id = jobs_of_every_kind(api, scene_dir)
    page, errors = signed_in(browser, static_web, api, auth, width)

    # the upload form: the source's example whole, the box's edge at -0.001 printed as 0
    page.get_by_role("button", name="Upload", exact=True).click()
    sync_api.expect(page.get_by_label("Smoke source")).to_be_visible()
    text_width, room = page.evaluate(PLACEHOLDER_FITS)
    assert text_width <= room, (text_width, room)
    page.locator("#upload-files").set_input_files([transforms_below_zero(tmp_path)])
    summary = page.locator("#camera-summary")
    sync_api.expect(summary).to_contain_text("scene box (-0.2, 0, -0.5) to (0.2, 0.8, 0)")
    assert "-0.00" not in summary.text_content() and "-0)" not in summary.text_content()
    page.get_by_label("Smoke source").scroll_into_view_if_needed()
    page.screenshot(path=screens / f"layout-upload-{width}.png", full_page=True)

    check_jobs_table(page, width)

    # the what-if view: no complaint about the empty source hint before it is touched
    page.evaluate(f"location.hash = '#whatif/{job_id}'")
    sync_api.expect(page.locator("#source-form")).to_be_visible()
    sync_api.expect(page.locator("#source-problems")).to_be_empty()
    sync_api.expect(page.get_by_text("Slide along the ray or type a source hint first.")).to_have_count(0)
    sync_api.expect(page.get_by_role("button", name="Reconstruct with this source")).to_be_disabled()
    page.screenshot(path=screens / f"layout-whatif-{width}.png", full_page=True)
    hint = page.get_by_label("Source hint for a new reconstruction")
    hint.fill("0, 0.1, 0.2")
    sync_api.expect(page.get_by_role("button", name="Reconstruct with this source")).to_be_enabled()
    hint.fill("")  # touched, then emptied: now it says what to do
    sync_api.expect(page.locator("#source-problems")).to_have_text("Slide along the ray or type a source hint first.")

    # a what-if branched at frame 0: no factual prediction queued, and the notice does not claim one
    predictions = lambda: api.client.get("/v1/jobs", params={"type": "predict"}, headers=auth).json()["total"]  # noqa: E731
    before = predictions()
    page.get_by_label("New frames to simulate").fill("2")
    page.get_by_label("Branch at frame").fill("0")
    sync_api.expect(page.locator("#whatif-problems")).to_be_empty()
    page.get_by_role("button", name="Run what-if").click()
    notice = page.locator("#notice")
    sync_api.expect(notice).to_contain_text("branched at frame 0: its side-by-side video shows the run without the intervention")
    assert "with the factual prediction" not in notice.text_content()
    assert predictions() == before
    page.screenshot(path=screens / f"layout-notice-branched-{width}.png")

    # from the run's last frame: the factual prediction it plays next to is queued, and named
    page.evaluate(f"location.hash = '#whatif/{job_id}'")
    sync_api.expect(page.locator("#box-limits")).to_contain_text("Scene box")
    page.get_by_label("New frames to simulate").fill("2")
    page.get_by_label("Branch at frame").fill("")
    page.get_by_role("button", name="Run what-if").click()
    sync_api.expect(notice).to_contain_text("with the factual prediction")
    assert predictions() == before + 1
    queued = api.client.get("/v1/jobs", params={"type": "predict"}, headers=auth).json()["items"][0]
    assert queued["params"]["frames"] == 2 and queued["id"][:8] in notice.text_content()

    check_jobs_table(page, width)  # with the what-ifs' rows too
    page.screenshot(path=screens / f"layout-jobs-{width}.png", full_page=True)
    assert not errors, errors
    page.close()
