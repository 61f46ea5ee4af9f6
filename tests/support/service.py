"""Helpers shared by the service tests (API, worker, storage, end to end): real databases, a tiny
scene upload, and test-double job runners.

Databases are real: SQLite in a temporary folder, and PostgreSQL on 127.0.0.1 with a fresh
database per test (so parallel xdist workers never share tables).
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import numpy as np
import pytest

PG_ADMIN_URL = "postgresql+psycopg://postgres@127.0.0.1:5432/postgres"
PG_URL = "postgresql+psycopg://postgres@127.0.0.1:5432/{name}"
REDIS_URL = "redis://127.0.0.1:6379/{db}"
ROOT = Path(__file__).resolve().parents[2]


def port_open(host: str, port: int) -> bool:
    with socket.socket() as sock:
        sock.settimeout(0.5)
        return sock.connect_ex((host, port)) == 0


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@contextmanager
def postgres_database() -> Iterator[str]:
    """A new, empty PostgreSQL database for one test; dropped afterwards."""
    if not port_open("127.0.0.1", 5432):
        pytest.skip("PostgreSQL is not running on 127.0.0.1:5432 (.ci/run starts it)")
    from sqlalchemy import create_engine, text

    name = f"fnx_test_{uuid.uuid4().hex[:12]}"
    admin = create_engine(PG_ADMIN_URL, isolation_level="AUTOCOMMIT")
    with admin.connect() as connection:
        connection.execute(text(f'CREATE DATABASE "{name}"'))
    try:
        yield PG_URL.format(name=name)
    finally:
        with admin.connect() as connection:
            connection.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()


@contextmanager
def database_url(kind: str, tmp_path: Path) -> Iterator[str]:
    """`kind` is 'sqlite' or 'postgres'."""
    if kind == "sqlite":
        yield sqlite_url(tmp_path)
    else:
        with postgres_database() as url:
            yield url


def sqlite_url(folder: Path) -> str:
    return f"sqlite:///{folder / 'service.sqlite3'}"


@contextmanager
def migrated_postgres() -> Iterator[str]:
    """One migrated PostgreSQL database for a whole test module (see `empty_tables`)."""
    from service.database import migrate

    with postgres_database() as url:
        migrate(url)
        yield url


@pytest.fixture(scope="module")
def postgres_url() -> Iterator[str]:
    """`migrated_postgres` as a fixture, for the API and worker tests that run on both databases."""
    with migrated_postgres() as url:
        yield url


def empty_tables(url: str) -> str:
    """Delete every row, children first, so tests sharing a migrated database start clean."""
    from sqlalchemy import create_engine

    from service.models import Base

    engine = create_engine(url)
    with engine.begin() as connection:
        for table in reversed(Base.metadata.sorted_tables):
            connection.execute(table.delete())
    engine.dispose()
    return url


# -- a tiny scene ---------------------------------------------------------------------------------

def camera_entry(name: str, width: int, height: int, x: float) -> dict:
    """A transforms.json frame: camera at (x, 0, 4) looking at the origin (OpenGL axes, no rotation
    needed when it looks along -z)."""
    return {
        "camera": name,
        "file_path": f"videos/{name}.mp4",
        "fl_x": 1.2 * width,
        "fl_y": 1.2 * width,
        "cx": width / 2,
        "cy": height / 2,
        "w": width,
        "h": height,
        "transform_matrix": [[1, 0, 0, x], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]],
    }


def write_transforms(path: Path, names: list[str], width: int = 32, height: int = 24) -> Path:
    frames = [camera_entry(name, width, height, 0.5 * i) for i, name in enumerate(names)]
    path.write_text(json.dumps({"frames": frames}))
    return path


def write_video(path: Path, width: int = 32, height: int = 24, n_frames: int = 6, fps: float = 30.0) -> Path:
    """A small grey clip with a moving bright blob, so frames differ."""
    from fluidcore.video import write_mp4

    yy, xx = np.mgrid[0:height, 0:width]
    frames = []
    for t in range(n_frames):
        blob = np.exp(-((xx - width * (0.3 + 0.05 * t)) ** 2 + (yy - height / 2) ** 2) / 20.0)
        frames.append(np.repeat((blob * 220)[..., None], 3, axis=-1).astype(np.uint8))
    return write_mp4(path, np.stack(frames), fps=fps)


def scene_files(folder: Path, names: tuple[str, ...] = ("cam0", "cam1"), **video: int) -> dict[str, Path]:
    """transforms.json plus one video per camera, named by camera."""
    folder.mkdir(parents=True, exist_ok=True)
    files = {"cameras": write_transforms(folder / "transforms.json", list(names))}
    for name in names:
        files[name] = write_video(folder / f"{name}.mp4", **video)
    return files


def upload_parts(files: dict[str, Path]) -> list[tuple[str, tuple[str, bytes, str]]]:
    """Multipart parts for POST /v1/scenes from `scene_files`' result."""
    parts = [("cameras", (files["cameras"].name, files["cameras"].read_bytes(), "application/json"))]
    for name, path in files.items():
        if name != "cameras":
            parts.append(("video", (path.name, path.read_bytes(), "video/mp4")))
    return parts


def keyed_client(tmp_path: Path, owner: str = "alice") -> Iterator[tuple[object, dict[str, str]]]:
    """An app on a fresh SQLite file with a recording queue, and the Bearer header of a key for
    `owner` (for tests that need one user and nothing else of the service)."""
    from fastapi.testclient import TestClient

    from api.app import create_app
    from api.auth import create_key
    from service.database import session_scope
    from service.settings import Settings

    settings = Settings(data_dir=tmp_path / "data", database_url=sqlite_url(tmp_path))
    with TestClient(create_app(settings, queue=RecordingQueue())) as client:
        with session_scope(client.app.state.sessionmaker) as session:
            auth = {"Authorization": f"Bearer {create_key(session, owner)}"}
        yield client, auth
        client.app.state.engine.dispose()


# -- test doubles -----------------------------------------------------------------------------------

class RecordingQueue:
    """A JobQueue that records what the API sends (for tests of the API's own logic). Its owner
    share is unbounded unless a test sets one (service.queue's turns are tested with one)."""

    def __init__(self, fail: bool = False, owner_share: int = 1_000_000) -> None:
        self.sent: list[tuple[str, str]] = []
        self.fail = fail
        self.owner_share = owner_share

    def enqueue(self, job_id: str, job_type: str) -> str:
        from service.queue import QueueUnavailable

        if self.fail:
            raise QueueUnavailable("broker down (test)")
        self.sent.append((job_id, job_type))
        return f"task-{len(self.sent)}"

    def ping(self) -> None:
        from service.queue import QueueUnavailable

        if self.fail:
            raise QueueUnavailable("broker down (test)")


class Receiver:
    """A webhook receiver on loopback: answers each POST with the next status of `statuses` (then
    200) and records what arrived, as (lower-cased headers, body)."""

    def __init__(self, statuses: list[int]) -> None:
        from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

        self.statuses, self.received = statuses, []
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:  # noqa: N802 - http.server's name
                body = self.rfile.read(int(self.headers["content-length"]))
                receiver.received.append(({k.lower(): v for k, v in self.headers.items()}, body))
                self.send_response(receiver.statuses.pop(0) if receiver.statuses else 200)
                self.end_headers()

            def log_message(self, *args: object) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_port}/hook"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def states(self, count: int, timeout: float = 10.0) -> dict[str, dict]:
        """The payloads of the first `count` deliveries by job id, once that many arrived (each
        webhook is sent on a thread of its own)."""
        deadline = time.monotonic() + timeout
        while len(self.received) < count and time.monotonic() < deadline:
            time.sleep(0.05)
        assert len(self.received) >= count, f"{len(self.received)} of {count} webhooks arrived"
        payloads = [json.loads(body) for _, body in self.received]
        return {payload["id"]: payload for payload in payloads}


@contextmanager
def webhook_receiver(statuses: list[int] | None = None) -> Iterator[Receiver]:
    receiver = Receiver(list(statuses or []))
    try:
        yield receiver
    finally:
        receiver.server.shutdown()
        receiver.server.server_close()


class SimulatedCrash(BaseException):
    """Stands for a worker killed mid-job: not an Exception, so nothing in the executor handles it."""


def fake_job(inputs, n_frames: int | None = None):  # type: ignore[no-untyped-def]
    """A test-double runner with the contract of fluidcore's: one state file per frame in the run
    folder plus a manifest, resume from the frames already there, should_cancel between frames,
    progress per frame; then one MP4 per camera and an orbit video.

    Like `fluidcore.runs.Run`, its manifest names the parent run relative to the run folder, and
    resuming refuses a folder whose manifest names another parent. It appends each frame it
    computes to `<work dir>/computed-<job id>.txt` (outside the job's folder, which the worker
    removes when the job ends), so tests can tell a resumed run from a restarted one.
    `params["crash_after"]` raises SimulatedCrash after that many frames; FAKE_FRAME_SECONDS slows
    each frame down.
    """
    import os
    import time

    from fluidcore.jobs import Cancelled

    params = inputs.params
    if n_frames is None:
        frames = params.get("frames")
        n_frames = int(frames) if isinstance(frames, int) else (frames[1] - frames[0] if frames else 4)
    states = inputs.run_dir / "states"
    states.mkdir(parents=True, exist_ok=True)
    computed = inputs.run_dir.parents[3] / f"computed-{inputs.job_id}.txt"  # run_dir = WORK/jobs/ID/runs/ID
    parent = os.path.relpath(inputs.parent_run, inputs.run_dir) if inputs.parent_run else None
    manifest_path = inputs.run_dir / "manifest.json"
    if manifest_path.exists() and json.loads(manifest_path.read_text())["parent"] != parent:
        raise ValueError(f"out: {inputs.run_dir} already holds a run with another parent")
    crash_after = params.get("crash_after")
    done = 0
    for t in range(n_frames):
        state = states / f"frame_{t:06d}.npz"
        if state.exists():
            continue
        if inputs.should_cancel():
            raise Cancelled(f"cancelled before frame {t}")
        time.sleep(float(os.environ.get("FAKE_FRAME_SECONDS", "0")))
        np.savez(state, positions=np.full((3, 3), t, dtype=np.float32))
        manifest = {"kind": inputs.job_type, "frames": [{"t": i} for i in range(t + 1)], "parent": parent}
        manifest_path.write_text(json.dumps(manifest))
        with computed.open("a") as log:
            log.write(f"{t}\n")
        inputs.progress((t + 1) / n_frames, "fit")
        done += 1
        if crash_after is not None and done >= crash_after:
            raise SimulatedCrash
    from fluidcore.video import write_mp4

    cameras = sorted(inputs.videos) if inputs.videos else ["cam0"]
    clip = np.zeros((n_frames, 16, 16, 3), dtype=np.uint8)
    return [write_mp4(inputs.render_dir / f"{name}.mp4", clip) for name in [*cameras, "orbit"]]


def fake_render(inputs):  # type: ignore[no-untyped-def]
    """The test double of a render job's runner: the video asked for as a 2-frame black clip,
    progress per frame, should_cancel between frames."""
    from fluidcore.jobs import Cancelled
    from fluidcore.names import safe_join
    from fluidcore.video import write_mp4

    for t in range(2):
        if inputs.should_cancel():
            raise Cancelled(f"cancelled before frame {t}")
        inputs.progress((t + 1) / 2, "render")
    video = safe_join(inputs.render_dir, f"{inputs.params['video']}.mp4")
    return [write_mp4(video, np.zeros((2, 16, 16, 3), dtype=np.uint8))]


def fake_bundle(inputs):  # type: ignore[no-untyped-def]
    """The test double of a bundle job's runner: the zip its parameters name (holding only its
    bundle.json), progress per frame, should_cancel between frames."""
    import zipfile

    from fluidcore.jobs import Cancelled
    from fluidcore.spec.jobs import BundleParams
    from service.bundles import params_plan

    plan = params_plan(BundleParams.model_validate(inputs.params))
    frames = range(*plan.frames)
    for done, t in enumerate(frames, start=1):
        if inputs.should_cancel():
            raise Cancelled(f"cancelled before frame {t}")
        inputs.progress(done / len(frames), "bundle")
    path = inputs.render_dir / plan.name
    path.parent.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(path, "w") as bundle:
        bundle.writestr("bundle.json", json.dumps({"format": plan.fmt, "frames": list(plan.frames)}))
    return [path]


FAKE_RUNNERS = {
    **{job_type: fake_job for job_type in ("reconstruct", "predict", "interact", "resimulate")},
    "render": fake_render,
    "bundle": fake_bundle,
}


def store_run(storage, job_id: str, positions: dict[int, np.ndarray] | None = None, source_estimate=None,  # noqa: ANN001 - Storage
              air=None, losses: dict[int, dict[str, float]] | None = None) -> None:  # noqa: ANN001 - SavedAir
    """What a worker leaves in storage: a run folder written by fluidcore.runs (scene box 1 unit
    wide, source at height 0.1), with `positions[t]` (P, 3) as frame t's particles, the last one
    dead; consecutive frames, or none; `source_estimate` (a `SourceEstimateRecord`) as its
    settings record how the source was found, or None (a source given whole); `air` (a
    `fluidcore.runs.SavedAir`) saved with every frame; `losses[t]` frame t's loss terms in the
    manifest's frame log (none by default)."""
    import tempfile

    from fluidcore.cameras import Camera
    from fluidcore.runs import FrameState, ReconstructSettings, Run, RunKind
    from fluidcore.spec.physics import PBFConfig, Source
    from fluidcore.spec.reconstruct import get
    from fluidcore.spec.scene import Air, Scene

    positions = positions or {}
    frames = sorted(positions) or [0]
    scene = Scene((-0.5, 0.0, -0.5), (0.5, 1.0, 0.5), (0.0, 1.0, 0.0), PBFConfig(dt=1 / 30, h=0.05), Source((0.0, 0.1, 0.0), 0.05, 1),
                  Air() if air is None else Air(max(air.cells)))  # the air the frames save, recorded in the scene
    camera = Camera("cam0", 30.0, 30.0, 16.0, 12.0, 32, 24, np.eye(4))
    gaussians = {"means": np.zeros((0, 3)), "log_scales": np.zeros((0, 3)), "quats": np.zeros((0, 4)),
                 "opacity_logits": np.zeros(0), "colors": np.zeros((0, 1))}
    with tempfile.TemporaryDirectory(prefix="fluidnexus-stored-run-") as tmp:
        run = Run.create(Path(tmp) / "run", kind=RunKind.RECONSTRUCT, cameras={"cam0": camera}, input_views=["cam0"],
                         frame_range=(frames[0], frames[-1] + 1), fps=30.0, channels=1, background_color=[1.0], scene=scene,
                         settings=ReconstructSettings(quality=get("preview"), source_estimate=source_estimate))
        for t, points in sorted(positions.items()):
            alive = np.ones(len(points), bool)
            alive[-1] = False
            run.write_frame(t, FrameState(points, np.zeros_like(points), alive, t / 30, gaussians, air=air), (losses or {}).get(t, {}), 0.0)
        for path in sorted(run.path.rglob("*")):
            if path.is_file():
                storage.put_bytes(f"jobs/{job_id}/run/{path.relative_to(run.path).as_posix()}", path.read_bytes())


# -- `fluidnexus serve` as a real process (end to end and browser tests) ------------------------------

CLI = [sys.executable, "-c", "from fluidnexus.cli import main; main()"]


FLUIDNEXUS = Path(sys.executable).with_name("fluidnexus")


def start_serve(data_dir: Path, *extra: str, env: dict[str, str] | None = None) -> tuple[subprocess.Popen[str], str]:
    """`fluidnexus serve` on a free loopback port (`extra`: its options, `env`: FLUIDNEXUS_* settings),
    once `/healthz` answers: the process (its output piped) and its base URL. The caller stops it."""
    port = free_port()
    env = {**os.environ, "FLUIDNEXUS_WORKER_TORCH_THREADS": "1", **(env or {})}
    process = subprocess.Popen(
        [FLUIDNEXUS, "serve", "--host", "127.0.0.1", "--port", str(port), "--data-dir", str(data_dir), *extra],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    base = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 90
    while time.monotonic() < deadline and process.poll() is None:
        try:
            if httpx.get(f"{base}/healthz", timeout=1).status_code == 200:
                return process, base
        except httpx.TransportError:
            time.sleep(0.3)
    process.kill()
    raise AssertionError(f"serve did not come up: {process.communicate()[0][-3000:]}")


class Server:
    def __init__(self, data_dir: Path) -> None:
        self.data_dir = data_dir
        self.port = free_port()
        env = {**os.environ, "FLUIDNEXUS_WORKER_TORCH_THREADS": "1", "OMP_NUM_THREADS": "1"}
        env.pop("FLUIDNEXUS_DATA_DIR", None)
        self.log = (data_dir.parent / "serve.log").open("wb")
        self.process = subprocess.Popen(
            [*CLI, "serve", "--host", "127.0.0.1", "--port", str(self.port), "--data-dir", str(data_dir)],
            cwd=ROOT, env=env, stdout=self.log, stderr=subprocess.STDOUT, start_new_session=True,
        )
        self.client = httpx.Client(base_url=f"http://127.0.0.1:{self.port}", timeout=30)
        self._wait_ready()
        key = subprocess.run([*CLI, "keys", "create", "--owner", "e2e", "--data-dir", str(data_dir)],
                             cwd=ROOT, capture_output=True, text=True, check=True).stdout.strip()
        self.client.headers["Authorization"] = f"Bearer {key}"

    def _wait_ready(self) -> None:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            assert self.process.poll() is None, self.output()
            try:
                if self.client.get("/readyz").status_code == 200:
                    return
            except httpx.TransportError:
                pass
            time.sleep(0.3)
        raise AssertionError(f"server not ready in 60 s:\n{self.output()}")

    def output(self) -> str:
        self.log.flush()
        return (self.data_dir.parent / "serve.log").read_text(errors="replace")[-4000:]

    def wait_job(self, job_id: str, timeout: float) -> dict:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            job = self.client.get(f"/v1/jobs/{job_id}").json()
            if job["state"] in ("succeeded", "failed", "cancelled"):
                return job
            time.sleep(0.5)
        raise AssertionError(f"job {job_id} not finished in {timeout} s: {job}\n{self.output()}")

    def worker_pids(self) -> list[int]:
        """The embedded worker: the server's child processes and their process groups (pool children)."""
        processes = {}
        for entry in Path("/proc").iterdir():
            if not entry.name.isdigit():
                continue
            try:
                stat = (entry / "stat").read_text()
            except (FileNotFoundError, ProcessLookupError, PermissionError):  # the process just ended
                continue
            fields = stat.rsplit(")", 1)[1].split()  # after "pid (name)": state, ppid, pgrp, ...
            processes[int(entry.name)] = (int(fields[1]), int(fields[2]))
        children = {pid for pid, (ppid, _) in processes.items() if ppid == self.process.pid}
        return sorted(pid for pid, (_, group) in processes.items() if pid in children or group in children)

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)  # what systemd and docker send
            try:
                self.process.wait(40)
            except subprocess.TimeoutExpired:
                os.killpg(self.process.pid, signal.SIGKILL)
                self.process.wait()
        self.client.close()
        self.log.close()
