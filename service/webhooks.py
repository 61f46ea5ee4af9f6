"""Signed completion webhooks: a job created with `"webhook": URL` gets one POST when it ends
(succeeded, failed or cancelled), retried with back-off when the receiver does not answer 2xx.
Whoever ends a job sends it (`announce`, called by `service.chaining.job_ended` for the job and
every waiting job its end cancelled): the worker, the API cancelling a queued job, the reaper.

The signature follows the Standard Webhooks convention (also Replicate's): headers
`webhook-id` (the same on every retry), `webhook-timestamp` (Unix seconds) and
`webhook-signature: v1,<base64 HMAC-SHA256 over "{id}.{timestamp}.{body}">`. The key is the
owner's webhook secret, `whsec_` + base64, derived from the server's signing key and the owner, so
it survives restarts and each owner sees only their own (GET /v1/webhook-secret). A receiver
recomputes the HMAC and rejects old timestamps.

Targets are the owner's URLs, so they are checked against internal addresses (loopback, private,
link-local, multicast, reserved, cloud metadata such as 169.254.169.254 and fd00:ec2::254):
when the job is created (`check_target`, a 422) and again for the address each connection
actually reaches (a name may resolve elsewhere by then: DNS rebinding). Redirects are never
followed. `FLUIDNEXUS_WEBHOOK_ALLOW_PRIVATE` lifts the address rule (tests, a receiver on the
same machine or network).
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import http.client
import ipaddress
import json
import logging
import os
import socket
import threading
import time
import urllib.request
from collections.abc import Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import TimeoutError as ResolveTimeout
from typing import Any
from urllib.parse import urlsplit

from service.models import Job
from service.settings import Settings, signing_key

log = logging.getLogger(__name__)

RETRY_DELAYS_S = (0.0, 2.0, 10.0, 30.0)  # first try at once, then back off; ~42 s in all
TIMEOUT_S = 10.0
# The host's name is looked up within this time, or refused. getaddrinfo has no timeout of its own,
# and a resolver that does not answer held a job's creation for 13 s (the API fuzz test, on a machine
# without outside DNS) where the lookup usually fails in 0.1 s.
RESOLVE_TIMEOUT_S = 3.0
RESOLVER_THREADS = 4
_RESOLVER: ThreadPoolExecutor


def _fresh_resolver() -> None:
    """Where lookups run, so a request waits on its own lookup for at most RESOLVE_TIMEOUT_S; a lookup
    that hangs keeps only one of these threads, and when all are held new lookups time out and are
    refused. Made at import and again in a forked child (a Celery worker process), which has none
    of its parent's threads."""
    global _RESOLVER
    _RESOLVER = ThreadPoolExecutor(max_workers=RESOLVER_THREADS, thread_name_prefix="webhook-dns")


_fresh_resolver()
os.register_at_fork(after_in_child=_fresh_resolver)


class RefusedTarget(ValueError):
    """A webhook URL whose host is, or resolves to, an internal address; the message says which."""


# Public by the registries but a cloud host's own service, reached from inside its VMs: Azure's
# wire server and instance metadata (168.63.129.16; the others' metadata addresses are link-local
# or private already).
HOST_SERVICES = (ipaddress.ip_address("168.63.129.16"),)


def refused_address(address: str) -> str | None:
    """Why `address` (an IP literal) is not a public unicast address, or None when it is one.

    An IPv6 address that carries an IPv4 one (v4-mapped `::ffff:a.b.c.d`, 6to4 `2002:AABB:CCDD::`)
    is judged by that IPv4 address: a 6to4 relay delivers it there. Site-local `fec0::/10`,
    deprecated but still routed by some stacks, is refused with the private ranges."""
    ip = ipaddress.ip_address(address.split("%", 1)[0])  # an IPv6 zone index is not part of the address
    if isinstance(ip, ipaddress.IPv6Address):
        if ip.is_site_local:
            return f"{ip} is a site-local address"
        ip = ip.ipv4_mapped or ip.sixtofour or ip
    if ip in HOST_SERVICES:
        return f"{ip} is a cloud host's own service"
    for kind in ("loopback", "link_local", "multicast", "private", "reserved", "unspecified"):
        if getattr(ip, f"is_{kind}"):
            return f"{ip} is a {kind.replace('_', '-')} address"
    if not ip.is_global:  # shared (100.64/10, where some clouds put their metadata), documentation, ...
        return f"{ip} is not a public address"
    return None


def check_target(url: str, allow_private: bool) -> None:
    """Raise RefusedTarget unless every address the URL's host resolves to is public."""
    if not allow_private:
        _resolve_public(urlsplit(url).hostname or "", 0)


def _resolve_public(host: str, port: int) -> list[str]:
    """The host's addresses, all checked: one internal address refuses the host (a resolver may
    hand them out in any order)."""
    lookup = _RESOLVER.submit(socket.getaddrinfo, host, port, type=socket.SOCK_STREAM)
    try:
        infos = lookup.result(timeout=RESOLVE_TIMEOUT_S)
    except ResolveTimeout:
        lookup.cancel()  # not started yet: drop it; started: its thread finishes when the resolver gives up
        raise RefusedTarget(f"host {host!r} did not resolve within {RESOLVE_TIMEOUT_S:g} s") from None
    except (socket.gaierror, UnicodeError) as exc:
        raise RefusedTarget(f"host {host!r} does not resolve ({exc})") from None
    addresses = [str(info[4][0]) for info in infos]
    for address in addresses:
        reason = refused_address(address)
        if reason is not None:
            raise RefusedTarget(f"host {host!r}: {reason}; set FLUIDNEXUS_WEBHOOK_ALLOW_PRIVATE to allow it")
    return addresses


def _public_connection(address: tuple[str, int], timeout: float | None = None,
                       source_address: tuple[str, int] | None = None) -> socket.socket:
    """`socket.create_connection` to an address checked now, at connect time."""
    host, port = address
    return socket.create_connection((_resolve_public(host, port)[0], port), timeout, source_address)


class _PublicHTTPConnection(http.client.HTTPConnection):
    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._create_connection = _public_connection  # http.client's seam for opening the socket


class _PublicHTTPSConnection(http.client.HTTPSConnection):
    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._create_connection = _public_connection  # TLS still checks the certificate against the name


class _PublicHTTPHandler(urllib.request.HTTPHandler):
    def http_open(self, req: urllib.request.Request) -> http.client.HTTPResponse:
        return self.do_open(_PublicHTTPConnection, req)


class _PublicHTTPSHandler(urllib.request.HTTPSHandler):
    def https_open(self, req: urllib.request.Request) -> http.client.HTTPResponse:
        return self.do_open(_PublicHTTPSConnection, req, context=self._context)


class _NoRedirects(urllib.request.HTTPRedirectHandler):
    """A 3xx is an answer like any other non-2xx (an HTTPError): never followed, wherever it points."""

    def redirect_request(self, *args: Any, **kwargs: Any) -> None:
        return None


def _opener(allow_private: bool) -> urllib.request.OpenerDirector:
    handlers: list[urllib.request.BaseHandler] = [_NoRedirects()]
    if not allow_private:
        handlers += [_PublicHTTPHandler(), _PublicHTTPSHandler()]
    return urllib.request.build_opener(*handlers)


def owner_secret(server_key: bytes, owner: str) -> str:
    """The owner's webhook secret: stable, and useless for anything but verifying webhooks."""
    digest = hmac.new(server_key, f"webhook:{owner}".encode(), hashlib.sha256).digest()
    return "whsec_" + base64.b64encode(digest).decode()


def sign(secret: str, message_id: str, timestamp: int, body: bytes) -> str:
    key = base64.b64decode(secret.removeprefix("whsec_"))
    mac = hmac.new(key, f"{message_id}.{timestamp}.".encode() + body, hashlib.sha256).digest()
    return "v1," + base64.b64encode(mac).decode()


def payload(job: Job) -> dict[str, Any]:
    """What the receiver gets: the job's identity, end state and where to fetch the rest."""
    base = f"/v1/jobs/{job.id}"
    return {
        "id": job.id, "type": job.type, "state": job.state, "error": job.error,
        "parent_job_id": job.parent_job_id, "scene_id": job.scene_id,
        "finished_at": job.finished_at.isoformat() if job.finished_at else None,
        "links": {"self": base, "artifacts": f"{base}/artifacts", "logs": f"{base}/logs"},
    }


def deliver(url: str, secret: str, message_id: str, body: dict[str, Any],
            delays: Sequence[float] = RETRY_DELAYS_S, allow_private: bool = False) -> bool:
    """POST `body` until a 2xx answer or the retries run out; True when delivered. A target that
    resolves to an internal address is refused at each attempt, like a receiver that is down."""
    data = json.dumps(body, sort_keys=True).encode()
    opener = _opener(allow_private)
    for attempt, delay in enumerate(delays, start=1):
        time.sleep(delay)
        timestamp = int(time.time())
        request = urllib.request.Request(url, data=data, method="POST", headers={
            "content-type": "application/json", "webhook-id": message_id, "webhook-timestamp": str(timestamp),
            "webhook-signature": sign(secret, message_id, timestamp, data),
        })
        try:
            with opener.open(request, timeout=TIMEOUT_S) as response:
                if 200 <= response.status < 300:
                    return True
                status = str(response.status)
        except (OSError, RefusedTarget) as exc:  # HTTPError (non-2xx, 3xx included), refused, timed out, DNS
            status = str(getattr(exc, "code", exc))
        log.warning("webhook %s to %s: attempt %d of %d failed (%s)", message_id, url, attempt, len(delays), status)
    return False


def deliver_in_background(url: str, secret: str, message_id: str, body: dict[str, Any],
                          allow_private: bool = False) -> threading.Thread:
    """`deliver` on a thread, so the worker takes its next job while a slow receiver is retried."""
    thread = threading.Thread(target=deliver, args=(url, secret, message_id, body),
                              kwargs={"allow_private": allow_private}, name=f"webhook-{message_id}", daemon=True)
    thread.start()
    return thread


def announce(settings: Settings, ended: Iterable[Job]) -> list[threading.Thread]:
    """Send the completion webhook of each ended job that asked for one, in the background, signed
    with its owner's key; the message id (`msg_JOB_STATE`) is the same on every retry. Returns the
    delivery threads (a test joins them)."""
    threads = []
    for job in ended:
        if job.webhook_url:
            secret = owner_secret(signing_key(settings), job.owner)
            threads.append(deliver_in_background(job.webhook_url, secret, f"msg_{job.id}_{job.state}", payload(job),
                                                 allow_private=settings.webhook_allow_private))
    return threads
