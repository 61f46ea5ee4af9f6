"""`/v1/jobs/{id}/artifacts`: list a job's results and download them (streamed, HTTP Range aware)."""

from __future__ import annotations

import re

from fastapi import APIRouter, Header, HTTPException, status
from fastapi.responses import StreamingResponse

from api.deps import OptionalOwnerDep, OwnerDep, SessionDep, SettingsDep, StorageDep, unauthorized
from api.errors import error_responses
from api.schemas import ArtifactList
from api.signing import signing_key, verify
from api.views import artifact_out, artifact_path
from service import jobs
from service.storage import ObjectNotFound

router = APIRouter(prefix="/v1/jobs", tags=["artifacts"], responses=error_responses(401, 422, 503))

_RANGE = re.compile(r"^bytes=(\d*)-(\d*)$")


class RangeNotSatisfiable(Exception):
    pass


def parse_range(header: str | None, size: int) -> tuple[int, int] | None:
    """The single byte range [start, end] (inclusive) asked for, or None for the whole object.

    Multi-range requests and malformed headers get the whole object, which RFC 9110 allows.
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
        length = int(last)
        if length == 0 or size == 0:
            raise RangeNotSatisfiable
        return max(0, size - length), size - 1
    start = int(first)
    end = min(int(last), size - 1) if last else size - 1
    if start >= size or (last and int(last) < start):
        raise RangeNotSatisfiable
    return start, end


@router.get("/{job_id}/artifacts", response_model=ArtifactList, responses=error_responses(404))
def list_artifacts(
    job_id: str, owner: OwnerDep, session: SessionDep, storage: StorageDep, settings: SettingsDep
) -> ArtifactList:
    """MP4s per camera, the orbit video, the exports (one file per frame of the VDB sequence),
    particle-state files and the manifest, with download URLs."""
    job = jobs.owned(session, job_id, owner)
    return ArtifactList(job_id=job.id, items=[artifact_out(row, storage, settings) for row in jobs.artifacts(session, job.id)])


@router.get(
    "/{job_id}/artifacts/{name:path}",
    response_class=StreamingResponse,
    responses={
        200: {"content": {"video/mp4": {}, "application/octet-stream": {}}},
        206: {"description": "a byte range"},
        **error_responses(403, 404, 416),
    },
    openapi_extra={"security": [{"HTTPBearer": []}, {}]},  # the key, or none with a signed link
)
def download_artifact(
    job_id: str,
    name: str,
    owner: OptionalOwnerDep,
    session: SessionDep,
    storage: StorageDep,
    settings: SettingsDep,
    expires: int | None = None,
    signature: str | None = None,
    range: str | None = Header(default=None),
) -> StreamingResponse:
    """Stream one artifact; honours `Range: bytes=a-b` (206) so videos seek in a browser.

    Authorised by the owner's Bearer key, or by the `expires` + `signature` of a signed URL
    from the artifact listing (what a <video> element can use).
    """
    if owner is not None:
        job = jobs.owned(session, job_id, owner)
    elif expires is not None and signature is not None:
        if not verify(signing_key(settings), artifact_path(job_id, name), expires, signature):
            raise HTTPException(status.HTTP_403_FORBIDDEN, "download link is invalid or has expired")
        job = jobs.get(session, job_id)
    else:
        raise unauthorized()
    row = jobs.artifact(session, job.id, name)
    if row is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"job {job_id} has no artifact {name!r}")
    try:
        size = storage.stat(row.key).size
        try:
            span = parse_range(range, size)
        except RangeNotSatisfiable:
            raise HTTPException(
                status.HTTP_416_RANGE_NOT_SATISFIABLE, f"range {range!r} outside 0..{size - 1}",
                headers={"Content-Range": f"bytes */{size}"},
            ) from None
        start, end = span if span is not None else (0, size - 1)
        body = storage.iter_range(row.key, start, end) if size else iter(())
    except ObjectNotFound:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"artifact {name!r} is missing from storage") from None
    disposition = "inline" if row.content_type.startswith("video/") else "attachment"
    headers = {
        "Accept-Ranges": "bytes",
        "Content-Length": str(end - start + 1 if size else 0),
        "Content-Disposition": f"{disposition}; filename=\"{name.rsplit('/', 1)[-1]}\"",
    }
    if span is not None:
        headers["Content-Range"] = f"bytes {start}-{end}/{size}"
    return StreamingResponse(
        body, status_code=206 if span is not None else 200, media_type=row.content_type, headers=headers
    )
