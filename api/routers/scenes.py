"""`/v1/scenes`: upload a capture (cameras file + videos) and read it back."""

from __future__ import annotations

import hashlib
import json
import tempfile
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, Depends, File, Form, Header, HTTPException, Request, Response, UploadFile, status
from pydantic import ValidationError
from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from api.deps import OwnerDep, PageLimit, PageOffset, QueueDep, SessionDep, SettingsDep, StorageDep, ValidatorsDep
from api.errors import error_responses, strict_json
from api.idempotency import replay
from api.schemas import Page, SceneGeometry, SceneOut, SceneVideo
from api.uploads import ValidatedScene, safe_filename, spool, store_scene
from fluidcore.names import safe_join
from fluidcore.reconstruct.source_hint import SourceHintError
from fluidcore.spec.jobs import ReconstructParams
from service.job_types import JobType
from service.models import Job, JobState, Scene, new_id
from service.queue import QueueUnavailable
from service.storage import Storage, run_prefix, scene_prefix

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
    responses=error_responses(400, 413),
    dependencies=[Depends(one_cameras_part)],
)
def create_scene(
    owner: OwnerDep,
    session: SessionDep,
    storage: StorageDep,
    settings: SettingsDep,
    queue: QueueDep,
    validators: ValidatorsDep,
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
    reconstruction are stored together: a refused reconstruction (422) or an unreachable queue
    (503) leaves no scene behind, so a retry never piles up copies."""
    idempotency_key = idempotency_key or None  # an empty header is no key
    if (cameras is None) == (fov is None):
        raise HTTPException(422, "cameras: give either a cameras file or fov (for one video without calibration), not both")
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
        single = None if fov is None else (fov, distance, up)
        validated, geometry = validators.check(folder, cameras_name, sizes, single, settings)
        if params is not None:
            check_reconstruct_params(params, validated.n_frames, geometry["box"], "reconstruct")

        scene_id = new_id()
        keys = store_scene(storage, f"{scene_prefix(scene_id)}/input", validated)
        job = None
        try:
            scene = _scene_row(scene_id, owner, name, validated, keys)
            scene.idempotency_key, scene.request_hash = idempotency_key, request_hash
            session.add(scene)
            if params is not None:
                session.flush()  # the scene row first: the job refers to it
                job = Job(owner=owner, type=JobType.RECONSTRUCT, scene_id=scene_id, params=params.model_dump(mode="json"))
                session.add(job)
            session.commit()
        except BaseException as exc:
            session.rollback()
            for key in keys.values():
                storage.delete(key)
            if isinstance(exc, IntegrityError) and idempotency_key is not None and request_hash is not None:
                # a concurrent upload with the same key won the race: answer with its scene
                existing = replay(session, Scene, owner, idempotency_key, request_hash)
                if existing is not None:
                    response.headers["Idempotent-Replayed"] = "true"
                    return scene_out(existing, scene_geometry(session, storage, existing), _queued_with(session, existing, reconstruct))
            raise
        if job is not None:
            try:
                job.task_id = queue.enqueue(job.id, job.type)
                session.commit()
            except QueueUnavailable as exc:  # nothing was queued: take the upload back
                session.delete(job)
                session.delete(scene)
                session.commit()
                for key in keys.values():
                    storage.delete(key)
                raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, str(exc)) from None
    return scene_out(scene, SceneGeometry.model_validate(geometry), job)


def parse_reconstruct(text: str) -> ReconstructParams:
    """The `reconstruct` form field: a reconstruction's params as JSON; 422 naming the field."""
    try:
        return ReconstructParams.model_validate(strict_json(text.encode()))  # no NaN, no deep nesting
    except json.JSONDecodeError as exc:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, f"reconstruct: not JSON ({exc.msg})") from None
    except ValidationError as exc:
        where = "; ".join(f"reconstruct.{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in exc.errors())
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, where) from None


def check_reconstruct_params(params: ReconstructParams, n_frames: int, box: dict[str, Any] | None, field: str) -> None:
    """A reconstruction against its scene: frames within the videos, the source hint inside the
    scene box (no box: the reconstruction refuses such a capture itself, with its own reason).
    One check for POST /v1/jobs and for an upload that asks for a reconstruction."""
    if params.frames is not None and params.frames[1] > n_frames:
        raise HTTPException(
            status.HTTP_422_UNPROCESSABLE_CONTENT, f"{field}.frames: end {params.frames[1]} is past the scene's {n_frames} frames"
        )
    if params.source is not None and box is not None:
        try:
            params.source.check_in_box(box["min"], box["max"])
        except SourceHintError as exc:
            raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, f"{field}.{exc}") from None


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
    if reconstruct is None:
        return None
    return session.scalars(
        select(Job).where(Job.scene_id == scene.id, Job.type == JobType.RECONSTRUCT).order_by(Job.created_at).limit(1)
    ).first()


@router.get("", response_model=Page[SceneOut])
def list_scenes(
    owner: OwnerDep,
    session: SessionDep,
    limit: PageLimit = 20,
    offset: PageOffset = 0,
) -> Page[SceneOut]:
    """The caller's scenes, newest first."""
    total = session.scalar(select(func.count()).select_from(Scene).where(Scene.owner == owner)) or 0
    rows = session.scalars(
        select(Scene).where(Scene.owner == owner).order_by(Scene.created_at.desc(), Scene.id).limit(limit).offset(offset)
    ).all()
    next_offset = offset + limit if offset + limit < total else None
    return Page[SceneOut](
        items=[scene_out(s) for s in rows], total=total, limit=limit, offset=offset, next_offset=next_offset
    )


@router.get("/{scene_id}", response_model=SceneOut, responses=error_responses(404))
def get_scene(scene_id: str, owner: OwnerDep, session: SessionDep, storage: StorageDep) -> SceneOut:
    """The scene, with its geometry in world units (box, source, camera centres) to place a ball."""
    scene = owned_scene(session, scene_id, owner)
    return scene_out(scene, scene_geometry(session, storage, scene))


def scene_geometry(session: Session, storage: Storage, scene: Scene) -> SceneGeometry:
    """From the latest succeeded reconstruction of the scene (its run knows the source, how its
    depth was found and, from one view, the range of depths the view allows; `source.job_id`
    names that job), else from the uploaded cameras file alone."""
    from fluidcore import scene_info
    from fluidcore.runs import MANIFEST, RunRecord

    job = session.scalars(
        select(Job)
        .where(Job.scene_id == scene.id, Job.type == JobType.RECONSTRUCT, Job.state == JobState.SUCCEEDED)
        .order_by(Job.finished_at.desc())
        .limit(1)
    ).first()
    if job is not None:
        record = RunRecord.from_bytes(storage.read_bytes(f"{run_prefix(job.id)}/{MANIFEST}"), f"job {job.id}'s run")
        geometry = scene_info.from_run(record)
        geometry["source"]["job_id"] = job.id
        return SceneGeometry.model_validate(geometry)
    return SceneGeometry.model_validate(capture_geometry_of(storage, scene))


def capture_geometry_of(storage: Storage, scene: Scene) -> dict[str, Any]:
    """`fluidcore.scene_info.from_cameras_file` of a stored scene's uploaded camera file."""
    from fluidcore import scene_info

    with tempfile.TemporaryDirectory(prefix="fluidnexus-scene-") as tmp:
        path = safe_join(tmp, Path(scene.cameras_key).name)
        storage.get_file(scene.cameras_key, path)
        return scene_info.from_cameras_file(path)


@router.delete("/{scene_id}", status_code=status.HTTP_204_NO_CONTENT, responses=error_responses(404, 409))
def delete_scene(scene_id: str, owner: OwnerDep, session: SessionDep, storage: StorageDep) -> None:
    """Delete a scene and its files; refused (409) while jobs made from it still exist."""
    scene = owned_scene(session, scene_id, owner)
    jobs = session.scalars(select(Job.id).where(Job.scene_id == scene.id)).all()
    if jobs:
        raise HTTPException(
            status.HTTP_409_CONFLICT, f"scene {scene_id} is used by jobs {', '.join(jobs)}; delete them first"
        )
    session.delete(scene)
    session.commit()  # the row goes first: a failed file removal leaves garbage, never a dangling row
    storage.delete_prefix(f"{scene_prefix(scene.id)}/")


def owned_scene(session: Session, scene_id: str, owner: str) -> Scene:
    """The scene if it exists and belongs to `owner`; 404 otherwise (never 403: ids are not disclosed)."""
    scene = session.get(Scene, scene_id)
    if scene is None or scene.owner != owner:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"scene {scene_id} not found")
    return scene


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
        videos={camera: SceneVideo(**{k: v for k, v in info.items() if k != "key"}) for camera, info in scene.videos.items()},
        n_frames=scene.n_frames,
        fps=scene.fps,
        geometry=geometry,
        reconstruct_job_id=None if job is None else job.id,
    )
