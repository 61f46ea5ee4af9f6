"""Signed download URLs for storage that has no presigning of its own (the local folder).

A browser's <video src> cannot send an Authorization header, so the artifact listing gives
each file a URL that carries its own short-lived permission: HMAC-SHA256 over the path and
the expiry time, with a key only the server knows. The key comes from the settings, or is
generated once into the data dir (so it survives restarts of an embedded server).
"""

from __future__ import annotations

import hashlib
import hmac
import os
import secrets
import time
from pathlib import Path
from urllib.parse import urlencode

from service.settings import Settings

KEY_FILE = "signing.key"


def signing_key(settings: Settings) -> bytes:
    """The configured key, else the data dir's key file (created on first use, readable by the owner only)."""
    if settings.signing_key:
        return settings.signing_key.encode()
    path = settings.resolved_data_dir() / KEY_FILE
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        except FileExistsError:  # another process created it first
            return Path(path).read_text().strip().encode()
        with os.fdopen(fd, "w") as handle:
            handle.write(secrets.token_hex(32))
    return path.read_text().strip().encode()


def _signature(key: bytes, path: str, expires: int) -> str:
    return hmac.new(key, f"{path}\n{expires}".encode(), hashlib.sha256).hexdigest()


def signed_url(key: bytes, path: str, lifetime_s: int) -> str:
    """`path` with `expires` and `signature` query parameters."""
    expires = int(time.time()) + lifetime_s
    return f"{path}?{urlencode({'expires': expires, 'signature': _signature(key, path, expires)})}"


def verify(key: bytes, path: str, expires: int, signature: str) -> bool:
    """True while the signature matches `path` and has not expired."""
    return expires >= time.time() and hmac.compare_digest(_signature(key, path, expires), signature)
