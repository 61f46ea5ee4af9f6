"""The API under load (issue 16): health answers without the database pool, a pool that is
somehow exhausted answers 503 instead of hanging, and a short burst of 200 pollers and listers
plus uploads against a live server gets no 5xx, no timeouts and prompt health answers.
The 60 s figures come from `bench/load.py`; this is its bounded smoke test."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path

import pytest

import service.database
from bench.load import live_server, run_load
from tests.support.api import Service, make_service


@pytest.fixture
def small_pool(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Service]:
    monkeypatch.setattr(service.database, "POOL_TIMEOUT_S", 0.5)
    yield from make_service(tmp_path, max_concurrent_requests=2, max_concurrent_uploads=1)


def test_health_answers_while_every_pooled_connection_is_taken(small_pool: Service) -> None:
    client, engine = small_pool.client, small_pool.app.state.engine
    alice = small_pool.key("alice")
    with ExitStack() as held:
        for _ in range(engine.pool.size()):
            held.enter_context(engine.connect())
        assert engine.pool.checkedout() == engine.pool.size() == 5  # 2 requests + 1 upload admitted, 1 upload key check, the reaper
        start = time.monotonic()
        assert client.get("/healthz").status_code == 200
        ready = client.get("/readyz")  # 503 only for want of a worker heartbeat (none runs here)
        assert ready.json()["checks"]["database"] == "ok" and ready.json()["checks"]["storage"] == "ok"
        assert time.monotonic() - start < 1.0
        busy = client.get("/v1/jobs", headers=alice)  # the key check needs a pooled connection
        assert busy.status_code == 503 and busy.headers["Retry-After"] == "1"
        assert busy.json() == {"detail": "database busy; retry shortly"}
    assert client.get("/v1/jobs", headers=alice).status_code == 200  # and recovers at once


def counted_sessions(service: Service, seen: Callable[[str], None]) -> None:
    """Call `seen(name)` each time the app opens a session of its `sessionmaker` (key checks, writes)
    or `read_sessionmaker` (a GET route's)."""
    for name in ("sessionmaker", "read_sessionmaker"):
        factory = getattr(service.app.state, name)
        setattr(service.app.state, name, lambda factory=factory, name=name: (seen(name), factory())[1])


def test_the_key_check_holds_no_connection_while_the_route_runs(small_pool: Service) -> None:
    """The route's own session is the only connection a request holds (issue 16's diagnosis:
    the key check's connection stayed checked out while the request waited for a thread)."""
    engine = small_pool.app.state.engine
    held: list[int] = []
    counted_sessions(small_pool, lambda name: held.append(engine.pool.checkedout()))
    alice = small_pool.key("alice")
    assert small_pool.client.get("/v1/jobs", headers=alice).status_code == 200
    assert held == [0, 0]  # the route's session and the key check's: nothing held when either opens
    assert engine.pool.checkedout() == 0


def test_a_key_checked_moments_ago_is_not_looked_up_again(small_pool: Service) -> None:
    """Issue 49 item 9: each poll paid a thread hop and a database lookup for its key. A key
    found valid is trusted for `key_cache_seconds` (2 s) from then; a wrong key is looked up (and
    refused) every time, and fills no cache."""
    alice = small_pool.key("alice")
    opened: list[str] = []
    counted_sessions(small_pool, opened.append)
    for _ in range(5):
        assert small_pool.client.get("/v1/jobs", headers=alice).status_code == 200
    assert opened == ["sessionmaker"] + ["read_sessionmaker"] * 5  # the key once, the route's session each time
    wrong = {"Authorization": "Bearer fnx_0000000000000000_" + "x" * 43}
    assert [small_pool.client.get("/v1/jobs", headers=wrong).status_code for _ in range(3)] == [401] * 3
    assert opened[6:] == ["sessionmaker"] * 3 and len(small_pool.app.state.keys._owners) == 1


def test_a_get_reads_without_a_transaction_and_a_post_writes_in_one(service: Service) -> None:
    """Issue 49 item 9: on PostgreSQL each poll paid BEGIN and ROLLBACK round trips besides its
    query (30 s A/B on this machine: 102 -> 165 GET/s, docs/reliability.md). A GET's session is
    in autocommit; anything that writes keeps its transaction."""
    alice = service.key("alice")
    opened: list[str] = []
    counted_sessions(service, opened.append)
    assert service.client.get("/v1/jobs", headers=alice).status_code == 200
    assert service.client.post("/v1/jobs", json={"type": "reconstruct", "scene_id": "none"}, headers=alice).status_code == 404
    assert opened == ["sessionmaker", "read_sessionmaker", "sessionmaker"]  # key check, the GET, the POST
    with service.app.state.read_sessionmaker() as reading, service.app.state.sessionmaker() as writing:
        assert reading.connection().get_execution_options().get("isolation_level") == "AUTOCOMMIT"
        assert writing.connection().get_execution_options().get("isolation_level") is None  # the backend's own


def test_a_short_burst_of_200_clients_gets_no_server_error(tmp_path: Path) -> None:
    with live_server("sqlite", log=tmp_path / "server.log") as server:
        result = run_load(server, seconds=6, clients=200, uploads=4, timeout=30)
    routes = result["routes"]
    assert all(routes[r]["2xx"] > 0 for r in ("GET /v1/jobs/{id}", "GET /v1/jobs/{id}/artifacts", "POST /v1/scenes"))
    assert result["total_5xx"] == 0 and result["total_timeouts"] == 0 and result["total_errors"] == 0, routes
    assert sum(r["4xx"] for r in routes.values()) == 0, routes
    assert result["health_max_s"] < 1.0, routes
    after = result["uploads_after"]  # every upload answered, none left behind for a client that had gone
    assert after["answered"] == routes["POST /v1/scenes"]["2xx"] and after["abandoned"] == after["stored_after_abandon"] == 0


def test_uploads_whose_clients_leave_are_not_stored(tmp_path: Path) -> None:
    """Against a live server: three uploads of the dev scene's view whose client closes the
    connection just after sending (before or while the upload is checked) leave no scene; one whose client
    waits is answered 201 and stored."""
    import socket
    import uuid

    import httpx

    from bench.load import multipart_body, prepared

    with live_server("sqlite", log=tmp_path / "server.log", scene="dev") as server:
        port = int(server.base_url.rsplit(":", 1)[1])
        auth = {"Authorization": f"Bearer {server.key}"}
        boundary = uuid.uuid4().hex
        request = prepared("POST", "/v1/scenes", {**auth, "Content-Type": f"multipart/form-data; boundary={boundary}"},
                           multipart_body(server.scene, boundary))

        def total() -> int:
            return httpx.get(f"{server.base_url}/v1/scenes", headers=auth, timeout=30).json()["total"]

        before = total()
        for _ in range(3):
            with socket.create_connection(("127.0.0.1", port)) as connection:
                connection.sendall(request)
                time.sleep(0.05)
        time.sleep(8.0)  # long enough for each check to finish, were it still wanted
        assert total() == before
        with socket.create_connection(("127.0.0.1", port), timeout=30) as connection:
            connection.sendall(request)
            assert connection.recv(64).startswith(b"HTTP/1.1 201")
        assert total() == before + 1

