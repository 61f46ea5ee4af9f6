"""FastAPI dependencies: the database session, storage, job queue and the calling owner.

They read what `create_app` put on `app.state`, so a test builds an app with its own
settings (database, storage folder, queue) and nothing is global.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, HTTPException, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session

from api.auth import owner_for_key
from service.queue import JobQueue
from service.settings import Settings
from service.storage import Storage

_bearer = HTTPBearer(auto_error=False, description="an API key from `fluidnexus keys create`")


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_session(request: Request) -> Iterator[Session]:
    session = request.app.state.sessionmaker()
    try:
        yield session
    finally:
        session.close()


def get_storage(request: Request) -> Storage:
    return request.app.state.storage


def get_queue(request: Request) -> JobQueue:
    return request.app.state.queue


def unauthorized() -> HTTPException:
    return HTTPException(
        status.HTTP_401_UNAUTHORIZED,
        "missing or invalid API key (send 'Authorization: Bearer KEY')",
        headers={"WWW-Authenticate": "Bearer"},
    )


def optional_owner(
    session: Annotated[Session, Depends(get_session)],
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> str | None:
    """The owner of the Bearer key; None without one; 401 for a key that is not valid."""
    if credentials is None:
        return None
    owner = owner_for_key(session, credentials.credentials)
    if owner is None:
        raise unauthorized()
    return owner


def current_owner(owner: Annotated[str | None, Depends(optional_owner)]) -> str:
    """The owner of the Bearer key, or 401."""
    if owner is None:
        raise unauthorized()
    return owner


SessionDep = Annotated[Session, Depends(get_session)]
StorageDep = Annotated[Storage, Depends(get_storage)]
QueueDep = Annotated[JobQueue, Depends(get_queue)]
SettingsDep = Annotated[Settings, Depends(get_settings)]
OwnerDep = Annotated[str, Depends(current_owner)]
OptionalOwnerDep = Annotated[str | None, Depends(optional_owner)]
