"""The FastAPI application: `create_app(settings)` wires settings, database, storage and the job
queue onto `app.state`; routers read them through `api.deps`. Run it with
`fluidnexus serve` or `uvicorn --factory api.app:create_app` (settings from the environment)."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse
from fastapi.staticfiles import StaticFiles
from fastapi_offline import FastAPIOffline
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from api.routers import artifacts, health, jobs, particles, scenes
from api.uploads import UploadRejected
from service.database import make_engine, make_sessionmaker, migrate
from service.queue import CeleryQueue, JobQueue
from service.settings import Settings, get_settings
from service.storage import StorageError, make_storage


def create_app(settings: Settings | None = None, queue: JobQueue | None = None) -> FastAPI:
    settings = settings or get_settings()
    url = settings.resolved_database_url()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        if settings.migrate_on_start:
            migrate(url)
        yield
        app.state.engine.dispose()

    # FastAPIOffline: /docs and /redoc load Swagger UI / ReDoc from the installed package, not a CDN,
    # so the reference renders on a machine without internet.
    app = FastAPIOffline(
        title="FluidNexus",
        summary="Reconstruct smoke from video, predict it, and ask what-if questions.",
        version="0.1.0",
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.engine = make_engine(url)
    app.state.sessionmaker = make_sessionmaker(app.state.engine)
    app.state.storage = make_storage(settings)
    app.state.queue = queue or CeleryQueue(settings)

    app.add_middleware(BodySizeLimit, limit=settings.max_upload_bytes)
    app.add_exception_handler(UploadRejected, _upload_rejected)
    app.add_exception_handler(StorageError, _storage_unavailable)
    for router in (scenes.router, jobs.router, artifacts.router, particles.router, health.router):
        app.include_router(router)
    if settings.web_dir.is_dir():  # mounted last: API routes take precedence over files
        app.mount("/", StaticFiles(directory=settings.web_dir, html=True), name="web")
    return app


async def _storage_unavailable(request: Request, exc: Exception) -> JSONResponse:
    """Object storage down or full: the request may succeed later, nothing was half-written."""
    return JSONResponse({"detail": f"storage unavailable: {exc}"}, status_code=503)


async def _upload_rejected(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, UploadRejected)
    return JSONResponse({"detail": str(exc)}, status_code=exc.status_code)


class BodySizeLimit:
    """Refuse request bodies over `limit` bytes with 413, by Content-Length or while streaming,
    before the multipart parser writes them to disk."""

    def __init__(self, app: ASGIApp, limit: int) -> None:
        self.app, self.limit = app, limit

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope["headers"]).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > self.limit:
            await self._reject(send)
            return
        received = 0

        async def counting_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.limit:
                    raise _TooLarge
            return message

        try:
            await self.app(scope, counting_receive, send)
        except _TooLarge:
            await self._reject(send)

    async def _reject(self, send: Send) -> None:
        response = JSONResponse({"detail": f"request body larger than {self.limit} bytes"}, status_code=413)
        await response({"type": "http"}, _no_receive, send)


class _TooLarge(Exception):
    pass


async def _no_receive() -> Message:
    return {"type": "http.disconnect"}

