"""Helpers shared by the worker tests: a `World` (database, storage and executors with their own
caches) and a `Deployment` whose jobs travel through a real broker to `celery` worker processes
started here with test-double runners."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Callable
from pathlib import Path

from service.database import make_engine, make_sessionmaker, migrate, session_scope
from service.models import Artifact, Job, Scene
from service.queue import CeleryQueue
from service.settings import Settings
from service.storage import LocalStorage, Storage
from worker.execution import JobExecutor
from tests.support.service import FAKE_RUNNERS, scene_files

ROOT = Path(__file__).resolve().parents[2]  # where tests.support.service (the test-double runners) imports from


def start_worker(settings: Settings, frame_seconds: float = 0.0) -> subprocess.Popen[bytes]:
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
        "FLUIDNEXUS_RUNNERS": "tests.support.service:FAKE_RUNNERS",
        "FAKE_FRAME_SECONDS": str(frame_seconds),
        "FLUIDNEXUS_DATA_DIR": str(settings.data_dir),
        "FLUIDNEXUS_DATABASE_URL": settings.resolved_database_url(),
        "FLUIDNEXUS_WORKER_TORCH_THREADS": "1",
        "FLUIDNEXUS_BROKER_KEY_PREFIX": settings.broker_key_prefix,
    }
    if settings.broker_url:
        env["FLUIDNEXUS_BROKER_URL"] = settings.broker_url
    command = [sys.executable, "-m", "celery", "-A", "worker.tasks", "worker", "-Q", "gpu", "--concurrency", "1",
               "--loglevel", "WARNING", "--without-gossip", "--without-mingle", "--without-heartbeat"]
    return subprocess.Popen(command, env=env, start_new_session=True)


def stop(process: subprocess.Popen[bytes], sig: int = signal.SIGTERM) -> None:
    if process.poll() is None:
        os.killpg(process.pid, sig)
        process.wait(30)


def wait_for(predicate: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.2)


class Deployment:
    def __init__(self, tmp_path: Path, url: str, broker_url: str | None) -> None:
        self.settings = Settings(
            data_dir=tmp_path / "data", database_url=url, broker_url=broker_url,
            broker_key_prefix=f"fnx-test-{uuid.uuid4().hex[:8]}:" if broker_url else "",
        )
        migrate(url)
        self.engine = make_engine(url)
        self.sessions = make_sessionmaker(self.engine)
        self.storage = LocalStorage(self.settings.resolved_storage_dir())
        self.queue = CeleryQueue(self.settings)
        files = scene_files(tmp_path / "scene")
        with session_scope(self.sessions) as session:
            for path in files.values():
                self.storage.put_file(f"scenes/s1/input/{path.name}", path)
            session.add(Scene(id="s1", owner="alice", cameras_key="scenes/s1/input/transforms.json",
                              cameras=["cam0", "cam1"], n_frames=6, fps=30.0,
                              videos={c: {"key": f"scenes/s1/input/{c}.mp4"} for c in ("cam0", "cam1")}))

    def submit(self, frames: int) -> str:
        with session_scope(self.sessions) as session:
            job = Job(owner="alice", type="reconstruct", scene_id="s1", params={"frames": [0, frames]})
            session.add(job)
        task_id = self.queue.enqueue(job.id, job.type)
        with session_scope(self.sessions) as session:  # as the API records it (a job with none waits on a parent)
            session.get(Job, job.id).task_id = task_id
        return job.id

    def job(self, job_id: str) -> Job:
        with session_scope(self.sessions) as session:
            return session.get(Job, job_id)


class World:
    """A database, a storage and a way to make executors that each have their own local cache."""

    def __init__(self, tmp_path: Path, url: str, storage: Storage) -> None:
        migrate(url)
        self.tmp_path, self.storage = tmp_path, storage
        self.engine = make_engine(url)
        self.sessions = make_sessionmaker(self.engine)
        self.settings = Settings(data_dir=tmp_path / "data", database_url=url, job_lease_seconds=60)

    def executor(self, name: str = "w1", runners: dict | None = None) -> JobExecutor:
        settings = self.settings.model_copy(update={"work_dir": self.tmp_path / f"cache-{name}"})
        return JobExecutor(settings, self.sessions, self.storage, runners or FAKE_RUNNERS, worker_name=name)

    def scene(self) -> str:
        files = scene_files(self.tmp_path / "scene")
        keys = {}
        for path in files.values():
            keys[path.name] = f"scenes/s1/input/{path.name}"
            self.storage.put_file(keys[path.name], path)
        with session_scope(self.sessions) as session:
            session.add(Scene(id="s1", owner="alice", cameras_key=keys["transforms.json"], cameras=["cam0", "cam1"],
                              videos={c: {"key": keys[f"{c}.mp4"]} for c in ("cam0", "cam1")}, n_frames=6, fps=30.0))
        return "s1"

    def job(self, job_type: str = "reconstruct", **fields: object) -> str:
        with session_scope(self.sessions) as session:
            job = Job(owner="alice", type=job_type, params=fields.pop("params", {}), **fields)
            session.add(job)
        return job.id

    def get(self, job_id: str) -> Job:
        with session_scope(self.sessions) as session:
            return session.get(Job, job_id)

    def artifacts(self, job_id: str) -> dict[str, Artifact]:
        with session_scope(self.sessions) as session:
            return {a.name: a for a in session.query(Artifact).filter_by(job_id=job_id)}
