"""API keys: `fnx_<id>_<secret>`. The id finds the row; only sha256(salt + secret) is stored, so a
leaked database does not leak usable keys. Comparison is constant-time."""

from __future__ import annotations

import hashlib
import hmac
import re
import secrets

from sqlalchemy.orm import Session

from service.models import ApiKey, utcnow

PREFIX = "fnx"
OWNER_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._@-]{0,127}$")
_KEY_PATTERN = re.compile(rf"^{PREFIX}_([0-9a-f]{{16}})_([A-Za-z0-9_-]{{32,64}})$")


class InvalidOwner(ValueError):
    """An owner name the service will not accept."""


class UnknownKey(ValueError):
    """No key with that id."""


def _hash(salt: str, secret: str) -> str:
    return hashlib.sha256(f"{salt}:{secret}".encode()).hexdigest()


def create_key(session: Session, owner: str) -> str:
    """Store a new key for `owner` and return it; this is the only time the full key is seen."""
    if not OWNER_PATTERN.match(owner):
        raise InvalidOwner(f"owner must be 1-128 letters, digits or ._@- (got {owner!r})")
    key_id = secrets.token_hex(8)
    secret = secrets.token_urlsafe(32)
    salt = secrets.token_hex(16)
    session.add(ApiKey(id=key_id, owner=owner, salt=salt, secret_hash=_hash(salt, secret)))
    session.flush()
    return f"{PREFIX}_{key_id}_{secret}"


def owner_for_key(session: Session, key: str) -> str | None:
    """The owner of a valid, unrevoked key, else None."""
    match = _KEY_PATTERN.match(key)
    if match is None:
        return None
    key_id, secret = match.groups()
    row = session.get(ApiKey, key_id)
    if row is None or row.revoked_at is not None:
        return None
    if not hmac.compare_digest(row.secret_hash, _hash(row.salt, secret)):
        return None
    return row.owner


def revoke_key(session: Session, key_id: str) -> ApiKey:
    """Revoke a key by its id (the part after `fnx_`); the row stays, for the record."""
    row = session.get(ApiKey, key_id)
    if row is None:
        raise UnknownKey(f"no API key with id {key_id!r}")
    if row.revoked_at is None:
        row.revoked_at = utcnow()
    return row
