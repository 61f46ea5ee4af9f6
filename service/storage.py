"""Object storage: one interface, a local-folder backend (embedded default) and an S3 backend
through the `minio` client (MinIO in production, any S3-compatible server in tests).

Keys are '/'-separated relative paths such as `scenes/<id>/videos/cam0.mp4`. Range reads
stream in chunks so a large MP4 never sits in memory.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from abc import ABC, abstractmethod
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path

from service.settings import Settings
from fluidcore.files import atomic_output
from fluidcore.names import safe_join

CHUNK = 1024 * 1024


class StorageError(Exception):
    """A storage operation failed for a reason outside the request (server down, disk full)."""


class ObjectNotFound(KeyError):
    """No object under this key."""


class InvalidKey(ValueError):
    """A key that could escape the storage root or is otherwise malformed."""


@dataclass(frozen=True)
class ObjectInfo:
    key: str
    size: int


# The layout of the service's objects, shared by the API and the worker.
def scene_prefix(scene_id: str) -> str:
    """An uploaded scene: `input/` holds the cameras file and videos under their upload names."""
    return f"scenes/{scene_id}"


def job_prefix(job_id: str) -> str:
    """A job: `run/` is its run folder (checkpoints, states, manifest), `videos/` its rendered
    MP4s, `exports/` its last frame in every export format and every frame as VDB."""
    return f"jobs/{job_id}"


def run_prefix(job_id: str) -> str:
    return f"{job_prefix(job_id)}/run"


def log_key(job_id: str) -> str:
    """The job's log lines (worker.execution.JobLog), all attempts, for GET /v1/jobs/{id}/logs."""
    return f"{job_prefix(job_id)}/log.txt"


def check_key(key: str) -> str:
    """Reject absolute keys, '..', empty parts, backslashes and NUL: a key is a plain relative path."""
    if not key or "\\" in key or "\0" in key or any(part in ("", ".", "..") for part in key.split("/")):
        raise InvalidKey(f"invalid storage key {key!r}")
    return key


class Storage(ABC):
    """What the API and the worker need from object storage."""

    @abstractmethod
    def put_file(self, key: str, path: Path, content_type: str = "application/octet-stream") -> None: ...

    @abstractmethod
    def get_file(self, key: str, path: Path) -> None:
        """Download `key` to `path` (written atomically)."""

    @abstractmethod
    def stat(self, key: str) -> ObjectInfo:
        """Size of `key`; ObjectNotFound if absent."""

    @abstractmethod
    def iter_range(self, key: str, start: int = 0, end: int | None = None) -> Iterator[bytes]:
        """Bytes start..end (inclusive, as in HTTP Range), streamed in chunks."""

    @abstractmethod
    def list(self, prefix: str) -> list[ObjectInfo]:
        """Every object whose key starts with `prefix`, sorted by key."""

    @abstractmethod
    def delete(self, key: str) -> None:
        """Remove `key`; absent keys are ignored."""

    @abstractmethod
    def presign(self, key: str, expires_s: int) -> str | None:
        """A time-limited GET URL that bypasses the API, or None when the backend has none."""

    @abstractmethod
    def check(self) -> None:
        """Raise StorageError unless the backend is reachable and writable (for /readyz)."""

    def put_bytes(self, key: str, data: bytes, content_type: str = "application/octet-stream") -> None:
        with tempfile.NamedTemporaryFile(delete=False) as tmp:
            tmp.write(data)
        try:
            self.put_file(key, Path(tmp.name), content_type)
        finally:
            os.unlink(tmp.name)

    def read_bytes(self, key: str) -> bytes:
        return b"".join(self.iter_range(key))

    def exists(self, key: str) -> bool:
        try:
            self.stat(key)
        except ObjectNotFound:
            return False
        return True

    def delete_prefix(self, prefix: str) -> None:
        for info in self.list(prefix):
            self.delete(info.key)


class LocalStorage(Storage):
    """Objects are files under `root`; writes go through a temporary file and a rename."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root).resolve()
        self.root.mkdir(parents=True, exist_ok=True)

    def _path(self, key: str) -> Path:
        return safe_join(self.root, check_key(key))

    def put_file(self, key: str, path: Path, content_type: str = "application/octet-stream") -> None:
        target = self._path(key)
        try:
            target.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=".upload-")
            os.close(fd)
            shutil.copyfile(path, tmp)
            os.replace(tmp, target)
        except OSError as exc:
            raise StorageError(f"cannot write {key}: {exc}") from exc

    def get_file(self, key: str, path: Path) -> None:
        source = self._path(key)
        if not source.is_file():
            raise ObjectNotFound(key)
        with atomic_output(path, suffix=".part") as tmp:
            shutil.copyfile(source, tmp)

    def stat(self, key: str) -> ObjectInfo:
        path = self._path(key)
        if not path.is_file():
            raise ObjectNotFound(key)
        return ObjectInfo(key, path.stat().st_size)

    def iter_range(self, key: str, start: int = 0, end: int | None = None) -> Iterator[bytes]:
        path = self._path(key)
        if not path.is_file():
            raise ObjectNotFound(key)
        return self._read(path, start, end)

    @staticmethod
    def _read(path: Path, start: int, end: int | None) -> Iterator[bytes]:
        with path.open("rb") as handle:
            handle.seek(start)
            remaining = None if end is None else end - start + 1
            while remaining is None or remaining > 0:
                chunk = handle.read(CHUNK if remaining is None else min(CHUNK, remaining))
                if not chunk:
                    return
                if remaining is not None:
                    remaining -= len(chunk)
                yield chunk

    def list(self, prefix: str) -> list[ObjectInfo]:
        found = []
        folder = self.root / prefix.rsplit("/", 1)[0] if "/" in prefix else self.root
        for path in folder.rglob("*"):
            if path.is_file() and not path.name.startswith(".upload-"):
                key = path.relative_to(self.root).as_posix()
                if key.startswith(prefix):
                    found.append(ObjectInfo(key, path.stat().st_size))
        return sorted(found, key=lambda info: info.key)

    def delete(self, key: str) -> None:
        self._path(key).unlink(missing_ok=True)

    def presign(self, key: str, expires_s: int) -> str | None:
        return None

    def check(self) -> None:
        try:
            with tempfile.NamedTemporaryFile(dir=self.root, prefix=".upload-"):
                pass
        except OSError as exc:
            raise StorageError(f"storage folder {self.root} is not writable: {exc}") from exc


class MinioStorage(Storage):
    """Objects in one S3 bucket, through the `minio` client."""

    def __init__(
        self,
        endpoint: str,
        access_key: str,
        secret_key: str,
        bucket: str,
        secure: bool = False,
        region: str | None = None,
        public_endpoint: str | None = None,
    ) -> None:
        """`public_endpoint`: the host:port clients outside the deployment reach (e.g. MinIO's published
        port while the service talks to `minio:9000`); presigned URLs are signed for it."""
        from minio import Minio

        self.bucket = bucket
        self.client = Minio(endpoint, access_key=access_key, secret_key=secret_key, secure=secure, region=region)
        self.public_client = (
            Minio(public_endpoint, access_key=access_key, secret_key=secret_key, secure=secure, region=region)
            if public_endpoint and public_endpoint != endpoint
            else self.client
        )

    def ensure_bucket(self) -> None:
        with _s3_errors("make_bucket"):
            if not self.client.bucket_exists(self.bucket):
                self.client.make_bucket(self.bucket)

    def put_file(self, key: str, path: Path, content_type: str = "application/octet-stream") -> None:
        with _s3_errors(f"put {key}", check_key(key)):
            self.client.fput_object(self.bucket, key, str(path), content_type)

    def get_file(self, key: str, path: Path) -> None:
        with _s3_errors(f"get {key}", check_key(key)), atomic_output(path, suffix=".part") as tmp:
            self.client.fget_object(self.bucket, key, str(tmp))

    def stat(self, key: str) -> ObjectInfo:
        with _s3_errors(f"stat {key}", check_key(key)):
            return ObjectInfo(key, int(self.client.stat_object(self.bucket, key).size))

    def iter_range(self, key: str, start: int = 0, end: int | None = None) -> Iterator[bytes]:
        length = 0 if end is None else end - start + 1  # 0 = to the end
        with _s3_errors(f"get {key}", check_key(key)):
            response = self.client.get_object(self.bucket, key, offset=start, length=length)
        return self._stream(response)

    @staticmethod
    def _stream(response) -> Iterator[bytes]:  # type: ignore[no-untyped-def]  # urllib3 response
        try:
            yield from response.stream(CHUNK)
        finally:
            response.close()
            response.release_conn()

    def list(self, prefix: str) -> list[ObjectInfo]:
        with _s3_errors(f"list {prefix}"):
            objects = list(self.client.list_objects(self.bucket, prefix=prefix, recursive=True))
        return sorted((ObjectInfo(o.object_name, int(o.size)) for o in objects), key=lambda info: info.key)

    def delete(self, key: str) -> None:
        with _s3_errors(f"delete {key}", check_key(key)):
            self.client.remove_object(self.bucket, key)

    def presign(self, key: str, expires_s: int) -> str | None:
        with _s3_errors(f"presign {key}", check_key(key)):
            return self.public_client.presigned_get_object(self.bucket, key, expires=timedelta(seconds=expires_s))

    def check(self) -> None:
        with _s3_errors("bucket_exists"):
            exists = self.client.bucket_exists(self.bucket)
        if not exists:
            raise StorageError(f"bucket {self.bucket!r} does not exist")


@contextmanager
def _s3_errors(what: str, key: str | None = None) -> Iterator[None]:
    """Map the client's errors: a missing key to ObjectNotFound, everything else to StorageError."""
    from minio.error import MinioException, S3Error
    from urllib3.exceptions import HTTPError

    try:
        yield
    except S3Error as exc:
        if key is not None and exc.code in ("NoSuchKey", "NoSuchObject"):
            raise ObjectNotFound(key) from exc
        raise StorageError(f"{what}: {exc.code}: {exc.message}") from exc
    except (MinioException, HTTPError, OSError) as exc:
        raise StorageError(f"{what}: {exc}") from exc


def make_storage(settings: Settings) -> Storage:
    """The backend the settings ask for."""
    if settings.storage_backend == "s3":
        return MinioStorage(
            settings.s3_endpoint,
            settings.s3_access_key,
            settings.s3_secret_key,
            settings.s3_bucket,
            secure=settings.s3_secure,
            region=settings.s3_region,
            public_endpoint=settings.s3_public_endpoint,
        )
    return LocalStorage(settings.resolved_storage_dir())
