"""`/v1/scenes`: upload a capture (cameras file + videos) and read it back, its videos too."""

from __future__ import annotations

import mimetypes
from typing import Annotated
from urllib.parse import quote

import anyio
from fastapi import APIRouter, Depends, File, Form, Header, HTTPException, Request, Response, UploadFile, status
from fastapi.responses import StreamingResponse
from sqlalchemy.orm import Session

from api.deps import (
    OptionalOwnerDep, OwnerDep, PageLimit, PageOffset, QueueDep, SessionDep, SettingsDep, StorageDep, ValidatorsDep,
)
from api.downloads import STREAMED, download_links, signed_in, stream
from api.errors import error_responses
from api.scene_uploads import Part, UploadForm, receive_scene
from api.schemas import Page, SceneGeometry, SceneOut, SceneVideo, SceneVideoLink, SceneVideoLinks
from fluidcore.names import check_name
from service import scenes
from service.models import Job, Scene
from service.storage import Storage

router = APIRouter(prefix="/v1/scenes", tags=["scenes"], responses=error_responses(401, 422, 503))


async def one_cameras_part(request: Request) -> None:
    """422 for a second `cameras` part, which the form binding would otherwise drop silently.
    The form is already parsed (and cached) when dependencies run, so this reads no body."""
    count = len((await request.form()).getlist("cameras"))
    if count > 1:
        raise HTTPException(422, f"cameras: give one cameras file, got {count} cameras parts")


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    response_model=SceneOut,
    responses=error_responses(400, 413, 429),
    dependencies=[Depends(one_cameras_part)],
)
def create_scene(
    owner: OwnerDep,
    session: SessionDep,
    storage: StorageDep,
    settings: SettingsDep,
    queue: QueueDep,
    validators: ValidatorsDep,
    request: Request,
    response: Response,
    video: Annotated[list[UploadFile], File(description="one per camera; file name stem = camera name")],
    cameras: Annotated[
        UploadFile | None, File(description="transforms.json, info.json or a zipped COLMAP model; or give fov instead")
    ] = None,
    fov: Annotated[
        float | None, Form(description="no cameras file: one video's horizontal field of view, degrees (docs/cameras.md)")
    ] = None,
    distance: Annotated[float, Form(description="with fov: camera distance from the scene centre, world units")] = 1.0,
    up: Annotated[str, Form(description="with fov: where world up points in the image: up, down, left, right")] = "up",
    name: Annotated[str, Form(max_length=256)] = "",
    reconstruct: Annotated[
        str | None,
        Form(max_length=4096, description="queue a reconstruction of the scene: its params as JSON, as in POST /v1/jobs"),
    ] = None,
    idempotency_key: Annotated[str | None, Header(max_length=256)] = None,
) -> SceneOut:
    """Validate the whole upload (cameras parse, videos decode, names and sizes match, limits), then store it.

    Without a cameras file, `fov` (and `distance`, `up`) declare the one video's camera and scene
    box as `fluidnexus cameras single` does. A repeated upload with the same `Idempotency-Key`
    returns the first scene (a client that timed out can retry without making a second one);
    the same key with different files or fields is 422. The scene is stored whole or not at all.
    With `reconstruct`, its params are checked against the upload (frames within the videos,
    source inside the box) before anything is stored, and the scene and its queued
    reconstruction are stored together: a refused reconstruction (422) leaves no scene behind,
    so a retry never piles up copies. 429 when the owner has too many scenes, stores too much, or
    (with `reconstruct`) has too many unfinished jobs (`service.quotas`), checked before the
    upload is validated, or has too many uploads in progress. A key that is not valid is a 401
    before the body is read; a body sent slower than the server reads it is a 408. While the job
    broker is down the reconstruction waits queued ("waiting for the queue") and is sent when the
    broker answers (`service.queue.send`). The work is `api.scene_uploads.receive_scene`'s."""
    form = UploadForm(
        videos=[Part(part.filename, part.file) for part in video],
        cameras=None if cameras is None else Part(cameras.filename, cameras.file),
        fov=fov, distance=distance, up=up, name=name, reconstruct=reconstruct,
        idempotency_key=idempotency_key or None,  # an empty header is no key
    )
    received = receive_scene(session, storage, queue, settings, validators, owner, form, gone=lambda: client_gone(request))
    if received.replayed:
        response.headers["Idempotent-Replayed"] = "true"
    return scene_out(received.scene, SceneGeometry.model_validate(received.geometry), received.job)


# uvicorn stops reading a connection once the request's body is in; the first ask resumes reading
# and returns at once, so a close the client sent meanwhile shows only to a second ask a moment
# later (asked once, all 3 abandoned uploads of tests/api/test_api_load.py were stored, in 2 busy
# full-suite runs; alone it passed).
DISCONNECT_PAUSE_S = 0.02


def client_gone(request: Request) -> bool:
    """Whether the client has closed the connection (asked from the route's worker thread): an
    upload its client gave up on is not stored (issue 36: 136 such scenes, 415 MB, in a minute)."""

    async def gone() -> bool:
        if await request.is_disconnected():
            return True
        await anyio.sleep(DISCONNECT_PAUSE_S)
        return await request.is_disconnected()

    return anyio.from_thread.run(gone)


@router.get("", response_model=Page[SceneOut])
def list_scenes(
    owner: OwnerDep,
    session: SessionDep,
    limit: PageLimit = 20,
    offset: PageOffset = 0,
) -> Page[SceneOut]:
    """The caller's scenes, newest first."""
    rows, total = scenes.page(session, owner, limit, offset)
    next_offset = offset + limit if offset + limit < total else None
    return Page[SceneOut](
        items=[scene_out(s) for s in rows], total=total, limit=limit, offset=offset, next_offset=next_offset
    )


@router.get("/{scene_id}", response_model=SceneOut, responses=error_responses(404))
def get_scene(scene_id: str, owner: OwnerDep, session: SessionDep, storage: StorageDep) -> SceneOut:
    """The scene, with its geometry in world units (box, source, camera centres) to place a ball."""
    scene = scenes.owned(session, scene_id, owner)
    return scene_out(scene, scene_geometry(session, storage, scene))


@router.get("/{scene_id}/videos", response_model=SceneVideoLinks, responses=error_responses(404))
def list_videos(scene_id: str, owner: OwnerDep, session: SessionDep, storage: StorageDep, settings: SettingsDep) -> SceneVideoLinks:
    """Each camera's uploaded video with a time-limited link a <video> element plays (the
    footage the results page shows beside the reconstruction's render of the same camera)."""
    scene = scenes.owned(session, scene_id, owner)
    items = []
    for camera in sorted(scene.videos):
        url, presigned = download_links(storage, settings, scene.videos[camera]["key"], scene_video_path(scene.id, camera))
        items.append(SceneVideoLink(camera=camera, url=url, presigned_url=presigned))
    return SceneVideoLinks(scene_id=scene.id, items=items)


@router.get(
    "/{scene_id}/videos/{camera}",
    response_class=StreamingResponse,
    responses={**STREAMED, **error_responses(403, 404, 416)},
    openapi_extra={"security": [{"HTTPBearer": []}, {}]},  # the key, or none with a signed link
)
def download_video(
    scene_id: str,
    camera: str,
    owner: OptionalOwnerDep,
    session: SessionDep,
    storage: StorageDep,
    settings: SettingsDep,
    expires: int | None = None,
    signature: str | None = None,
    range: str | None = Header(default=None),
) -> StreamingResponse:
    """The video uploaded for `camera`, as it was sent: the footage a reconstruction is judged
    against. Honours `Range: bytes=a-b` (206) so a browser's player seeks. Authorised by the
    owner's Bearer key (another owner's scene is a 404), or by the signed `presigned_url` of
    `GET /v1/scenes/{id}/videos` (what a <video> element can use)."""
    owner = signed_in(owner, settings, scene_video_path(scene_id, camera), expires, signature)
    camera = check_name(camera, "camera")
    scene = scenes.owned(session, scene_id, owner) if owner is not None else scenes.get(session, scene_id)
    video = scenes.uploaded_video(scene, camera)
    content_type = mimetypes.guess_type(video.filename)[0] or "application/octet-stream"
    return stream(storage, video.key, range, content_type, video.filename, f"the video of camera {camera!r}")


def scene_video_path(scene_id: str, camera: str) -> str:
    return f"/v1/scenes/{quote(scene_id)}/videos/{quote(camera)}"


def scene_geometry(session: Session, storage: Storage, scene: Scene) -> SceneGeometry:
    """The scene's geometry (`service.scenes.geometry`: from its latest succeeded reconstruction,
    else from the uploaded cameras file)."""
    return SceneGeometry.model_validate(scenes.geometry(session, storage, scene))


@router.delete("/{scene_id}", status_code=status.HTTP_204_NO_CONTENT, responses=error_responses(404, 409))
def delete_scene(scene_id: str, owner: OwnerDep, session: SessionDep, storage: StorageDep) -> None:
    """Delete a scene and its files; refused (409) while jobs made from it still exist."""
    scenes.delete(session, storage, scene_id, owner)


def scene_out(scene: Scene, geometry: SceneGeometry | None = None, job: Job | None = None) -> SceneOut:
    return SceneOut(
        id=scene.id,
        name=scene.name,
        created_at=scene.created_at,
        cameras=scene.cameras,
        videos={
            camera: SceneVideo(**{k: v for k, v in info.items() if k != "key"}, url=scene_video_path(scene.id, camera))
            for camera, info in scene.videos.items()
        },
        n_frames=scene.n_frames,
        fps=scene.fps,
        geometry=geometry,
        reconstruct_job_id=None if job is None else job.id,
    )
