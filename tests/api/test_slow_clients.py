"""Clients that send their request slowly, over real sockets against `fluidnexus serve` (issue 49
item 1): before, two connections with a wrong key sending a 190 kB upload at 10 bytes a second
held both upload places for 40 s+, and every other owner's upload got a 429 "busy" after 3 s.
Now an upload's key is checked before it may take a place (401 at once), and a body that falls
behind `min_body_rate` after `body_grace_seconds` is a 408 that frees its place."""

from __future__ import annotations

import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from tests.support.service import FLUIDNEXUS, scene_files, start_serve, upload_parts

BOUNDARY = "slowslowslow"
DECLARED = 190_000  # the probe's body


@pytest.fixture
def served(tmp_path: Path) -> Iterator[tuple[str, dict[str, str]]]:
    """A server with two upload places (the probe's 2-core default), 3 s to wait for one, and a
    key for alice and for bob."""
    data = tmp_path / "data"
    keys = {owner: subprocess.run([FLUIDNEXUS, "keys", "create", "--owner", owner, "--data-dir", str(data)],
                                  capture_output=True, text=True, check=True).stdout.strip() for owner in ("alice", "bob")}
    process, base = start_serve(data, "--no-worker", env={"FLUIDNEXUS_MAX_CONCURRENT_UPLOADS": "2",
                                                         "FLUIDNEXUS_UPLOAD_WAIT_SECONDS": "3"})
    try:
        yield base, keys
    finally:
        process.terminate()
        try:
            process.communicate(timeout=30)
        except subprocess.TimeoutExpired:  # a connection still open holds uvicorn's graceful shutdown
            process.kill()
            process.communicate()


class Dribble:
    """A raw connection that sends an upload's headers, then its body 10 bytes a second, and
    records when the server answered (and with what status line)."""

    def __init__(self, base: str, key: str) -> None:
        host, port = base.removeprefix("http://").split(":")
        self.sock = socket.create_connection((host, int(port)), timeout=1)
        self.sock.sendall((f"POST /v1/scenes HTTP/1.1\r\nHost: {host}\r\nAuthorization: Bearer {key}\r\n"
                           f"Content-Type: multipart/form-data; boundary={BOUNDARY}\r\n"
                           f"Content-Length: {DECLARED}\r\n\r\n").encode())
        self.started, self.answered_after, self.status = time.monotonic(), None, None
        self._thread = threading.Thread(target=self._send, daemon=True)
        self._thread.start()

    def _send(self) -> None:
        body = (f"--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"video\"; filename=\"cam0.mp4\"\r\n\r\n"
                ).encode() + b"x" * DECLARED
        for at in range(0, 600, 10):  # at most a minute of dribbling
            try:
                self.sock.sendall(body[at:at + 10])
                answer = self.sock.recv(200)
            except TimeoutError:
                continue
            except OSError:  # the server closed the connection after answering
                answer = b""
            if self.answered_after is None:
                self.answered_after = time.monotonic() - self.started
                self.status = answer.split(b"\r\n", 1)[0].decode(errors="replace")
            return

    def wait(self, timeout: float) -> None:
        self._thread.join(timeout)
        self.sock.close()


def test_keyless_slow_uploads_hold_no_place_and_other_owners_upload_meanwhile(served, tmp_path: Path) -> None:
    base, keys = served
    wrong = "fnx_0000000000000000_" + "x" * 43
    slow = [Dribble(base, wrong) for _ in range(2)]
    time.sleep(1.0)  # both are in, as in the probe
    parts = upload_parts(scene_files(tmp_path / "scene"))
    begun = time.monotonic()
    answer = httpx.post(f"{base}/v1/scenes", files=parts, headers={"Authorization": f"Bearer {keys['bob']}"}, timeout=30)
    assert answer.status_code == 201, answer.text  # before: 429 "busy: 2 uploads are being checked" after 3 s
    assert time.monotonic() - begun < 3
    for client in slow:
        client.wait(10)
        assert client.status is not None and client.status.startswith("HTTP/1.1 401"), client.status
        assert client.answered_after < 2.0  # answered on its headers, not after its body


def test_a_keyed_upload_sent_too_slowly_is_408_and_frees_its_place(served, tmp_path: Path) -> None:
    base, keys = served
    slow = [Dribble(base, keys["alice"]) for _ in range(2)]  # alice's share is 2: both places
    for client in slow:
        client.wait(20)
        assert client.status is not None and client.status.startswith("HTTP/1.1 408"), client.status
        assert 5.0 <= client.answered_after < 9.0  # FLUIDNEXUS_BODY_GRACE_SECONDS (5) and the rate's slack
    parts = upload_parts(scene_files(tmp_path / "scene"))
    answer = httpx.post(f"{base}/v1/scenes", files=parts, headers={"Authorization": f"Bearer {keys['bob']}"}, timeout=30)
    assert answer.status_code == 201, answer.text
    listed = httpx.get(f"{base}/v1/scenes", headers={"Authorization": f"Bearer {keys['alice']}"}).json()
    assert listed["total"] == 0  # nothing of the slow uploads was stored
