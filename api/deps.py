"""FastAPI dependencies: the database session, storage, job queue and the calling owner.

They read what `create_app` put on `app.state`, so a test builds an app with its own
settings (database, storage folder, queue) and nothing is global.
"""

from __future__ import annotations

import hashlib
import time
from collections import OrderedDict
from collections.abc import AsyncIterator
from typing import Annotated

import anyio.to_thread

from fastapi import Depends, HTTPException, Query, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session, sessionmaker

from api.auth import owner_for_key
from api.uploads import Validators
from service.queue import JobQueue
from service.settings import Settings
from service.storage import Storage

_bearer = HTTPBearer(auto_error=False, description="an API key from `fluidnexus keys create`")


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


async def get_session(request: Request) -> AsyncIterator[Session]:
    """The route's session. Async so that closing it (returning its connection to the pool) runs
    on the event loop the moment the response is ready, instead of queueing for a worker thread
    while the connection stays checked out (issue 16: under load that wait emptied the pool)."""
    factory = request.app.state.read_sessionmaker if request.method in READS else request.app.state.sessionmaker
    session = factory()
    try:
        yield session
    finally:
        session.close()


READS = frozenset({"GET", "HEAD"})  # routes that only read: their sessions run without a transaction (create_app)


def get_storage(request: Request) -> Storage:
    return request.app.state.storage


def get_queue(request: Request) -> JobQueue:
    return request.app.state.queue


def get_validators(request: Request) -> Validators:
    return request.app.state.validators


def unauthorized() -> HTTPException:
    return HTTPException(
        status.HTTP_401_UNAUTHORIZED,
        "missing or invalid API key (send 'Authorization: Bearer KEY')",
        headers={"WWW-Authenticate": "Bearer"},
    )


async def optional_owner(
    request: Request,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> str | None:
    """The owner of the Bearer key; None without one; 401 for a key that is not valid.

    A key checked within the last `KeyCache.ttl_s` is answered on the event loop (issue 49: under
    100 pollers each request paid a thread hop and a database round trip for its key, and the GET
    p99 was 2.3-3.1 s); any other is checked in a thread, in a session of its own closed before
    this returns, so no pooled connection is held while the request waits for a thread to run its
    route. A scene upload's was checked before it was admitted (api.middleware.AdmissionLimit)."""
    if credentials is None:
        return None
    keys: KeyCache = request.app.state.keys
    owner = getattr(request.state, "owner", None) or keys.owner(credentials.credentials)
    if owner is None:
        owner = await anyio.to_thread.run_sync(owner_of_key, request.app.state.sessionmaker, credentials.credentials)
        if owner is None:
            raise unauthorized()
        keys.remember(credentials.credentials, owner)
    return owner


def owner_of_key(sessions: sessionmaker[Session], key: str) -> str | None:
    """The owner of a valid, unrevoked key, else None, in a session of its own (closed on return)."""
    with sessions() as session:
        return owner_for_key(session, key)


class KeyCache:
    """Valid keys seen within the last `ttl_s` seconds, by a hash of the key (never the key
    itself), at most `size` of them (the least recently checked go first). Only keys found
    valid are kept, so random keys cost a lookup each and fill nothing. A revoked key is refused
    once its entry expires: within `ttl_s` in this process."""

    def __init__(self, ttl_s: float, size: int = 1024) -> None:
        self.ttl_s, self.size = ttl_s, size
        self._owners: OrderedDict[bytes, tuple[str, float]] = OrderedDict()

    def owner(self, key: str) -> str | None:
        """The owner of `key` if it was found valid within the last `ttl_s`, else None."""
        digest = hashlib.sha256(key.encode()).digest()
        found = self._owners.get(digest)
        if found is None or found[1] < time.monotonic():
            self._owners.pop(digest, None)
            return None
        self._owners.move_to_end(digest)
        return found[0]

    def remember(self, key: str, owner: str) -> None:
        if self.ttl_s <= 0:
            return
        self._owners[hashlib.sha256(key.encode()).digest()] = (owner, time.monotonic() + self.ttl_s)
        while len(self._owners) > self.size:
            self._owners.popitem(last=False)


def owner_of_header(sessions: sessionmaker[Session], authorization: bytes | None) -> str | None:
    """The owner of an `Authorization: Bearer KEY` header as sent (raw bytes, from the ASGI scope,
    before any route runs), else None: a missing header, another scheme or a key not valid."""
    scheme, _, key = (authorization or b"").decode("latin-1").strip().partition(" ")
    if scheme.lower() != "bearer" or not key.strip():
        return None
    return owner_of_key(sessions, key.strip())


def current_owner(owner: Annotated[str | None, Depends(optional_owner)]) -> str:
    """The owner of the Bearer key, or 401."""
    if owner is None:
        raise unauthorized()
    return owner


MAX_PAGE_OFFSET = 1_000_000_000  # far past any real listing; keeps OFFSET inside every database's integer

PageLimit = Annotated[int, Query(ge=1, le=100, description="items per page")]
PageOffset = Annotated[int, Query(ge=0, le=MAX_PAGE_OFFSET, description="items to skip")]
SessionDep = Annotated[Session, Depends(get_session)]
StorageDep = Annotated[Storage, Depends(get_storage)]
QueueDep = Annotated[JobQueue, Depends(get_queue)]
SettingsDep = Annotated[Settings, Depends(get_settings)]
ValidatorsDep = Annotated[Validators, Depends(get_validators)]
OwnerDep = Annotated[str, Depends(current_owner)]
OptionalOwnerDep = Annotated[str | None, Depends(optional_owner)]
