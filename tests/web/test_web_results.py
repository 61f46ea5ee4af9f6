"""The results page of a reconstruction (web/js/results.js) in headless Chromium, the in-process
API behind it (tests.support.browser): the uploaded footage of the input view plays beside the
render of that view, in step from the run's first frame (one play and seek control drives both),
overlaid on it or as their difference; and the per-frame plots: each loss term relative to its
first frame on a log axis, a legend that reads without hovering, the forecast PSNR explained.

The run, its manifest and its rendered input view are stored as a worker leaves them
(tests.support.service.store_run); nothing here waits for a real reconstruction."""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest

from tests.support.api import Service, reconstruct, upload
from tests.support.browser import signed_in

pytestmark = pytest.mark.browser
sync_api = pytest.importorskip("playwright.sync_api")

FIRST, END = 2, 6  # the run reconstructs frames 2..5 of the 6-frame clip
LOSSES = {  # image falls to a fifth; sim is 0 on the first frame; incomp is 0 throughout; the fit within 2 dB of the background
    2: {"image": 0.05, "sim": 0.0, "incomp": 0.0, "input_psnr": 20.0, "forecast_psnr": 18.0, "background_psnr": 19.0,
        "explained": 0.2, "smoke_up": -0.3, "smoke_across": 0.0, "particles": 10.0, "gaussians": 20.0},
    3: {"image": 0.03, "sim": 0.002, "incomp": 0.0, "input_psnr": 22.0, "forecast_psnr": 19.0, "background_psnr": 20.0,
        "explained": 0.35, "smoke_up": -0.2, "smoke_across": 0.0, "particles": 12.0, "gaussians": 24.0},
    4: {"image": 0.02, "sim": 0.004, "incomp": 0.0, "input_psnr": 23.0, "forecast_psnr": 21.0, "background_psnr": 21.0,
        "explained": 0.35, "smoke_up": -0.1, "smoke_across": 0.0, "particles": 14.0, "gaussians": 28.0},
    5: {"image": 0.01, "sim": 0.001, "incomp": 0.0, "input_psnr": 24.0, "forecast_psnr": 22.0, "background_psnr": 22.0,
        "explained": 0.35, "smoke_up": 0.0, "smoke_across": 0.0, "particles": 16.0, "gaussians": 32.0},
}
# uPlot is loaded by a plain <script>: wrap its constructor to record what each chart was given
RECORD_PLOTS = """(() => { let wrapped;
  Object.defineProperty(window, 'uPlot', { configurable: true, get: () => wrapped, set: (real) => {
    wrapped = function (opts, data, target) {
      (window.__plots = window.__plots || []).push({ title: opts.title, distr: (opts.scales.y || {}).distr || 1,
        labels: opts.series.slice(1).map((s) => s.label), data: data.slice(1) });
      return new real(opts, data, target);
    };
  } }); })()"""


def published_reconstruction(api: Service, scene_dir: dict[str, Path], tmp_path: Path) -> tuple[dict[str, str], str]:
    """alice's succeeded reconstruction of frames FIRST..END-1 of an uploaded scene: its run and
    manifest, and its input view (cam0) rendered as a plain grey clip, published as a worker does."""
    from fluidcore.video import write_mp4
    from service.database import session_scope
    from service.models import Artifact, JobState
    from service.videos import artifact_name, video_key
    from tests.support.service import store_run

    auth = api.key("alice")
    scene_id = upload(api, auth, scene_dir).json()["id"]
    job_id = reconstruct(api, auth, scene_id, frames=[FIRST, END]).json()["id"]
    store_run(api.storage, job_id, {t: np.array([[0.0, 0.2, 0.0], [0.1, 0.3, 0.0]]) for t in range(FIRST, END)}, losses=LOSSES)
    render = write_mp4(tmp_path / "cam0.mp4", np.full((END - FIRST, 24, 32, 3), 90, np.uint8), fps=30.0)
    api.storage.put_file(video_key(job_id, "cam0"), render, "video/mp4")
    manifest = f"jobs/{job_id}/run/manifest.json"
    with session_scope(api.sessions) as session:
        session.add(Artifact(job_id=job_id, name=artifact_name("cam0"), kind="video", camera="cam0", key=video_key(job_id, "cam0"),
                             size=render.stat().st_size, content_type="video/mp4"))
        session.add(Artifact(job_id=job_id, name="run/manifest.json", kind="manifest", key=manifest,
                             size=api.storage.stat(manifest).size, content_type="application/json"))
    api.set_job(job_id, state=JobState.SUCCEEDED, finished_at=datetime.now(UTC))
    return auth, job_id


def open_results(browser, static_web: str, api: Service, auth: dict[str, str], job_id: str, width: int):  # type: ignore[no-untyped-def]
    page, _ = signed_in(browser, static_web, api, auth, width, RECORD_PLOTS)
    page.evaluate(f"location.hash = '#results/{job_id}'")
    sync_api.expect(page.locator("#results-title")).to_contain_text("Results of reconstruct")
    return page


@pytest.mark.parametrize("width", [700, 1280])
def test_the_footage_plays_beside_the_input_view_in_step_overlaid_or_as_a_difference(  # type: ignore[no-untyped-def]
    static_web: str, browser, sqlite_service: Service, scene_dir: dict, tmp_path: Path, screens: Path, width: int,
) -> None:
    api = sqlite_service
    auth, job_id = published_reconstruction(api, scene_dir, tmp_path)
    page = open_results(browser, static_web, api, auth, job_id, width)
    errors: list[str] = []
    page.on("pageerror", lambda error: errors.append(str(error)))

    footage = page.get_by_role("figure").filter(has=page.locator("video[aria-label='Footage, camera cam0']"))
    sync_api.expect(footage).to_have_count(1)
    titles = page.locator("#players figure label").all_text_contents()
    assert titles[:2] == ["Input view", "Footage, camera cam0: compare with the input view"]  # next to each other
    page.wait_for_function("() => [...document.querySelectorAll('#players video')].slice(0, 2).every(v => v.readyState >= 2)")
    src = page.evaluate("() => document.querySelector('#players figure.footage video').src")
    assert f"/v1/scenes/{api.client.get(f'/v1/jobs/{job_id}', headers=auth).json()['scene_id']}/videos/cam0?" in src
    # the bytes the page played are the upload's own
    played = api.client.get("/" + src.split("/", 3)[3])  # the signed link, without a key
    assert played.content == scene_dir["cam0"].read_bytes()

    # one seek control drives both: the footage is FIRST frames ahead (the run starts at frame FIRST)
    offset = FIRST / 30
    for fraction in (0.5, 0.25):
        page.locator("#seek-all").fill(str(fraction))
        page.wait_for_function("""([fraction, offset]) => { const [render, footage] = document.querySelectorAll('#players video');
            return Math.abs(render.currentTime - fraction * render.duration) < 0.02
                && Math.abs(footage.currentTime - (render.currentTime + offset)) < 0.02 && !render.seeking && !footage.seeking; }""",
                               arg=[fraction, offset])
    page.get_by_role("button", name="Play").click()
    page.wait_for_function("() => [...document.querySelectorAll('#players video')].slice(0, 2).every(v => !v.paused)")
    page.get_by_role("button", name="Pause").click()
    page.wait_for_function("() => [...document.querySelectorAll('#players video')].slice(0, 2).every(v => v.paused)")

    # the comparison: the grey render over the bright blob of the footage, or their difference
    compare = page.get_by_label("Footage, camera cam0: compare with the input view")
    canvas = footage.locator("canvas")
    sync_api.expect(canvas).to_be_hidden()  # side by side: the footage itself
    pixels = """() => { const c = document.querySelector('#players figure.footage canvas');
        const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data; const out = [];
        for (let i = 0; i < d.length; i += 4) out.push(d[i]); return out; }"""
    footage_red = np.array(page.evaluate("""() => { const v = document.querySelector('#players figure.footage video');
        const c = document.createElement('canvas'); c.width = v.videoWidth; c.height = v.videoHeight;
        const x = c.getContext('2d'); x.drawImage(v, 0, 0); const d = x.getImageData(0, 0, c.width, c.height).data;
        const out = []; for (let i = 0; i < d.length; i += 4) out.push(d[i]); return out; }"""), float)
    compare.select_option("difference")
    sync_api.expect(canvas).to_be_visible()
    page.wait_for_function("() => document.querySelector('#players figure.footage canvas').width === 32")
    difference = np.array(page.evaluate(pixels), float)
    np.testing.assert_allclose(difference, np.abs(footage_red - 90), atol=12)  # |footage - render|, the render a flat 90
    page.screenshot(path=screens / f"results-footage-difference-{width}.png", full_page=True)
    compare.select_option("overlay")
    page.wait_for_timeout(100)  # the sync loop redraws every animation frame
    overlay = np.array(page.evaluate(pixels), float)
    np.testing.assert_allclose(overlay, (footage_red + 90) / 2, atol=12)  # half and half
    page.screenshot(path=screens / f"results-footage-overlay-{width}.png", full_page=True)
    box = footage.bounding_box()
    assert box is not None and box["x"] + box["width"] <= width  # in view at this width
    assert not errors, errors
    page.close()


def test_the_loss_plot_shows_each_term_relative_to_its_first_frame_on_a_log_axis(  # type: ignore[no-untyped-def]
    static_web: str, browser, sqlite_service: Service, scene_dir: dict, tmp_path: Path, screens: Path,
) -> None:
    api = sqlite_service
    auth, job_id = published_reconstruction(api, scene_dir, tmp_path)
    page = open_results(browser, static_web, api, auth, job_id, 1280)
    losses = page.locator("#plots figure[aria-label='Loss per frame, relative to the first']")
    sync_api.expect(losses).to_have_count(1)
    plots = {p["title"]: p for p in page.evaluate("() => window.__plots")}
    loss_plot = plots["Loss per frame, relative to the first"]
    # log; incomp (0 throughout) not drawn; the yardstick's records are no losses
    assert loss_plot["distr"] == 3 and loss_plot["labels"] == ["image", "sim"]
    np.testing.assert_allclose(loss_plot["data"][0], [1.0, 0.6, 0.4, 0.2])  # image ÷ its first frame
    assert loss_plot["data"][1][0] is None  # sim's first frame is 0: a gap on a log axis, and sim ÷ its first non-zero
    np.testing.assert_allclose(loss_plot["data"][1][1:], [1.0, 2.0, 0.5])
    sync_api.expect(losses.locator("figcaption")).to_contain_text("incomp: 0 on every frame")
    # the legend reads without a hover: the last frame's values
    legend = {row.locator(".u-label").text_content(): row.locator(".u-value").text_content()
              for row in losses.locator(".u-legend .u-series").all()}
    assert legend == {"frame": f"{END - 1} (last)", "image": "0.2", "sim": "0.5"}, legend
    psnr = page.locator("#plots figure[aria-label='PSNR of the input view']")
    psnr_legend = [v.text_content() for v in psnr.locator(".u-legend .u-value").all()]
    assert psnr_legend == [f"{END - 1} (last)", "24", "22", "22"], psnr_legend
    sync_api.expect(psnr).to_contain_text("forecast, before the fit")
    sync_api.expect(psnr).to_contain_text("background alone")
    sync_api.expect(psnr.locator("figcaption")).to_contain_text("Background alone: what an empty reconstruction scores")
    sync_api.expect(psnr.locator("figcaption")).to_contain_text("Forecast: before fitting a frame, the previous frame's smoke moved on")
    # hovering shows the frame under the pointer, leaving shows the last again
    plot_box = losses.locator(".u-over").bounding_box()
    assert plot_box is not None
    page.mouse.move(plot_box["x"] + 2, plot_box["y"] + plot_box["height"] / 2)
    sync_api.expect(losses.locator(".u-legend .u-series").first.locator(".u-value")).to_have_text(str(FIRST))
    page.mouse.move(0, 0)
    sync_api.expect(losses.locator(".u-legend .u-series").first.locator(".u-value")).to_have_text(f"{END - 1} (last)")
    losses.scroll_into_view_if_needed()
    page.screenshot(path=screens / "results-loss-plot.png", full_page=True)
    page.close()


def test_the_health_report_says_what_to_do_when_the_fit_is_poor(  # type: ignore[no-untyped-def]
    static_web: str, browser, sqlite_service: Service, scene_dir: dict, tmp_path: Path, screens: Path,
) -> None:
    """The run's input view is fitted at 20-24 dB (LOSSES): below the 30 dB healthy runs reach and
    within 3 dB of the background alone, so the page warns twice and names the remedies
    (fluidcore.health) as this page's form fields, not the command line's flags."""
    api = sqlite_service
    auth, job_id = published_reconstruction(api, scene_dir, tmp_path)
    page = open_results(browser, static_web, api, auth, job_id, 700)
    # what the simulation used, said even when it is nothing
    sync_api.expect(page.locator("#results-summary")).to_contain_text("air: still; no spreading")
    warnings = page.locator("#results-health li.warning")
    sync_api.expect(warnings).to_have_count(2)
    warning = warnings.first
    sync_api.expect(warning).to_contain_text("Warning (this reconstruction): the reconstruction fits its own input view at only 22.2 dB")
    sync_api.expect(warning).to_contain_text("give a background plate (the upload form's Background plate: frames without smoke)")
    sync_api.expect(warnings.nth(1)).to_contain_text("the background alone scores 20.5 dB on the same frames")
    sync_api.expect(warnings.nth(1)).to_contain_text("within 3 dB of the background")
    for text in warnings.all_text_contents():
        assert "--" not in text and "params." not in text, text  # neither the CLI's flags nor the API's fields
    box = warning.bounding_box()
    assert box is not None and box["x"] + box["width"] <= 700
    page.screenshot(path=screens / "results-health-700.png", full_page=True)
    page.close()


def test_the_results_page_states_the_scene_box_and_the_source(  # type: ignore[no-untyped-def]
    static_web: str, browser, sqlite_service: Service, scene_dir: dict, tmp_path: Path,
) -> None:
    """Issue 48: the box and the source's size were on the what-if page only. The results page
    states the run's own (its manifest's scene: box -0.5..0.5 x 0..1 x -0.5..0.5, source of
    radius 0.05 at (0, 0.1, 0), tests.support.service.store_run) in the what-if page's words."""
    api = sqlite_service
    auth, job_id = published_reconstruction(api, scene_dir, tmp_path)
    page = open_results(browser, static_web, api, auth, job_id, 700)
    scene = page.locator("#results-scene")
    sync_api.expect(scene).to_have_text("Scene box: x from -0.5 to 0.5, y from 0 to 1, z from -0.5 to 0.5 (world units; up (0, 1, 0)). "
                                        "Smoke source: centre (0, 0.1, 0), radius 0.05 (0.1 across).")
    box = scene.bounding_box()
    assert box is not None and box["x"] + box["width"] <= 700
    page.close()
