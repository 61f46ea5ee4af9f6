"""Both storage backends behave the same: the local folder, and S3 through the minio client against
moto's S3 server on loopback."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from service.storage import InvalidKey, LocalStorage, MinioStorage, ObjectNotFound, Storage, StorageError
from tests.support.service import free_port

DATA = bytes(range(256)) * 5000  # 1.28 MB: more than one streaming chunk


@pytest.fixture(scope="module")
def s3_endpoint() -> Iterator[str]:
    from moto.server import ThreadedMotoServer

    port = free_port()
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    yield f"127.0.0.1:{port}"
    server.stop()


def minio_storage(endpoint: str, bucket: str) -> MinioStorage:
    return MinioStorage(endpoint, "testing", "testing", bucket, secure=False, region="us-east-1")


@pytest.fixture(params=["local", "s3"])
def storage(request: pytest.FixtureRequest, tmp_path: Path) -> Storage:
    if request.param == "local":
        return LocalStorage(tmp_path / "store")
    backend = minio_storage(request.getfixturevalue("s3_endpoint"), f"test-{tmp_path.name[-20:].lower().replace('_', '-')}")
    backend.ensure_bucket()
    return backend


def test_put_get_stat_list_delete(storage: Storage, tmp_path: Path) -> None:
    source = tmp_path / "source.bin"
    source.write_bytes(DATA)
    storage.put_file("jobs/a/run/states/frame_000001.npz", source)
    storage.put_bytes("jobs/a/run/manifest.json", b'{"frames": []}', "application/json")
    storage.put_bytes("jobs/ab/other.txt", b"x")

    assert storage.stat("jobs/a/run/states/frame_000001.npz").size == len(DATA)
    assert storage.exists("jobs/a/run/manifest.json") and not storage.exists("jobs/a/run/missing")
    assert [i.key for i in storage.list("jobs/a/")] == ["jobs/a/run/manifest.json", "jobs/a/run/states/frame_000001.npz"]
    assert [i.key for i in storage.list("jobs/a")] == [
        "jobs/a/run/manifest.json", "jobs/a/run/states/frame_000001.npz", "jobs/ab/other.txt"
    ]

    target = tmp_path / "copy" / "frame.npz"
    storage.get_file("jobs/a/run/states/frame_000001.npz", target)
    assert target.read_bytes() == DATA
    assert storage.read_bytes("jobs/a/run/manifest.json") == b'{"frames": []}'

    storage.put_bytes("jobs/a/run/manifest.json", b"{}")  # overwrite
    assert storage.read_bytes("jobs/a/run/manifest.json") == b"{}"
    storage.delete_prefix("jobs/a/")
    assert [i.key for i in storage.list("jobs/")] == ["jobs/ab/other.txt"]
    storage.delete("jobs/a/never-existed")  # no error


def test_byte_ranges(storage: Storage) -> None:
    storage.put_bytes("v.mp4", DATA)
    assert b"".join(storage.iter_range("v.mp4", 10, 19)) == DATA[10:20]
    assert b"".join(storage.iter_range("v.mp4", len(DATA) - 3)) == DATA[-3:]
    assert b"".join(storage.iter_range("v.mp4", 5, 1_100_000)) == DATA[5:1_100_001]
    assert b"".join(storage.iter_range("v.mp4")) == DATA


def test_missing_objects_and_bad_keys(storage: Storage, tmp_path: Path) -> None:
    with pytest.raises(ObjectNotFound):
        storage.stat("nope")
    with pytest.raises(ObjectNotFound):
        storage.get_file("nope", tmp_path / "x")
    with pytest.raises(ObjectNotFound):
        b"".join(storage.iter_range("nope"))
    for key in ("../escape", "/abs", "a//b", "a/./b", ""):
        with pytest.raises(InvalidKey):
            storage.put_bytes(key, b"x")
    storage.check()


def test_presigned_urls_work_without_credentials(s3_endpoint: str) -> None:
    backend = minio_storage(s3_endpoint, "presign-test")
    backend.ensure_bucket()
    backend.put_bytes("jobs/j/videos/cam0.mp4", DATA, "video/mp4")
    url = backend.presign("jobs/j/videos/cam0.mp4", 600)
    assert url is not None and "X-Amz-Signature" in url
    response = httpx.get(url)
    assert response.status_code == 200 and response.content == DATA
    assert LocalStorage(Path("/tmp")).presign("anything", 600) is None


def test_s3_failures_are_storage_errors(s3_endpoint: str) -> None:
    with pytest.raises(StorageError, match="does not exist"):
        minio_storage(s3_endpoint, "never-created").check()
    unreachable = MinioStorage(f"127.0.0.1:{free_port()}", "a", "b", "bucket", region="us-east-1")
    with pytest.raises(StorageError):
        unreachable.check()


def test_presigned_urls_use_the_public_endpoint(s3_endpoint: str) -> None:
    """Inside a deployment the service reaches `minio:9000`; users' browsers reach the published port."""
    port = s3_endpoint.rsplit(":", 1)[1]
    backend = MinioStorage(s3_endpoint, "testing", "testing", "public-test", region="us-east-1",
                           public_endpoint=f"localhost:{port}")
    backend.ensure_bucket()
    backend.put_bytes("a.bin", DATA[:100])
    url = backend.presign("a.bin", 600)
    assert url is not None and url.startswith(f"http://localhost:{port}/public-test/a.bin?")
    assert httpx.get(url).content == DATA[:100]
