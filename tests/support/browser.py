"""The browser tests' shared pieces (tests/web): headless Chromium (Debian's `chromium`, driven by
the `playwright` package), web/ served as plain files, the in-process API answering the page's
/v1 requests (byte ranges included, so <video> elements play and seek), and the folder the
screenshots go to (docs/screens/ with FLUIDNEXUS_SCREENSHOTS=1, else the test's own)."""

from __future__ import annotations

import base64
import functools
import os
import shutil
import threading
from collections.abc import Callable, Iterator
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np
import pytest

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
ROOT = Path(__file__).resolve().parents[2]
# what the page sends that the API reads, and what a <video> needs back to play and seek
REQUEST_HEADERS = ("authorization", "content-type", "range")
ANSWER_HEADERS = ("content-type", "content-range", "accept-ranges", "content-length", "content-disposition")


@pytest.fixture(scope="module")
def browser() -> Iterator[object]:
    sync_api = pytest.importorskip("playwright.sync_api")
    if not Path(CHROMIUM).is_file():
        pytest.skip("Debian's chromium is not installed (.ci/run installs it)")
    with sync_api.sync_playwright() as playwright:
        browser = playwright.chromium.launch(
            executable_path=CHROMIUM,
            # WebGL through the software rasteriser: there is no GPU in CI
            args=["--enable-unsafe-swiftshader", "--use-angle=swiftshader", "--autoplay-policy=no-user-gesture-required"],
        )
        yield browser
        browser.close()


@pytest.fixture
def screens(tmp_path: Path) -> Path:
    folder = ROOT / "docs" / "screens" if os.environ.get("FLUIDNEXUS_SCREENSHOTS") == "1" else tmp_path
    folder.mkdir(parents=True, exist_ok=True)
    return folder


@pytest.fixture
def static_web() -> Iterator[str]:
    """web/ served as plain files (no API, no worker): enough for the page's modules on their own."""
    handler = functools.partial(SimpleHTTPRequestHandler, directory=str(ROOT / "web"))
    httpd = ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{httpd.server_address[1]}/"
    httpd.shutdown()
    httpd.server_close()


def signed_in(browser, static_web: str, api, auth: dict[str, str], width: int = 1280,  # type: ignore[no-untyped-def]
              init_script: str | None = None):
    """A page of web/ as plain files, its /v1 requests answered by the in-process API `api`, signed
    in with `auth`'s key and on the job list; and the list its page errors are collected in.
    `init_script` runs before the page's own scripts."""
    from playwright.sync_api import expect

    page = browser.new_page(viewport={"width": width, "height": 900})
    if init_script is not None:
        page.add_init_script(init_script)
    errors: list[str] = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    page.route("**/v1/**", in_process(api))
    page.goto(static_web)
    page.get_by_label("API key").fill(auth["Authorization"].removeprefix("Bearer "))
    page.keyboard.press("Enter")
    expect(page.locator("#jobs-title")).to_be_visible()
    return page, errors


def canvas_pixels(page, selector: str) -> np.ndarray:  # type: ignore[no-untyped-def]
    """(H, W, 3) uint8 RGB of the <canvas> `selector` as drawn (a WebGL one keeps its drawing
    buffer: the what-if view's does)."""
    import cv2

    url = page.evaluate("(selector) => document.querySelector(selector).toDataURL('image/png')", selector)
    image = cv2.imdecode(np.frombuffer(base64.b64decode(url.split(",", 1)[1]), np.uint8), cv2.IMREAD_COLOR)
    return image[..., ::-1]


def in_process(api) -> Callable[[object], None]:  # type: ignore[no-untyped-def]  # tests.support.api.Service
    """A route handler answering the page's /v1 requests with the in-process API `api`."""

    def to_api(route) -> None:  # type: ignore[no-untyped-def]
        request, url = route.request, urlsplit(route.request.url)
        answer = api.client.request(request.method, url.path + (f"?{url.query}" if url.query else ""),
                                    headers={k: v for k, v in request.headers.items() if k.lower() in REQUEST_HEADERS},
                                    content=request.post_data_buffer)
        headers = {k: v for k, v in answer.headers.items() if k.lower() in ANSWER_HEADERS}
        route.fulfill(status=answer.status_code, body=answer.content, headers={"content-type": "text/plain", **headers})

    return to_api
