"""End to end through `fluidnexus serve` (embedded mode: SQLite, local storage, filesystem broker,
embedded Celery worker process): create a key with the CLI, upload a tiny synthetic scene over
HTTP, reconstruct it, ask what a wind would do (and predict on from there), and download a
playable MP4.

Nothing is faked: the worker runs fluidcore's real pipeline (preview quality, a 2-frame
24x32 scene, one torch thread: about 20 s on a 2-core CPU). The test also checks the
process wiring: the worker starts with the server and stops with it.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.support.service import Server
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

    published = server.client.get(f"/v1/jobs/{job['id']}/artifacts").json()["items"]
    assert sorted(a["camera"] for a in published if a["kind"] == "video") == sorted(scene["videos"])  # its input views
    assert "orbit" not in {a["kind"] for a in published}  # and the orbit on request
    asked = server.client.post(f"/v1/jobs/{interacted['id']}/videos/orbit")  # a what-if's videos: on request
    assert asked.status_code == 202, asked.text
    rendered = server.wait_job(asked.json()["render_job"]["id"], timeout=600)
    assert rendered["state"] == "succeeded" and "render" in rendered["timings"]["stages"], rendered
    served = server.client.post(f"/v1/jobs/{interacted['id']}/videos/orbit")
    assert served.status_code == 200 and served.json()["render_job"] is None  # stored: no second render
    artifacts = server.client.get(f"/v1/jobs/{interacted['id']}/artifacts").json()["items"]
    kinds = {a["kind"] for a in artifacts}
    assert {"orbit", "manifest", "state", "export"} <= kinds
    video = next(a for a in artifacts if a["kind"] == "orbit")
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
