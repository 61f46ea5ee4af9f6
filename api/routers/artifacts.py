"""`/v1/jobs/{id}/artifacts`: list a job's results and download them (streamed, HTTP Range aware)."""

from __future__ import annotations

from fastapi import APIRouter, Header, HTTPException, status
from fastapi.responses import StreamingResponse

from api.deps import OptionalOwnerDep, OwnerDep, SessionDep, SettingsDep, StorageDep
from api.downloads import STREAMED, signed_in, stream
from api.errors import error_responses
from api.schemas import ArtifactList
from api.views import artifact_out, artifact_path
from service import jobs

router = APIRouter(prefix="/v1/jobs", tags=["artifacts"], responses=error_responses(401, 422, 503))


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
    responses={**STREAMED, **error_responses(403, 404, 416)},
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
    path = artifact_path(job_id, name)
    owner = signed_in(owner, settings, path, expires, signature)
    job = jobs.owned(session, job_id, owner) if owner is not None else jobs.get(session, job_id)
    row = jobs.artifact(session, job.id, name)
    if row is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"job {job_id} has no artifact {name!r}")
    return stream(storage, row.key, range, row.content_type, name.rsplit("/", 1)[-1], f"artifact {name!r}")
