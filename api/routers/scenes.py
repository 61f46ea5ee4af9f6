"""`/v1/scenes`: upload a capture (cameras file + videos) and read it back, its videos too."""

from __future__ import annotations

import hashlib
import json
import mimetypes
import tempfile
from pathlib import Path
from typing import Annotated
from urllib.parse import quote

import anyio
from fastapi import APIRouter, Depends, File, Form, Header, HTTPException, Request, Response, UploadFile, status
from fastapi.responses import StreamingResponse
from pydantic import ValidationError
from sqlalchemy.orm import Session

from api.deps import (
    OptionalOwnerDep, OwnerDep, PageLimit, PageOffset, QueueDep, SessionDep, SettingsDep, StorageDep, ValidatorsDep,
)
from api.downloads import STREAMED, download_links, signed_in, stream
from api.errors import error_responses, strict_json
from api.idempotency import replay
from api.schemas import Page, SceneGeometry, SceneOut, SceneVideo, SceneVideoLink, SceneVideoLinks
from api.uploads import ClientGone, ValidatedScene, safe_filename, spool, store_scene
from fluidcore.names import check_name, safe_join
from fluidcore.spec.jobs import ReconstructParams
from service import quotas, scenes
from service.errors import DuplicateRequest
from service.models import Job, Scene, new_id
from service.storage import Storage, scene_prefix

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
    upload is validated. While the job broker is down the reconstruction waits
    queued ("waiting for the queue") and is sent when the broker answers (`service.queue.send`)."""
    idempotency_key = idempotency_key or None  # an empty header is no key
    if cameras is None and fov is None:
        raise HTTPException(422, "cameras: give a cameras file (transforms.json, info.json or a zipped COLMAP model), "
                                 "or fov (the horizontal field of view in degrees) for one video without calibration")
    if cameras is not None and fov is not None:
        raise HTTPException(422, "cameras: give a cameras file or fov, not both: fov makes the cameras file of a "
                                 "video without calibration")
    params = None if reconstruct is None else parse_reconstruct(reconstruct)
    with tempfile.TemporaryDirectory(prefix="fluidnexus-upload-") as tmp:
        folder = Path(tmp)
        cameras_name = None
        if cameras is not None:
            cameras_name = safe_filename(cameras.filename, "cameras")
            spool(cameras.file, safe_join(folder, cameras_name), settings.max_cameras_bytes, "cameras")
        sizes: dict[str, int] = {}
        for part in video:
            filename = safe_filename(part.filename, "video")
            if filename in sizes or filename == cameras_name:
                raise HTTPException(422, f"video: file name {filename!r} is used twice in this upload")
            sizes[filename] = spool(part.file, safe_join(folder, filename), settings.max_video_bytes, "video")
        request_hash = None
        if idempotency_key is not None:
            request_hash = _upload_hash(folder, cameras_name, list(sizes), [fov, distance, up, name, reconstruct])
            if (existing := replay(session, Scene, owner, idempotency_key, request_hash)) is not None:
                response.headers["Idempotent-Replayed"] = "true"
                return scene_out(existing, scene_geometry(session, storage, existing), _queued_with(session, existing, reconstruct))
        quotas.check_new_scene(session, owner, settings, sum(sizes.values()))  # the videos, as stored_bytes counts
        if params is not None:
            quotas.check_new_job(session, owner, settings)
        single = None if fov is None else (fov, distance, up)
        validated, geometry = validators.check(folder, cameras_name, sizes, single, settings, gone=lambda: client_gone(request))
        if params is not None:
            scenes.check_reconstruct_params(params, validated.n_frames, geometry["box"], "reconstruct")
        if client_gone(request):  # the last moment nothing is stored yet
            raise ClientGone()

        scene_id = new_id()
        keys = store_scene(storage, f"{scene_prefix(scene_id)}/input", validated)
        scene = _scene_row(scene_id, owner, name, validated, keys)
        scene.idempotency_key, scene.request_hash = idempotency_key, request_hash
        try:
            job = scenes.store(session, storage, queue, scene, list(keys.values()), params)
        except DuplicateRequest:  # a concurrent upload with the same key won the race: answer with its scene
            existing = replay(session, Scene, owner, idempotency_key or "", request_hash or "")
            if existing is None:
                raise
            response.headers["Idempotent-Replayed"] = "true"
            return scene_out(existing, scene_geometry(session, storage, existing), _queued_with(session, existing, reconstruct))
    return scene_out(scene, SceneGeometry.model_validate(geometry), job)


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


def parse_reconstruct(text: str) -> ReconstructParams:
    """The `reconstruct` form field: a reconstruction's params as JSON; 422 naming the field."""
    try:
        return ReconstructParams.model_validate(strict_json(text.encode()))  # no NaN, no deep nesting
    except json.JSONDecodeError as exc:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, f"reconstruct: not JSON ({exc.msg})") from None
    except ValidationError as exc:
        where = "; ".join(f"reconstruct.{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in exc.errors())
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, where) from None


def _upload_hash(folder: Path, cameras_name: str | None, videos: list[str], fields: list[object]) -> str:
    """SHA-256 over the spooled parts (names and bytes, in order) and the form fields: what
    tells a retried upload from a different one under the same Idempotency-Key."""
    digest = hashlib.sha256(json.dumps([cameras_name, videos, fields]).encode())
    for filename in ([cameras_name] if cameras_name else []) + videos:
        with safe_join(folder, filename).open("rb") as handle:
            digest.update(hashlib.file_digest(handle, "sha256").digest())
    return digest.hexdigest()


def _queued_with(session: Session, scene: Scene, reconstruct: str | None) -> Job | None:
    """The reconstruction an upload with a `reconstruct` field queued with its scene (a replayed
    upload answers with it); None for an upload without one."""
    return None if reconstruct is None else scenes.reconstruction_of(session, scene)


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


def _scene_row(scene_id: str, owner: str, name: str, validated: ValidatedScene, keys: dict[str, str]) -> Scene:
    videos = {
        camera: {
            "key": keys[v.filename],
            "filename": v.filename,
            "size": v.size,
            "width": v.width,
            "height": v.height,
            "fps": v.fps,
            "n_frames": v.n_frames,
            "codec": v.codec,
        }
        for camera, v in validated.videos.items()
    }
    return Scene(
        id=scene_id,
        owner=owner,
        name=name,
        cameras_key=keys[validated.cameras_path.name],
        cameras=validated.camera_names,
        videos=videos,
        n_frames=validated.n_frames,
        fps=validated.fps,
    )


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
