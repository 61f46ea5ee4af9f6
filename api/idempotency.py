"""`Idempotency-Key` replays, shared by the routes that create things (jobs, scenes): a row keeps
the key and a hash of the request that made it; the same key with the same request returns that
row, with another request a 422 (the key cannot mean two things)."""

from __future__ import annotations

from typing import TypeVar

from fastapi import HTTPException, status
from sqlalchemy import select
from sqlalchemy.orm import Session

from service.models import Job, Scene

Row = TypeVar("Row", Job, Scene)


def replay(session: Session, model: type[Row], owner: str, key: str, request_hash: str) -> Row | None:
    """The owner's row made under `key`, None if there is none; 422 if it was made by another request."""
    row = session.scalars(select(model).where(model.owner == owner, model.idempotency_key == key)).first()
    if row is not None and row.request_hash != request_hash:
        kind = model.__tablename__.removesuffix("s")
        raise HTTPException(
            status.HTTP_422_UNPROCESSABLE_CONTENT,
            f"Idempotency-Key {key!r} was already used for a different request ({kind} {row.id})",
        )
    return row
