"""Signed download URLs for storage that has no presigning of its own (the local folder).

A browser's <video src> cannot send an Authorization header, so the artifact listing gives
each file a URL that carries its own short-lived permission: HMAC-SHA256 over the path and
the expiry time, with a key only the server knows. The key comes from the settings, or is
generated once into the data dir (so it survives restarts of an embedded server).
"""

from __future__ import annotations

import hashlib
import hmac
import time
from urllib.parse import urlencode

from service.settings import signing_key

__all__ = ["signed_url", "signing_key", "verify"]


def _signature(key: bytes, path: str, expires: int) -> str:
    return hmac.new(key, f"{path}\n{expires}".encode(), hashlib.sha256).hexdigest()


def signed_url(key: bytes, path: str, lifetime_s: int) -> str:
    """`path` with `expires` and `signature` query parameters."""
    expires = int(time.time()) + lifetime_s
    return f"{path}?{urlencode({'expires': expires, 'signature': _signature(key, path, expires)})}"


def verify(key: bytes, path: str, expires: int, signature: str) -> bool:
    """True while the signature matches `path` and has not expired."""
    return expires >= time.time() and hmac.compare_digest(_signature(key, path, expires), signature)
