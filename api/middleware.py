"""ASGI middleware that keeps the API answering under load, oversized or slow input (issues 16, 49).

`AdmissionLimit` lets at most N requests into the app at once; the others wait on the event
loop holding nothing (no thread, no database connection). The database pool and the thread
pool are sized to N, so an admitted request never waits for a pooled connection, and the
pile-up that used to jam both pools (each waiting request holding a connection while it
waited for a thread) cannot form. Health checks skip the queue. A scene upload's key is checked
before it may wait for one of the few upload places (issue 49: two clients with a wrong key,
sending 10 bytes a second, held both places for 40 s while every owner's uploads got 429s).

`BodyLimit` answers 413 as soon as a body passes its limit, whether declared by Content-Length
or only found while streaming a chunked body, before the multipart parser spools it to disk;
and 408 once a body falls behind `min_rate` bytes a second after `grace` seconds, so no client
holds a place by sending slowly (the time to read a body is at most grace + size / min_rate).
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass

import anyio.to_thread
from fastapi import HTTPException, status
from fastapi.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from api.deps import owner_of_header, unauthorized
from api.uploads import UPLOAD_RETRY_AFTER_S
from service.errors import OverLimit

HEALTH_PATHS = frozenset({"/healthz", "/readyz"})
UPLOAD_ROUTE = ("POST", "/v1/scenes")


def is_upload(scope: Scope) -> bool:
    return (scope.get("method"), scope.get("path", "").rstrip("/")) == UPLOAD_ROUTE


@dataclass
class AdmissionLimit:
    """At most `requests` requests (`uploads` of them scene uploads, counted apart so slow uploads
    cannot starve polling) inside `app` at once. An upload is let in only with a valid key, and
    only `OwnerUploads.limit` of one owner's at once (both answered before it waits, holding no
    place: issue 49); it then waits at most `upload_wait` seconds for its place and gets a 429
    with `Retry-After`: a client that would have timed out learns when to come back, and no
    upload is checked for a client that has long given up (issue 36). A 429, not a 503: the
    server is shedding load it chose to refuse, not failing (Stripe's API answers its load
    shedding the same way), and clients retry either after `Retry-After`."""

    app: ASGIApp
    requests: int
    uploads: int
    upload_wait: float = 5.0

    def __post_init__(self) -> None:
        self._requests = asyncio.Semaphore(self.requests)
        self._uploads = asyncio.Semaphore(self.uploads)
        self._key_checks = asyncio.Semaphore(self.uploads)  # their connections: create_app sizes the pool for them

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope.get("path") in HEALTH_PATHS:
            await self.app(scope, receive, send)
            return
        if not is_upload(scope):
            async with self._requests:
                await self.app(scope, receive, send)
            return
        await self._upload(scope, receive, send)

    async def _upload(self, scope: Scope, receive: Receive, send: Send) -> None:
        """The key (401), the owner's share (429), then a place (429 after `upload_wait`)."""
        state = scope["app"].state
        async with self._key_checks:
            owner = await anyio.to_thread.run_sync(owner_of_header, state.sessionmaker, dict(scope["headers"]).get(b"authorization"))
        if owner is None:
            refused = unauthorized()
            await JSONResponse({"detail": refused.detail}, status_code=401, headers=refused.headers)(scope, receive, send)
            return
        try:
            state.owner_uploads.take(owner)
        except OverLimit as exc:
            await _too_many(str(exc))(scope, receive, send)
            return
        scope.setdefault("state", {})["owner"] = owner  # api.deps.optional_owner: checked once
        try:
            await self._in_an_upload_place(scope, receive, send)
        finally:
            state.owner_uploads.release(owner)

    async def _in_an_upload_place(self, scope: Scope, receive: Receive, send: Send) -> None:
        try:
            await asyncio.wait_for(self._uploads.acquire(), self.upload_wait)
        except TimeoutError:
            busy = f"busy: {self.uploads} uploads are being checked; send it again in {UPLOAD_RETRY_AFTER_S} s"
            await _too_many(busy)(scope, receive, send)
            return
        try:
            await self.app(scope, receive, send)
        finally:
            self._uploads.release()


def _too_many(detail: str) -> JSONResponse:
    return JSONResponse({"detail": detail}, status_code=429, headers={"Retry-After": str(UPLOAD_RETRY_AFTER_S)})


@dataclass
class BodyLimit:
    """413 for a scene upload over `upload_limit` bytes or any other body over `json_limit`; 408
    for a body that arrives slower than `min_rate` bytes a second once `grace` seconds have passed
    since the app began reading it (nginx's client_body_timeout answers a stalled body with 408)."""

    app: ASGIApp
    upload_limit: int
    json_limit: int
    min_rate: float
    grace: float

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit = self.upload_limit if is_upload(scope) else self.json_limit
        message = f"request body larger than {limit} bytes"
        declared = dict(scope["headers"]).get(b"content-length")
        if declared is not None and declared.isdigit() and (len(declared) > 18 or int(declared) > limit):
            await JSONResponse({"detail": message}, status_code=413)(scope, receive, send)
            return
        received = 0
        started: float | None = None
        complete = False

        async def limited_receive() -> Message:
            """Raised from inside the app, the HTTPException becomes FastAPI's 413 or 408 answer.
            Once the body is in, a receive waits for the client's disconnect (a streamed
            download listens for it throughout): no clock then."""
            nonlocal received, started, complete
            if complete:
                return await receive()
            now = time.monotonic()
            started = now if started is None else started
            allowed = started + self.grace + received / self.min_rate - now  # on schedule until then
            try:
                incoming = await asyncio.wait_for(receive(), max(allowed, 0.0))
            except TimeoutError:
                raise HTTPException(status.HTTP_408_REQUEST_TIMEOUT,
                                    f"request body too slow: {received} bytes in {time.monotonic() - started:.1f} s; "
                                    f"send at least {self.min_rate:.0f} bytes a second") from None
            if incoming["type"] == "http.request":
                received += len(incoming.get("body", b""))
                if received > limit:
                    raise HTTPException(status.HTTP_413_CONTENT_TOO_LARGE, message)
            complete = incoming["type"] != "http.request" or not incoming.get("more_body", False)
            return incoming

        await self.app(scope, limited_receive, send)
