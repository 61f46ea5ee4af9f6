"""Videos rendered on request (`/v1/jobs/{id}/videos`, api.routers.videos): a what-if publishes
no video when it ends; its cameras, orbit and side-by-side are rendered by a `render` job when asked for,
stored under the what-if's keys and served from storage the next time, with no second render.

The what-if and the render run through the worker's executor with fluidcore's own runners on a
small plume, so the stored MP4 is a real one; the database is SQLite and PostgreSQL."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.support.api import Service, executor
from fluidcore.runs import Run
from fluidcore.video import probe
from tests.support.predict_scenes import plume_run
from service.models import Artifact, Job, JobState
from service.storage import run_prefix
from service.videos import video_key
from worker.runners import FLUIDCORE_RUNNERS
from worker.sync import FolderMirror

BALL = {"center": [0.0, 0.2, 0.0], "radius": 0.05}


@pytest.fixture
def what_if(service: Service, tmp_path: Path) -> str:
    """A succeeded what-if of alice's, run by the worker on a 4-frame plume reconstruction."""
    parent = service.add_job("reconstruct", state=JobState.SUCCEEDED)
    FolderMirror(service.storage, plume_run(tmp_path / "plume", frames=4), run_prefix(parent)).push()
    job = service.add_job("interact", parent_job_id=parent, params={"frames": 2, "ball": BALL})
    assert _worker(service, tmp_path).run(job) == "succeeded"
    return job


def _worker(service: Service, tmp_path: Path):  # type: ignore[no-untyped-def]
    worker = executor(service, tmp_path)
    worker.runners = FLUIDCORE_RUNNERS
    return worker


def _renders(service: Service, job_id: str) -> list[Job]:
    with service.sessions() as session:
        return session.query(Job).filter_by(parent_job_id=job_id, type="render").all()


def test_a_what_if_renders_its_orbit_once_on_request_and_serves_it_from_storage(
    service: Service, what_if: str, tmp_path: Path
) -> None:
    alice = service.key("alice")
    listed = service.client.get(f"/v1/jobs/{what_if}/videos", headers=alice).json()["items"]
    names = [item["name"] for item in listed]
    assert names[-2:] == ["orbit", "side_by_side"] and len(names) > 3  # every camera of the run, and the two scene videos
    ready = {item["name"] for item in listed if item["artifact"] is not None}
    assert ready == set() and Run.open(tmp_path / "plume").input_views[0] in names  # none rendered with the job
    assert not service.storage.exists(video_key(what_if, "orbit"))

    asked = service.client.post(f"/v1/jobs/{what_if}/videos/orbit", headers=alice)
    assert asked.status_code == 202, asked.text
    render = asked.json()["render_job"]
    assert render["type"] == "render" and render["state"] == "queued" and render["parent_job_id"] == what_if
    again = service.client.post(f"/v1/jobs/{what_if}/videos/orbit", headers=alice)  # asked twice: one render
    assert again.status_code == 202 and again.json()["render_job"]["id"] == render["id"]
    assert [sent for sent in service.queue.sent if sent[1] == "render"] == [(render["id"], "render")]

    assert _worker(service, tmp_path / "render").run(render["id"]) == "succeeded"
    with service.sessions() as session:
        done = session.get(Job, render["id"])
        assert done.stage == "done" and "render" in done.stage_seconds
        assert session.query(Artifact).filter_by(job_id=render["id"]).count() == 0  # published with the what-if's
    assert service.storage.exists(video_key(what_if, "orbit"))

    served = service.client.post(f"/v1/jobs/{what_if}/videos/orbit", headers=alice)
    assert served.status_code == 200 and served.json()["render_job"] is None
    artifact = served.json()["artifact"]
    assert artifact["name"] == "videos/orbit.mp4" and artifact["kind"] == "orbit"
    assert [job.id for job in _renders(service, what_if)] == [render["id"]]  # no second render job
    assert [sent for sent in service.queue.sent if sent[1] == "render"] == [(render["id"], "render")]
    download = service.client.get(artifact["url"], headers=alice)
    assert download.status_code == 200 and download.headers["content-type"] == "video/mp4"
    (tmp_path / "orbit.mp4").write_bytes(download.content)
    assert probe(tmp_path / "orbit.mp4").n_frames == 2  # as long as the what-if: the players stay in step
    listed = service.client.get(f"/v1/jobs/{what_if}/artifacts", headers=alice).json()["items"]
    assert "videos/orbit.mp4" in {item["name"] for item in listed}

    # deleting the render job deletes the video it made, as a bundle job's bundle (issue 49)
    assert service.client.delete(f"/v1/jobs/{render['id']}", headers=alice).status_code == 204
    assert not service.storage.exists(video_key(what_if, "orbit"))
    listed = service.client.get(f"/v1/jobs/{what_if}/artifacts", headers=alice).json()["items"]
    assert "videos/orbit.mp4" not in {item["name"] for item in listed}

    # the record of the render goes with the what-if
    assert service.client.delete(f"/v1/jobs/{what_if}", headers=alice).status_code == 204
    assert service.client.get(f"/v1/jobs/{render['id']}", headers=alice).status_code == 404
    assert not service.storage.exists(video_key(what_if, "orbit"))


def test_video_requests_are_checked(service: Service, what_if: str) -> None:
    alice = service.key("alice")
    unknown = service.client.post(f"/v1/jobs/{what_if}/videos/spin", headers=alice)
    assert unknown.status_code == 404 and "has no video 'spin'" in unknown.json()["detail"]
    assert "orbit, side_by_side" in unknown.json()["detail"]
    for unsafe in ("..", ".hidden", "a%20b", "-rf"):
        response = service.client.post(f"/v1/jobs/{what_if}/videos/{unsafe}", headers=alice)
        assert 400 <= response.status_code < 500, (unsafe, response.text)  # ".." is resolved by the client: a 405
    refused = service.client.post(f"/v1/jobs/{what_if}/videos/a%20b", headers=alice)
    assert refused.status_code == 422 and "is not an accepted name" in refused.json()["detail"]
    assert service.client.post(f"/v1/jobs/{what_if}/videos/orbit", headers=service.key("bob")).status_code == 404
    assert service.client.post("/v1/jobs/nosuchjob/videos/orbit", headers=alice).status_code == 404
    assert service.client.post(f"/v1/jobs/{what_if}/videos/orbit").status_code == 401

    running = service.add_job("predict", parent_job_id=what_if, state=JobState.RUNNING)
    early = service.client.post(f"/v1/jobs/{running}/videos/orbit", headers=alice)
    assert early.status_code == 409 and "once it has succeeded" in early.json()["detail"]
    render = service.client.post(f"/v1/jobs/{what_if}/videos/side_by_side", headers=alice).json()["render_job"]["id"]
    assert service.client.get(f"/v1/jobs/{render}/videos", headers=alice).status_code == 404  # a render has none of its own
    continued = service.client.post("/v1/jobs", json={"type": "predict", "parent_job_id": render}, headers=alice)
    assert continued.status_code == 422 and "no run to continue" in continued.json()["detail"]
    created = service.client.post("/v1/jobs", json={"type": "render", "parent_job_id": what_if, "params": {"video": "orbit"}},
                                  headers=alice)
    assert created.status_code == 422  # asked for at /videos/{name}, where a stored video is served without one
    assert len(_renders(service, what_if)) == 1
    assert service.client.delete(f"/v1/jobs/{what_if}", headers=alice).status_code == 409  # rendering: cancel first
