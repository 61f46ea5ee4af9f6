"""One scene upload, from its form to its stored scene (and the reconstruction it asks for):
what `POST /v1/scenes` does, in one call (`receive_scene`), so the route only parses and answers.

The steps, each a small function below, in the order that keeps an upload cheap to refuse and
whole or absent once it is over: the form's own rules (a cameras file or fov); its parts spooled
to a private folder under their size limits; a retry under the same `Idempotency-Key` answered
with its first scene; the owner's quotas; the files checked in the validation processes
(`api.uploads.Validators`); the reconstruction's params against what was checked; nothing stored
for a client that left; then the files and the rows, a concurrent retry answered with its scene.
The key and the owner's share of upload places were checked before the body was read
(`api.middleware.AdmissionLimit`).
"""

from __future__ import annotations

import hashlib
import json
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

from pydantic import ValidationError
from sqlalchemy.orm import Session

from api.errors import strict_json
from api.idempotency import replay
from api.uploads import ClientGone, UploadRejected, ValidatedScene, Validators, safe_filename, spool, store_scene
from fluidcore.names import safe_join
from fluidcore.spec.jobs import ReconstructParams
from service import quotas, scenes
from service.errors import DuplicateRequest
from service.models import Job, Scene, new_id
from service.queue import JobQueue
from service.settings import Settings
from service.storage import Storage, scene_prefix


@dataclass(frozen=True)
class Part:
    """An uploaded file part: its name as sent and its content."""

    filename: str | None
    file: BinaryIO


@dataclass(frozen=True)
class UploadForm:
    """The upload's parts and fields as the route received them (docs in api.routers.scenes)."""

    videos: list[Part]
    cameras: Part | None
    fov: float | None
    distance: float
    up: str
    name: str
    reconstruct: str | None
    idempotency_key: str | None

    def single(self) -> tuple[float, float, str] | None:
        """The camera of a video without a cameras file (fov, distance, up); None with one."""
        return None if self.fov is None else (self.fov, self.distance, self.up)

    def fields(self) -> list[object]:
        """The form fields a retry must repeat to be the same upload (what `_upload_hash` covers)."""
        return [self.fov, self.distance, self.up, self.name, self.reconstruct]


@dataclass(frozen=True)
class Received:
    """The stored scene, its geometry (`fluidcore.scene_info`), the reconstruction queued with it
    (None without `reconstruct`), and whether it was stored by an earlier request (a replay)."""

    scene: Scene
    geometry: dict[str, Any]
    job: Job | None
    replayed: bool


@dataclass(frozen=True)
class Spooled:
    """The parts in the upload's private folder: the cameras file's name (None with fov) and
    each video's size by file name."""

    folder: Path
    cameras: str | None
    sizes: dict[str, int]


def receive_scene(session: Session, storage: Storage, queue: JobQueue, settings: Settings, validators: Validators,
                  owner: str, form: UploadForm, gone: Callable[[], bool]) -> Received:
    """Check, then store the upload `form` of `owner` (module docstring). UploadRejected (422 or
    413) for a bad upload, OverLimit (429) over a quota, ClientGone once `gone()` says the client
    left; nothing is stored in any of these cases."""
    check_form(form)
    params = None if form.reconstruct is None else parse_reconstruct(form.reconstruct)
    with tempfile.TemporaryDirectory(prefix="fluidnexus-upload-") as tmp:
        spooled = spool_form(Path(tmp), form, settings)
        request_hash = None if form.idempotency_key is None else _upload_hash(spooled, form.fields())
        earlier = _replayed(session, storage, owner, form, request_hash)
        if earlier is not None:
            return earlier
        quotas.check_new_scene(session, owner, settings, sum(spooled.sizes.values()))  # the videos, as stored_bytes counts
        if params is not None:
            quotas.check_new_job(session, owner, settings)
        validated, geometry = validators.check(spooled.folder, spooled.cameras, spooled.sizes, form.single(), settings, gone=gone)
        if params is not None:
            scenes.check_reconstruct_params(params, validated.n_frames, geometry["box"], "reconstruct")
        if gone():  # the last moment nothing is stored yet
            raise ClientGone()
        return _store(session, storage, queue, owner, form, validated, geometry, params, request_hash)


def check_form(form: UploadForm) -> None:
    """A cameras file or fov, not neither nor both (422 naming `cameras`)."""
    if form.cameras is None and form.fov is None:
        raise UploadRejected("cameras: give a cameras file (transforms.json, info.json or a zipped COLMAP model), "
                             "or fov (the horizontal field of view in degrees) for one video without calibration")
    if form.cameras is not None and form.fov is not None:
        raise UploadRejected("cameras: give a cameras file or fov, not both: fov makes the cameras file of a "
                             "video without calibration")


def parse_reconstruct(text: str) -> ReconstructParams:
    """The `reconstruct` form field: a reconstruction's params as JSON; 422 naming the field."""
    try:
        return ReconstructParams.model_validate(strict_json(text.encode()))  # no NaN, no deep nesting
    except json.JSONDecodeError as exc:
        raise UploadRejected(f"reconstruct: not JSON ({exc.msg})") from None
    except ValidationError as exc:
        raise UploadRejected("; ".join(f"reconstruct.{'.'.join(str(p) for p in e['loc'])}: {e['msg']}"
                                       for e in exc.errors())) from None


def spool_form(folder: Path, form: UploadForm, settings: Settings) -> Spooled:
    """Every part into `folder` under its checked name (`api.uploads.safe_filename`) and its
    size limit; a name used twice is refused."""
    cameras = None
    if form.cameras is not None:
        cameras = safe_filename(form.cameras.filename, "cameras")
        spool(form.cameras.file, safe_join(folder, cameras), settings.max_cameras_bytes, "cameras")
    sizes: dict[str, int] = {}
    for part in form.videos:
        filename = safe_filename(part.filename, "video")
        if filename in sizes or filename == cameras:
            raise UploadRejected(f"video: file name {filename!r} is used twice in this upload")
        sizes[filename] = spool(part.file, safe_join(folder, filename), settings.max_video_bytes, "video")
    return Spooled(folder, cameras, sizes)


def _upload_hash(spooled: Spooled, fields: list[object]) -> str:
    """SHA-256 over the spooled parts (names and bytes, in order) and the form fields: what
    tells a retried upload from a different one under the same Idempotency-Key."""
    digest = hashlib.sha256(json.dumps([spooled.cameras, list(spooled.sizes), fields]).encode())
    for filename in ([spooled.cameras] if spooled.cameras else []) + list(spooled.sizes):
        with safe_join(spooled.folder, filename).open("rb") as handle:
            digest.update(hashlib.file_digest(handle, "sha256").digest())
    return digest.hexdigest()


def _replayed(session: Session, storage: Storage, owner: str, form: UploadForm, request_hash: str | None) -> Received | None:
    """The scene an earlier upload stored under the same Idempotency-Key, with the reconstruction
    it queued (a retry of a different upload under the key: 422); None without one."""
    if form.idempotency_key is None or request_hash is None:
        return None
    scene = replay(session, Scene, owner, form.idempotency_key, request_hash)
    if scene is None:
        return None
    job = None if form.reconstruct is None else scenes.reconstruction_of(session, scene)
    return Received(scene, scenes.geometry(session, storage, scene), job, replayed=True)


def _store(session: Session, storage: Storage, queue: JobQueue, owner: str, form: UploadForm, validated: ValidatedScene,
           geometry: dict[str, Any], params: ReconstructParams | None, request_hash: str | None) -> Received:
    """The checked files, then the scene row and its reconstruction (`service.scenes.store`: whole
    or not at all). A concurrent upload under the same key that stored first is answered instead."""
    scene_id = new_id()
    keys = store_scene(storage, f"{scene_prefix(scene_id)}/input", validated)
    scene = _scene_row(scene_id, owner, form.name, validated, keys)
    scene.idempotency_key, scene.request_hash = form.idempotency_key, request_hash
    try:
        job = scenes.store(session, storage, queue, scene, list(keys.values()), params)
    except DuplicateRequest:
        earlier = _replayed(session, storage, owner, form, request_hash)
        if earlier is None:
            raise
        return earlier
    return Received(scene, geometry, job, replayed=False)


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
