"""The browser tests' shared pieces (tests/web): headless Chromium (Debian's `chromium`, driven by
the `playwright` package), web/ served as plain files, the in-process API answering the page's
/v1 requests (byte ranges included, so <video> elements play and seek), and the folder the
screenshots go to (docs/screens/ with FLUIDNEXUS_SCREENSHOTS=1, else the test's own)."""

from __future__ import annotations

import functools
import os
import shutil
import threading
from collections.abc import Callable, Iterator
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import urlsplit

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
