"""The browser UI in headless Chromium (Debian's `chromium`, driven by the `playwright` package)
against a real `fluidnexus serve` with its embedded worker running fluidcore's pipeline on a
tiny synthetic scene: sign in (a wrong key first), upload (a bad upload first, and a frame range
past the clip, refused with nothing stored), reconstruct, chain a prediction onto the running
reconstruction, play the results in sync and list their MP4s, refuse a ball outside the box,
run a wind what-if branched at a chosen frame and a ball what-if, and play each: the videos a
job did not render before it ended (orbit, side-by-side, other cameras) are rendered as the
players ask for them, shown as "rendering…", then played in step.

One journey in one test: the reconstruction it waits for is what every later step needs.
Screenshots of every screen go to docs/screens/ (README shows them) when
FLUIDNEXUS_SCREENSHOTS=1, else to the test's temporary folder.
"""

from __future__ import annotations

import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.support.browser import CHROMIUM, ROOT, canvas_pixels, in_process, signed_in
from tests.support.service import CLI, Server

pytestmark = pytest.mark.browser

JOB_TIMEOUT_MS = 240_000
SERVER_MS = 30_000  # an upload is probed by the server; on a loaded 2-core machine that takes seconds
NEW_FRAMES = 2

if not Path(CHROMIUM).is_file():
    pytest.skip("Debian's chromium is not installed (.ci/run installs it)", allow_module_level=True)
sync_api = pytest.importorskip("playwright.sync_api")
# Waits sized for a loaded 2-core machine (the suite runs two test processes beside the server's
# worker); a check that fails still fails, only later.
sync_api.expect.set_options(timeout=20_000)


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    server = Server(tmp_path_factory.mktemp("web") / "data")
    yield server
    server.stop()


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> dict[str, list[Path] | Path]:
    """A 2-frame, 2-camera synthetic plume, a video matching no camera, one of the wrong size and a
    broken COLMAP zip."""
    from fluidcore import synth
    from tests.support.service import write_video

    folder = tmp_path_factory.mktemp("scene")
    transforms = synth.write(synth.generate(synth.SynthSpec(frames=2, width=24, height=32, views=2)), folder / "scene")
    videos = sorted((transforms.parent / "videos").glob("*.mp4"))
    wrong_size = write_video(folder / videos[0].name, width=32, height=24, n_frames=2)
    unknown = write_video(folder / "nobody.mp4", width=24, height=32, n_frames=2)
    colmap_zip = folder / "sparse.zip"
    colmap_zip.write_bytes(b"PK\x03\x04" + b"not a zip archive")
    return {"cameras": transforms, "videos": videos, "wrong_size": wrong_size, "unknown": unknown, "colmap_zip": colmap_zip}


def row(page, kind: str, nth: int = 0):  # type: ignore[no-untyped-def]
    """The nth row (newest first) of the jobs table for jobs of one type."""
    return page.locator("#jobs-table tbody tr", has=page.locator(".job-title", has_text=kind)).nth(nth)


def wait_succeeded(page, count: int) -> None:  # type: ignore[no-untyped-def]
    """Until `count` jobs succeeded and every other job is cancelled (none failed, none left running)."""
    page.wait_for_function(
        """n => { const s = [...document.querySelectorAll('#jobs-table .job-state')].map(c => c.textContent);
                 if (s.includes('failed')) throw new Error('a job failed: ' + [...document.querySelectorAll('#jobs-table .job-error')].map(e => e.textContent));
                 return s.filter(x => x === 'succeeded').length === n && s.every(x => x === 'succeeded' || x === 'cancelled'); }""",
        arg=count, timeout=JOB_TIMEOUT_MS, polling=1000,
    )


def drop(page, path: Path) -> None:  # type: ignore[no-untyped-def]
    """Drag a file onto the drop zone, as a user would from a file manager."""
    page.locator("#drop-zone").dispatch_event("drop", {"dataTransfer": page.evaluate_handle(
        """([name, text]) => { const d = new DataTransfer(); d.items.add(new File([text], name)); return d; }""",
        [path.name, path.read_text()])})


def wait_rendered(page) -> None:  # type: ignore[no-untyped-def]
    """Until no player waits for a video rendered on request (a render job on the server's worker)."""
    page.wait_for_function("() => document.querySelectorAll('#players figure').length > 0 && "
                           "!document.querySelector('#players figure.rendering')", timeout=JOB_TIMEOUT_MS, polling=500)
    sync_api.expect(page.locator("#players .player-status", has_text="Could not")).to_have_count(0)


def play_first_video(page) -> None:  # type: ignore[no-untyped-def]
    page.wait_for_function("() => [...document.querySelectorAll('#players video')].length >= 2 && "
                           "[...document.querySelectorAll('#players video')].every(v => v.readyState >= 2)",
                           timeout=30_000)
    page.get_by_role("button", name="Play").click()
    page.wait_for_function("() => { const v = document.querySelector('#players video'); return v !== null && (v.currentTime > 0 || v.ended); }",
                           timeout=30_000)


def players_in_sync(page) -> None:  # type: ignore[no-untyped-def]
    """Every player's video has the leader's length, and over a second of playing none drifts from it."""
    page.wait_for_function("() => [...document.querySelectorAll('#players video')].every(v => v.readyState >= 1)")
    durations = page.evaluate("() => [...document.querySelectorAll('#players video')].map(v => v.duration)")
    assert max(durations) - min(durations) < 0.05, durations  # one length: none stops or loops early
    drift = page.evaluate("""() => new Promise(done => {
        const videos = [...document.querySelectorAll('#players video')], end = performance.now() + 1000;
        let worst = 0;
        const look = () => {
            const lead = videos[0].currentTime;
            for (const v of videos.slice(1)) worst = Math.max(worst, Math.abs(v.currentTime - lead));
            if (performance.now() < end) requestAnimationFrame(look); else done(worst);
        };
        requestAnimationFrame(look); })""")
    assert drift < 0.2, drift  # the sync loop nudges followers past 0.08 s; a frame of rAF delay on top


def test_browser_journey(server: Server, browser, scene: dict, screens: Path) -> None:  # type: ignore[no-untyped-def]
    page = browser.new_page(viewport={"width": 1366, "height": 900})
    page.set_default_timeout(30_000)
    errors: list[str] = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    page.goto(f"http://127.0.0.1:{server.port}/")

    # sign in: a wrong key is refused in words, the real one lands on the job list
    page.get_by_label("API key").fill("fnx_0123456789abcdef_" + "x" * 40)
    page.get_by_role("button", name="Sign in").click()
    sync_api.expect(page.locator("#signin-error")).to_contain_text("not accepted: it is wrong or has been revoked")
    page.screenshot(path=screens / "signin.png")
    page.get_by_label("API key").fill(server.client.headers["Authorization"].removeprefix("Bearer "))
    page.keyboard.press("Enter")  # the form submits from the keyboard
    sync_api.expect(page.locator("#jobs-title")).to_be_visible()

    # a bad upload is explained before anything is sent
    page.get_by_role("button", name="Upload", exact=True).click()
    page.locator("#upload-files").set_input_files([scene["cameras"], scene["wrong_size"], scene["unknown"]])
    problems = page.locator("#upload-problems")
    sync_api.expect(problems).to_contain_text("nobody.mp4 matches no camera")
    sync_api.expect(problems).to_contain_text("must have its camera's exact frame size")
    sync_api.expect(page.locator("#upload-button")).to_be_disabled()
    page.screenshot(path=screens / "upload-problems.png", full_page=True)

    # what only the server can judge (a COLMAP zip) comes back as the server's message
    page.get_by_role("button", name="Clear").click()
    page.locator("#upload-files").set_input_files([scene["colmap_zip"], scene["videos"][0]])
    sync_api.expect(page.locator("#camera-summary")).to_contain_text("COLMAP model (zip); the server reads it")
    page.locator("#upload-button").click()
    sync_api.expect(page.locator("#upload-error")).to_contain_text("Upload refused: cameras:", timeout=SERVER_MS)

    # a real capture (ScalarFlow: 5 cameras, the input view's 648x1160 video) passes the browser's checks
    scalarflow = ROOT.parent / "shared" / "realdata" / "scalarflow"
    if (scalarflow / "transforms.json").is_file():
        page.get_by_role("button", name="Clear").click()
        page.locator("#upload-files").set_input_files([scalarflow / "transforms.json", scalarflow / "videos" / "input_view_02.mp4"])
        sync_api.expect(page.locator("#video-list")).to_contain_text("648x1160, 4.00 s, 120 frames → camera view_02")
        sync_api.expect(page.locator("#camera-summary")).to_contain_text("5 cameras")
        sync_api.expect(page.locator("#upload-problems")).to_be_empty()
        page.get_by_label("End frame").fill("500")  # the case: refused before anything is sent
        sync_api.expect(page.locator("#upload-problems")).to_contain_text(
            "End frame 500 is past the video: input_view_02.mp4 has 120 frames (4.00 s at 30 fps)")
        sync_api.expect(page.locator("#upload-button")).to_be_disabled()
        page.get_by_label("End frame").fill("")
        page.screenshot(path=screens / "upload-scalarflow.png", full_page=True)

    # from the keyboard: a pointer click here can miss while the problem list above it shrinks
    page.get_by_role("button", name="Clear").press("Enter")
    drop(page, scene["cameras"])
    sync_api.expect(page.locator("#camera-summary")).to_contain_text("nerfstudio transforms.json")
    page.locator("#upload-files").set_input_files(scene["videos"])
    sync_api.expect(page.locator("#video-list canvas")).to_have_count(len(scene["videos"]))
    sync_api.expect(page.locator("#camera-summary")).to_contain_text(f"{len(scene['videos'])} cameras")
    sync_api.expect(page.locator("#upload-button")).to_be_enabled()
    source = page.get_by_label("Smoke source")
    source.fill("0, 0.075")
    sync_api.expect(page.locator("#upload-problems")).to_contain_text("Smoke source: expected x, y, z")
    sync_api.expect(page.locator("#upload-button")).to_be_disabled()
    source.fill("0, 0.075, 0, 0.05")  # the synth's source, where whoever built the rig knows it is
    page.get_by_label("Let the fit move and resize this source").check()  # ... roughly
    sync_api.expect(page.locator("#upload-button")).to_be_enabled()
    ball = page.get_by_label("Ball in the scene")  # a solid of the scene: refused outside the box, by its centre
    ball.fill("0, 0.3, 0")
    sync_api.expect(page.locator("#upload-problems")).to_contain_text("Ball: expected x, y, z, radius")
    ball.fill("0, 5, 0, 0.05")
    sync_api.expect(page.locator("#upload-problems")).to_contain_text("Ball centre (0, 5, 0) is outside the scene box")
    sync_api.expect(page.locator("#upload-button")).to_be_disabled()
    ball.fill("0, 0.3, 0, 0.05")
    sync_api.expect(page.locator("#upload-button")).to_be_enabled()
    plate = page.get_by_label("Background plate")
    plate.fill("5:2")  # a plate's frames the wrong way round: refused before anything is sent
    sync_api.expect(page.locator("#upload-problems")).to_contain_text("Background plate: its end frame (2) must come after its first (5).")
    sync_api.expect(page.locator("#upload-button")).to_be_disabled()
    plate.fill("")
    sync_api.expect(page.locator("#upload-button")).to_be_enabled()
    page.get_by_label("End frame").fill("3")  # a range past the 2-frame clip: refused, nothing stored
    sync_api.expect(page.locator("#upload-problems")).to_contain_text("End frame 3 is past the video")
    sync_api.expect(page.locator("#upload-button")).to_be_disabled()
    page.get_by_label("Scene name").press("Enter")  # the keyboard cannot send it either
    assert server.client.get("/v1/scenes").json()["total"] == 0
    page.get_by_label("End frame").fill("2")
    air = page.get_by_label("Simulated air")
    air.fill("4")  # below the grid's range: refused before anything is sent
    sync_api.expect(page.locator("#upload-problems")).to_contain_text("Simulated air must be 0 or a whole number from")
    sync_api.expect(page.locator("#upload-button")).to_be_disabled()
    motion = page.get_by_label("Motion: how the smoke moves")
    motion.select_option("carrier")
    air.fill("0")  # still air cannot carry the smoke: refused for the carrier
    sync_api.expect(page.locator("#upload-problems")).to_contain_text("Simulated air 0 is still air")
    air.fill("8")
    sync_api.expect(page.get_by_label("Let the plume spread")).to_be_disabled()  # the paper model's spreading
    motion.select_option("paper")
    page.get_by_label("Let the plume spread").check()
    page.get_by_label("World up: the axis the smoke rises along").select_option("+y")  # the synth's, said outright
    sync_api.expect(page.locator("#upload-button")).to_be_enabled()
    page.get_by_label("Scene name").fill("plume")
    page.screenshot(path=screens / "upload.png", full_page=True)
    # Sent from the keyboard: a pointer click here missed in a checkout without ../shared (its
    # mousedown and mouseup met different elements, so the click went to the form itself).
    page.get_by_label("Scene name").press("Enter")
    sync_api.expect(page.locator("#notice")).to_contain_text("uploaded; reconstruction", timeout=SERVER_MS)
    assert "stored: 2 frames at 30 fps" in page.locator("#upload-percent").text_content()  # the XHR's answer
    sent = server.client.get("/v1/jobs", params={"type": "reconstruct"}).json()["items"][0]["params"]
    assert sent["source"] == {"center": [0.0, 0.075, 0.0], "radius": 0.05, "refine": True} and sent["physics"] == "auto"
    assert sent["solids"] == [{"center": [0.0, 0.3, 0.0], "radius": 0.05}]
    assert (sent["motion"], sent["air_cells"], sent["entrainment"], sent["world_up"]) == ("paper", 8, True, "+y")
    sync_api.expect(row(page, "reconstruct").locator(".job-params")).to_contain_text("air 8 cells, spreading")
    assert server.client.get("/v1/scenes").json()["total"] == 1  # one scene, with its reconstruction
    sync_api.expect(row(page, "reconstruct").locator(".job-origin")).to_contain_text("scene plume")

    # chaining: a prediction started on the unfinished reconstruction waits for it; one is
    # cancelled while it waits and sent again with Retry
    page.get_by_label("New frames for Predict").fill(str(NEW_FRAMES))
    row(page, "reconstruct").get_by_role("button", name="Predict").click()
    sync_api.expect(row(page, "predict").locator(".job-stage")).to_contain_text("waiting for job")
    row(page, "predict").get_by_role("button", name="Cancel").click()
    sync_api.expect(row(page, "predict").locator(".job-state")).to_have_text("cancelled")
    row(page, "predict").get_by_role("button", name="Retry").click()
    sync_api.expect(page.locator("#jobs-table tbody tr")).to_have_count(3)
    sync_api.expect(row(page, "predict").locator(".job-state")).to_have_text("queued")
    page.screenshot(path=screens / "jobs.png", full_page=True)
    page.set_viewport_size({"width": 600, "height": 900})  # a narrow window keeps the Actions column in view
    box = row(page, "reconstruct").get_by_role("button", name="Predict").bounding_box()
    assert box is not None and box["x"] + box["width"] <= 600, box
    page.set_viewport_size({"width": 1366, "height": 900})
    wait_succeeded(page, 2)
    # the reconstruction ran with the air the form asked for: its frames carry it to the what-if view
    reconstruction = server.client.get("/v1/jobs", params={"type": "reconstruct"}).json()["items"][0]["id"]
    air = server.client.get(f"/v1/jobs/{reconstruction}/particles").json()["air"]
    assert air is not None and max(abs(v) for v in air["velocities"]) > 0
    # its prepare stage reported the identification's progress as a stage of its own (issue 48: no more 0 % throughout)
    stages = server.client.get(f"/v1/jobs/{reconstruction}").json()["timings"]["stages"]
    assert list(stages).index("prepare: identifying the physics") < list(stages).index("reconstruct"), stages

    # results: players of one length in sync, plots from the manifest, downloads of the MP4s too;
    # the job published its input view, the other camera and the orbit are rendered as the players ask
    row(page, "reconstruct").get_by_role("button", name="Results").click()
    wait_rendered(page)
    play_first_video(page)
    players_in_sync(page)
    sync_api.expect(page.locator("#plots figure")).to_have_count(4)
    # forecast PSNR (tens of dB) is drawn with the input view's PSNR, not on the loss axis
    sync_api.expect(page.locator("#plots figure[aria-label='Loss per frame, relative to the first']")).not_to_contain_text("forecast")
    sync_api.expect(page.locator("#plots figure[aria-label='PSNR of the input view']")).to_contain_text("forecast")
    sync_api.expect(page.locator("#downloads a", has_text="manifest.json")).to_have_count(1)
    sync_api.expect(page.locator("#downloads a", has_text="orbit.mp4")).to_have_count(1)
    sync_api.expect(page.locator("#downloads a", has_text=".mp4")).to_have_count(len(scene["videos"]) + 1)
    # downloads grouped, videos first; every frame as one zip, made by a job, listed under Bundles
    sync_api.expect(page.locator("#downloads h4").first).to_have_text("Videos")
    page.locator("#bundle-format").select_option("vdb")
    page.get_by_role("button", name="Make zip").click()
    sync_api.expect(page.locator("#bundle-status")).to_contain_text("Ready: bundles/vdb_f000000-000002_v", timeout=SERVER_MS)
    bundles = page.locator("#downloads section", has_text="Bundles").locator("a")
    sync_api.expect(bundles).to_have_count(1)
    assert bundles.get_attribute("download").startswith("vdb_f000000-000002_v")
    page.screenshot(path=screens / "results.png", full_page=True)

    # what-if: the ball outside the box is refused with the box's limits; wind, then ball, are sent
    page.get_by_role("button", name="Jobs").click()
    row(page, "reconstruct").get_by_role("button", name="What-if").click()
    sync_api.expect(page.locator("#box-limits")).to_contain_text("Scene box: x from")
    page.get_by_label("New frames to simulate").fill(str(NEW_FRAMES))
    page.get_by_label("Ball", exact=True).check()
    page.get_by_label("ball centre x").fill("1000")
    sync_api.expect(page.locator("#whatif-problems")).to_contain_text("Ball centre x = 1000 is outside the scene box: x must be from")
    page.screenshot(path=screens / "whatif-refused.png", full_page=True)
    page.get_by_label("Ball", exact=True).uncheck()
    # the default wind comes from the scene: a quarter of the box's width in 15 frames from rest
    rec_id = server.client.get("/v1/jobs", params={"type": "reconstruct"}).json()["items"][0]["id"]
    run_scene = server.client.get(f"/v1/jobs/{rec_id}/particles").json()["scene"]
    width, seconds = run_scene["box_hi"][0] - run_scene["box_lo"][0], 15 * run_scene["dt"]
    assert float(page.get_by_label("Strength").input_value()) == pytest.approx(2 * 0.25 * width / seconds**2, rel=1e-2)
    page.get_by_label("Strength").fill("1000")  # allowed in general, too strong for this scene: the server says so
    page.get_by_role("button", name="Run what-if").click()
    sync_api.expect(page.locator("#whatif-error")).to_contain_text("Refused: params: wind.strength 1000", timeout=SERVER_MS)
    page.get_by_label("Strength").fill("2")
    page.get_by_label("Branch at frame").fill("5")  # not a frame of the 2-frame run
    sync_api.expect(page.locator("#whatif-problems")).to_contain_text("Branch frame 5 is not a finished frame of the run")
    page.get_by_label("Branch at frame").fill("0")  # what if it had blown from the first frame on
    page.get_by_role("button", name="Run what-if").click()
    sync_api.expect(page.locator("#notice")).to_contain_text("What-if")
    sync_api.expect(row(page, "interact").locator(".job-params")).to_contain_text("from frame 0, wind 2")

    row(page, "reconstruct").get_by_role("button", name="What-if").click()
    sync_api.expect(page.locator("#box-limits")).to_contain_text("Scene box")
    page.get_by_label("New frames to simulate").fill(str(NEW_FRAMES))
    page.get_by_label("Branch at frame").fill("")  # from the run's last frame
    sync_api.expect(page.get_by_label("Branch at frame")).to_have_value("")  # the last what-if's 0 is gone
    page.get_by_label("Wind", exact=True).uncheck()
    page.get_by_label("Ball", exact=True).check()
    page.get_by_label("ball centre x").fill("0")  # the synthetic scene's box is centred on x = 0
    sync_api.expect(page.locator("#whatif-problems")).to_be_empty()
    sync_api.expect(page.get_by_label("Branch at frame")).to_have_value("")  # still: the ball goes from the last frame
    page.screenshot(path=screens / "whatif-ball.png", full_page=True)
    page.get_by_role("button", name="Run what-if").click()
    sync_api.expect(page.locator("#notice")).to_contain_text("What-if")
    wait_succeeded(page, 4)  # reconstruct, the factual prediction, two what-ifs: no second factual

    for nth, shot in ((0, "whatif-results.png"), (1, "whatif-branch-results.png")):
        page.get_by_role("button", name="Jobs").click()
        short_id = row(page, "interact", nth).locator(".job-id").text_content()
        job_id = row(page, "interact", nth).get_attribute("data-job-id")
        row(page, "interact", nth).get_by_role("button", name="Results").click()
        sync_api.expect(page.locator("#results-title")).to_have_text(f"Results of interact {short_id}")
        # a what-if renders no video before it ends: the players ask for theirs, say so, then play them
        sync_api.expect(page.locator("#players figure.rendering .player-status").first).to_contain_text("rendering")
        wait_rendered(page)
        videos = {v["name"]: v for v in server.client.get(f"/v1/jobs/{job_id}/videos").json()["items"]}
        rendered = {name for name, v in videos.items() if v["artifact"]}
        assert {"orbit", *(["side_by_side"] if nth == 1 else [])} < rendered  # and the input view
        assert all(videos[name]["render_job"]["state"] == "succeeded" for name in rendered), videos
        renders = server.client.get("/v1/jobs", params={"type": "render", "parent_job_id": job_id}).json()["items"]
        assert sorted(r["params"]["video"] for r in renders) == sorted(rendered)  # one render per video asked for
        if nth == 0:  # the ball, from the run's last frame: next to the factual prediction
            sync_api.expect(page.locator("#results-summary")).to_contain_text("next to the factual prediction")
            sync_api.expect(page.locator("#players select").nth(1)).to_contain_text("factual: camera")
        else:  # the wind branched at frame 0: its side-by-side shows the run without the wind
            sync_api.expect(page.locator("#results-summary")).to_contain_text("branched at frame 0")
            sync_api.expect(page.locator("#players select").nth(1).locator("option:checked")).to_have_text("what-if: side by side")
        play_first_video(page)
        players_in_sync(page)
        page.screenshot(path=screens / shot, full_page=True)

    # a key revoked while signed in: the next poll sends the page back to sign-in, saying why
    key_id = server.client.headers["Authorization"].split("_")[1]
    subprocess.run([*CLI, "keys", "revoke", key_id, "--data-dir", str(server.data_dir)], cwd=ROOT, check=True,
                   capture_output=True)
    sync_api.expect(page.locator("#signin-error")).to_contain_text("no longer accepted", timeout=10_000)
    sync_api.expect(page.locator("#nav")).to_be_hidden()
    assert not errors, errors


def camera_files(folder: Path) -> list[Path]:
    """A transforms.json with a voxel box, the same cameras as a PINF info.json with a rotated
    box, one of them with a scene_box, and ScalarFlow's real transforms.json when ../shared is there."""
    import json

    from tests.support.service import camera_entry

    frames = [camera_entry(f"cam{i}", 32, 24, x) for i, x in enumerate((-1.0, 0.5, 2.0))]
    box = {"voxel_scale": [0.5, 0.8, 0.4], "voxel_matrix": [[1, 0, 0, -0.2], [0, 1, 0, 0.0], [0, 0, 1, -0.1], [0, 0, 0, 1]]}
    (folder / "transforms.json").write_text(json.dumps({"frames": frames, **box}))
    pinf = {
        "train_videos": [{"file_name": f"train0{i}.mp4", "camera_angle_x": 0.7, "camera_hw": [f["h"], f["w"]],
                          "transform_matrix": f["transform_matrix"]} for i, f in enumerate(frames)],
        "voxel_scale": [0.5, 0.8, 0.4],
        "voxel_matrix": [[0, 0, 1, 0.1], [0, 1, 0, -0.2], [-1, 0, 0, 0.3], [0, 0, 0, 1]],
    }
    (folder / "info.json").write_text(json.dumps(pinf))
    # what `fluidnexus cameras single` writes: FluidNexus's own scene_box (the browser said "no box in the file")
    single = {"frames": frames[:1], "scene_box": {"min": [-0.18, -0.32, -0.18], "max": [0.18, 0.32, 0.18]}, "up": "+y"}
    (folder / "single.json").write_text(json.dumps(single))
    files = [folder / "transforms.json", folder / "info.json", folder / "single.json"]
    scalarflow = ROOT.parent / "shared" / "realdata" / "scalarflow" / "transforms.json"
    return files + [scalarflow] if scalarflow.is_file() else files


def test_the_forms_judge_values_by_the_apis_limits_as_the_models_do(static_web: str, browser, sqlite_service) -> None:  # type: ignore[no-untyped-def]
    """web/js/limits.js reads GET /v1/limits (the in-process API behind the page) and accepts a
    value exactly when the parameter model does; its refusal names the range the model declares."""
    from pydantic import ValidationError

    from fluidcore.spec.simulation import AIR_CELLS
    from fluidcore.spec.jobs import InteractParams, ReconstructParams

    wind = {"direction": [1, 0, 0], "strength": 1.0}
    models = {
        "air_cells": lambda v: ReconstructParams(motion="paper", air_cells=v),  # the per-field rule (the carrier also refuses 0)
        "wind.strength": lambda v: InteractParams(wind={**wind, "strength": v}),
        "wind.growth": lambda v: InteractParams(wind={**wind, "growth": v}),
        "wind.start_frame": lambda v: InteractParams(wind={**wind, "start_frame": v}),
        "ball.radius": lambda v: InteractParams(ball={"center": [0, 0, 0], "radius": v}),
        "from_frame": lambda v: InteractParams(wind=wind, from_frame=v),
    }
    values = [-51, -1, -0.5, 0, 0.01, 1, 2.5, AIR_CELLS[0] - 1, AIR_CELLS[0], AIR_CELLS[1], AIR_CELLS[1] + 1, 999, 1000, 1000.5]
    cases = [("reconstruct" if field == "air_cells" else "interact", field, v) for field in models for v in values]

    def accepted(field: str, value: float) -> bool:
        try:
            models[field](value)
        except ValidationError:
            return False
        return True

    page = browser.new_page()
    page.route("**/v1/**", in_process(sqlite_service))
    page.goto(static_web + "vendor/README.md")
    verdicts = page.evaluate("""async (cases) => { const { loadLimits, limitProblem } = await import('/js/limits.js');
        const limits = await loadLimits();
        return cases.map(([type, field, value]) => limitProblem(field, value, limits[type][field])); }""", cases)
    for (_, field, value), problem in zip(cases, verdicts, strict=True):
        assert (problem is None) == accepted(field, value), (field, value, problem)
    air = page.evaluate("""async () => (await import('/js/limits.js')).limitProblem(
        'Simulated air', 4, (await (await import('/js/limits.js')).loadLimits()).reconstruct.air_cells)""")
    assert air == f"Simulated air must be 0 or a whole number from {AIR_CELLS[0]} to {AIR_CELLS[1]}, got 4."
    page.close()


def test_browser_camera_reader_agrees_with_fluidcore(static_web: str, browser, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    """web/js/cameras.js (what the upload view shows) reads the same names, sizes, camera centres
    and scene box as fluidcore.cameras, which the server validates uploads with."""
    import numpy as np

    from fluidcore.cameras import load, scene_box

    page = browser.new_page()
    page.goto(static_web + "vendor/README.md")  # any page of the same origin; main.js is not needed
    for path in camera_files(tmp_path):
        parsed = page.evaluate(
            """async ([name, text]) => (await import('/js/cameras.js')).parseCameraFile(name, new TextEncoder().encode(text).buffer)""",
            [path.name, path.read_text()],
        )
        expected = load(path)
        assert [c["name"] for c in parsed["cameras"]] == list(expected), path
        for camera in parsed["cameras"]:
            truth = expected[camera["name"]]
            assert (camera["width"], camera["height"]) == (truth.width, truth.height)
            # 1e-6: the server re-orthonormalises rotations stored in single precision (ScalarFlow's)
            np.testing.assert_allclose(camera["center"], truth.center(), atol=1e-6)
        lo, hi = scene_box(path)
        np.testing.assert_allclose(parsed["box"]["lo"], lo, atol=1e-9)
        np.testing.assert_allclose(parsed["box"]["hi"], hi, atol=1e-9)
    page.close()


def test_browser_frame_count_agrees_with_the_server(static_web: str, browser, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    """web/js/mp4.js (the upload form's frame-range check) counts the frames fluidcore.video.probe
    (the server's check) counts, at their rate; a file that is not an MP4 gives null."""
    import base64

    from fluidcore.video import probe
    from tests.support.service import write_video

    videos = [write_video(tmp_path / "a.mp4", n_frames=2), write_video(tmp_path / "b.mp4", n_frames=40, fps=10.0)]
    scalarflow = ROOT.parent / "shared" / "realdata" / "scalarflow" / "videos" / "input_view_02.mp4"
    videos += [scalarflow] if scalarflow.is_file() else []
    page = browser.new_page()
    page.goto(static_web + "vendor/README.md")
    count = """async ([name, data]) => (await import('/js/mp4.js')).mp4Frames(
        new File([Uint8Array.from(atob(data), c => c.charCodeAt(0))], name))"""
    for path in videos:
        counted = page.evaluate(count, [path.name, base64.b64encode(path.read_bytes()).decode()])
        info = probe(path)
        assert counted["frames"] == info.n_frames, path
        assert abs(counted["fps"] - info.fps) < 1e-3 * info.fps, path
    assert page.evaluate(count, ["x.mp4", base64.b64encode(b"not a video at all" * 10).decode()]) is None
    page.close()


def test_controls_are_labelled_and_reachable_by_keyboard(static_web: str, browser) -> None:  # type: ignore[no-untyped-def]
    """Every input and select has a label a screen reader reads, actions are real buttons, and the
    sign-in form works from the keyboard (focus starts in the key field; Tab reaches Sign in)."""
    page = browser.new_page()
    page.goto(static_web)
    sync_api.expect(page.get_by_label("API key")).to_be_focused()
    unlabelled = page.evaluate("""() => [...document.querySelectorAll('input, select')]
        .filter(e => !e.labels.length && !e.getAttribute('aria-label') && !e.getAttribute('aria-labelledby'))
        .map(e => e.id || e.outerHTML)""")
    assert unlabelled == []
    assert page.evaluate("() => document.querySelectorAll('[onclick], div[role=button], span[role=button]').length") == 0
    page.keyboard.press("Tab")
    sync_api.expect(page.get_by_role("button", name="Sign in")).to_be_focused()
    page.close()


def test_the_whatif_view_draws_the_saved_air(static_web: str, browser) -> None:  # type: ignore[no-untyped-def]
    """The particles answer's `air` (GET /v1/jobs/{id}/particles, faked here) reaches the 3D what-if
    view: one violet arrow per sampled point, drawn on the canvas and counted in the summary; a run
    without the air says so and draws none."""
    import json

    import numpy as np

    from api.routers.limits import limits
    from service.settings import Settings

    lattice = np.stack(np.meshgrid(*[np.linspace(-0.4, 0.4, 5)] * 3, indexing="ij"), -1).reshape(-1, 3)
    air = {"points": lattice.ravel().tolist(), "velocities": np.tile([0.0, 0.3, 0.1], len(lattice)).tolist()}
    job = {"id": "job-air", "type": "predict", "state": "succeeded", "scene_id": None, "parent_job_id": "job-rec", "params": {}}

    def particles(with_air: bool) -> str:
        return json.dumps({
            "job_id": job["id"], "frame": 1, "frames": [0, 1], "total": 3, "positions": [0.0, 0.1, 0.0] * 3,
            "scene": {"box_lo": [-0.5, -0.5, -0.5], "box_hi": [0.5, 0.5, 0.5], "up": [0.0, 1.0, 0.0],
                      "source": {"center": [0.0, -0.4, 0.0], "radius": 0.05}, "dt": 1 / 30},
            "air": air if with_air else None,
        })

    def answer(body: str):  # a route handler of one argument (one of two is handed the request as well)
        return lambda route: route.fulfill(body=body, content_type="application/json")

    def violet(page) -> int:  # type: ignore[no-untyped-def]  # pixels of the air's colour (0xb36bff): nothing else in the view is violet
        rgb = canvas_pixels(page, "#scene3d").astype(int)
        return int(((rgb[..., 0] > 130) & (rgb[..., 1] < 140) & (rgb[..., 2] > 200)).sum())

    for with_air in (True, False):
        page = browser.new_page()
        page.route("**/v1/jobs?limit=100", lambda route: route.fulfill(json={"items": [job]}))
        page.route("**/v1/jobs/job-air/particles*", answer(particles(with_air)))
        page.route("**/v1/limits", answer(json.dumps(limits(Settings()))))
        page.route("**/v1/wind/accelerations", answer(json.dumps({"accelerations": [1.0] * 5})))  # arrows drawn blue
        page.goto(static_web)
        page.evaluate("""async () => { document.getElementById('view-whatif').hidden = false;
                                       await (await import('/js/whatif.js')).showWhatif('job-air'); }""")
        summary = page.locator("#whatif-summary")
        if with_air:
            sync_api.expect(summary).to_contain_text("Violet arrows: the air's velocity at 125 of 125 sampled points (fastest 0.316 units/s)")
            assert violet(page) > 50
        else:
            sync_api.expect(summary).to_contain_text("This run does not simulate the air (still air): no air arrows.")
            assert violet(page) == 0
        page.close()


def test_the_what_if_view_draws_one_views_depth_range_and_its_slider_fills_the_source_hint(  # type: ignore[no-untyped-def]
    static_web: str, browser, sqlite_service, scene_dir: dict, screens: Path,
) -> None:
    """A reconstruction from one view whose source depth was a guess: the what-if view reads the
    stretch of the input ray the video allows (GET /v1/scenes/{id}, the in-process API behind the
    page), says where it runs, and moving the slider along it fills the source hint; a hint outside
    the box is refused in the form, and the button queues a new reconstruction of the scene with
    the hint as its source and the first one's other params."""
    from datetime import UTC, datetime

    import numpy as np

    from tests.support.api import reconstruct, upload
    from fluidcore.runs import SourceEstimateRecord
    from service.models import JobState
    from tests.support.service import store_run

    api = sqlite_service
    auth = api.key("alice")
    scene_id = upload(api, auth, scene_dir).json()["id"]
    job_id = reconstruct(api, auth, scene_id, quality="preview").json()["id"]
    near, far = (0.0, 0.1, 0.5), (0.0, 0.1, -0.5)  # the run's box is x, z in -0.5..0.5, y in 0..1
    estimate = SourceEstimateRecord(depth_cue="box axis", depth_range=(near, far), pixels={"cam0": (16.0, 20.0, 2.0)})
    store_run(api.storage, job_id, {0: np.array([[0.0, 0.2, 0.0], [0.1, 0.3, 0.0]])}, source_estimate=estimate)
    api.set_job(job_id, state=JobState.SUCCEEDED, finished_at=datetime.now(UTC))

    page, errors = signed_in(browser, static_web, api, auth, 1366)
    page.evaluate(f"location.hash = '#whatif/{job_id}'")

    sync_api.expect(page.locator("#source-form")).to_be_visible()
    # the wind's arrows come from the API, which also says what it refuses of the form's wind
    page.get_by_label("Profile").select_option("uniform")
    page.get_by_label("Growth with height").fill("1")
    sync_api.expect(page.locator("#whatif-problems")).to_contain_text("growth must be 0 for a uniform wind")
    page.get_by_label("Growth with height").fill("0")
    sync_api.expect(page.locator("#whatif-problems")).not_to_contain_text("growth must be 0")
    sync_api.expect(page.locator("#source-depth")).to_contain_text("from (0, 0.1, 0.5) (nearest) to (0, 0.1, -0.5) (farthest)")
    sync_api.expect(page.locator("#source-depth")).to_contain_text("put it at (0, 0.1, 0), radius 0.05")
    slider, hint = page.get_by_label("Source centre along the input ray"), page.get_by_label("Source hint for a new reconstruction")
    assert float(slider.input_value()) == pytest.approx(0.5)  # the run's source, halfway along
    sync_api.expect(page.get_by_role("button", name="Reconstruct with this source")).to_be_disabled()  # no hint yet
    slider.fill("0.25")
    sync_api.expect(hint).to_have_value("0, 0.1, 0.25")
    hint.fill("0, 0.1, 0.9")
    sync_api.expect(page.locator("#source-problems")).to_contain_text("outside the scene box")
    sync_api.expect(page.get_by_role("button", name="Reconstruct with this source")).to_be_disabled()
    slider.focus()
    page.keyboard.press("End")  # from the keyboard: the farthest point the view allows
    sync_api.expect(hint).to_have_value("0, 0.1, -0.5")
    slider.fill("0.75")
    sync_api.expect(hint).to_have_value("0, 0.1, -0.25")
    page.locator("#scene3d").scroll_into_view_if_needed()
    page.screenshot(path=screens / "whatif-source-depth.png", full_page=True)
    page.get_by_role("button", name="Reconstruct with this source").click()
    sync_api.expect(page.locator("#notice")).to_contain_text("queued with your source hint")
    sent = api.client.get("/v1/jobs", params={"type": "reconstruct"}, headers=auth).json()["items"]
    assert len(sent) == 2 and sent[0]["scene_id"] == scene_id
    assert sent[0]["params"]["source"]["center"] == pytest.approx([0.0, 0.1, -0.25])
    assert sent[0]["params"]["source"].get("radius") is None  # measured again at the new depth
    assert {k: v for k, v in sent[0]["params"].items() if k != "source"} == {k: v for k, v in sent[1]["params"].items() if k != "source"}
    assert not errors, errors
    page.close()


def test_a_clip_without_cameras_and_a_video_named_by_hand(  # type: ignore[no-untyped-def]
    browser, scene: dict, screens: Path, tmp_path: Path,
) -> None:
    """One video and a field of view make a scene without a camera file (the server writes its one
    camera, named after the video); a video whose name matches no camera is given one from the
    menu beside it and is sent under that camera's name. A server of its own: the journey revokes
    its key at the end."""
    server = Server(tmp_path / "data")
    try:
        upload_by_hand(server, browser, scene, screens)
    finally:
        server.stop()


def upload_by_hand(server: Server, browser, scene: dict, screens: Path) -> None:  # type: ignore[no-untyped-def]
    import shutil

    page = browser.new_page(viewport={"width": 1280, "height": 900})
    page.set_default_timeout(30_000)
    page.goto(f"http://127.0.0.1:{server.port}/")
    page.get_by_label("API key").fill(server.client.headers["Authorization"].removeprefix("Bearer "))
    page.keyboard.press("Enter")
    sync_api.expect(page.locator("#jobs-title")).to_be_visible()
    page.get_by_role("button", name="Upload", exact=True).click()
    page.get_by_label("Start the reconstruction after the upload").uncheck()

    clip = shutil.copy(scene["videos"][0], Path(scene["cameras"]).parent.parent / "clip.mp4")
    page.locator("#upload-files").set_input_files([clip])
    problems = page.locator("#upload-problems")
    sync_api.expect(problems).to_contain_text("Add a camera file (transforms.json, info.json or a zipped COLMAP model), or give one video's field of view.")
    page.get_by_label("Horizontal field of view").fill("200")
    sync_api.expect(problems).to_contain_text("Field of view: give degrees between 0 and 180")
    page.get_by_label("Horizontal field of view").fill("40")
    sync_api.expect(problems).to_be_empty()
    sync_api.expect(page.locator("#camera-summary")).to_contain_text("one camera with a 40° field of view")
    page.get_by_label("Scene name").fill("phone clip")
    page.get_by_label("Scene name").press("Enter")
    sync_api.expect(page.locator("#upload-percent")).to_contain_text("Scene phone clip stored: 2 frames at 30 fps", timeout=SERVER_MS)
    assert named(server, "phone clip")["cameras"] == ["clip"]

    # a camera file and a video named after none of its cameras: picked by hand, sent under the camera's name
    page.get_by_role("button", name="Upload", exact=True).click()  # the upload went on to the jobs
    page.get_by_label("Start the reconstruction after the upload").uncheck()
    page.locator("#upload-files").set_input_files([scene["cameras"], clip])
    sync_api.expect(problems).to_contain_text("clip.mp4 matches no camera; pick its camera beside it")
    page.get_by_label("Camera of clip.mp4").select_option("view_00")
    sync_api.expect(problems).to_be_empty()
    sync_api.expect(page.locator("#video-list")).to_contain_text("→ camera view_00")
    page.screenshot(path=screens / "upload-camera-picked.png", full_page=True)
    page.get_by_label("Scene name").fill("picked")
    page.get_by_label("Scene name").press("Enter")
    sync_api.expect(page.locator("#upload-percent")).to_contain_text("Scene picked stored: 2 frames", timeout=SERVER_MS)
    assert list(named(server, "picked")["videos"]) == ["view_00"]
    page.close()


def named(server: Server, name: str) -> dict:
    """The newest scene of that name."""
    return next(s for s in server.client.get("/v1/scenes", params={"limit": 100}).json()["items"] if s["name"] == name)


def test_the_whatif_view_draws_the_runs_solids(static_web: str, browser) -> None:  # type: ignore[no-untyped-def]
    """The particles answer's `scene.solids` (faked here) are drawn in the 3D what-if view as the
    what-if's ball is (red shells); a run without solids draws none (the what-if's own ball off)."""
    import json

    from api.routers.limits import limits
    from service.settings import Settings

    job = {"id": "job-solid", "type": "reconstruct", "state": "succeeded", "scene_id": None, "parent_job_id": None, "params": {}}

    def particles(solids: list) -> str:
        return json.dumps({
            "job_id": job["id"], "frame": 1, "frames": [0, 1], "total": 3, "positions": [0.0, -0.3, 0.0] * 3,
            "scene": {"box_lo": [-0.5, -0.5, -0.5], "box_hi": [0.5, 0.5, 0.5], "up": [0.0, 1.0, 0.0],
                      "source": {"center": [0.0, -0.4, 0.0], "radius": 0.05}, "dt": 1 / 30, "solids": solids},
            "air": None,
        })

    def answer(body: str):  # a route handler of one argument (one of two is handed the request as well)
        return lambda route: route.fulfill(body=body, content_type="application/json")

    def red(page) -> int:  # type: ignore[no-untyped-def]  # pixels of the balls' colour (0xe74c3c over the dark view)
        rgb = canvas_pixels(page, "#scene3d").astype(int)
        return int(((rgb[..., 0] > 60) & (rgb[..., 0] > 2 * rgb[..., 1]) & (rgb[..., 0] > 2 * rgb[..., 2])).sum())

    counts = {}
    for solids in ([{"center": [0.0, 0.2, 0.0], "radius": 0.15}], []):
        page = browser.new_page()
        page.route("**/v1/jobs?limit=100", lambda route: route.fulfill(json={"items": [job]}))
        page.route("**/v1/jobs/job-solid/particles*", answer(particles(solids)))
        page.route("**/v1/limits", answer(json.dumps(limits(Settings()))))
        page.goto(static_web)
        page.evaluate("""async () => { document.getElementById('view-whatif').hidden = false;
                                       await (await import('/js/whatif.js')).showWhatif('job-solid'); }""")
        sync_api.expect(page.locator("#whatif-summary")).to_contain_text("particles at frame 1")
        if page.locator("#ball-on").is_checked():
            page.locator("#ball-on").uncheck()
        counts[len(solids)] = red(page)
        page.close()
    assert counts[0] == 0 and counts[1] > 100, counts
