"""Bundles made on request (`/v1/jobs/{id}/bundles`, api.routers.bundles): a sequence of a job's
run as one zip, made by a `bundle` job on the worker, stored with the job's artifacts under a name
that says what it holds, served from storage the next time; requests the run cannot satisfy are
422s before anything is queued.

The reconstruction's run is a real one (a 4-frame plume); the bundle job runs through the
worker's executor with fluidcore's own runners, so the zip is read back; the database is SQLite
and PostgreSQL."""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path

import pytest

from fluidcore.exports import BUNDLE_SPACING
from fluidcore.runs import Run
from service.models import Artifact, Job, JobState
from service.storage import run_prefix
from tests.support.api import Service, executor
from tests.support.predict_scenes import plume_run
from worker.runners import FLUIDCORE_RUNNERS
from worker.sync import FolderMirror


@pytest.fixture
def plume(service: Service, tmp_path: Path) -> tuple[str, Run]:
    """A succeeded reconstruction of alice's: a 4-frame plume run in storage."""
    folder = plume_run(tmp_path / "plume", frames=4)
    job = service.add_job("reconstruct", state=JobState.SUCCEEDED)
    FolderMirror(service.storage, folder, run_prefix(job)).push()
    return job, Run.open(folder)


def _bundle_jobs(service: Service, job_id: str) -> list[Job]:
    with service.sessions() as session:
        return session.query(Job).filter_by(parent_job_id=job_id, type="bundle").all()


def test_a_vdb_bundle_is_made_once_on_request_and_served_from_storage(
    service: Service, plume: tuple[str, Run], tmp_path: Path
) -> None:
    job, run = plume
    alice = service.key("alice")
    listed = service.client.get(f"/v1/jobs/{job}/bundles", headers=alice).json()
    h = run.scene.physics.h
    assert listed["formats"] == ["vdb", "ply", "density"] and listed["items"] == []
    assert listed["frames"] == [run.frames()[0], run.frames()[-1] + 1] and listed["kernel_radius"] == h
    assert listed["default_voxel_size"] == pytest.approx(BUNDLE_SPACING * h, rel=1e-3)

    asked = service.client.post(f"/v1/jobs/{job}/bundles", json={"format": "vdb", "frames": [1, 3]}, headers=alice)
    assert asked.status_code == 202, asked.text
    made = asked.json()
    voxel = listed["default_voxel_size"]
    assert made["name"] == f"bundles/vdb_f000001-000003_v{voxel:.4g}.zip" and made["artifact"] is None
    assert made["frames"] == [1, 3] and made["voxel_size"] == voxel and made["format"] == "vdb"
    bundle_job = made["bundle_job"]
    assert bundle_job["type"] == "bundle" and bundle_job["state"] == "queued" and bundle_job["parent_job_id"] == job
    again = service.client.post(f"/v1/jobs/{job}/bundles", json={"format": "vdb", "frames": [1, 3], "voxel_size": voxel},
                                headers=alice)  # the default, said out loud: the same bundle, one job
    assert again.status_code == 202 and again.json()["bundle_job"]["id"] == bundle_job["id"]
    assert [sent for sent in service.queue.sent if sent[1] == "bundle"] == [(bundle_job["id"], "bundle")]

    worker = executor(service, tmp_path / "worker")
    worker.runners = FLUIDCORE_RUNNERS
    assert worker.run(bundle_job["id"]) == "succeeded"
    with service.sessions() as session:
        done = session.get(Job, bundle_job["id"])
        assert done.stage == "done" and "bundle" in done.stage_seconds
        assert session.query(Artifact).filter_by(job_id=bundle_job["id"]).count() == 0  # published with the job's own

    served = service.client.post(f"/v1/jobs/{job}/bundles", json={"format": "vdb", "frames": [1, 3]}, headers=alice)
    assert served.status_code == 200 and served.json()["bundle_job"] is None
    artifact = served.json()["artifact"]
    assert artifact["name"] == made["name"] and artifact["kind"] == "bundle" and artifact["content_type"] == "application/zip"
    download = service.client.get(artifact["url"], headers=alice)
    assert download.status_code == 200 and len(download.content) == artifact["size"] > 0
    with zipfile.ZipFile(io.BytesIO(download.content)) as bundle:
        assert bundle.namelist() == ["smoke_000001.vdb", "smoke_000002.vdb", "bundle.json"]
        about = json.loads(bundle.read("bundle.json"))
    assert about["voxel_size"] == voxel and about["frames"] == [1, 3] and about["fps"] == run.fps
    assert [j.id for j in _bundle_jobs(service, job)] == [bundle_job["id"]]  # no second job

    items = service.client.get(f"/v1/jobs/{job}/bundles", headers=alice).json()["items"]
    assert [(item["name"], item["artifact"]["size"]) for item in items] == [(made["name"], artifact["size"])]
    with service.sessions() as session:  # the job's own files, published in an order the listing must not keep
        for name, kind in [("run/manifest.json", "manifest"), ("exports/a.vdb", "export"), ("videos/zz.mp4", "video")]:
            session.add(Artifact(job_id=job, name=name, kind=kind, key=f"k/{name}", size=1, content_type="x"))
        session.commit()
    listed = service.client.get(f"/v1/jobs/{job}/artifacts", headers=alice).json()["items"]
    assert [item["kind"] for item in listed] == ["video", "bundle", "export", "manifest"]  # watch, then download

    assert service.client.delete(f"/v1/jobs/{job}", headers=alice).status_code == 204  # the bundle goes with its job
    assert service.client.get(f"/v1/jobs/{bundle_job['id']}", headers=alice).status_code == 404
    assert not service.storage.exists(artifact_key(service, artifact["name"], job))


def artifact_key(service: Service, name: str, job: str) -> str:
    from service.storage import job_prefix

    return f"{job_prefix(job)}/{name}"


@pytest.mark.parametrize(("body", "message"), [
    ({"format": "nrrd"}, "Input should be 'vdb', 'ply' or 'density'"),
    ({"format": "vdb", "frames": [0, 9]}, "frames 0:9: frame 4 is not a finished frame of job"),
    ({"format": "vdb", "voxel_size": 5.0}, "voxel size must be in (0, "),
    ({"format": "vdb", "voxel_size": 0.0001}, "the smallest that fits this box is"),
    ({"format": "vdb", "voxel_size": 1e-9}, "the smallest that fits this box is"),  # issue 49: int64 overflow, a 202
    ({"format": "density", "voxel_size": 1e-300}, "the smallest that fits this box is"),
    ({"format": "vdb", "voxel_size": "0.01"}, "Input should be a valid number"),  # issue 49: coerced, a 202
    ({"format": "vdb", "voxel_size": True}, "Input should be a valid number"),
    ({"format": "vdb", "frames": ["0", "2"]}, "Input should be a valid integer"),
    ({"format": "ply", "voxel_size": 0.01}, "ply holds particles, not a grid"),
    ({"format": "vdb", "frames": [3, 1]}, "frames must satisfy 0 <= START < END"),
    ({"format": "vdb", "shape": 1}, "Extra inputs are not permitted"),
])
def test_a_bundle_the_run_cannot_make_is_a_422_before_anything_is_queued(
    service: Service, plume: tuple[str, Run], body: dict, message: str
) -> None:
    job, _ = plume
    refused = service.client.post(f"/v1/jobs/{job}/bundles", json=body, headers=service.key("alice"))
    assert refused.status_code == 422 and message in json.dumps(refused.json()), refused.text
    assert _bundle_jobs(service, job) == [] and not [sent for sent in service.queue.sent if sent[1] == "bundle"]


def test_bundles_belong_to_their_job_and_come_once_it_succeeded(service: Service, plume: tuple[str, Run]) -> None:
    job, _ = plume
    alice = service.key("alice")
    assert service.client.post(f"/v1/jobs/{job}/bundles", json={"format": "ply"}, headers=service.key("bob")).status_code == 404
    assert service.client.get(f"/v1/jobs/{job}/bundles", headers=service.key("bob")).status_code == 404
    assert service.client.post(f"/v1/jobs/{job}/bundles", json={"format": "ply"}).status_code == 401
    running = service.add_job("reconstruct", state=JobState.RUNNING)
    early = service.client.post(f"/v1/jobs/{running}/bundles", json={"format": "ply"}, headers=alice)
    assert early.status_code == 409 and "once it has succeeded" in early.json()["detail"]
    listed = service.client.get(f"/v1/jobs/{running}/bundles", headers=alice).json()
    assert listed["frames"] is None and listed["items"] == []
    made = service.client.post(f"/v1/jobs/{job}/bundles", json={"format": "ply"}, headers=alice).json()
    assert made["name"] == "bundles/ply_f000000-000004.zip" and made["voxel_size"] is None
    bundle_job = made["bundle_job"]["id"]
    assert service.client.get(f"/v1/jobs/{bundle_job}/bundles", headers=alice).status_code == 404  # it has no run
    continued = service.client.post("/v1/jobs", json={"type": "predict", "parent_job_id": bundle_job}, headers=alice)
    assert continued.status_code == 422 and "no run to continue" in continued.json()["detail"]
    created = service.client.post("/v1/jobs", json={"type": "bundle", "parent_job_id": job, "params": {"format": "ply"}},
                                  headers=alice)
    assert created.status_code == 422  # asked for at /bundles, where a stored bundle is served without one
    deleted = service.client.delete(f"/v1/jobs/{job}", headers=alice)
    assert deleted.status_code == 409 and "being made" in deleted.json()["detail"]


def test_a_bundle_body_that_is_not_json_is_a_422(service: Service, plume: tuple[str, Run]) -> None:
    """As every JSON route (api.errors.StrictJSONRoute): a body that does not parse is a 422, not an
    undocumented 400 (the schema fuzzer's case: one byte 0xff)."""
    job, _ = plume
    alice = {**service.key("alice"), "Content-Type": "application/json"}
    for body in (b"\xff", b'{"format": NaN}'):
        refused = service.client.post(f"/v1/jobs/{job}/bundles", content=body, headers=alice)
        assert refused.status_code == 422, refused.text
    assert _bundle_jobs(service, job) == []


def test_a_bundles_declared_size_is_reserved_against_its_owners_quota_before_work(
    service: Service, plume: tuple[str, Run]
) -> None:
    """Issue 49 item 5: the quota was checked only before a job started (stored < limit), so a
    bundle of any size, and any number of them asked at once, passed it. Now each declares its
    size (`BundlePlan.bytes`) and an unfinished one's counts as stored until it ends."""
    from fluidcore.exports import plan_bundle

    job, run = plume
    alice = service.key("alice")
    declared = plan_bundle(run, "density").bytes
    service.app.state.settings.max_stored_bytes_per_owner = declared + declared // 2  # one fits, two do not
    first = service.client.post(f"/v1/jobs/{job}/bundles", json={"format": "density"}, headers=alice)
    assert first.status_code == 202, first.text
    with service.sessions() as session:
        assert session.get(Job, first.json()["bundle_job"]["id"]).reserved_bytes == declared
    second = service.client.post(f"/v1/jobs/{job}/bundles", json={"format": "density", "frames": [0, 3]}, headers=alice)
    assert second.status_code == 429, second.text
    assert "this job may write" in second.json()["detail"] and "delete jobs or scenes" in second.json()["detail"]
    assert [j.id for j in _bundle_jobs(service, job)] == [first.json()["bundle_job"]["id"]]
    assert service.client.post(f"/v1/jobs/{first.json()['bundle_job']['id']}/cancel", headers=alice).status_code == 202
    again = service.client.post(f"/v1/jobs/{job}/bundles", json={"format": "density", "frames": [0, 3]}, headers=alice)
    assert again.status_code == 202, again.text  # a cancelled job's reservation is released


def test_identical_bundle_requests_at_once_make_one_job(service: Service, plume: tuple[str, Run],
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 49 item 6: ten parallel identical requests started six bundle jobs. Each request here
    is held after its checks until all ten have made them (or 3 s have passed), the race made sure."""
    import threading
    from concurrent.futures import ThreadPoolExecutor

    from service import quotas

    job, _ = plume
    alice = service.key("alice")
    barrier, checked = threading.Barrier(10, timeout=3), quotas.check_new_job

    def held(*args, **kwargs):  # type: ignore[no-untyped-def]
        checked(*args, **kwargs)
        try:
            barrier.wait()
        except threading.BrokenBarrierError:  # PostgreSQL's row lock lets one through at a time
            pass

    monkeypatch.setattr(quotas, "check_new_job", held)
    with ThreadPoolExecutor(10) as pool:
        answers = list(pool.map(lambda _: service.client.post(f"/v1/jobs/{job}/bundles", json={"format": "vdb"},
                                                               headers=alice), range(10)))
    assert [a.status_code for a in answers] == [202] * 10, [a.text for a in answers if a.status_code != 202]
    made = _bundle_jobs(service, job)
    assert len(made) == 1 and {a.json()["bundle_job"]["id"] for a in answers} == {made[0].id}
    assert [sent for sent in service.queue.sent if sent[1] == "bundle"] == [(made[0].id, "bundle")]


def test_deleting_a_bundle_job_deletes_its_bundle(service: Service, plume: tuple[str, Run], tmp_path: Path) -> None:
    """Issue 49 item 5: DELETE of a bundle job answered 204 and the bundle stayed listed and stored."""
    job, _ = plume
    alice = service.key("alice")
    made = service.client.post(f"/v1/jobs/{job}/bundles", json={"format": "ply"}, headers=alice).json()
    worker = executor(service, tmp_path / "worker")
    worker.runners = FLUIDCORE_RUNNERS
    assert worker.run(made["bundle_job"]["id"]) == "succeeded"
    stored = service.client.get(f"/v1/jobs/{job}/bundles", headers=alice).json()["items"]
    assert [item["name"] for item in stored] == [made["name"]] and stored[0]["artifact"]["size"] > 0
    assert service.storage.exists(artifact_key(service, made["name"], job))

    assert service.client.delete(f"/v1/jobs/{made['bundle_job']['id']}", headers=alice).status_code == 204
    assert service.client.get(f"/v1/jobs/{job}/bundles", headers=alice).json()["items"] == []
    assert not service.storage.exists(artifact_key(service, made["name"], job))
    assert [item["name"] for item in service.client.get(f"/v1/jobs/{job}/artifacts", headers=alice).json()["items"]
            if item["kind"] == "bundle"] == []
    asked = service.client.post(f"/v1/jobs/{job}/bundles", json={"format": "ply"}, headers=alice)
    assert asked.status_code == 202 and asked.json()["bundle_job"]["id"] != made["bundle_job"]["id"]  # made afresh
