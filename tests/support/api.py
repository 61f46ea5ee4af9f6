"""The API in-process for the tests of the API, the web UI's endpoints and the service around it:
an app over a real database (SQLite, or PostgreSQL where it runs) with a recording job queue, the
fixtures that make one, and an executor that runs its jobs with test-double runners.

Kept apart from tests.support.service because that module is also loaded by worker processes
(FLUIDNEXUS_RUNNERS), which have no use for the API and its test client."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from api.auth import create_key
from service.database import session_scope
from service.models import Job
from service.settings import Settings
from tests.support.service import FAKE_RUNNERS, RecordingQueue, empty_tables, scene_files, sqlite_url, upload_parts
from worker.execution import JobExecutor


class Service:
    """A running app plus handles on what is behind it."""

    def __init__(self, client: TestClient, queue: RecordingQueue) -> None:
        self.client, self.queue = client, queue
        self.app = client.app
        self.sessions = self.app.state.sessionmaker
        self.storage = self.app.state.storage

    def key(self, owner: str) -> dict[str, str]:
        with session_scope(self.sessions) as session:
            return {"Authorization": f"Bearer {create_key(session, owner)}"}

    def count(self, model: type) -> int:
        with session_scope(self.sessions) as session:
            return session.query(model).count()

    def add_job(self, job_type: str, owner: str = "alice", **fields: object) -> str:
        """A job row written directly (no queue, no checks), with `fields` as given; its id."""
        with session_scope(self.sessions) as session:
            job = Job(owner=owner, type=job_type, params=fields.pop("params", {}), **fields)
            session.add(job)
            session.flush()
            return job.id

    def set_job(self, job_id: str, **fields: object) -> None:
        with session_scope(self.sessions) as session:
            job = session.get(Job, job_id)
            for name, value in fields.items():
                setattr(job, name, value)


def make_service(
    tmp_path: Path, url: str | None = None, queue: RecordingQueue | None = None, **overrides: object
) -> Iterator[Service]:
    """An app on `url` (default: a new SQLite file) with storage and data dir under `tmp_path`."""
    settings = Settings(data_dir=tmp_path / "data", database_url=url or sqlite_url(tmp_path), **overrides)
    queue = queue or RecordingQueue()
    with TestClient(create_app(settings, queue=queue)) as client:
        yield Service(client, queue)
        client.app.state.engine.dispose()


@pytest.fixture(params=["sqlite", "postgres"])
def service(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Service]:
    url = empty_tables(request.getfixturevalue("postgres_url")) if request.param == "postgres" else None
    yield from make_service(tmp_path, url)


@pytest.fixture
def sqlite_service(tmp_path: Path) -> Iterator[Service]:
    yield from make_service(tmp_path)


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    return scene_files(tmp_path_factory.mktemp("scene"))


def upload(service: Service, headers: dict[str, str], files: dict[str, Path]):  # type: ignore[no-untyped-def]
    return service.client.post("/v1/scenes", files=upload_parts(files), data={"name": "test"}, headers=headers)


def reconstruct(service: Service, headers: dict[str, str], scene_id: str, **params: object):  # type: ignore[no-untyped-def]
    body = {"type": "reconstruct", "scene_id": scene_id, "params": params}
    return service.client.post("/v1/jobs", json=body, headers=headers)


@pytest.fixture
def scene_id(service: Service, scene_dir: dict[str, Path]) -> str:
    return upload(service, service.key("alice"), scene_dir).json()["id"]


def executor(service: Service, tmp_path: Path) -> JobExecutor:
    settings = service.app.state.settings.model_copy(update={"work_dir": tmp_path / "work"})
    return JobExecutor(settings, service.sessions, service.storage, FAKE_RUNNERS, queue=service.queue)

