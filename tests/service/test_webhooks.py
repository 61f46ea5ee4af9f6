"""Completion webhooks (service.webhooks): a job created with a webhook URL is POSTed, signed with
the owner's secret, when it ends; a receiver that fails gets the same message again. The
receiver is a loopback HTTP server in this process; it stops with the test."""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
import threading
import time
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest

from service import webhooks
from tests.support.service import Receiver, scene_files, upload_parts, webhook_receiver
from tests.support.api import Service, executor, make_service


@pytest.fixture
def receiver() -> Iterator[Receiver]:
    with webhook_receiver([500, 200]) as receiver:
        yield receiver


@pytest.fixture
def service(tmp_path: Path) -> Iterator[Service]:
    yield from make_service(tmp_path)


@pytest.fixture
def local_service(tmp_path: Path) -> Iterator[Service]:
    """The receivers here listen on loopback: allowed only with the setting."""
    yield from make_service(tmp_path, webhook_allow_private=True)


def test_a_finished_job_posts_a_signed_webhook_and_retries_a_failing_receiver(
    local_service: Service, receiver: Receiver, tmp_path: Path
) -> None:
    service = local_service
    alice = service.key("alice")
    scene = service.client.post("/v1/scenes", files=upload_parts(scene_files(tmp_path / "scene")), headers=alice)
    body = {"type": "reconstruct", "scene_id": scene.json()["id"], "params": {"frames": [0, 2]}, "webhook": receiver.url}
    job = service.client.post("/v1/jobs", json=body, headers=alice).json()
    assert executor(service, tmp_path).run(job["id"]) == "succeeded"

    deadline = time.monotonic() + 30
    while len(receiver.received) < 2 and time.monotonic() < deadline:
        time.sleep(0.1)
    assert len(receiver.received) == 2  # a 500, then the retry answered 200
    secret = service.client.get("/v1/webhook-secret", headers=alice).json()["key"]
    key = base64.b64decode(secret.removeprefix("whsec_"))
    ids = set()
    for headers, raw in receiver.received:
        message = f"{headers['webhook-id']}.{headers['webhook-timestamp']}.".encode() + raw
        expected = "v1," + base64.b64encode(hmac.new(key, message, hashlib.sha256).digest()).decode()
        assert hmac.compare_digest(headers["webhook-signature"], expected)
        assert abs(time.time() - int(headers["webhook-timestamp"])) < 60
        ids.add(headers["webhook-id"])
        payload = json.loads(raw)
        assert payload["id"] == job["id"] and payload["state"] == "succeeded"
        assert payload["links"]["artifacts"] == f"/v1/jobs/{job['id']}/artifacts"
    assert len(ids) == 1  # a retry is the same message
    bob_secret = service.client.get("/v1/webhook-secret", headers=service.key("bob")).json()["key"]
    assert bob_secret != secret


@pytest.mark.parametrize("url", ["ftp://127.0.0.1/x", "not a url", "http://" + "a" * 2100 + ".com/"])
def test_a_webhook_must_be_an_http_url(service: Service, url: str) -> None:
    body = {"type": "predict", "parent_job_id": "x", "webhook": url}
    response = service.client.post("/v1/jobs", json=body, headers=service.key("alice"))
    assert response.status_code == 422 and "webhook" in response.text


INTERNAL = ["http://127.0.0.1:18101/x", "http://localhost/x", "http://[::1]/x", "http://10.1.2.3/x",
            "http://192.168.0.7/x", "http://169.254.169.254/latest/meta-data/", "http://[fd00:ec2::254]/x",
            "http://100.100.100.200/x", "http://224.0.0.1/x", "http://0.0.0.0/x", "http://[::ffff:127.0.0.1]/x",
            "http://2130706433/x", "http://0x7f.1/x", "http://[2002:7f00:1::]/x", "http://[2002:a9fe:a9fe::]/x",
            "http://[fec0::1]/x", "http://168.63.129.16/x"]


@pytest.mark.parametrize("url", INTERNAL)
def test_a_webhook_to_an_internal_address_is_refused_when_the_job_is_created(service: Service, url: str) -> None:
    """Issue 20 item 6: loopback, private, link-local, metadata, multicast and reserved targets are a
    422 naming `webhook` (they used to be accepted and POSTed to)."""
    body = {"type": "predict", "parent_job_id": "x", "webhook": url}
    response = service.client.post("/v1/jobs", json=body, headers=service.key("alice"))
    assert response.status_code == 422, response.text
    assert response.json()["detail"].startswith("webhook: ") and "ALLOW_PRIVATE" in response.json()["detail"]


def test_the_setting_allows_a_local_receiver(local_service: Service) -> None:
    body = {"type": "predict", "parent_job_id": "x", "webhook": "http://127.0.0.1:18101/x"}
    response = local_service.client.post("/v1/jobs", json=body, headers=local_service.key("alice"))
    assert response.status_code == 404  # past the webhook check, on to the (missing) parent job


def test_delivery_checks_the_address_it_connects_to(receiver: Receiver, monkeypatch: pytest.MonkeyPatch) -> None:
    """DNS rebinding: a name that was public when the job was created resolves to loopback at
    delivery time; the connection is refused and nothing reaches the receiver."""
    import socket

    real = socket.getaddrinfo
    port = receiver.server.server_port

    def rebound(host: str, *args: object, **kwargs: object) -> list:  # type: ignore[type-arg]
        return real("127.0.0.1" if host == "hooks.example.com" else host, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(socket, "getaddrinfo", rebound)
    url = f"http://hooks.example.com:{port}/hook"
    assert not webhooks.deliver(url, "whsec_" + "A" * 44, "msg_1", {"id": "j"}, delays=(0.0,))
    assert receiver.received == []
    webhooks.deliver(url, "whsec_" + "A" * 44, "msg_1", {"id": "j"}, delays=(0.0,), allow_private=True)
    assert len(receiver.received) == 1  # the same name reaches it once the setting allows loopback


def test_a_redirect_is_not_followed() -> None:
    """A 302 from the receiver is a failed attempt, not a GET to wherever it points."""
    followed: list[str] = []

    class Handler(BaseHTTPRequestHandler):
        def do_POST(self) -> None:  # noqa: N802 - http.server's name
            self.rfile.read(int(self.headers["content-length"]))
            self.send_response(302)
            self.send_header("Location", f"http://127.0.0.1:{self.server.server_port}/internal")
            self.end_headers()

        def do_GET(self) -> None:  # noqa: N802
            followed.append(self.path)
            self.send_response(200)
            self.end_headers()

        def log_message(self, *args: object) -> None:
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        url = f"http://127.0.0.1:{server.server_port}/hook"
        assert not webhooks.deliver(url, "whsec_" + "A" * 44, "msg_1", {"id": "j"}, delays=(0.0,), allow_private=True)
        assert followed == []
    finally:
        server.shutdown()
        server.server_close()


def test_a_host_that_does_not_resolve_in_time_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    """A resolver that never answers holds no request: the lookup is given up after
    RESOLVE_TIMEOUT_S and the target refused, naming the host."""
    import socket

    answer = threading.Event()

    def silent(*args: object, **kwargs: object) -> list:  # type: ignore[type-arg]
        answer.wait(5.0)  # a resolver that does not answer (released at the end of the test)
        raise socket.gaierror("released")

    monkeypatch.setattr(socket, "getaddrinfo", silent)
    monkeypatch.setattr(webhooks, "RESOLVE_TIMEOUT_S", 0.05)
    try:
        with pytest.raises(webhooks.RefusedTarget, match="'slow.example.com' did not resolve within 0.05 s"):
            webhooks.check_target("https://slow.example.com/hook", allow_private=False)
    finally:
        answer.set()


def test_a_forked_worker_process_resolves_with_a_pool_of_its_own(monkeypatch: pytest.MonkeyPatch) -> None:
    """Celery forks its worker processes: a child gets none of the parent's lookup threads, so a
    pool carried over from the parent would never run the child's lookups (each refused after
    RESOLVE_TIMEOUT_S). The child checks a public host as the parent does."""
    import multiprocessing
    import socket

    def public(*args: object, **kwargs: object) -> list:  # type: ignore[type-arg]
        return [(socket.AF_INET, socket.SOCK_STREAM, 6, "", ("93.184.215.14", 443))]

    monkeypatch.setattr(socket, "getaddrinfo", public)
    webhooks.check_target("https://hooks.example.com/hook", allow_private=False)  # the parent's pool has a thread now
    context = multiprocessing.get_context("fork")
    child = context.Process(target=webhooks.check_target, args=("https://hooks.example.com/hook", False))
    child.start()
    child.join(30)
    assert child.exitcode == 0
