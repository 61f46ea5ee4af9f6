"""How many uploads are checked at once, and for whom (issue 36): one owner's uploads beyond their
share are a 429, an upload that finds every place taken waits a bounded time and then gets a
429 too (the server shedding load, not failing), both with `Retry-After`; an upload whose client
has left is not stored."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from service.models import Job, Scene
from tests.support.api import Service, make_service
from tests.support.service import upload_parts


def held_checks(service: Service) -> tuple[threading.Event, threading.Event]:
    """Make the first upload's check wait until released: (started, release)."""
    started, release = threading.Event(), threading.Event()
    validators = service.app.state.validators
    real: Callable = validators.check
    calls = iter(range(10**6))

    def check(*args, **kwargs):  # type: ignore[no-untyped-def]
        if next(calls) == 0:
            started.set()
            assert release.wait(30)
        return real(*args, **kwargs)

    validators.check = check
    return started, release


def upload_in_background(service: Service, headers: dict[str, str], scene_dir: dict[str, Path]) -> tuple[threading.Thread, list]:
    answers: list = []
    thread = threading.Thread(target=lambda: answers.append(
        service.client.post("/v1/scenes", files=upload_parts(scene_dir), headers=headers)))
    thread.start()
    return thread, answers


@pytest.fixture
def gated(tmp_path: Path) -> Iterator[Service]:
    yield from make_service(tmp_path, max_uploads_per_owner=1, max_concurrent_uploads=2)


def test_an_owners_uploads_beyond_their_share_are_429_while_anothers_go_on(gated: Service, scene_dir: dict[str, Path]) -> None:
    alice, bob = gated.key("alice"), gated.key("bob")
    started, release = held_checks(gated)
    thread, answers = upload_in_background(gated, alice, scene_dir)
    try:
        assert started.wait(30)
        second = gated.client.post("/v1/scenes", files=upload_parts(scene_dir), headers=alice)
        assert second.status_code == 429 and second.headers["Retry-After"] == "5"
        assert "1 of your uploads are being checked already" in second.json()["detail"]
        assert gated.client.post("/v1/scenes", files=upload_parts(scene_dir), headers=bob).status_code == 201
    finally:
        release.set()
        thread.join(60)
    assert answers[0].status_code == 201  # the first one, answered once checked
    assert gated.client.post("/v1/scenes", files=upload_parts(scene_dir), headers=alice).status_code == 201  # her share is back


def test_an_upload_waits_a_bounded_time_for_a_place_then_is_told_when_to_come_back(tmp_path: Path, scene_dir: dict[str, Path]) -> None:
    for service in make_service(tmp_path, max_concurrent_uploads=1, upload_wait_seconds=0.3):
        started, release = held_checks(service)
        thread, answers = upload_in_background(service, service.key("alice"), scene_dir)
        try:
            assert started.wait(30)
            begun = time.monotonic()
            busy = service.client.post("/v1/scenes", files=upload_parts(scene_dir), headers=service.key("bob"))
            waited = time.monotonic() - begun
            assert busy.status_code == 429 and busy.headers["Retry-After"] == "5", busy.text
            assert "uploads are being checked" in busy.json()["detail"] and 0.3 <= waited < 5
            assert service.client.get("/v1/scenes", headers=service.key("bob")).status_code == 200  # polling is not held
        finally:
            release.set()
            thread.join(60)
        assert answers[0].status_code == 201 and service.count(Scene) == 1


def test_an_upload_whose_client_left_stores_nothing(sqlite_service: Service, scene_dir: dict[str, Path],
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    import api.routers.scenes

    monkeypatch.setattr(api.routers.scenes, "client_gone", lambda request: True)
    parts = upload_parts(scene_dir)
    answer = sqlite_service.client.post("/v1/scenes", files=parts, data={"reconstruct": "{}"}, headers=sqlite_service.key("alice"))
    assert answer.status_code == 499 and "nothing was stored" in answer.json()["detail"]
    assert (sqlite_service.count(Scene), sqlite_service.count(Job), sqlite_service.storage.list("")) == (0, 0, [])
