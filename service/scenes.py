"""Scenes (uploaded captures) as the API keeps them: an owner's scene, listing, storing an upload
with the reconstruction it asks for, its geometry, and deleting it. The upload's checks (cameras,
videos, limits) are the API's (`api.uploads`); this is what happens to a scene once it is valid.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from fluidcore.errors import InputError
from fluidcore.names import safe_join
from fluidcore.spec.solids import SolidError, check_solids
from fluidcore.spec.source_hint import SourceHintError
from service.database import commit_or_conflict
from service.errors import Conflict, DuplicateRequest, NotFound, RefusedParams
from fluidcore.spec.jobs import ReconstructParams
from service.job_types import JobType
from service.models import SENDING, Job, JobState, Scene
from service.queue import JobQueue, send
from service.runs import read_manifest
from service.storage import Storage, scene_prefix


def owned(session: Session, scene_id: str, owner: str, for_update: bool = False) -> Scene:
    """The scene if it exists and belongs to `owner`; NotFound otherwise (ids are not disclosed).
    `for_update` locks its row (PostgreSQL) until the session commits."""
    scene = session.get(Scene, scene_id, with_for_update=for_update)
    if scene is None or scene.owner != owner:
        raise NotFound.named("scene", scene_id)
    return scene


def get(session: Session, scene_id: str) -> Scene:
    """The scene, whoever owns it (a signed link to one of its videos names it); NotFound otherwise."""
    scene = session.get(Scene, scene_id)
    if scene is None:
        raise NotFound.named("scene", scene_id)
    return scene


@dataclass(frozen=True)
class UploadedVideo:
    """One camera's uploaded video as stored: where, and under which file name it came."""

    key: str
    filename: str


def uploaded_video(scene: Scene, camera: str) -> UploadedVideo:
    """The video uploaded for `camera` (a name already checked by `fluidcore.names.check_name`:
    it only selects among the scene's own videos, it never becomes a key); NotFound naming the
    scene's cameras otherwise."""
    video = scene.videos.get(camera)
    if video is None:
        raise NotFound(f"scene {scene.id} has no video of camera {camera!r}; its cameras: {', '.join(sorted(scene.videos))}")
    return UploadedVideo(video["key"], video["filename"])


def page(session: Session, owner: str, limit: int, offset: int) -> tuple[list[Scene], int]:
    """One page of the owner's scenes, newest first, and how many they have in all."""
    total = session.scalar(select(func.count()).select_from(Scene).where(Scene.owner == owner)) or 0
    rows = session.scalars(
        select(Scene).where(Scene.owner == owner).order_by(Scene.created_at.desc(), Scene.id).limit(limit).offset(offset)
    ).all()
    return list(rows), total


def check_reconstruct_params(params: ReconstructParams, n_frames: int, box: dict[str, Any] | None, field: str) -> None:
    """A reconstruction against its scene: frames within the videos, the source hint and the solids
    inside the scene box (no box: the reconstruction refuses such a capture itself, with its own reason).
    One check for a new reconstruct job and for an upload that asks for a reconstruction;
    `field` names the parameters in the message."""
    if params.frames is not None and params.frames[1] > n_frames:
        raise RefusedParams(f"{field}.frames: end {params.frames[1]} is past the scene's {n_frames} frames")
    if params.source is not None and box is not None:
        try:
            params.source.check_in_box(box["min"], box["max"])
        except SourceHintError as exc:
            raise RefusedParams(f"{field}.{exc}") from None
    if box is not None:
        try:
            check_solids(params.solids, box["min"], box["max"], f"{field}.solids")
        except SolidError as exc:
            raise RefusedParams(str(exc)) from None


def store(
    session: Session, storage: Storage, queue: JobQueue, scene: Scene, keys: list[str], params: ReconstructParams | None
) -> Job | None:
    """Store an upload's scene row (its files are at `keys` already) and, with `params`, its
    reconstruction, in one transaction, then send the job (`service.queue.send`). Anything
    failing before the commit removes the files: a scene is stored whole or not at all.
    DuplicateRequest: a concurrent upload with the same Idempotency-Key stored its scene first."""
    job = None
    try:
        session.add(scene)
        if params is not None:
            session.flush()  # the scene row first: the job refers to it
            job = Job(owner=scene.owner, type=JobType.RECONSTRUCT, scene_id=scene.id, params=params.model_dump(mode="json"),
                      task_id=SENDING)  # being handed on (NULL would be a job waiting for a parent)
            session.add(job)
        session.commit()
    except BaseException as exc:
        session.rollback()
        for key in keys:
            storage.delete(key)
        if isinstance(exc, IntegrityError) and scene.idempotency_key is not None:
            raise DuplicateRequest(f"scene with Idempotency-Key {scene.idempotency_key!r}") from None
        raise
    if job is not None:
        send(session, job, queue)
    return job


def reconstruction_of(session: Session, scene: Scene) -> Job | None:
    """The first reconstruction queued with the scene (what a replayed upload answers with)."""
    return session.scalars(
        select(Job).where(Job.scene_id == scene.id, Job.type == JobType.RECONSTRUCT).order_by(Job.created_at).limit(1)
    ).first()


def geometry(session: Session, storage: Storage, scene: Scene) -> dict[str, Any]:
    """`fluidcore.scene_info` of the latest succeeded reconstruction of the scene (its run knows
    the source, how its depth was found and, from one view, the range of depths the view allows;
    `source.job_id` names that job), else of the uploaded cameras file alone."""
    from fluidcore import scene_info

    job = session.scalars(
        select(Job)
        .where(Job.scene_id == scene.id, Job.type == JobType.RECONSTRUCT, Job.state == JobState.SUCCEEDED)
        .order_by(Job.finished_at.desc())
        .limit(1)
    ).first()
    if job is None:
        return capture_geometry(storage, scene)
    found = scene_info.from_run(read_manifest(storage, job.id), "api")
    found["source"]["job_id"] = job.id
    return found


def capture_geometry(storage: Storage, scene: Scene) -> dict[str, Any]:
    """`fluidcore.scene_info.from_cameras_file` of a stored scene's uploaded camera file."""
    from fluidcore import scene_info

    with tempfile.TemporaryDirectory(prefix="fluidnexus-scene-") as tmp:
        path = safe_join(tmp, Path(scene.cameras_key).name)
        storage.get_file(scene.cameras_key, path)
        return scene_info.from_cameras_file(path)


def delete(session: Session, storage: Storage, scene_id: str, owner: str) -> None:
    """Delete a scene and its files; Conflict while jobs made from it still exist, and when a job
    made from it is stored while it is being deleted. Its row is locked first, so on PostgreSQL
    such a job waits for the delete and is refused then (service.jobs.create)."""
    scene = owned(session, scene_id, owner, for_update=True)
    jobs = session.scalars(select(Job.id).where(Job.scene_id == scene.id)).all()
    if jobs:
        raise Conflict(f"scene {scene_id} is used by jobs {', '.join(jobs)}; delete them first")
    session.delete(scene)
    # the row goes first: a failed file removal leaves garbage, never a dangling row
    commit_or_conflict(session, f"scene {scene_id} was named by a new job while it was being deleted; nothing was deleted")
    storage.delete_prefix(f"{scene_prefix(scene.id)}/")


@dataclass(frozen=True)
class SceneFiles:
    """Where a scene's uploaded files are in storage: what a reconstruction fetches."""

    cameras_key: str
    video_keys: dict[str, str]  # camera name -> its video's key


def files(session: Session, scene_id: str) -> SceneFiles:
    """The storage keys of the scene's cameras file and videos. InputError if it was deleted
    after its job was queued: the job fails with that message."""
    scene = session.get(Scene, scene_id)
    if scene is None:
        raise InputError(f"scene {scene_id} no longer exists")
    return SceneFiles(scene.cameras_key, {camera: video["key"] for camera, video in scene.videos.items()})
