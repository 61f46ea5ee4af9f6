"""End to end through `fluidnexus serve` (embedded mode: SQLite, local storage, filesystem broker,
embedded Celery worker process): create a key with the CLI, upload a tiny synthetic scene over
HTTP, reconstruct it, ask what a wind would do (and predict on from there), and download a
playable MP4.

Nothing is faked: the worker runs fluidcore's real pipeline (preview quality, a 2-frame
24x32 scene, one torch thread: about 20 s on a 2-core CPU). The test also checks the
process wiring: the worker starts with the server and stops with it.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from service_support import free_port

ROOT = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-c", "from fluidnexus.cli import main; main()"]


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


@pytest.fixture
def server(tmp_path: Path) -> Iterator[Server]:
    server = Server(tmp_path / "data")
    yield server
    server.stop()


def test_upload_reconstruct_interact_download(server: Server, tmp_path: Path) -> None:
    from fluidcore import synth
    from fluidcore.video import probe

    assert server.client.get("/readyz").json()["checks"] == {"database": "ok", "broker": "ok", "storage": "ok", "worker": "ok"}
    assert "/docs" in server.client.get("/").text
    workers = server.worker_pids()
    assert workers, "no embedded worker process"

    spec = synth.SynthSpec(frames=2, width=24, height=32, views=2)
    transforms = synth.write(synth.generate(spec), tmp_path / "scene")
    videos = sorted((transforms.parent / "videos").glob("*.mp4"))
    parts = [("cameras", ("transforms.json", transforms.read_bytes(), "application/json"))]
    parts += [("video", (path.name, path.read_bytes(), "video/mp4")) for path in videos]
    scene = server.client.post("/v1/scenes", files=parts, data={"name": "synthetic plume"})
    assert scene.status_code == 201, scene.text
    scene = scene.json()

    body = {"type": "reconstruct", "scene_id": scene["id"], "params": {"quality": "preview", "frames": [0, 2]}}
    job = server.client.post("/v1/jobs", json=body, headers={"Idempotency-Key": "e2e-reconstruct"}).json()
    reconstructed = server.wait_job(job["id"], timeout=900)
    assert reconstructed["state"] == "succeeded", reconstructed
    assert reconstructed["progress"] == 1.0 and "reconstruct" in reconstructed["timings"]["stages"]

    far_ball = {"center": [100.0, 0.0, 0.0], "radius": 0.05}  # checked against the real run's scene box
    body = {"type": "interact", "parent_job_id": job["id"], "params": {"frames": 2, "ball": far_ball}}
    refused = server.client.post("/v1/jobs", json=body)
    assert refused.status_code == 422 and "ball" in refused.json()["detail"], refused.text

    wind = {"direction": [1, 0, 0], "strength": 2.0}
    body = {"type": "interact", "parent_job_id": job["id"], "params": {"frames": 2, "wind": wind}}
    interact = server.client.post("/v1/jobs", json=body)
    assert interact.status_code == 202, interact.text
    interacted = server.wait_job(interact.json()["id"], timeout=600)
    assert interacted["state"] == "succeeded", interacted

    body = {"type": "predict", "parent_job_id": interacted["id"], "params": {"frames": 1}}  # a chain of runs
    chained = server.wait_job(server.client.post("/v1/jobs", json=body).json()["id"], timeout=600)
    assert chained["state"] == "succeeded", chained

    artifacts = server.client.get(f"/v1/jobs/{interacted['id']}/artifacts").json()["items"]
    kinds = {a["kind"] for a in artifacts}
    assert {"video", "orbit", "manifest", "state"} <= kinds
    video = next(a for a in artifacts if a["kind"] == "video")
    assert video["camera"] in scene["cameras"]
    download = server.client.get(video["url"])
    assert download.status_code == 200 and download.headers["content-type"] == "video/mp4"
    path = tmp_path / "download.mp4"
    path.write_bytes(download.content)
    info = probe(path)
    assert info.codec == "h264" and info.n_frames >= 2
    head = server.client.get(video["url"], headers={"Range": "bytes=0-7"})
    assert head.status_code == 206 and head.content == download.content[:8]

    server.stop()
    assert not [pid for pid in workers if Path(f"/proc/{pid}").exists()], "the worker outlived the server"
