"""The HTTP API against real databases (SQLite and PostgreSQL) and local storage, with a recording
job queue standing in for the broker (the worker has its own tests)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support.api import Service, make_service, reconstruct, upload
from service.database import session_scope
from service.models import Artifact, Job, JobState, Scene
from service.settings import Settings
from service.worker_beats import WorkerBeacon
from tests.support.service import RecordingQueue, scene_files, store_run, upload_parts, write_video

ROOT = Path(__file__).resolve().parents[2]


# -- process and auth ---------------------------------------------------------------------------------

def test_the_api_never_imports_torch(tmp_path: Path, scene_dir: dict[str, Path]) -> None:
    """Build the app and serve a whole upload plus a job request in a fresh interpreter: torch stays out."""
    code = f"""
import sys
from fastapi.testclient import TestClient
from api.app import create_app
from api.auth import create_key
from service.database import session_scope
from service.settings import Settings
from tests.support.service import RecordingQueue, upload_parts
from pathlib import Path

files = {{k: Path(v) for k, v in {json.dumps({k: str(v) for k, v in scene_dir.items()})}.items()}}
with TestClient(create_app(Settings(data_dir={str(tmp_path)!r}), queue=RecordingQueue())) as client:
    with session_scope(client.app.state.sessionmaker) as session:
        auth = {{"Authorization": "Bearer " + create_key(session, "alice")}}
    scene = client.post("/v1/scenes", files=upload_parts(files), headers=auth)
    assert scene.status_code == 201, scene.text
    job = client.post("/v1/jobs", headers=auth, json={{"type": "reconstruct", "scene_id": scene.json()["id"]}})
    assert job.status_code == 202, job.text
print(sorted(m for m in sys.modules if m == "torch" or m.startswith("torch.")))
"""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, env=env)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "[]"


def test_health_ready_and_web_page(sqlite_service: Service) -> None:
    client = sqlite_service.client
    assert client.get("/healthz").json() == {"status": "ok", "checks": {}}
    no_worker = client.get("/readyz")  # issue 20 item 3: jobs sent now would only wait
    assert no_worker.status_code == 503 and no_worker.json()["checks"]["worker"].startswith("error: no worker")
    assert no_worker.headers["retry-after"] == "4"  # a quarter of the 16 s lease: when workers beat again
    beacon = WorkerBeacon(sqlite_service.sessions, "host:1", period_s=60)
    beacon.beat()
    ready = client.get("/readyz")
    assert ready.status_code == 200
    assert ready.json()["checks"] == {"database": "ok", "broker": "ok", "storage": "ok", "worker": "ok"}
    beacon.stop()  # a worker that shut down is not counted
    assert client.get("/readyz").status_code == 503
    page = client.get("/")
    assert page.status_code == 200 and "/docs" in page.text
    assert client.get("/openapi.json").json()["info"]["title"] == "FluidNexus"


def test_readyz_names_the_failing_dependency(tmp_path: Path) -> None:
    for service in make_service(tmp_path, queue=RecordingQueue(fail=True)):
        ready = service.client.get("/readyz")
        assert ready.status_code == 503 and ready.headers["retry-after"] == "4"  # issue 36: the docs promise it
        body = ready.json()
        assert body["status"] == "unavailable"
        assert body["checks"]["broker"].startswith("error:") and body["checks"]["database"] == "ok"


def test_requests_without_a_valid_key_are_refused(sqlite_service: Service) -> None:
    client = sqlite_service.client
    assert client.get("/v1/jobs").status_code == 401
    assert client.get("/v1/jobs", headers={"Authorization": "Bearer fnx_0000000000000000_" + "x" * 43}).status_code == 401
    good = sqlite_service.key("alice")["Authorization"]
    forged = good[:-4] + ("AAAA" if not good.endswith("AAAA") else "BBBB")
    assert client.get("/v1/jobs", headers={"Authorization": forged}).status_code == 401
    response = client.get("/v1/jobs", headers={"Authorization": good})
    assert response.status_code == 200 and response.json()["items"] == []


# -- scenes ---------------------------------------------------------------------------------------------

def test_upload_scene_then_read_and_list_it(service: Service, scene_dir: dict[str, Path]) -> None:
    alice = service.key("alice")
    created = upload(service, alice, scene_dir)
    assert created.status_code == 201, created.text
    scene = created.json()
    assert scene["cameras"] == ["cam0", "cam1"]
    assert set(scene["videos"]) == {"cam0", "cam1"}
    assert scene["videos"]["cam1"]["width"] == 32 and scene["videos"]["cam1"]["n_frames"] == 6
    assert scene["n_frames"] == 6 and scene["fps"] == pytest.approx(30.0)
    stored = [info.key for info in service.storage.list(f"scenes/{scene['id']}/")]
    assert sorted(Path(k).name for k in stored) == ["cam0.mp4", "cam1.mp4", "transforms.json"]
    assert service.storage.read_bytes(f"scenes/{scene['id']}/input/cam0.mp4") == scene_dir["cam0"].read_bytes()

    assert service.client.get(f"/v1/scenes/{scene['id']}", headers=alice).json() == scene
    second = upload(service, alice, scene_dir).json()
    page = service.client.get("/v1/scenes", params={"limit": 1}, headers=alice).json()
    assert page["total"] == 2 and page["next_offset"] == 1 and len(page["items"]) == 1
    rest = service.client.get("/v1/scenes", params={"limit": 1, "offset": 1}, headers=alice).json()
    assert {page["items"][0]["id"], rest["items"][0]["id"]} == {scene["id"], second["id"]}
    assert rest["next_offset"] is None


def test_video_matched_by_file_path_base_name(sqlite_service: Service, tmp_path: Path) -> None:
    files = scene_files(tmp_path, names=("cam0",))
    data = files["cameras"].read_text().replace('"camera": "cam0", ', "").replace("videos/cam0.mp4", "videos/side.mp4")
    files["cameras"].write_text(data)
    files["cam0"] = files["cam0"].rename(tmp_path / "side.mp4")
    response = upload(sqlite_service, sqlite_service.key("alice"), files)
    assert response.status_code == 201, response.text
    assert response.json()["cameras"] == ["side"]


@pytest.mark.parametrize(
    ("breakage", "status", "message"),
    [
        ("unknown_camera", 422, "known cameras: cam0, cam1"),
        ("not_a_video", 422, "video: cam1.mp4"),
        ("wrong_size", 422, "video: cam1.mp4 is 40x24 but camera"),
        ("too_long", 422, "longer than the limit"),
        ("bad_cameras", 422, "cameras:"),
        ("duplicate_camera", 422, "both for camera 'cam0'"),
        ("path_in_name", 422, "file name"),
    ],
)
def test_bad_uploads_are_refused_and_store_nothing(
    sqlite_service: Service, scene_dir: dict[str, Path], tmp_path: Path, breakage: str, status: int, message: str
) -> None:
    alice = sqlite_service.key("alice")
    assert upload(sqlite_service, alice, scene_dir).status_code == 201  # something already stored
    before = sqlite_service.storage.list("")
    parts = upload_parts(scene_dir)
    if breakage == "unknown_camera":
        parts[1] = ("video", ("cam9.mp4", parts[1][1][1], "video/mp4"))
    elif breakage == "not_a_video":
        parts[2] = ("video", ("cam1.mp4", b"this is not a video" * 100, "video/mp4"))
    elif breakage == "wrong_size":
        parts[2] = ("video", ("cam1.mp4", write_video(tmp_path / "cam1.mp4", width=40, height=24).read_bytes(), "video/mp4"))
    elif breakage == "too_long":
        parts[2] = ("video", ("cam1.mp4", write_video(tmp_path / "cam1.mp4", n_frames=40, fps=10.0).read_bytes(), "video/mp4"))
        sqlite_service.app.state.settings.max_video_seconds = 2.0
    elif breakage == "bad_cameras":
        parts[0] = ("cameras", ("transforms.json", b'{"frames": [{"camera": "cam0"}]}', "application/json"))
    elif breakage == "duplicate_camera":
        parts[2] = ("video", ("cam0.MP4", parts[1][1][1], "video/mp4"))
    elif breakage == "path_in_name":
        parts[1] = ("video", ("../..", parts[1][1][1], "video/mp4"))
    response = sqlite_service.client.post("/v1/scenes", files=parts, headers=alice)
    assert response.status_code == status, response.text
    assert message in response.json()["detail"]
    assert sqlite_service.storage.list("") == before
    assert sqlite_service.count(Scene) == 1


def test_upload_limits_answer_413(tmp_path: Path, scene_dir: dict[str, Path]) -> None:
    for service in make_service(tmp_path, max_video_bytes=1000):
        response = upload(service, service.key("alice"), scene_dir)
        assert response.status_code == 413 and "larger than the limit" in response.json()["detail"]
    for service in make_service(tmp_path / "b", max_upload_bytes=2000):
        response = upload(service, service.key("alice"), scene_dir)
        assert response.status_code == 413
        assert service.storage.list("") == [] and service.count(Scene) == 0


# -- jobs -----------------------------------------------------------------------------------------------

def test_create_get_and_list_jobs(service: Service, scene_id: str) -> None:
    alice = service.key("alice")
    created = reconstruct(service, alice, scene_id, quality="standard", frames=[1, 5])
    assert created.status_code == 202, created.text
    job = created.json()
    assert job["state"] == "queued" and job["progress"] == 0.0
    assert job["params"] == {"quality": "standard", "physics": "auto", "frames": [1, 5], "source": None,
                             "motion": "paper", "air_cells": None, "air_vorticity": 0.0, "entrainment": False,
                             "background_frames": None,
                             "world_up": None, "solids": []}
    assert service.queue.sent == [(job["id"], "reconstruct")]
    fetched = service.client.get(f"/v1/jobs/{job['id']}", headers=alice).json()
    assert fetched["id"] == job["id"] and fetched["timings"]["started_at"] is None
    assert fetched["links"]["artifacts"] == f"/v1/jobs/{job['id']}/artifacts"

    other = reconstruct(service, alice, scene_id).json()
    service.set_job(other["id"], state=JobState.SUCCEEDED)
    listed = service.client.get("/v1/jobs", params={"state": "succeeded"}, headers=alice).json()
    assert [j["id"] for j in listed["items"]] == [other["id"]]
    by_scene = service.client.get("/v1/jobs", params={"scene_id": scene_id, "type": "reconstruct"}, headers=alice).json()
    assert by_scene["total"] == 2


@pytest.mark.parametrize(
    ("params", "field"),
    [
        ({"quality": "ultra"}, "quality"), ({"physics": "phiflow"}, "physics"), ({"frames": [4, 2]}, "frames"),
        ({"frames": [0, 99]}, "frames"), ({"speed": 1}, "speed"),
        ({"air_cells": 4}, "air_cells"), ({"air_cells": 129}, "air_cells"), ({"air_cells": 32, "air_vorticity": 3}, "air_vorticity"),
        ({"motion": "paper", "air_vorticity": 0.5}, "air_vorticity needs the simulated air"),
        ({"entrainment": "yes please"}, "entrainment"), ({"motion": "eulerian"}, "motion"),
        ({"motion": "carrier", "air_cells": 0}, "cannot carry the smoke"),
        ({"motion": "carrier", "entrainment": True}, "the paper model's spreading"),
    ],
)
def test_bad_reconstruct_params_are_422(service: Service, scene_id: str, params: dict, field: str) -> None:
    response = reconstruct(service, service.key("alice"), scene_id, **params)
    assert response.status_code == 422
    assert field in response.text
    assert service.queue.sent == []


def test_a_source_hint_is_checked_against_the_capture_box(service: Service, tmp_path: Path) -> None:
    alice = service.key("alice")
    files = scene_files(tmp_path)
    box = {"min": [-0.5, 0.0, -0.5], "max": [0.5, 1.0, 0.5]}
    files["cameras"].write_text(json.dumps({**json.loads(files["cameras"].read_text()), "scene_box": box}))
    scene_id = upload(service, alice, files).json()["id"]
    inside = [0.1, 0.2, -0.1]
    refused = reconstruct(service, alice, scene_id, source={"center": [box["max"][0] + 1.0, *inside[1:]]})
    assert refused.status_code == 422 and "outside the scene box" in refused.text
    assert reconstruct(service, alice, scene_id, source={"center": inside, "radius": -1}).status_code == 422
    assert service.queue.sent == []
    created = reconstruct(service, alice, scene_id, source={"center": inside, "radius": 0.05})
    assert created.status_code == 202, created.text
    assert created.json()["params"]["source"] == {"center": inside, "radius": 0.05, "refine": False}  # kept as given
    refined = reconstruct(service, alice, scene_id, source={"center": inside, "refine": True})
    assert refined.status_code == 202 and refined.json()["params"]["source"]["refine"] is True


def test_solids_are_checked_against_the_capture_box_by_name(service: Service, tmp_path: Path) -> None:
    alice = service.key("alice")
    files = scene_files(tmp_path)
    box = {"min": [-0.5, 0.0, -0.5], "max": [0.5, 1.0, 0.5]}
    files["cameras"].write_text(json.dumps({**json.loads(files["cameras"].read_text()), "scene_box": box}))
    scene_id = upload(service, alice, files).json()["id"]
    inside = {"center": [0.1, 0.5, -0.1], "radius": 0.1}
    for solids, message in (
        ([inside, {"center": [0.1, 1.5, -0.1], "radius": 0.1}], "params.solids[1].center [0.1, 1.5, -0.1] is outside the scene box"),
        ([{"center": [0.1, 0.5, -0.1], "radius": 2.0}], "params.solids[0].radius 2.0 is larger than the scene box"),
        ([{"center": [0.1, 0.5, -0.1], "radius": 0}], '"params","solids",0,"radius"'),  # the request schema's own 422s
        ([inside] * 9, "at most 8 items"),
        ([{"center": [0.1, 0.5, -0.1], "radius": 0.1, "velocity": [1, 0, 0]}], '"params","solids",0,"velocity"'),
    ):
        refused = reconstruct(service, alice, scene_id, solids=solids)
        assert refused.status_code == 422 and message in refused.text, refused.text
    assert service.queue.sent == []
    created = reconstruct(service, alice, scene_id, solids=[inside])
    assert created.status_code == 202, created.text
    assert created.json()["params"]["solids"] == [inside]
    limits = service.client.get("/v1/limits").json()["reconstruct"]
    assert limits["solids"]["maxItems"] == 8 and limits["solids[].radius"]["exclusiveMinimum"] == 0


def test_reconstruct_takes_the_motion_model_the_simulated_air_and_the_spreading(service: Service, scene_id: str) -> None:
    created = reconstruct(service, service.key("alice"), scene_id, motion="paper", air_cells=32, air_vorticity=0.3,
                          entrainment=True)
    assert created.status_code == 202, created.text
    params = created.json()["params"]
    assert (params["motion"], params["air_cells"], params["air_vorticity"], params["entrainment"]) == ("paper", 32, 0.3, True)
    assert service.queue.sent == [(created.json()["id"], "reconstruct")]


def test_reconstruct_takes_the_physics_choice(service: Service, scene_id: str) -> None:
    created = reconstruct(service, service.key("alice"), scene_id, physics="scalarflow")
    assert created.status_code == 202, created.text
    assert created.json()["params"]["physics"] == "scalarflow"


def test_idempotency_key_returns_the_same_job(service: Service, scene_id: str) -> None:
    alice = {**service.key("alice"), "Idempotency-Key": "upload-42"}
    first = reconstruct(service, alice, scene_id, quality="preview")
    again = reconstruct(service, alice, scene_id, quality="preview")
    assert first.status_code == again.status_code == 202
    assert again.json()["id"] == first.json()["id"] and again.headers["Idempotent-Replayed"] == "true"
    assert len(service.queue.sent) == 1 and service.count(Job) == 1
    different = reconstruct(service, alice, scene_id, quality="paper")
    assert different.status_code == 422 and "Idempotency-Key" in different.json()["detail"]


def succeed_with_run(service: Service, job_id: str) -> None:
    """What a worker leaves behind: a succeeded job and a run with its scene (box 1 unit wide)."""
    store_run(service.storage, job_id)
    service.set_job(job_id, state=JobState.SUCCEEDED)


def test_continuations_need_a_succeeded_parent(service: Service, scene_id: str) -> None:
    alice = service.key("alice")
    parent = reconstruct(service, alice, scene_id).json()["id"]
    interact = {"type": "interact", "parent_job_id": parent,
                "params": {"frames": 10, "wind": {"direction": [1, 0, 0], "strength": 2.0}}}
    early = service.client.post("/v1/jobs", json=interact, headers=alice)  # waits for its parent (service.chaining)
    assert early.status_code == 202 and early.json()["stage"] == f"waiting for job {parent}"
    assert service.queue.sent == [(parent, "reconstruct")]
    service.client.post(f"/v1/jobs/{early.json()['id']}/cancel", headers=alice)

    succeed_with_run(service, parent)
    created = service.client.post("/v1/jobs", json=interact, headers=alice)
    assert created.status_code == 202, created.text
    assert created.json()["params"]["wind"]["direction"] == [1.0, 0.0, 0.0]
    assert created.json()["parent_job_id"] == parent

    chained = {"type": "predict", "parent_job_id": created.json()["id"], "params": {"frames": 5}}
    service.set_job(created.json()["id"], state=JobState.SUCCEEDED)
    further = service.client.post("/v1/jobs", json=chained, headers=alice)  # runs continue runs of any kind
    assert further.status_code == 202 and further.json()["parent_job_id"] == created.json()["id"]

    for bad, field in (({"frames": 10}, "a wind, a ball or both"),
                       ({"frames": 10, "wind": {"direction": [0, 0, 0], "strength": 1}}, "direction"),
                       ({"frames": 100000, "ball": {"center": [0, 0.5, 0], "radius": 0.1}}, "frames"),
                       ({"frames": 10, "ball": {"center": [3, 0.5, 0], "radius": 0.1}}, "ball")):  # outside the box
        response = service.client.post("/v1/jobs", json={**interact, "params": bad}, headers=alice)
        assert response.status_code == 422 and field in response.text, (bad, response.text)
    scene_for_predict = {"type": "predict", "scene_id": scene_id, "params": {"frames": 5}}
    assert service.client.post("/v1/jobs", json=scene_for_predict, headers=alice).status_code == 422


def test_cancel(service: Service, scene_id: str) -> None:
    alice = service.key("alice")
    queued = reconstruct(service, alice, scene_id).json()["id"]
    cancelled = service.client.post(f"/v1/jobs/{queued}/cancel", headers=alice)
    assert cancelled.status_code == 202 and cancelled.json()["state"] == "cancelled"
    assert service.client.post(f"/v1/jobs/{queued}/cancel", headers=alice).status_code == 409

    running = reconstruct(service, alice, scene_id).json()["id"]
    service.set_job(running, state=JobState.RUNNING)
    response = service.client.post(f"/v1/jobs/{running}/cancel", headers=alice).json()
    assert response["state"] == "running" and response["cancel_requested"] is True


def test_storage_down_is_a_503_with_retry_after(sqlite_service: Service, monkeypatch: pytest.MonkeyPatch) -> None:
    """What docs/service.md promises of every 503: the client is told when to try again."""
    from service.storage import StorageError

    alice = sqlite_service.key("alice")

    def down(*_: object) -> bytes:
        raise StorageError("connection refused (test)")

    monkeypatch.setattr(sqlite_service.storage, "read_bytes", down)
    with sqlite_service.sessions() as session:
        session.add(Job(id="j1", owner="alice", type="reconstruct"))
        session.commit()
    response = sqlite_service.client.get("/v1/jobs/j1/logs", headers=alice)
    assert response.status_code == 503 and response.headers["Retry-After"] == "1"
    assert response.json()["detail"] == "storage unavailable: connection refused (test)"


@pytest.mark.parametrize(
    ("reconstruct_field", "status", "message"),
    [
        ('{"frames": [0, 500]}', 422, "reconstruct.frames: end 500 is past the scene's"),
        ('{"quality": "ultra"}', 422, "reconstruct.quality"),
        ('{"frames": [0', 422, "reconstruct: not JSON"),
        ("[" * 2000 + "]" * 2000, 422, "reconstruct: not JSON (JSON nested too deeply)"),
        ('{"frames": [0, NaN]}', 422, "reconstruct: not JSON"),
    ],
)
def test_an_upload_whose_reconstruction_is_refused_stores_nothing(
    tmp_path: Path, scene_dir: dict[str, Path], reconstruct_field: str, status: int, message: str
) -> None:
    for service in make_service(tmp_path):
        alice = service.key("alice")
        for attempt in range(2):  # a retry does not pile up copies either
            response = service.client.post(
                "/v1/scenes", files=upload_parts(scene_dir), data={"name": "test", "reconstruct": reconstruct_field}, headers=alice
            )
            assert response.status_code == status, response.text
            assert message in response.json()["detail"]
        assert service.storage.list("") == [] and service.count(Scene) == 0 and service.count(Job) == 0


def test_an_upload_can_queue_its_reconstruction_in_the_same_request(service: Service, scene_dir: dict[str, Path]) -> None:
    alice = service.key("alice")
    response = service.client.post(
        "/v1/scenes", files=upload_parts(scene_dir), data={"name": "plume", "reconstruct": '{"frames": [0, 2], "quality": "preview"}'},
        headers=alice,
    )
    assert response.status_code == 201, response.text
    scene = response.json()
    job = service.client.get(f"/v1/jobs/{scene['reconstruct_job_id']}", headers=alice).json()
    assert job["scene_id"] == scene["id"] and job["type"] == "reconstruct" and job["params"]["frames"] == [0, 2]
    assert service.queue.sent == [(job["id"], "reconstruct")]
    assert upload(service, alice, scene_dir).json()["reconstruct_job_id"] is None  # without the field: a scene only


# -- artifacts and isolation ----------------------------------------------------------------------------

def add_artifact(service: Service, job_id: str, name: str, data: bytes, kind: str = "video") -> None:
    key = f"jobs/{job_id}/{name}"
    service.storage.put_bytes(key, data)
    with session_scope(service.sessions) as session:
        session.add(Artifact(job_id=job_id, name=name, kind=kind, camera="cam0" if kind == "video" else None,
                             key=key, size=len(data), content_type="video/mp4"))


def test_artifacts_list_and_download_with_ranges(service: Service, scene_id: str) -> None:
    alice = service.key("alice")
    job = reconstruct(service, alice, scene_id).json()["id"]
    data = bytes(range(256)) * 40
    add_artifact(service, job, "videos/cam0.mp4", data)
    listing = service.client.get(f"/v1/jobs/{job}/artifacts", headers=alice).json()
    assert listing["job_id"] == job
    [item] = listing["items"]
    assert item["kind"] == "video" and item["camera"] == "cam0" and item["size"] == len(data)
    signed = item["presigned_url"]  # local storage: signed by the API, usable without a key (<video src>)
    assert signed.startswith(item["url"] + "?")
    assert service.client.get(signed).content == data
    assert service.client.get(signed, headers={"Range": "bytes=0-9"}).content == data[:10]
    assert service.client.get(signed.replace("signature=", "signature=0")).status_code == 403
    other = signed.replace("videos/cam0.mp4", "run/manifest.json")
    assert service.client.get(other).status_code == 403  # a signature covers one file only
    assert service.client.get(item["url"]).status_code == 401

    whole = service.client.get(item["url"], headers=alice)
    assert whole.status_code == 200 and whole.content == data and whole.headers["accept-ranges"] == "bytes"
    part = service.client.get(item["url"], headers={**alice, "Range": "bytes=100-299"})
    assert part.status_code == 206 and part.content == data[100:300]
    assert part.headers["content-range"] == f"bytes 100-299/{len(data)}"
    tail = service.client.get(item["url"], headers={**alice, "Range": "bytes=-10"})
    assert tail.status_code == 206 and tail.content == data[-10:]
    open_end = service.client.get(item["url"], headers={**alice, "Range": f"bytes={len(data) - 5}-"})
    assert open_end.content == data[-5:]
    beyond = service.client.get(item["url"], headers={**alice, "Range": f"bytes={len(data)}-"})
    assert beyond.status_code == 416 and beyond.headers["content-range"] == f"bytes */{len(data)}"
    for overflowing in (f"bytes=0-{'9' * 4301}", f"bytes={'9' * 4301}-"):  # issue 49: a 500 before
        for target, headers in ((item["url"], alice), (signed, {})):
            refused = service.client.get(target, headers={**headers, "Range": overflowing})
            assert refused.status_code == 416 and refused.headers["content-range"] == f"bytes */{len(data)}"
    assert service.client.get(f"/v1/jobs/{job}/artifacts/videos/nope.mp4", headers=alice).status_code == 404


def test_other_owners_get_404_for_everything(service: Service, scene_id: str) -> None:
    alice, bob = service.key("alice"), service.key("bob")
    job = reconstruct(service, alice, scene_id).json()["id"]
    add_artifact(service, job, "run/manifest.json", b"{}", kind="manifest")
    for path in (f"/v1/scenes/{scene_id}", f"/v1/jobs/{job}", f"/v1/jobs/{job}/artifacts",
                 f"/v1/jobs/{job}/artifacts/run/manifest.json"):
        assert service.client.get(path, headers=alice).status_code == 200, path
        assert service.client.get(path, headers=bob).status_code == 404, path
    assert service.client.post(f"/v1/jobs/{job}/cancel", headers=bob).status_code == 404
    assert reconstruct(service, bob, scene_id).status_code == 404
    assert service.client.get("/v1/scenes", headers=bob).json()["total"] == 0
    assert service.client.get("/v1/jobs", headers=bob).json()["total"] == 0


def test_migrations_match_the_models_on_postgres(postgres_url: str) -> None:
    """`alembic check`: the models have no change that a migration does not carry."""
    from alembic import command
    from alembic.config import Config

    config = Config(str(ROOT / "alembic.ini"))
    config.set_main_option("sqlalchemy.url", postgres_url)
    command.check(config)


def test_s3_backend_upload_and_presigned_download(tmp_path: Path, scene_dir: dict[str, Path]) -> None:
    """With MinIO/S3 storage (moto's server), uploads land in the bucket and artifacts come with a
    presigned URL that works without the API key, next to the API's own Range-aware download."""
    import httpx
    from moto.server import ThreadedMotoServer

    from tests.support.service import free_port

    port = free_port()
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    try:
        s3 = {"storage_backend": "s3", "s3_endpoint": f"127.0.0.1:{port}", "s3_region": "us-east-1"}
        for service in make_service(tmp_path, **s3):
            service.storage.ensure_bucket()
            alice = service.key("alice")
            scene = upload(service, alice, scene_dir).json()
            assert service.storage.stat(f"scenes/{scene['id']}/input/cam0.mp4").size == scene["videos"]["cam0"]["size"]
            job = reconstruct(service, alice, scene["id"]).json()["id"]
            data = b"\x00\x00\x00\x18ftypmp42" * 100
            add_artifact(service, job, "videos/cam0.mp4", data)
            [item] = service.client.get(f"/v1/jobs/{job}/artifacts", headers=alice).json()["items"]
            assert httpx.get(item["presigned_url"]).content == data
            part = service.client.get(item["url"], headers={**alice, "Range": "bytes=4-11"})
            assert part.status_code == 206 and part.content == data[4:12]
    finally:
        server.stop()


def test_delete_jobs_then_their_scene(service: Service, scene_id: str) -> None:
    alice, bob = service.key("alice"), service.key("bob")
    parent = reconstruct(service, alice, scene_id).json()["id"]
    add_artifact(service, parent, "videos/cam0.mp4", b"video")
    assert service.client.delete(f"/v1/jobs/{parent}", headers=alice).status_code == 409  # still queued
    succeed_with_run(service, parent)
    child = service.client.post("/v1/jobs", headers=alice, json={"type": "predict", "parent_job_id": parent}).json()["id"]
    service.set_job(child, state=JobState.FAILED)

    in_use = service.client.delete(f"/v1/scenes/{scene_id}", headers=alice)
    assert in_use.status_code == 409 and parent in in_use.json()["detail"]
    continued = service.client.delete(f"/v1/jobs/{parent}", headers=alice)
    assert continued.status_code == 409 and child in continued.json()["detail"]
    assert service.client.delete(f"/v1/jobs/{child}", headers=bob).status_code == 404
    assert service.client.delete(f"/v1/jobs/{child}", headers=alice).status_code == 204
    assert service.client.delete(f"/v1/jobs/{parent}", headers=alice).status_code == 204
    assert service.storage.list(f"jobs/{parent}/") == [] and service.count(Artifact) == 0
    assert service.client.get(f"/v1/jobs/{parent}", headers=alice).status_code == 404

    assert service.client.delete(f"/v1/scenes/{scene_id}", headers=bob).status_code == 404
    assert service.client.delete(f"/v1/scenes/{scene_id}", headers=alice).status_code == 204
    assert service.storage.list(f"scenes/{scene_id}/") == [] and service.count(Scene) == 0


def test_signed_urls_expire_and_the_key_persists(tmp_path: Path) -> None:
    from urllib.parse import parse_qs, urlsplit

    from api.signing import signed_url, signing_key, verify

    key = signing_key(Settings(data_dir=tmp_path))
    assert signing_key(Settings(data_dir=tmp_path)) == key  # an embedded server's restart keeps its links valid
    assert (tmp_path / "signing.key").stat().st_mode & 0o077 == 0
    assert signing_key(Settings(data_dir=tmp_path, signing_key="configured")) == b"configured"

    def check(url: str) -> bool:
        query = parse_qs(urlsplit(url).query)
        return verify(key, urlsplit(url).path, int(query["expires"][0]), query["signature"][0])

    path = "/v1/jobs/j1/artifacts/videos/cam0.mp4"
    assert check(signed_url(key, path, 60))
    assert not check(signed_url(key, path, -1))
