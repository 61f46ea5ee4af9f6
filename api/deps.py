"""FastAPI dependencies: the database session, storage, job queue and the calling owner.

They read what `create_app` put on `app.state`, so a test builds an app with its own
settings (database, storage folder, queue) and nothing is global.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from typing import Annotated

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
    session = request.app.state.sessionmaker()
    try:
        yield session
    finally:
        session.close()


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


def optional_owner(
    request: Request,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> str | None:
    """The owner of the Bearer key; None without one; 401 for a key that is not valid.

    The key is checked in a session of its own, closed before this returns, so no pooled
    connection is held while the request waits for a thread to run its route. A scene upload's
    was checked before it was admitted (api.middleware.AdmissionLimit), which left its owner."""
    if credentials is None:
        return None
    owner = getattr(request.state, "owner", None) or owner_of_key(request.app.state.sessionmaker, credentials.credentials)
    if owner is None:
        raise unauthorized()
    return owner


def owner_of_key(sessions: sessionmaker[Session], key: str) -> str | None:
    """The owner of a valid, unrevoked key, else None, in a session of its own (closed on return)."""
    with sessions() as session:
        return owner_for_key(session, key)


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
