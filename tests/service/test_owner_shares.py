"""Each owner's share of the service (issue 36 item 5): the workers serve owners in turn
(service.queue: at most `owner_share` jobs of one owner sent or running, the rest "waiting for
their turn"), and each owner's limits on unfinished jobs, scenes and stored bytes
(service.quotas) answer 429 naming the limit and how to free room, storing nothing.
The API runs in-process with a recording queue (whose order is the broker's FIFO order); jobs
run on a real JobExecutor with test-double runners."""

from __future__ import annotations

from pathlib import Path

from service.job_states import TURN_STAGE
from service.models import HELD, Job, JobState, Scene
from service.queue import reap_stale
from tests.support.api import Service, executor, make_service
from tests.support.service import RecordingQueue, scene_files, upload_parts

LEASE = 30.0


def upload(service: Service, headers: dict[str, str], folder: Path, **data: str):  # type: ignore[no-untyped-def]
    return service.client.post("/v1/scenes", files=upload_parts(scene_files(folder)), data=data, headers=headers)


def post_job(service: Service, headers: dict[str, str], scene_id: str):  # type: ignore[no-untyped-def]
    return service.client.post("/v1/jobs", json={"type": "reconstruct", "scene_id": scene_id, "params": {"frames": [0, 2]}},
                               headers=headers)


def test_a_second_owners_job_is_sent_before_the_first_owners_backlog_drains(tmp_path: Path) -> None:
    """Alice queues six jobs, then Bob one. With a share of two, Bob's job is the broker's third
    message, not its seventh; each of Alice's waits its turn, sent as hers end: by the worker
    that ends one, and by the reaper's pass for a turn freed by a cancel."""
    for service in make_service(tmp_path, queue=RecordingQueue(owner_share=2)):
        alice, bob = service.key("alice"), service.key("bob")
        alice_scene = upload(service, alice, tmp_path / "a").json()["id"]
        bob_scene = upload(service, bob, tmp_path / "b").json()["id"]
        backlog = [post_job(service, alice, alice_scene).json() for _ in range(6)]
        assert [job["stage"] for job in backlog] == ["queued"] * 2 + [TURN_STAGE] * 4
        assert all(job["state"] == "queued" for job in backlog)
        single = post_job(service, bob, bob_scene).json()
        assert single["stage"] == "queued"
        a = [job["id"] for job in backlog]
        assert [job_id for job_id, _ in service.queue.sent] == [a[0], a[1], single["id"]]

        assert executor(service, tmp_path).run(a[0]) == "succeeded"  # its end gives Alice's next job its turn
        assert [job_id for job_id, _ in service.queue.sent] == [a[0], a[1], single["id"], a[2]]
        cancelled = service.client.post(f"/v1/jobs/{a[1]}/cancel", headers=alice)
        assert cancelled.json()["state"] == "cancelled"
        assert reap_stale(service.sessions, service.queue, LEASE) == [a[3]]  # the turn the cancel freed
        assert [job_id for job_id, _ in service.queue.sent] == [a[0], a[1], single["id"], a[2], a[3]]
        with service.sessions() as session:
            waiting = session.query(Job).filter(Job.id.in_(a[4:])).all()
            assert {(job.state, job.task_id, job.stage) for job in waiting} == {(JobState.QUEUED, HELD, TURN_STAGE)}


def test_too_many_unfinished_jobs_is_a_429_until_one_ends(tmp_path: Path) -> None:
    for service in make_service(tmp_path, max_unfinished_jobs_per_owner=2):
        alice, bob = service.key("alice"), service.key("bob")
        scene = upload(service, alice, tmp_path / "a").json()["id"]
        first, second = post_job(service, alice, scene), post_job(service, alice, scene)
        assert first.status_code == second.status_code == 202
        refused = post_job(service, alice, scene)
        assert refused.status_code == 429 and refused.headers["Retry-After"] == "60"
        assert refused.json()["detail"] == (
            "you have 2 unfinished jobs, the most allowed (2): wait for some to finish, or cancel queued ones "
            "(POST /v1/jobs/ID/cancel), then ask again"
        )
        with_reconstruction = upload(service, alice, tmp_path / "a2", reconstruct='{"frames": [0, 2]}')
        assert with_reconstruction.status_code == 429 and "2 unfinished jobs" in with_reconstruction.json()["detail"]
        assert service.count(Job) == 2 and service.count(Scene) == 1  # nothing stored for the refusals
        assert upload(service, bob, tmp_path / "b").status_code == 201  # Bob's own limits are untouched
        service.client.post(f"/v1/jobs/{first.json()['id']}/cancel", headers=alice)
        assert post_job(service, alice, scene).status_code == 202


def test_too_many_scenes_or_bytes_is_a_429_that_says_what_to_delete(tmp_path: Path) -> None:
    files = scene_files(tmp_path / "a")
    video_bytes = sum(path.stat().st_size for name, path in files.items() if name != "cameras")
    for service in make_service(tmp_path, max_scenes_per_owner=2, max_stored_bytes_per_owner=video_bytes + 1):
        alice = service.key("alice")
        kept = upload(service, alice, tmp_path / "a")
        assert kept.status_code == 201
        stored = service.storage.list("")
        too_big = upload(service, alice, tmp_path / "b")
        assert too_big.status_code == 429 and "Retry-After" not in too_big.headers
        detail = too_big.json()["detail"]
        assert detail.startswith(f"you store {video_bytes / 1024:.1f} KiB; this upload adds {video_bytes / 1024:.1f} KiB")
        assert detail.endswith("delete jobs or scenes you no longer need (DELETE /v1/jobs/ID, DELETE /v1/scenes/ID), then ask again")
        assert service.count(Scene) == 1 and service.storage.list("") == stored

    for service in make_service(tmp_path / "count", max_scenes_per_owner=1):
        alice = service.key("alice")
        assert upload(service, alice, tmp_path / "a").status_code == 201
        refused = upload(service, alice, tmp_path / "b")
        assert refused.status_code == 429 and "Retry-After" not in refused.headers
        assert refused.json()["detail"] == (
            "you have 1 scenes, the most allowed (1): delete scenes you no longer need "
            "(DELETE /v1/scenes/ID, once their jobs are deleted), then upload again"
        )
        assert service.count(Scene) == 1
