"""Continuations of unfinished jobs (service.chaining): queued through the API while the parent is
queued or running, sent when it succeeds, failed with the reason when it fails or is cancelled;
and a job's log lines over the API (GET /v1/jobs/{id}/logs).
The API runs in-process with a recording queue; the jobs run on a real JobExecutor with
test-double runners, against the same database and storage."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from service.chaining import release_children
from service.job_states import Actor
from service.models import JobState
from tests.support.service import FAKE_RUNNERS, scene_files, upload_parts
from tests.support.api import Service, executor, make_service


@pytest.fixture
def service(tmp_path: Path) -> Iterator[Service]:
    yield from make_service(tmp_path)


def submit(service: Service, headers: dict[str, str], body: dict) -> dict:
    response = service.client.post("/v1/jobs", json=body, headers=headers)
    assert response.status_code == 202, response.text
    return response.json()


def chain(service: Service, tmp_path: Path) -> tuple[dict[str, str], str, str, str]:
    """A reconstruction, a prediction of it and an interaction with the prediction, queued at once."""
    alice = service.key("alice")
    scene = service.client.post("/v1/scenes", files=upload_parts(scene_files(tmp_path / "scene")), headers=alice)
    parent = submit(service, alice, {"type": "reconstruct", "scene_id": scene.json()["id"], "params": {"frames": [0, 3]}})
    child = submit(service, alice, {"type": "predict", "parent_job_id": parent["id"], "params": {"frames": 2}})
    grandchild = submit(service, alice, {
        "type": "interact", "parent_job_id": child["id"],
        "params": {"frames": 2, "wind": {"direction": [1, 0, 0], "strength": 1.0}},
    })
    assert child["state"] == grandchild["state"] == "queued"
    assert child["stage"] == f"waiting for job {parent['id']}" and grandchild["stage"] == f"waiting for job {child['id']}"
    return alice, parent["id"], child["id"], grandchild["id"]


def test_continuations_start_when_their_parent_succeeds(service: Service, tmp_path: Path) -> None:
    alice, parent, child, grandchild = chain(service, tmp_path)
    assert service.queue.sent == [(parent, "reconstruct")]  # the waiting ones are not sent yet

    worker = executor(service, tmp_path)
    assert worker.run(parent) == "succeeded"
    assert service.queue.sent[-1] == (child, "predict")
    assert service.client.get(f"/v1/jobs/{child}", headers=alice).json()["stage"] == "queued"
    assert worker.run(child) == "succeeded"
    assert service.queue.sent[-1] == (grandchild, "interact")
    assert worker.run(grandchild) == "succeeded"
    assert len(service.queue.sent) == 3


def test_a_failed_or_cancelled_parent_fails_the_whole_chain_with_the_reason(service: Service, tmp_path: Path) -> None:
    alice, parent, child, grandchild = chain(service, tmp_path)
    assert service.client.post(f"/v1/jobs/{parent}/cancel", headers=alice).json()["state"] == "cancelled"
    with service.sessions() as session:  # what the worker does after ending a job (here: the cancel)
        assert release_children(session, parent, service.queue, Actor.WORKER) == [child, grandchild]
    jobs = {j: service.client.get(f"/v1/jobs/{j}", headers=alice).json() for j in (child, grandchild)}
    assert jobs[child]["state"] == "failed" and jobs[child]["error"] == f"parent job {parent} was cancelled"
    assert jobs[grandchild]["state"] == "failed" and jobs[grandchild]["error"] == f"parent job {child} failed"
    assert service.queue.sent == [(parent, "reconstruct")]


def test_a_parent_that_ends_between_the_check_and_the_commit_still_releases_the_child(
    service: Service, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The worker's release ran before the waiting job was stored, so the API's own release after
    its commit is what sends it."""
    import service.jobs as jobs

    alice, parent, child, _ = chain(service, tmp_path)
    check = jobs.check_references

    def parent_succeeds_meanwhile(*args):  # type: ignore[no-untyped-def]
        waits_for = check(*args)
        service.set_job(parent, state=JobState.SUCCEEDED)
        return waits_for

    monkeypatch.setattr(jobs, "check_references", parent_succeeds_meanwhile)
    late = submit(service, alice, {"type": "predict", "parent_job_id": parent, "params": {"frames": 2}})
    assert late["stage"] == "queued" and service.queue.sent[-1] == (late["id"], "predict")
    assert service.queue.sent.count((child, "predict")) == 1  # and the earlier waiting child, exactly once

    service.set_job(parent, state=JobState.FAILED, error="boom")
    refused = service.client.post("/v1/jobs", json={"type": "predict", "parent_job_id": parent}, headers=alice)
    assert refused.status_code == 409 and "cannot be continued" in refused.json()["detail"]


def test_a_jobs_log_lines_are_served_while_and_after_it_runs(service: Service, tmp_path: Path) -> None:
    import logging

    alice, parent, child, _ = chain(service, tmp_path)
    assert service.client.get(f"/v1/jobs/{parent}/logs", headers=alice).json() == {
        "job_id": parent, "lines": [], "next_offset": 0,
    }
    seen_while_running = []

    def talkative(inputs):  # type: ignore[no-untyped-def]
        logging.getLogger("fluidcore.test").info("fitting frame %d", 0)
        inputs.progress(0.5, "fit")  # a report flushes the log to storage
        seen_while_running.extend(service.client.get(f"/v1/jobs/{parent}/logs", headers=alice).json()["lines"])
        return FAKE_RUNNERS["reconstruct"](inputs)

    worker = executor(service, tmp_path)
    worker.runners = {**FAKE_RUNNERS, "reconstruct": talkative}
    assert worker.run(parent) == "succeeded"
    assert any("fitting frame 0" in line for line in seen_while_running)
    logs = service.client.get(f"/v1/jobs/{parent}/logs", headers=alice).json()
    assert any("lease token 1" in line for line in logs["lines"])
    assert any(line.endswith(f"job {parent} succeeded") for line in logs["lines"])
    assert any(f"job {child}: parent done, sent" in line for line in logs["lines"])
    later = service.client.get(f"/v1/jobs/{parent}/logs", params={"offset": logs["next_offset"]}, headers=alice).json()
    assert later["lines"] == [] and later["next_offset"] == logs["next_offset"]
    other = service.key("bob")
    assert service.client.get(f"/v1/jobs/{parent}/logs", headers=other).status_code == 404
