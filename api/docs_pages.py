"""/redoc without the internet: ReDoc's bundle (from fastapi_offline's package) draws the
"API docs by Redocly" logo from cdn.redoc.ly, a broken image offline. This serves the bundle
with that one address pointed at the server's own /favicon.ico, and the page that loads it."""

from __future__ import annotations

from functools import cache
from pathlib import Path

import fastapi_offline
from fastapi import FastAPI
from fastapi.openapi.docs import get_redoc_html
from starlette.responses import HTMLResponse, Response

REDOC_BUNDLE = Path(fastapi_offline.__file__).parent / "static" / "redoc.standalone.js"
CDN_LOGO = "https://cdn.redoc.ly/redoc/logo-mini.svg"
FAVICON = "/favicon.ico"
BUNDLE_URL = "/redoc-offline.js"


@cache
def offline_bundle() -> bytes:
    """The ReDoc bundle with its CDN logo replaced by the local favicon (read once)."""
    return REDOC_BUNDLE.read_bytes().replace(CDN_LOGO.encode(), FAVICON.encode())


def add_redoc(app: FastAPI, title: str) -> None:
    """GET /redoc and the bundle it loads; the app must be made with redoc_url=None."""

    @app.get("/redoc", include_in_schema=False)
    def redoc() -> HTMLResponse:
        return get_redoc_html(
            openapi_url=app.openapi_url or "/openapi.json", title=f"{title} - ReDoc", redoc_js_url=BUNDLE_URL,
            redoc_favicon_url=FAVICON, with_google_fonts=False,
        )

    @app.get(BUNDLE_URL, include_in_schema=False)
    def bundle() -> Response:
        return Response(offline_bundle(), media_type="text/javascript")
