"""The one rule for a job broker that is down (service.queue.send), on every path that sends a
job: a new job, an upload's reconstruction, a released continuation, a render asked for, the
reaper's stale jobs and serve's orphans. Each job the broker refuses stays queued ("waiting for
the queue"), nothing is failed or deleted, and the reaper sends it once the broker answers."""

from __future__ import annotations

from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path

import pytest
from sqlalchemy import select

from tests.support.api import Service, executor, make_service
from service.job_states import RESUME_STAGE, UNSENT_STAGE
from service.models import SENDING, UNSENT, Job, JobState, Scene, utcnow
from service.queue import reap_stale, requeue_orphans
from tests.support.service import scene_files, store_run, upload_parts

LEASE = 30.0


@pytest.fixture
def service(tmp_path: Path) -> Iterator[Service]:
    yield from make_service(tmp_path)


def job_row(service: Service, job_id: str) -> Job:
    with service.sessions() as session:
        row = session.get(Job, job_id)
        assert row is not None
        return row


def waits_for_the_queue(service: Service, job_id: str) -> None:
    row = job_row(service, job_id)
    assert (row.state, row.stage, row.task_id, row.error) == (JobState.QUEUED, UNSENT_STAGE, UNSENT, None)


def broker_back_and_reaped(service: Service, job_id: str, job_type: str) -> None:
    """The broker answers again: the reaper's next pass sends the job, once."""
    assert reap_stale(service.sessions, service.queue, LEASE) == []  # still down: nothing sent, nothing raised
    service.queue.fail = False
    assert reap_stale(service.sessions, service.queue, LEASE) == [job_id]
    assert service.queue.sent[-1] == (job_id, job_type) and service.queue.sent.count((job_id, job_type)) == 1
    assert job_row(service, job_id).task_id == f"task-{len(service.queue.sent)}"
    assert reap_stale(service.sessions, service.queue, LEASE) == []


def scene(service: Service, tmp_path: Path, headers: dict[str, str]) -> str:
    response = service.client.post("/v1/scenes", files=upload_parts(scene_files(tmp_path / "scene")), headers=headers)
    assert response.status_code == 201, response.text
    return response.json()["id"]


def test_a_new_job_waits_for_the_queue_and_its_key_replays_it(service: Service, tmp_path: Path) -> None:
    alice = {**service.key("alice"), "Idempotency-Key": "k"}
    body = {"type": "reconstruct", "scene_id": scene(service, tmp_path, alice), "params": {}}
    service.queue.fail = True
    created = service.client.post("/v1/jobs", json=body, headers=alice)
    assert created.status_code == 202 and created.json()["stage"] == UNSENT_STAGE
    waits_for_the_queue(service, created.json()["id"])
    retried = service.client.post("/v1/jobs", json=body, headers=alice)  # the job exists: no second one
    assert retried.headers["idempotent-replayed"] == "true" and retried.json()["id"] == created.json()["id"]
    broker_back_and_reaped(service, created.json()["id"], "reconstruct")
    assert job_row(service, created.json()["id"]).stage == "queued"


def test_an_uploads_reconstruction_waits_for_the_queue_and_the_upload_is_kept(service: Service, tmp_path: Path) -> None:
    alice = service.key("alice")
    service.queue.fail = True
    response = service.client.post(
        "/v1/scenes", files=upload_parts(scene_files(tmp_path / "scene")), data={"reconstruct": '{"frames": [0, 2]}'},
        headers=alice,
    )
    assert response.status_code == 201, response.text
    assert service.count(Scene) == 1 and service.storage.list("")
    job_id = response.json()["reconstruct_job_id"]
    waits_for_the_queue(service, job_id)
    broker_back_and_reaped(service, job_id, "reconstruct")


def test_a_released_continuation_waits_for_the_queue_instead_of_failing(service: Service, tmp_path: Path) -> None:
    alice = service.key("alice")
    body = {"type": "reconstruct", "scene_id": scene(service, tmp_path, alice), "params": {"frames": [0, 3]}}
    parent = service.client.post("/v1/jobs", json=body, headers=alice).json()["id"]
    child = service.client.post(
        "/v1/jobs", json={"type": "predict", "parent_job_id": parent, "params": {"frames": 2}}, headers=alice
    ).json()["id"]
    service.queue.fail = True
    assert executor(service, tmp_path).run(parent) == "succeeded"  # its worker releases the child
    waits_for_the_queue(service, child)
    broker_back_and_reaped(service, child, "predict")


def test_a_render_asked_for_waits_for_the_queue(service: Service) -> None:
    alice = service.key("alice")
    with service.sessions() as session:
        done = Job(owner="alice", type="reconstruct", state=JobState.SUCCEEDED)
        session.add(done)
        session.commit()
        done_id = done.id
    store_run(service.storage, done_id)
    service.queue.fail = True
    response = service.client.post(f"/v1/jobs/{done_id}/videos/orbit", headers=alice)
    assert response.status_code == 202, response.text
    render = response.json()["render_job"]["id"]
    waits_for_the_queue(service, render)
    again = service.client.post(f"/v1/jobs/{done_id}/videos/orbit", headers=alice)  # the same render, not a second
    assert again.json()["render_job"]["id"] == render
    broker_back_and_reaped(service, render, "render")


def test_the_reapers_jobs_wait_for_the_queue_and_keep_their_lost_attempt(service: Service) -> None:
    stale = utcnow() - timedelta(seconds=2 * LEASE)
    with service.sessions() as session:
        rows = [Job(owner="alice", type="reconstruct", state=JobState.RUNNING, heartbeat_at=stale, attempts=1) for _ in range(2)]
        session.add_all(rows)
        session.commit()
        dead, orphan = rows[0].id, rows[1].id
    service.queue.fail = True
    assert reap_stale(service.sessions, service.queue, LEASE) == []  # taken, but the broker took none
    for job_id in (dead, orphan):
        row = job_row(service, job_id)
        assert (row.state, row.stage, row.task_id) == (JobState.QUEUED, RESUME_STAGE, UNSENT)  # the claim counts it lost
    service.queue.fail = False
    assert sorted(reap_stale(service.sessions, service.queue, LEASE)) == sorted([dead, orphan])
    assert job_row(service, dead).stage == RESUME_STAGE


def test_servers_orphans_wait_for_the_queue(service: Service) -> None:
    with service.sessions() as session:
        row = Job(owner="alice", type="predict", state=JobState.RUNNING, heartbeat_at=utcnow())
        session.add(row)
        session.commit()
        orphan = row.id
    service.queue.fail = True
    assert requeue_orphans(service.sessions, service.queue) == [orphan]
    row = job_row(service, orphan)
    assert (row.state, row.stage, row.task_id) == (JobState.QUEUED, RESUME_STAGE, UNSENT)
    service.queue.fail = False
    assert reap_stale(service.sessions, service.queue, LEASE) == [orphan] and service.queue.sent == [(orphan, "predict")]


def test_a_reaper_pass_tries_a_broker_that_is_still_down_once(
    service: Service, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    alice = service.key("alice")
    body = {"type": "reconstruct", "scene_id": scene(service, tmp_path, alice), "params": {}}
    service.queue.fail = True
    waiting = [service.client.post("/v1/jobs", json=body, headers=alice).json()["id"] for _ in range(3)]
    tried: list[str] = []
    enqueue = service.queue.enqueue

    def counted(job_id: str, job_type: str) -> str:
        tried.append(job_id)
        return enqueue(job_id, job_type)

    monkeypatch.setattr(service.queue, "enqueue", counted)
    assert reap_stale(service.sessions, service.queue, LEASE) == []
    assert tried == waiting[:1]  # the oldest; then the pass ends
    for job_id in waiting:
        waits_for_the_queue(service, job_id)  # the one tried is unsent again, not left "sending"
    service.queue.fail = False
    assert reap_stale(service.sessions, service.queue, LEASE) == waiting


def test_a_job_whose_hand_off_never_ended_is_sent_by_the_reaper(
    service: Service, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A process that stores a job (or releases a continuation) and dies before the broker answers
    leaves it `SENDING`; a lease after the hand-off began, the reaper sends it, once. An upload's
    reconstruction was stored with no task at all, which nothing ever sent (issue 36)."""
    def dies(*args: object) -> bool:  # the hand-off never ends; here a 500, in life the process gone
        raise RuntimeError("the API process died here")

    monkeypatch.setattr("service.scenes.send", dies)
    alice = service.key("alice")
    with pytest.raises(RuntimeError, match="died here"):  # the test client raises what the 500 hides
        service.client.post("/v1/scenes", files=upload_parts(scene_files(tmp_path / "scene")),
                            data={"reconstruct": '{"frames": [0, 2]}'}, headers=alice)
    with service.sessions() as session:
        stored = session.scalars(select(Job.id)).one()
    fresh = Job(owner="alice", type="reconstruct", state=JobState.QUEUED, task_id=SENDING)  # being sent right now
    released = Job(owner="alice", type="predict", state=JobState.QUEUED, task_id=SENDING,
                   created_at=utcnow() - timedelta(hours=1), resent_at=utcnow())  # its parent just ended
    with service.sessions() as session:
        session.add_all([fresh, released])
        session.commit()
    assert reap_stale(service.sessions, service.queue, LEASE) == []  # none has been handed off for a lease
    service.set_job(stored, created_at=utcnow() - timedelta(seconds=2 * LEASE))
    service.set_job(released.id, resent_at=utcnow() - timedelta(seconds=2 * LEASE))
    assert sorted(reap_stale(service.sessions, service.queue, LEASE)) == sorted([stored, released.id])
    assert sorted(service.queue.sent) == sorted([(stored, "reconstruct"), (released.id, "predict")])
    assert job_row(service, stored).stage == "queued" and job_row(service, fresh.id).task_id == SENDING
    assert reap_stale(service.sessions, service.queue, LEASE) == []  # sent once
