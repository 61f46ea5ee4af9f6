"""ASGI middleware that keeps the API answering under load and oversized input (issue 16).

`AdmissionLimit` lets at most N requests into the app at once; the others wait on the event
loop holding nothing (no thread, no database connection). The database pool and the thread
pool are sized to N, so an admitted request never waits for a pooled connection, and the
pile-up that used to jam both pools (each waiting request holding a connection while it
waited for a thread) cannot form. Health checks skip the queue.

`BodySizeLimit` answers 413 as soon as a body passes its limit, whether declared by
Content-Length or only found while streaming a chunked body, before the multipart parser
spools it to disk.
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass

from fastapi import HTTPException, status
from fastapi.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from api.uploads import UPLOAD_RETRY_AFTER_S

HEALTH_PATHS = frozenset({"/healthz", "/readyz"})
UPLOAD_ROUTE = ("POST", "/v1/scenes")


def is_upload(scope: Scope) -> bool:
    return (scope.get("method"), scope.get("path", "").rstrip("/")) == UPLOAD_ROUTE


@dataclass
class AdmissionLimit:
    """At most `requests` requests (`uploads` of them scene uploads, counted apart so slow uploads
    cannot starve polling) inside `app` at once. An upload waits at most `upload_wait` seconds
    for its place, then gets a 429 with `Retry-After`: a client that would have timed out learns
    when to come back, and no upload is checked for a client that has long given up (issue 36).
    A 429, not a 503: the server is shedding load it chose to refuse, not failing (Stripe's API
    answers its load shedding the same way), and clients retry either after `Retry-After`."""

    app: ASGIApp
    requests: int
    uploads: int
    upload_wait: float = 5.0

    def __post_init__(self) -> None:
        self._requests = asyncio.Semaphore(self.requests)
        self._uploads = asyncio.Semaphore(self.uploads)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope.get("path") in HEALTH_PATHS:
            await self.app(scope, receive, send)
            return
        if not is_upload(scope):
            async with self._requests:
                await self.app(scope, receive, send)
            return
        try:
            await asyncio.wait_for(self._uploads.acquire(), self.upload_wait)
        except TimeoutError:
            busy = JSONResponse({"detail": f"busy: {self.uploads} uploads are being checked; send it again in "
                                           f"{UPLOAD_RETRY_AFTER_S} s"},
                                status_code=429, headers={"Retry-After": str(UPLOAD_RETRY_AFTER_S)})
            await busy(scope, receive, send)
            return
        try:
            await self.app(scope, receive, send)
        finally:
            self._uploads.release()


@dataclass
class BodySizeLimit:
    """413 for a scene upload over `upload_limit` bytes or any other body over `json_limit`."""

    app: ASGIApp
    upload_limit: int
    json_limit: int

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit = self.upload_limit if is_upload(scope) else self.json_limit
        message = f"request body larger than {limit} bytes"
        declared = dict(scope["headers"]).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > limit:
            await JSONResponse({"detail": message}, status_code=413)(scope, receive, send)
            return
        received = 0

        async def counting_receive() -> Message:
            """Raised from inside the app, the HTTPException becomes FastAPI's 413 answer."""
            nonlocal received
            incoming = await receive()
            if incoming["type"] == "http.request":
                received += len(incoming.get("body", b""))
                if received > limit:
                    raise HTTPException(status.HTTP_413_CONTENT_TOO_LARGE, message)
            return incoming

        await self.app(scope, counting_receive, send)
