"""Continuations of unfinished jobs and what follows a job's end (service.chaining): queued
through the API while the parent is queued or running, sent when it succeeds, cancelled with the
reason when it fails or is cancelled, whoever ends it (the cancel route, the worker's runner or
claim, the reaper for an end nobody followed up), with a webhook for every end; and a job's log
lines over the API (GET /v1/jobs/{id}/logs).
The API runs in-process with a recording queue; the jobs run on a real JobExecutor with
test-double runners, against the same database and storage."""

from __future__ import annotations

from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path

import pytest

from fluidcore.errors import InputError
from service.chaining import release_stranded
from service.models import JobState, utcnow
from service.queue import reap_stale
from tests.support.service import FAKE_RUNNERS, empty_tables, scene_files, upload_parts, webhook_receiver
from tests.support.service import postgres_url  # noqa: F401  fixture
from tests.support.api import Service, executor, make_service


@pytest.fixture
def service(tmp_path: Path) -> Iterator[Service]:
    yield from make_service(tmp_path)


def submit(service: Service, headers: dict[str, str], body: dict) -> dict:
    response = service.client.post("/v1/jobs", json=body, headers=headers)
    assert response.status_code == 202, response.text
    return response.json()


def chain(service: Service, tmp_path: Path, webhook: str | None = None) -> tuple[dict[str, str], str, str, str]:
    """A reconstruction, a prediction of it and an interaction with the prediction, queued at once
    (each with `webhook` when given)."""
    alice = service.key("alice")
    hook = {} if webhook is None else {"webhook": webhook}
    scene = service.client.post("/v1/scenes", files=upload_parts(scene_files(tmp_path / "scene")), headers=alice)
    parent = submit(service, alice, {
        "type": "reconstruct", "scene_id": scene.json()["id"], "params": {"frames": [0, 3]}, **hook,
    })
    child = submit(service, alice, {"type": "predict", "parent_job_id": parent["id"], "params": {"frames": 2}, **hook})
    grandchild = submit(service, alice, {
        "type": "interact", "parent_job_id": child["id"],
        "params": {"frames": 2, "wind": {"direction": [1, 0, 0], "strength": 1.0}}, **hook,
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


@pytest.mark.parametrize("database", ["sqlite", "postgres"])
def test_cancelling_a_queued_parent_cancels_its_waiting_chain_and_sends_every_webhook(
    tmp_path: Path, request: pytest.FixtureRequest, database: str
) -> None:
    """Issue 36 item 4: the children of a queued parent cancelled through the API stayed "waiting
    for job ..." for ever, and no webhook was sent for any of the three ends. On both databases:
    the cancel and each child's release lock the row they end on PostgreSQL."""
    url = empty_tables(request.getfixturevalue("postgres_url")) if database == "postgres" else None
    with webhook_receiver() as receiver:
        for service in make_service(tmp_path, url, webhook_allow_private=True):
            alice, parent, child, grandchild = chain(service, tmp_path, webhook=receiver.url)
            cancelled = service.client.post(f"/v1/jobs/{parent}/cancel", headers=alice)
            assert cancelled.status_code == 202 and cancelled.json()["state"] == "cancelled"
            assert cancelled.json()["error"] is None  # its owner asked: no reason to give
            jobs = {j: service.client.get(f"/v1/jobs/{j}", headers=alice).json() for j in (child, grandchild)}
            assert (jobs[child]["state"], jobs[child]["error"]) == ("cancelled", f"parent job {parent} was cancelled")
            assert (jobs[grandchild]["state"], jobs[grandchild]["error"]) == (
                "cancelled", f"parent job {child} was cancelled"
            )
            assert service.queue.sent == [(parent, "reconstruct")]
            hooks = receiver.states(3)
            assert {j: (hooks[j]["state"], hooks[j]["error"]) for j in hooks} == {
                parent: ("cancelled", None),
                child: ("cancelled", f"parent job {parent} was cancelled"),
                grandchild: ("cancelled", f"parent job {child} was cancelled"),
            }
            assert {headers["webhook-id"] for headers, _ in receiver.received} == {
                f"msg_{j}_cancelled" for j in (parent, child, grandchild)
            }


def test_a_parent_its_worker_fails_cancels_its_waiting_chain_with_webhooks(tmp_path: Path) -> None:
    """The worker's failure path ends the chain by the same rule as the cancel route."""

    def broken(inputs):  # type: ignore[no-untyped-def]
        raise InputError("frames: nothing to fit")

    with webhook_receiver() as receiver:
        for service in make_service(tmp_path, webhook_allow_private=True):
            alice, parent, child, grandchild = chain(service, tmp_path, webhook=receiver.url)
            worker = executor(service, tmp_path)
            worker.runners = {**FAKE_RUNNERS, "reconstruct": broken}
            assert worker.run(parent) == "failed"
            states = {j: service.client.get(f"/v1/jobs/{j}", headers=alice).json() for j in (parent, child, grandchild)}
            assert (states[parent]["state"], states[parent]["error"]) == ("failed", "frames: nothing to fit")
            assert (states[child]["state"], states[child]["error"]) == ("cancelled", f"parent job {parent} failed")
            assert (states[grandchild]["state"], states[grandchild]["error"]) == (
                "cancelled", f"parent job {child} was cancelled"
            )
            hooks = receiver.states(3)
            assert {j: hooks[j]["state"] for j in hooks} == {parent: "failed", child: "cancelled", grandchild: "cancelled"}
            assert service.queue.sent == [(parent, "reconstruct")]


def test_a_claim_that_ends_the_parent_releases_its_chain(service: Service, tmp_path: Path) -> None:
    """A cancel asked of a running parent whose worker died is carried out by the next claim,
    which ends the chain too (the claim used to end the job and stop there)."""
    alice, parent, child, grandchild = chain(service, tmp_path)
    lost = utcnow() - timedelta(hours=1)
    service.set_job(parent, state=JobState.RUNNING, heartbeat_at=lost, attempts=1, cancel_requested=True)
    assert executor(service, tmp_path).run(parent) == "cancelled"
    for job_id, reason in ((child, f"parent job {parent} was cancelled"), (grandchild, f"parent job {child} was cancelled")):
        job = service.client.get(f"/v1/jobs/{job_id}", headers=alice).json()
        assert (job["state"], job["error"]) == ("cancelled", reason)


def test_the_reaper_releases_the_chains_whose_parents_end_went_unnoticed(service: Service, tmp_path: Path) -> None:
    """A process that ends a job and dies before releasing its children (the end is committed, the
    release is not): the reaper's pass sends or cancels them, once."""
    alice, parent, child, grandchild = chain(service, tmp_path)
    service.set_job(parent, state=JobState.SUCCEEDED)  # ended by a process that died right after
    settings = service.app.state.settings
    assert release_stranded(service.sessions, service.queue, settings) == [child]
    assert service.queue.sent[-1] == (child, "predict")
    assert release_stranded(service.sessions, service.queue, settings) == []
    service.set_job(child, state=JobState.FAILED, error="boom")
    assert release_stranded(service.sessions, service.queue, settings) == [grandchild]
    job = service.client.get(f"/v1/jobs/{grandchild}", headers=alice).json()
    assert (job["state"], job["error"]) == ("cancelled", f"parent job {child} failed")


def test_a_continuation_the_broker_refused_is_sent_by_the_reaper(service: Service, tmp_path: Path) -> None:
    """Released while the broker is down, a child stays queued ("waiting for the queue"), never
    failed, and the reaper sends it once the broker answers (issue 36 item 4: it used to fail for
    good with "the job broker did not accept the job")."""
    alice, parent, child, grandchild = chain(service, tmp_path)
    service.queue.fail = True
    assert executor(service, tmp_path).run(parent) == "succeeded"
    job = service.client.get(f"/v1/jobs/{child}", headers=alice).json()
    assert (job["state"], job["stage"], job["error"]) == ("queued", "waiting for the queue", None)
    assert reap_stale(service.sessions, service.queue, 30.0) == []  # still down
    service.queue.fail = False
    assert reap_stale(service.sessions, service.queue, 30.0) == [child]
    assert service.queue.sent[-1] == (child, "predict")
    assert executor(service, tmp_path).run(child) == "succeeded"
    assert service.queue.sent[-1] == (grandchild, "interact")


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
