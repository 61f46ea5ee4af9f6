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

from service_support import scene_files, upload_parts
from test_api import Service, make_service
from test_chaining import executor


class Receiver:
    """Answers each POST with the next status of `statuses` and records what arrived."""

    def __init__(self, statuses: list[int]) -> None:
        self.statuses, self.received = statuses, []
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:  # noqa: N802 - http.server's name
                body = self.rfile.read(int(self.headers["content-length"]))
                receiver.received.append(({k.lower(): v for k, v in self.headers.items()}, body))
                self.send_response(receiver.statuses.pop(0) if receiver.statuses else 200)
                self.end_headers()

            def log_message(self, *args: object) -> None:
                pass

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_port}/hook"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()


@pytest.fixture
def receiver() -> Iterator[Receiver]:
    receiver = Receiver([500, 200])
    yield receiver
    receiver.server.shutdown()
    receiver.server.server_close()


@pytest.fixture
def service(tmp_path: Path) -> Iterator[Service]:
    yield from make_service(tmp_path)


def test_a_finished_job_posts_a_signed_webhook_and_retries_a_failing_receiver(
    service: Service, receiver: Receiver, tmp_path: Path
) -> None:
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
