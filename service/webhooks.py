"""Signed completion webhooks: a job created with `"webhook": URL` gets one POST when it ends
(succeeded, failed or cancelled), retried with back-off when the receiver does not answer 2xx.

The signature follows the Standard Webhooks convention (also Replicate's): headers
`webhook-id` (the same on every retry), `webhook-timestamp` (Unix seconds) and
`webhook-signature: v1,<base64 HMAC-SHA256 over "{id}.{timestamp}.{body}">`. The key is the
owner's webhook secret, `whsec_` + base64, derived from the server's signing key and the owner, so
it survives restarts and each owner sees only their own (GET /v1/webhook-secret). A receiver
recomputes the HMAC and rejects old timestamps.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
import logging
import threading
import time
import urllib.request
from collections.abc import Sequence
from typing import Any

log = logging.getLogger(__name__)

RETRY_DELAYS_S = (0.0, 2.0, 10.0, 30.0)  # first try at once, then back off; ~42 s in all
TIMEOUT_S = 10.0


def owner_secret(server_key: bytes, owner: str) -> str:
    """The owner's webhook secret: stable, and useless for anything but verifying webhooks."""
    digest = hmac.new(server_key, f"webhook:{owner}".encode(), hashlib.sha256).digest()
    return "whsec_" + base64.b64encode(digest).decode()


def sign(secret: str, message_id: str, timestamp: int, body: bytes) -> str:
    key = base64.b64decode(secret.removeprefix("whsec_"))
    mac = hmac.new(key, f"{message_id}.{timestamp}.".encode() + body, hashlib.sha256).digest()
    return "v1," + base64.b64encode(mac).decode()


def payload(job: Any) -> dict[str, Any]:
    """What the receiver gets: the job's identity, end state and where to fetch the rest."""
    base = f"/v1/jobs/{job.id}"
    return {
        "id": job.id, "type": job.type, "state": job.state, "error": job.error,
        "parent_job_id": job.parent_job_id, "scene_id": job.scene_id,
        "finished_at": job.finished_at.isoformat() if job.finished_at else None,
        "links": {"self": base, "artifacts": f"{base}/artifacts", "logs": f"{base}/logs"},
    }


def deliver(url: str, secret: str, message_id: str, body: dict[str, Any],
            delays: Sequence[float] = RETRY_DELAYS_S) -> bool:
    """POST `body` until a 2xx answer or the retries run out; True when delivered."""
    data = json.dumps(body, sort_keys=True).encode()
    for attempt, delay in enumerate(delays, start=1):
        time.sleep(delay)
        timestamp = int(time.time())
        request = urllib.request.Request(url, data=data, method="POST", headers={
            "content-type": "application/json", "webhook-id": message_id, "webhook-timestamp": str(timestamp),
            "webhook-signature": sign(secret, message_id, timestamp, data),
        })
        try:
            with urllib.request.urlopen(request, timeout=TIMEOUT_S) as response:  # noqa: S310 - the owner's URL
                if 200 <= response.status < 300:
                    return True
                status = str(response.status)
        except OSError as exc:  # HTTPError (non-2xx), refused, timed out, DNS
            status = str(getattr(exc, "code", exc))
        log.warning("webhook %s to %s: attempt %d of %d failed (%s)", message_id, url, attempt, len(delays), status)
    return False


def deliver_in_background(url: str, secret: str, message_id: str, body: dict[str, Any]) -> threading.Thread:
    """`deliver` on a thread, so the worker takes its next job while a slow receiver is retried."""
    thread = threading.Thread(target=deliver, args=(url, secret, message_id, body), name=f"webhook-{message_id}",
                              daemon=True)
    thread.start()
    return thread
