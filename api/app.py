"""The FastAPI application: `create_app(settings)` wires settings, database, storage and the job
queue onto `app.state`; routers read them through `api.deps`. Run it with
`fluidnexus serve` or `uvicorn --factory api.app:create_app` (settings from the environment)."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import anyio.to_thread
from fastapi import FastAPI
from fastapi.routing import APIRoute
from fastapi.staticfiles import StaticFiles
from fastapi_offline import FastAPIOffline

from api.deps import KeyCache
from api.docs_pages import add_redoc
from api.errors import HANDLERS, add_unmatched_routes
from api.middleware import AdmissionLimit, BodyLimit
from api.routers import artifacts, bundles, cameras, health, jobs, limits, particles, scenes, videos, webhooks, wind
from api.uploads import OwnerUploads, Validators
from service.chaining import release_stranded
from service.database import make_engine, make_sessionmaker, migrate
from service.queue import CeleryQueue, JobQueue, reap_stale
from service.settings import Settings, get_settings
from service.storage import make_storage

log = logging.getLogger(__name__)


def create_app(settings: Settings | None = None, queue: JobQueue | None = None) -> FastAPI:
    settings = settings or get_settings()
    url = settings.resolved_database_url()
    admitted = settings.max_concurrent_requests + settings.max_concurrent_uploads

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        if settings.migrate_on_start:
            migrate(url)
        # One thread per admitted request (its key check, route and response run one after another).
        anyio.to_thread.current_default_thread_limiter().total_tokens = admitted
        reaper = asyncio.create_task(_reap_forever(app))
        yield
        reaper.cancel()
        app.state.validators.close()
        app.state.engine.dispose()
        app.state.probe_engine.dispose()

    # FastAPIOffline: /docs loads Swagger UI from the installed package, not a CDN, so the reference
    # renders on a machine without internet; /redoc likewise, with its logo made local (api.docs_pages).
    app = FastAPIOffline(
        title="FluidNexus",
        summary="Reconstruct smoke from video, predict it, and ask what-if questions.",
        version="0.1.0",
        lifespan=lifespan,
        redoc_url=None,
        favicon_url="/favicon.ico",
    )
    add_redoc(app, app.title)
    app.state.settings = settings
    # + an upload's key check before it is admitted (at most max_concurrent_uploads at once) + the reaper's
    app.state.engine = make_engine(url, pool_size=admitted + settings.max_concurrent_uploads + 1)
    app.state.probe_engine = health.probe_engine(app.state.engine)  # /readyz's own connections
    app.state.sessionmaker = make_sessionmaker(app.state.engine)
    # GET routes only read: without a transaction a poll on PostgreSQL is its query alone, not BEGIN,
    # the query and ROLLBACK (issue 49: each round trip waits for a database process on busy cores)
    app.state.read_sessionmaker = make_sessionmaker(app.state.engine.execution_options(isolation_level="AUTOCOMMIT"))
    app.state.storage = make_storage(settings)
    app.state.queue = queue or CeleryQueue(settings)
    app.state.validators = Validators(settings.max_concurrent_uploads)
    app.state.owner_uploads = OwnerUploads(settings.max_uploads_per_owner)
    app.state.keys = KeyCache(settings.key_cache_seconds)

    app.add_middleware(BodyLimit, upload_limit=settings.max_upload_bytes, json_limit=settings.max_json_bytes,
                       min_rate=settings.min_body_rate, grace=settings.body_grace_seconds)
    app.add_middleware(
        AdmissionLimit, requests=settings.max_concurrent_requests, uploads=settings.max_concurrent_uploads,
        upload_wait=settings.upload_wait_seconds,
    )
    for exception, handler in HANDLERS.items():
        app.add_exception_handler(exception, handler)
    routers = (scenes.router, jobs.router, artifacts.router, videos.router, bundles.router, particles.router, webhooks.router, health.router,
               limits.router, wind.router, cameras.router)
    for router in routers:
        app.include_router(router)
    add_unmatched_routes(app, [route for router in routers for route in router.routes if isinstance(route, APIRoute)])
    if settings.web_dir.is_dir():  # mounted last: API routes take precedence over files
        app.mount("/", StaticFiles(directory=settings.web_dir, html=True), name="web")
    return app


async def _reap_forever(app: FastAPI) -> None:
    """Every quarter lease, send again the running jobs whose heartbeat stopped and the queued jobs
    whose message was lost (service.queue.reap_stale), so a job whose worker died is picked up
    within about 1.25 leases, whatever the broker does; and release the continuations of jobs
    that ended without releasing them (service.chaining.release_stranded)."""
    state = app.state
    lease = state.settings.job_lease_seconds
    while True:
        await asyncio.sleep(lease / 4)
        try:
            reaped = await anyio.to_thread.run_sync(reap_stale, state.sessionmaker, state.queue, lease)
            reaped += await anyio.to_thread.run_sync(release_stranded, state.sessionmaker, state.queue, state.settings)
        except Exception:  # database or broker down: the next round tries again
            log.warning("reaper: could not check for stale jobs", exc_info=True)
            continue
        if reaped:
            log.warning("reaper: sent again or released %d job(s) whose worker stopped, whose message was lost "
                        "or whose parent ended unnoticed: %s", len(reaped), ", ".join(reaped))
