"""A stored object as a download: who may read it (the owner's Bearer key, or a signed link a
<video> element can carry, since it cannot send a header) and its bytes streamed with HTTP Range
(206) so a browser's player seeks without fetching the whole file. One mechanism for every route
that hands out stored files: a job's artifacts (`api.routers.artifacts`) and a scene's uploaded
videos (`api.routers.scenes`)."""

from __future__ import annotations

import re

from fastapi import HTTPException, status
from fastapi.responses import StreamingResponse

from api.deps import unauthorized
from api.signing import signed_url, signing_key, verify
from service.settings import Settings
from service.storage import ObjectNotFound, Storage

_RANGE = re.compile(r"^bytes=(\d*)-(\d*)$")
MAX_POSITION = 2**63 - 1  # no stored object is larger; a position past it is refused (416)

STREAMED = {  # what a streaming route documents besides its own errors
    200: {"content": {"video/mp4": {}, "application/octet-stream": {}}},
    206: {"description": "a byte range"},
}


class RangeNotSatisfiable(Exception):
    pass


def _position(digits: str) -> int:
    """A byte position as sent; RangeNotSatisfiable past MAX_POSITION, read without converting a
    long string (Python refuses int() of over 4,300 digits: a 4,301-digit Range header was a 500
    on every download route, issue 49). nginx refuses an overflowing position with a 416 too."""
    digits = digits.lstrip("0") or "0"
    if len(digits) > len(str(MAX_POSITION)) or int(digits) > MAX_POSITION:
        raise RangeNotSatisfiable
    return int(digits)


def parse_range(header: str | None, size: int) -> tuple[int, int] | None:
    """The single byte range [start, end] (inclusive) asked for, or None for the whole object.

    Multi-range requests and malformed headers get the whole object, which RFC 9110 allows; a
    position over MAX_POSITION is unsatisfiable (416).
    """
    if not header:
        return None
    match = _RANGE.match(header.strip())
    if match is None:
        return None
    first, last = match.groups()
    if not first and not last:
        return None
    if not first:  # suffix: the last N bytes
        length = _position(last)
        if length == 0 or size == 0:
            raise RangeNotSatisfiable
        return max(0, size - length), size - 1
    start = _position(first)
    end = min(_position(last), size - 1) if last else size - 1
    if start >= size or (last and _position(last) < start):
        raise RangeNotSatisfiable
    return start, end


def _shown(header: str, most: int = 64) -> str:
    """A header quoted in a message, cut to `most` characters (a 4,301-digit one is not echoed)."""
    return repr(header) if len(header) <= most else f"{header[:most]!r}... ({len(header)} characters)"


def download_links(storage: Storage, settings: Settings, key: str, path: str) -> tuple[str, str]:
    """The API's URL of the object served at `path` (Bearer key) and a time-limited one that
    needs no key: object storage's own presigned URL, or `path` signed by the API."""
    presigned = storage.presign(key, settings.presign_seconds) or signed_url(signing_key(settings), path, settings.presign_seconds)
    return path, presigned


def signed_in(owner: str | None, settings: Settings, path: str, expires: int | None, signature: str | None) -> str | None:
    """The owner whose key came with the request; None when instead a valid signed link for
    `path` did (anyone holding the link may read it); 401 with neither, 403 for a bad link."""
    if owner is not None:
        return owner
    if expires is None or signature is None:
        raise unauthorized()
    if not verify(signing_key(settings), path, expires, signature):
        raise HTTPException(status.HTTP_403_FORBIDDEN, "download link is invalid or has expired")
    return None


def stream(storage: Storage, key: str, range_header: str | None, content_type: str, filename: str, what: str) -> StreamingResponse:
    """The object at `key`, whole (200) or the byte range asked for (206; 416 outside it);
    inline for a video (a browser plays it), else an attachment. `what` names the object in
    the 404 when it is missing from storage."""
    try:
        size = storage.stat(key).size
        try:
            span = parse_range(range_header, size)
        except RangeNotSatisfiable:
            raise HTTPException(
                status.HTTP_416_RANGE_NOT_SATISFIABLE, f"range {_shown(range_header or '')} outside 0..{size - 1}",
                headers={"Content-Range": f"bytes */{size}"},
            ) from None
        start, end = span if span is not None else (0, size - 1)
        body = storage.iter_range(key, start, end) if size else iter(())
    except ObjectNotFound:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"{what} is missing from storage") from None
    disposition = "inline" if content_type.startswith("video/") else "attachment"
    headers = {
        "Accept-Ranges": "bytes",
        "Content-Length": str(end - start + 1 if size else 0),
        "Content-Disposition": f'{disposition}; filename="{filename}"',
    }
    if span is not None:
        headers["Content-Range"] = f"bytes {start}-{end}/{size}"
    return StreamingResponse(body, status_code=206 if span is not None else 200, media_type=content_type, headers=headers)
