"""Load on a live `fluidnexus serve` over loopback: pollers, listers and uploads at once (issue 16).

    python bench/load.py [--backend sqlite|postgres] [--seconds 60] [--clients 200] [--uploads 20]
                         [--scene phone|dev|tiny] [--computing] [--json]

Starts `fluidnexus serve --no-worker` on 127.0.0.1 with a fresh data folder (`--backend
postgres`: a fresh database on the local PostgreSQL and a key prefix of its own on the local
Redis, both removed afterwards), creates a key, a scene and one job, then for `--seconds` runs
  - `--clients` closed-loop clients, half polling the job (GET /v1/jobs/{id}), half listing
    (GET /v1/jobs/{id}/artifacts and GET /v1/jobs, alternately);
  - `--uploads` clients uploading a scene (POST /v1/scenes) again and again: with `--scene dev`
    (default) the dev scene's transforms.json and its 150-frame 270x480 input view
    (../shared/devdata/phiflow_D/D/videos/view_02.mp4, 95 kB), or a synthesized clip of the same
    size and length when ../shared is absent; `--scene tiny` two 6-frame 32x24 clips;
  - one health probe (GET /healthz, then GET /readyz) every 0.25 s, on a thread of its own;
  - with `--computing`, the same load twice on one server with its embedded worker (issue 49):
    first a quiet baseline, polling a job that was cancelled before it computed (the worker
    idle), then polling a job the worker reconstructs meanwhile (issue 20), so the GET p99 with
    and without a computing job come from one run on one machine state; both are reported, each
    with the load average after it.
Every request has a total `--timeout` (10 s). Reported per route: requests/s, p50/p99/max latency,
answers by class (2xx/4xx/5xx), timeouts and connection errors; and for the uploads, how many were
answered, refused, abandoned by their client, and stored although their client had left. Everything is bounded: the
clients stop at the deadline, the server is stopped after, and nothing but 127.0.0.1 is
contacted. The server's threads are not limited: it gets what the machine has (2 cores here,
shared with this client).
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
import uuid
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import typer

if __package__ in (None, ""):  # `python bench/load.py`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fluidnexus.reporting import UserError, echo_json, user_errors  # noqa: E402

HOST = "127.0.0.1"  # loopback only: this benchmark never targets another address
PG_ADMIN_URL = "postgresql+psycopg://postgres@127.0.0.1:5432/postgres"
REDIS_URL = "redis://127.0.0.1:6379/0"
HEALTH_PERIOD_S = 0.25
BUSY = 429  # the answer to an upload that found no checking place in time (with Retry-After)
NO_WORKER = "503_no_worker"  # /readyz of a server run --no-worker: every check ok but the worker's
STARTUP_TIMEOUT_S = 60.0
DEV_SCENE = Path(__file__).resolve().parents[2] / "shared" / "devdata" / "phiflow_D" / "D"
DEV_VIEW = "view_02"  # the dev scene's input view: 150 frames of 270x480


@dataclass
class Server:
    base_url: str
    key: str
    job_id: str
    scene: dict[str, tuple[str, bytes, str]]  # multipart parts: field -> (filename, content, type)
    backend: str
    pid: int  # the server's process
    worker: bool = False  # without one, /readyz answers 503 "no worker" by design (NO_WORKER)
    plume_id: str | None = None  # with the worker: the scene a computing job reconstructs (`computing_job`)


@dataclass
class RouteStats:
    latencies: list[float] = field(default_factory=list)
    classes: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    examples: list[str] = field(default_factory=list)  # the first few failures, for diagnosis
    busy: int = 0  # the 4xx that were BUSY

    def record(self, outcome: str, seconds: float, failure: str | None = None, status: int | None = None) -> None:
        self.classes[outcome] += 1
        self.busy += status == BUSY
        if outcome in ("2xx", "4xx", "5xx", NO_WORKER):
            self.latencies.append(seconds)
        if failure is not None and len(self.examples) < 3:
            self.examples.append(failure)

    def summary(self, seconds: float) -> dict[str, Any]:
        ordered = sorted(self.latencies)

        def quantile(q: float) -> float | None:
            return ordered[min(len(ordered) - 1, int(q * len(ordered)))] if ordered else None

        return {
            "requests": sum(self.classes.values()),
            "requests_per_s": len(ordered) / seconds,
            "p50_s": quantile(0.50),
            "p99_s": quantile(0.99),
            "max_s": ordered[-1] if ordered else None,
            **{name: self.classes.get(name, 0) for name in ("2xx", "4xx", "5xx", "timeout", "error", NO_WORKER)},
            "busy_429": self.busy,
            "failures": self.examples,
        }


def tiny_scene(folder: Path) -> dict[str, tuple[str, bytes, str]]:
    """Two 32x24 cameras with a six-frame video each: a complete, valid upload of a few kB."""
    import numpy as np

    from fluidcore.video import write_mp4

    frames = []
    for name, x in (("left", -0.5), ("right", 0.5)):
        frames.append({
            "camera": name, "fl_x": 38.4, "fl_y": 38.4, "cx": 16, "cy": 12, "w": 32, "h": 24,
            "transform_matrix": [[1, 0, 0, x], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]],
        })
        clip = np.full((6, 24, 32, 3), 40, dtype=np.uint8)
        clip[:, 8:16, 10:20] = 200
        write_mp4(folder / f"{name}.mp4", clip, fps=30.0)
    parts = {"cameras": ("transforms.json", json.dumps({"frames": frames}).encode(), "application/json")}
    for name in ("left", "right"):
        parts[name] = (f"{name}.mp4", (folder / f"{name}.mp4").read_bytes(), "video/mp4")
    return parts


def camera_json(name: str, width: int, height: int) -> bytes:
    """A transforms.json of one camera named `name` of that size, looking at the origin."""
    frame = {
        "camera": name, "fl_x": 1.2 * width, "fl_y": 1.2 * width, "cx": width / 2, "cy": height / 2,
        "w": width, "h": height, "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]],
    }
    return json.dumps({"frames": [frame]}).encode()


def dev_scene(folder: Path) -> dict[str, tuple[str, bytes, str]]:
    """The upload a user of the dev scene makes: its transforms.json and its input view; without
    ../shared, one camera and a synthesized 150-frame 270x480 clip of a rising noisy plume (about
    the same bytes and decoding cost)."""
    video = DEV_SCENE / "videos" / f"{DEV_VIEW}.mp4"
    if video.is_file():
        cameras = (DEV_SCENE / "transforms.json").read_bytes()
        return {"cameras": ("transforms.json", cameras, "application/json"),
                DEV_VIEW: (video.name, video.read_bytes(), "video/mp4")}
    import numpy as np

    from fluidcore.video import write_mp4

    yy, xx = np.mgrid[0:480, 0:270]
    grain = np.random.default_rng(0).integers(0, 6, (480, 270), dtype=np.uint8)  # a fixed sensor pattern
    frames = np.stack([
        (np.exp(-((xx - 135 - 20 * np.sin(yy / 40 + t / 10)) ** 2 / 900 + (yy - 400 + 2 * t) ** 2 / 4000)) * 200)
        .astype(np.uint8) + grain
        for t in range(150)
    ])
    path = write_mp4(folder / f"{DEV_VIEW}.mp4", np.repeat(frames[..., None], 3, axis=-1))
    return {"cameras": ("transforms.json", camera_json(DEV_VIEW, 270, 480), "application/json"),
            DEV_VIEW: (path.name, path.read_bytes(), "video/mp4")}


def phone_scene(folder: Path) -> dict[str, tuple[str, bytes, str]]:
    """What a user films: one portrait 1080x1920 phone clip, 2 s at 30 fps, a soft plume over a
    fixed sensor pattern with a little fresh noise per frame (2.6 MB, the size of issue 36's
    clip), and its one-camera transforms.json."""
    import numpy as np

    from fluidcore.video import write_mp4

    height, width, frames = 1920, 1080, 60
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    rng = np.random.default_rng(0)
    pattern = rng.normal(0.0, 4.0, (height, width)).astype(np.float32)
    video = np.empty((frames, height, width, 3), np.uint8)
    for t in range(frames):
        plume = np.exp(-((xx - 540 - 80 * np.sin(yy / 160 + t / 10)) ** 2 / 60000 + (yy - 1600 + 16 * t) ** 2 / 64000)) * 180
        video[t] = np.clip(40 + plume + pattern + rng.normal(0.0, 1.5, (height, width)), 0, 255).astype(np.uint8)[..., None]
    path = write_mp4(folder / "phone.mp4", video)
    return {"cameras": ("transforms.json", camera_json("phone", width, height), "application/json"),
            "phone": (path.name, path.read_bytes(), "video/mp4")}


def plume_scene(folder: Path) -> dict[str, tuple[str, bytes, str]]:
    """A synthetic plume (fluidcore.synth) that reconstructs: the job `--computing` keeps the worker
    busy with (120 frames of 2 views at 48x64: 30 finished within a 60 s load on a quiet 2-core machine)."""
    from fluidcore import synth

    transforms = synth.write(synth.generate(synth.SynthSpec(frames=120, width=48, height=64, views=2)), folder / "plume")
    parts = {"cameras": ("transforms.json", transforms.read_bytes(), "application/json")}
    for path in sorted((transforms.parent / "videos").glob("*.mp4")):
        parts[path.stem] = (path.name, path.read_bytes(), "video/mp4")
    return parts


SCENES = {"phone": phone_scene, "dev": dev_scene, "tiny": tiny_scene}


def multipart(scene: dict[str, tuple[str, bytes, str]]) -> list[tuple[str, tuple[str, bytes, str]]]:
    return [("cameras" if name == "cameras" else "video", part) for name, part in scene.items()]


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind((HOST, 0))
        return sock.getsockname()[1]


@contextmanager
def backend_env(backend: str, data_dir: Path) -> Iterator[dict[str, str]]:
    """FLUIDNEXUS_* variables for the backend; PostgreSQL database and Redis keys removed afterwards."""
    # Its clients stand for many users under one key: one owner's limits (service.quotas, the
    # uploads one owner may have checked at once) would refuse its uploads and measure those instead.
    env = {"FLUIDNEXUS_DATA_DIR": str(data_dir), "FLUIDNEXUS_MAX_SCENES_PER_OWNER": str(10**9),
           "FLUIDNEXUS_MAX_UPLOADS_PER_OWNER": str(10**6)}
    if backend == "sqlite":
        yield env
        return
    from sqlalchemy import create_engine, text

    name = f"fnx_load_{uuid.uuid4().hex[:10]}"
    prefix = f"{name}:"
    admin = create_engine(PG_ADMIN_URL, isolation_level="AUTOCOMMIT")
    try:
        with admin.connect() as connection:
            connection.execute(text(f'CREATE DATABASE "{name}"'))
    except Exception as exc:
        raise UserError(f"--backend postgres needs PostgreSQL on 127.0.0.1:5432 ({exc.__class__.__name__})") from None
    try:
        yield {
            **env,
            "FLUIDNEXUS_DATABASE_URL": f"postgresql+psycopg://postgres@127.0.0.1:5432/{name}",
            "FLUIDNEXUS_BROKER_URL": REDIS_URL,
            "FLUIDNEXUS_BROKER_KEY_PREFIX": prefix,
        }
    finally:
        with admin.connect() as connection:
            connection.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()
        import redis

        client = redis.Redis.from_url(REDIS_URL)
        for key in client.scan_iter(f"{prefix}*"):
            client.delete(key)


@contextmanager
def live_server(
    backend: str, log: Path | None = None, worker: bool = False, scene: str = "tiny"
) -> Iterator[Server]:
    """`fluidnexus serve --no-worker` on a free loopback port with one key, one scene (`dev_scene`
    or `tiny_scene`) and one job (`worker`: with its embedded worker, which computes the job while
    the load runs)."""
    import httpx

    fluidnexus = Path(sys.executable).with_name("fluidnexus")
    with tempfile.TemporaryDirectory(prefix="fluidnexus-load-") as tmp, backend_env(backend, Path(tmp) / "data") as env:
        env = {**os.environ, **env}
        key = subprocess.run([fluidnexus, "keys", "create", "--owner", "load"], env=env, check=True,
                             capture_output=True, text=True).stdout.strip()
        port = free_port()
        base_url = f"http://{HOST}:{port}"
        out = (log or Path(tmp) / "server.log").open("w")
        serve = [fluidnexus, "serve", "--host", HOST, "--port", str(port), *([] if worker else ["--no-worker"])]
        process = subprocess.Popen(serve, env=env, stdout=out, stderr=subprocess.STDOUT)
        try:
            _wait_healthy(base_url, process)
            parts = SCENES[scene](Path(tmp))
            headers = {"Authorization": f"Bearer {key}"}
            with httpx.Client(base_url=base_url, headers=headers, timeout=30) as client:
                created = client.post("/v1/scenes", files=multipart(plume_scene(Path(tmp)) if worker else parts))
                created.raise_for_status()
                job = client.post("/v1/jobs", json={"type": "reconstruct", "scene_id": created.json()["id"]})
                job.raise_for_status()
                if worker:  # the quiet baseline polls a job that computes nothing, the worker idle
                    client.post(f"/v1/jobs/{job.json()['id']}/cancel").raise_for_status()
                    _wait_for_state(client, job.json()["id"], ("cancelled",), "the first job to be cancelled")
            plume = created.json()["id"] if worker else None
            yield Server(base_url, key, job.json()["id"], parts, backend, process.pid, worker, plume)
        finally:
            process.send_signal(signal.SIGINT)
            try:
                process.wait(30)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
            out.close()


def computing_job(server: Server) -> Server:
    """`server` polling a new reconstruction of its plume, once the embedded worker runs it
    (the load must start with the job computing)."""
    import httpx

    with httpx.Client(base_url=server.base_url, headers={"Authorization": f"Bearer {server.key}"}, timeout=30) as client:
        job = client.post("/v1/jobs", json={"type": "reconstruct", "scene_id": server.plume_id})
        job.raise_for_status()
        _wait_for_state(client, job.json()["id"], ("running",), "the embedded worker to start the job")
    return replace(server, job_id=job.json()["id"])


def _wait_for_state(client: Any, job_id: str, states: tuple[str, ...], what: str) -> None:
    deadline = time.monotonic() + STARTUP_TIMEOUT_S
    while client.get(f"/v1/jobs/{job_id}").json()["state"] not in states:
        if time.monotonic() > deadline:
            raise UserError(f"timed out after {STARTUP_TIMEOUT_S:g} s waiting for {what}")
        time.sleep(0.2)


def _wait_healthy(base_url: str, process: subprocess.Popen[bytes]) -> None:
    import httpx

    deadline = time.monotonic() + STARTUP_TIMEOUT_S
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise UserError(f"fluidnexus serve exited with {process.returncode} before answering")
        try:
            if httpx.get(f"{base_url}/healthz", timeout=1).status_code == 200:
                return
        except httpx.TransportError:
            pass
        time.sleep(0.2)
    raise UserError(f"fluidnexus serve did not answer within {STARTUP_TIMEOUT_S:g} s")


class Connection:
    """One keep-alive HTTP/1.1 connection with requests prepared as bytes.

    A deliberately small client: httpx spends several milliseconds of CPU per request, and with
    220 clients on a 2-core machine the latencies it measured were mostly its own. Every answer of
    this API carries Content-Length, so reading one is a status line, headers and that many bytes.
    """

    def __init__(self, port: int) -> None:
        self.port = port
        self.streams: tuple[asyncio.StreamReader, asyncio.StreamWriter] | None = None

    async def send(self, request: bytes) -> tuple[int, bytes]:
        if self.streams is None:
            self.streams = await asyncio.open_connection(HOST, self.port)
        reader, writer = self.streams
        writer.write(request)
        await writer.drain()
        status = int((await reader.readline()).split(b" ", 2)[1])
        length = 0
        while (line := await reader.readline()) not in (b"\r\n", b""):
            name, _, value = line.partition(b":")
            if name.strip().lower() == b"content-length":
                length = int(value)
        return status, await reader.readexactly(length)

    def close(self) -> None:
        if self.streams is not None:
            self.streams[1].close()
            self.streams = None


def prepared(method: str, path: str, headers: dict[str, str], body: bytes = b"") -> bytes:
    lines = [f"{method} {path} HTTP/1.1", f"Host: {HOST}", f"Content-Length: {len(body)}"]
    lines += [f"{name}: {value}" for name, value in headers.items()]
    return ("\r\n".join(lines) + "\r\n\r\n").encode() + body


def multipart_body(scene: dict[str, tuple[str, bytes, str]], boundary: str) -> bytes:
    body = b""
    for name, (filename, content, content_type) in scene.items():
        field_name = "cameras" if name == "cameras" else "video"
        body += (f"--{boundary}\r\nContent-Disposition: form-data; name=\"{field_name}\"; filename=\"{filename}\"\r\n"
                 f"Content-Type: {content_type}\r\n\r\n").encode() + content + b"\r\n"
    return body + f"--{boundary}--\r\n".encode()


async def _timed(connection: Connection, stats: RouteStats, request: bytes, timeout: float) -> None:
    """One request with a total `timeout`; a timed-out or broken connection is replaced."""
    start = time.perf_counter()
    failure, status = None, None
    try:
        status, body = await asyncio.wait_for(connection.send(request), timeout)
        outcome = f"{status // 100}xx"
        if status >= 400:
            failure = f"{status} {body[:200].decode(errors='replace')}"
    except TimeoutError:
        outcome, failure = "timeout", f"no answer within {timeout:g} s"
        connection.close()
    except (OSError, asyncio.IncompleteReadError, ValueError, IndexError) as exc:
        outcome, failure = "error", repr(exc)
        connection.close()
    stats.record(outcome, time.perf_counter() - start, failure, status)


async def _load(server: Server, seconds: float, clients: int, uploads: int, timeout: float) -> dict[str, Any]:
    import httpx

    stats: dict[str, RouteStats] = defaultdict(RouteStats)
    deadline = time.monotonic() + seconds
    port = int(server.base_url.rsplit(":", 1)[1])
    auth = {"Authorization": f"Bearer {server.key}"}
    job = f"/v1/jobs/{server.job_id}"
    boundary = uuid.uuid4().hex
    requests = {
        "GET /v1/jobs/{id}": prepared("GET", job, auth),
        "GET /v1/jobs/{id}/artifacts": prepared("GET", f"{job}/artifacts", auth),
        "GET /v1/jobs": prepared("GET", "/v1/jobs?limit=20", auth),
        "POST /v1/scenes": prepared(
            "POST", "/v1/scenes", {**auth, "Content-Type": f"multipart/form-data; boundary={boundary}"},
            multipart_body(server.scene, boundary),
        ),
    }

    async def client(routes: tuple[str, ...]) -> None:
        connection = Connection(port)
        try:
            while time.monotonic() < deadline:
                for route in routes:
                    await _timed(connection, stats[route], requests[route], timeout)
        finally:
            connection.close()

    def health() -> None:
        """On a thread with its own client, so its timings are the server's, not this event loop's."""
        with httpx.Client(base_url=server.base_url, timeout=timeout) as probe:
            while time.monotonic() < deadline:
                for path in ("/healthz", "/readyz"):
                    start = time.perf_counter()
                    try:
                        response = probe.get(path)
                        outcome = f"{response.status_code // 100}xx"
                        failure = f"{response.status_code} {response.text[:200]}" if response.status_code >= 400 else None
                        if path == "/readyz" and not server.worker and _only_the_worker_missing(response):
                            outcome, failure = NO_WORKER, None
                    except httpx.TransportError as exc:
                        outcome, failure = "error", repr(exc)
                    stats[f"GET {path}"].record(outcome, time.perf_counter() - start, failure)
                time.sleep(HEALTH_PERIOD_S)

    started = time.monotonic()
    tasks = [client(("GET /v1/jobs/{id}",)) for _ in range(clients - clients // 2)]
    tasks += [client(("GET /v1/jobs/{id}/artifacts", "GET /v1/jobs")) for _ in range(clients // 2)]
    tasks += [client(("POST /v1/scenes",)) for _ in range(uploads)]
    await asyncio.gather(asyncio.to_thread(health), *tasks)
    elapsed = time.monotonic() - started
    routes = {route: route_stats.summary(elapsed) for route, route_stats in sorted(stats.items())}
    return {
        "backend": server.backend,
        "seconds": elapsed,
        "clients": clients,
        "uploads": uploads,
        "upload_bytes": sum(len(part[1]) for part in server.scene.values()),
        "timeout_s": timeout,
        "routes": routes,
        "total_5xx": sum(r["5xx"] for r in routes.values()),
        "total_timeouts": sum(r["timeout"] for r in routes.values()),
        "total_errors": sum(r["error"] for r in routes.values()),
        "health_max_s": max(routes[r]["max_s"] or 0.0 for r in ("GET /healthz", "GET /readyz") if r in routes),
    }


def _only_the_worker_missing(response: Any) -> bool:
    checks = response.json().get("checks", {}) if response.status_code == 503 else {}
    return checks.get("worker", "ok") != "ok" and all(v == "ok" for k, v in checks.items() if k != "worker")


SETTLE_S = 60.0  # how long the uploads a client gave up on may take to finish (or not) after the load


def scene_count(server: Server) -> int:
    """How many scenes the server holds (its key's)."""
    import httpx

    answer = httpx.get(f"{server.base_url}/v1/scenes", params={"limit": 1}, headers={"Authorization": f"Bearer {server.key}"},
                       timeout=30)
    return int(answer.json()["total"])


def _uploads_after(server: Server, uploads: dict[str, Any] | None, before: int) -> dict[str, int]:
    """What became of the uploads: answered (2xx), told busy (429 with Retry-After: no checking
    place free in time), refused (another 4xx: a limit), failed (5xx), abandoned
    (the client timed out), and how many scenes were stored for clients that had given up, counted
    once the server's scene count stops changing (`before`: the scenes it held before the load)."""
    answered = 0 if uploads is None else uploads["2xx"]
    counts: list[int] = []
    deadline = time.monotonic() + SETTLE_S
    while time.monotonic() < deadline and not (len(counts) >= 3 and len(set(counts[-3:])) == 1):  # 6 s unchanged
        counts.append(scene_count(server))
        time.sleep(2.0)
    previous = counts[-1] if counts else before
    return {
        "answered": answered,
        "busy_429": 0 if uploads is None else uploads["busy_429"],
        "refused_4xx": 0 if uploads is None else uploads["4xx"] - uploads["busy_429"],
        "failed_5xx": 0 if uploads is None else uploads["5xx"],
        "abandoned": 0 if uploads is None else uploads["timeout"] + uploads["error"],
        "stored_after_abandon": max(0, previous - before - answered),
    }


def run_load(server: Server, seconds: float, clients: int, uploads: int, timeout: float) -> dict[str, Any]:
    """The load phase against a `live_server`; returns the JSON result, with the job's state at the end
    (with `--computing`, "running" shows the worker computed through the whole load)."""
    import httpx

    before, worker_cpu = scene_count(server), worker_cpu_seconds(server.pid)
    result = asyncio.run(_load(server, seconds, clients, uploads, timeout))
    result["load_average"] = os.getloadavg()
    result["worker_cpu_s"] = round(worker_cpu_seconds(server.pid) - worker_cpu, 2)  # what the job got meanwhile
    result["uploads_after"] = _uploads_after(server, result["routes"].get("POST /v1/scenes"), before)
    result["cpus"] = os.cpu_count()
    job = httpx.get(f"{server.base_url}/v1/jobs/{server.job_id}", headers={"Authorization": f"Bearer {server.key}"},
                    timeout=30).json()
    result["job_after"] = {"state": job["state"], "stage": job["stage"], "progress": job["progress"]}
    result["get_p99_s"] = max(route["p99_s"] or 0.0 for name, route in result["routes"].items() if name in GET_ROUTES)
    return result


def worker_cpu_seconds(server_pid: int) -> float:
    """CPU seconds used so far by the server's embedded Celery worker and its pool child (Linux
    /proc; 0 elsewhere or without a worker): whether a "computing" job got the CPU to compute."""
    ticks = os.sysconf("SC_CLK_TCK")
    children: dict[int, tuple[int, float, bool]] = {}  # pid -> (parent, CPU seconds, a Celery process)
    for entry in Path("/proc").glob("[0-9]*"):
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            children[int(entry.name)] = (int(fields[1]), (int(fields[11]) + int(fields[12])) / ticks,
                                         b"celery" in (entry / "cmdline").read_bytes())
        except (OSError, ValueError, IndexError):  # a process that just ended
            continue
    below, todo = set(), [server_pid]
    while todo:
        parent = todo.pop()
        for pid, (ppid, _, _) in children.items():
            if ppid == parent and pid not in below:
                below.add(pid)
                todo.append(pid)
    return sum(cpu for pid, (_, cpu, celery) in children.items() if pid in below and celery)


GET_ROUTES = ("GET /v1/jobs/{id}", "GET /v1/jobs/{id}/artifacts", "GET /v1/jobs")  # what clients poll


def run_with_baseline(server: Server, seconds: float, clients: int, uploads: int, timeout: float) -> dict[str, Any]:
    """`--computing`: the load against a quiet server (its worker idle), then the same load while
    the worker reconstructs the polled job; the second's result, with the first as `baseline`
    and the GET p99 (worst polled route) and slowest health answer of both side by side."""
    baseline = run_load(server, seconds, clients, uploads, timeout)
    result = run_load(computing_job(server), seconds, clients, uploads, timeout)
    result["baseline"] = baseline
    result["compared"] = {phase: {"get_p99_s": r["get_p99_s"], "health_max_s": r["health_max_s"],
                                  "get_requests_per_s": sum(r["routes"][name]["requests_per_s"] for name in GET_ROUTES),
                                  "load_average": r["load_average"], "worker_cpu_s": r["worker_cpu_s"],
                                  "job_after": r["job_after"]}
                          for phase, r in (("quiet", baseline), ("computing", result))}
    return result


def command(
    backend: str = typer.Option("sqlite", "--backend", help="sqlite (embedded) | postgres (with Redis)."),
    seconds: float = typer.Option(60.0, "--seconds", min=1.0, max=600.0, help="How long the load runs."),
    clients: int = typer.Option(200, "--clients", min=2, max=1000, help="Concurrent pollers + listers."),
    uploads: int = typer.Option(20, "--uploads", min=0, max=200, help="Concurrent uploaders."),
    timeout: float = typer.Option(10.0, "--timeout", min=0.1, help="Per-request timeout, seconds."),
    scene: str = typer.Option(
        "phone", "--scene", help="phone (a 2.6 MB 1080x1920 clip) | dev (the dev scene's 150-frame view) | tiny (6-frame 32x24 clips)."
    ),
    server_log: Path | None = typer.Option(None, "--server-log", help="Keep the server's log here."),
    json_out: bool = typer.Option(False, "--json", help="Print one JSON object on stdout."),
    computing: bool = typer.Option(
        False, "--computing", help="Serve with the embedded worker, which computes the job during the load."
    ),
) -> None:
    with user_errors():
        if backend not in ("sqlite", "postgres"):
            raise UserError(f"--backend must be sqlite or postgres, got {backend!r}")
        if scene not in SCENES:
            raise UserError(f"--scene must be one of {', '.join(SCENES)}, got {scene!r}")
        with live_server(backend, server_log, worker=computing, scene=scene) as server:
            load = run_with_baseline if computing else run_load
            result = load(server, seconds, clients, uploads, timeout)
    if json_out:
        echo_json(result)
        return
    if computing:
        _print_phase(result["baseline"], "quiet baseline (worker idle)", clients, uploads, scene, timeout)
        print()
    _print_phase(result, "job computing" if computing else backend, clients, uploads, scene, timeout)
    if computing:
        quiet, busy = result["compared"]["quiet"], result["compared"]["computing"]
        print(f"GET p99 (worst polled route): quiet {quiet['get_p99_s']:.3f} s, computing {busy['get_p99_s']:.3f} s; "
              f"slowest health answer: quiet {quiet['health_max_s']:.3f} s, computing {busy['health_max_s']:.3f} s")


def _print_phase(result: dict[str, Any], phase: str, clients: int, uploads: int, scene: str, timeout: float) -> None:
    """One phase's table: each route's rate, latencies and answers, then the uploads' fate."""
    computed = (f", job {result['job_after']['state']} at {result['job_after']['progress']:.2f} "
                f"(worker {result['worker_cpu_s']:.1f} CPU s)")
    print(f"{result['backend']}, {phase}: {clients} clients + {uploads} uploaders ({result['upload_bytes']} bytes each, "
          f"--scene {scene}) for {result['seconds']:.0f} s{computed}, timeout {timeout:g} s, "
          f"{result['cpus']} CPUs, load {result['load_average'][0]:.2f}")
    print(f"{'route':<30} {'req/s':>7} {'p50 s':>7} {'p99 s':>7} {'max s':>7} {'2xx':>6} {'4xx':>5} {'5xx':>5} {'t/o':>4} {'err':>4}")
    for route, r in result["routes"].items():
        print(f"{route:<30} {r['requests_per_s']:7.1f} {r['p50_s'] or 0:7.3f} {r['p99_s'] or 0:7.3f} {r['max_s'] or 0:7.3f} "
              f"{r['2xx']:6d} {r['4xx']:5d} {r['5xx']:5d} {r['timeout']:4d} {r['error']:4d}")
    print(f"5xx {result['total_5xx']}, timeouts {result['total_timeouts']}, connection errors {result['total_errors']}, "
          f"slowest health answer {result['health_max_s']:.3f} s")
    after = result["uploads_after"]
    print(f"uploads: {after['answered']} answered, {after['busy_429']} told busy (429), {after['refused_4xx']} refused "
          f"(other 4xx), {after['failed_5xx']} failed (5xx), "
          f"{after['abandoned']} abandoned by their client, {after['stored_after_abandon']} stored after their client left")


if __name__ == "__main__":
    from bench.registry import run_script

    run_script("load", command)
