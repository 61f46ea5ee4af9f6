"""Deletes racing creates (issue 36 item 7): a job or scene deleted while a job naming it is being
created. Whichever loses answers 409 saying what happened, never a 500 (the database's
foreign-key error), and nothing half-made is left. On SQLite and PostgreSQL."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest
from sqlalchemy import event
from sqlalchemy.orm import Session

from service import jobs, scenes
from service.errors import Conflict
from service.models import Job, JobState, Scene
from tests.support.api import Service, reconstruct, upload


def succeeded_job(service: Service, headers: dict[str, str], scene: str) -> str:
    job_id = reconstruct(service, headers, scene).json()["id"]
    service.set_job(job_id, state=JobState.SUCCEEDED)
    return job_id


@pytest.mark.parametrize("deleted", ["parent job", "scene"])
def test_a_create_whose_parent_or_scene_is_deleted_after_its_check_is_a_409(
    service: Service, scene_dir: dict[str, Path], monkeypatch: pytest.MonkeyPatch, deleted: str
) -> None:
    """The reference is deleted between the API's check and its insert (deterministically: right
    after the check)."""
    alice = service.key("alice")
    scene = upload(service, alice, scene_dir).json()["id"]
    if deleted == "parent job":
        parent = succeeded_job(service, alice, scene)
        body = {"type": "predict", "parent_job_id": parent, "params": {"frames": 2}}
        gone, remove = parent, lambda session: jobs.delete(session, service.storage, parent, "alice")
    else:
        body = {"type": "reconstruct", "scene_id": scene, "params": {}}
        gone, remove = scene, lambda session: scenes.delete(session, service.storage, scene, "alice")
    check = jobs.check_references

    def deleted_meanwhile(*args):  # type: ignore[no-untyped-def]
        waits_for = check(*args)
        with service.sessions() as session:
            remove(session)
        return waits_for

    monkeypatch.setattr(jobs, "check_references", deleted_meanwhile)
    response = service.client.post("/v1/jobs", json=body, headers=alice)
    assert response.status_code == 409, response.text
    assert response.json()["detail"] == f"{deleted} {gone} was deleted while this job was being created; nothing was queued"
    assert service.count(Job) == 0 and service.queue.sent == ([] if deleted == "scene" else [(gone, "reconstruct")])


@pytest.mark.parametrize("deleted", ["job", "scene"])
def test_a_delete_and_a_create_naming_it_at_once_one_wins_and_the_other_is_a_409(
    service: Service, scene_dir: dict[str, Path], deleted: str
) -> None:
    """A job naming the target is created from another thread at the moment the delete writes (its
    checks passed). On PostgreSQL the delete holds the target's row lock, so the insert waits and
    is refused once the delete commits; on SQLite the insert may commit first, and the delete's
    commit is then refused. Either way exactly one wins and the other is a Conflict saying so."""
    alice = service.key("alice")
    scene = upload(service, alice, scene_dir).json()["id"]
    if deleted == "job":
        target = succeeded_job(service, alice, scene)
        new = Job(owner="alice", type="predict", parent_job_id=target, params={"frames": 2})
        row, path = Job, f"/v1/jobs/{target}"
    else:
        target = scene
        new = Job(owner="alice", type="reconstruct", scene_id=target, params={})
        row, path = Scene, f"/v1/scenes/{target}"
    outcome: list[str] = []

    def create() -> None:
        with service.sessions() as session:
            try:
                jobs.create(session, service.queue, service.app.state.settings, new, waits_for=None)
                outcome.append("created")
            except Conflict as exc:
                outcome.append(str(exc))

    racer = threading.Thread(target=create)

    def create_while_deleting(session: Session, *_: object) -> None:
        if not racer.is_alive() and not outcome and any(isinstance(o, row) and o.id == target for o in session.deleted):
            racer.start()
            racer.join(timeout=1.0)  # PostgreSQL: still waiting on the delete's row lock

    event.listen(service.sessions, "before_flush", create_while_deleting)
    try:
        response = service.client.delete(path, headers=alice)
    finally:
        event.remove(service.sessions, "before_flush", create_while_deleting)
    racer.join(timeout=30)
    assert outcome, "the racing create never ran"
    if response.status_code == 204:
        assert outcome == [f"{'parent job' if deleted == 'job' else 'scene'} {target} was deleted while this job was being "
                           "created; nothing was queued"]
        assert service.count(row) == 0
    else:
        assert response.status_code == 409, response.text
        assert response.json()["detail"] == (
            f"{deleted} {target} was named by a new job while it was being deleted; nothing was deleted"
        )
        assert outcome == ["created"]
        assert service.count(row) == (2 if deleted == "job" else 1)
